"""User-facing errors: the CLI prints these as one paragraph, without a traceback."""

from __future__ import annotations

import contextlib
from pathlib import Path


class UserError(Exception):
    """An error caused by the user's input, with a message that names the file and the fix.

    Args:
        message: what is wrong, in one or two sentences.
        path: the file or folder concerned, if any.
        hint: what the user can do about it.
    """

    def __init__(self, message: str, *, path: str | Path | None = None, hint: str | None = None):
        self.message = message
        self.path = None if path is None else Path(path)
        self.hint = hint
        super().__init__(self.render())

    def render(self) -> str:
        parts = []
        if self.path is not None:
            parts.append(f"{self.path}: {self.message}")
        else:
            parts.append(self.message)
        text = parts[0]
        if self.hint:
            # messages are written without a final full stop; the hint is a sentence of its own
            text = text if text.rstrip().endswith((".", "!", "?", ":")) else text.rstrip() + "."
            text = f"{text} {self.hint}"
        return text


@contextlib.contextmanager
def naming_overrides(overrides: list[str] | None):
    """Errors raised inside name the ``--set`` values that went into the checked configuration, so that a bad value
    given on the command line is not blamed on the file alone."""
    try:
        yield
    except UserError as err:
        if not overrides:
            raise
        err.message = f"{err.message} (the file's values with --set {' '.join(overrides)})"
        err.args = (err.render(),)
        raise


def require_extra(module: str, *, feature: str, extra: str):
    """Import an optional dependency, or raise one UserError naming the feature and the install command.

    Args:
        module: the package to import (``"ray"``).
        feature: what needs it, as the user asked for it (``"--executor ray"``).
        extra: the project's extra that installs it (``pip install 'uncertsplat[EXTRA]'``).
    """
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError as err:
        raise UserError(f"{feature} needs the {module} package, which is not installed ({err})",
                        hint=f"Install it with: pip install 'uncertsplat[{extra}]' (or: pip install {module}).") from None


class WriteFailed(UserError):
    """A file could not be written (``io.atomic``; nothing was left half-written). ``space``: the disk (or the quota)
    was full, and the advice frees space. Its advice, "then run again", is the writer's, which knows no command: the
    CLI gives a command's own where that one would not work (``evaluate`` has no output folder to choose; a ``train``
    run folder that exists is refused without --resume)."""

    def __init__(self, message: str, *, path: str | Path | None = None, hint: str | None = None, space: bool = False):
        self.space = space
        super().__init__(message, path=path, hint=hint)


class StageError(UserError):
    """A pipeline stage failed; the message says which stage and why."""


class NoPosterior(UserError):
    """A stage that works on the per-Gaussian posterior (prune) was given a run its settings left without one (a run
    too short for its first densification: a quick test): a pipeline skips such a stage with this message, and the
    stages that read its output, and goes on to its report. A method without a posterior is a ``UserError``."""


class Interrupted(UserError):
    """The user stopped the work (Ctrl-C, SIGTERM) and what was done is kept (e.g. a checkpoint): the message says
    where and the hint how to continue. The CLI exits with 130, as for Ctrl-C; a sweep stops instead of retrying."""


_MEMORY_ADVICE = {
    "train": "--set scene.downscale=2 (each halving of the photos' side quarters their memory; or a larger factor), "
             "or train on fewer photos",
    "evaluate": "--set residual_views=16 and --set consistency_views=16 (the training views the pixel noise and the "
                "view-consistency term render: 64 each by default), fewer --num-samples, or --set max_views=N",
    "prune": "--set free_space_views=16 (the training views its free-space score renders: 64 by default), "
             "--set num_samples=4, or a run trained at a larger scene.downscale",
    "reconstruct": "--max-image-size 1600 (or less) and --set num_threads=1 (feature extraction holds a copy of the "
                   "image per thread)",
}
"""What lowers each command's memory, named when it ran out (``out_of_memory``)."""


IMPOSSIBLE_ALLOCATION = 1 << 50
"""An allocation of more bytes than this (a pebibyte) that failed is no machine's memory running out but a size gone
wrong (``torch.empty(2**62)``): ``out_of_memory`` leaves it to be raised as a bug."""


def out_of_memory(err: BaseException, command: str) -> UserError | None:
    """A ``UserError`` that says ``command`` ran out of memory and what lowers its use, for an allocation that failed
    (``MemoryError``, torch's "can't allocate memory" on the CPU, a CUDA out-of-memory error); None for any other
    error. It was a traceback of the allocator."""
    text = str(err)
    cuda = type(err).__name__ == "OutOfMemoryError" or "CUDA out of memory" in text or (
        "CUDA error: out of memory" in text)
    if not (isinstance(err, MemoryError) or cuda or (isinstance(err, RuntimeError) and (
            "can't allocate memory" in text or "DefaultCPUAllocator" in text))):
        return None
    import re

    size = re.search(r"allocate (\d+) bytes", text) or re.search(r"allocate ([\d.]+ [KMGT]iB)", text)
    asked = (f"{int(size.group(1)) / 2**30:.2f} GiB" if size.group(1).isdigit() else size.group(1)) if size else None
    if size and size.group(1).isdigit() and int(size.group(1)) > IMPOSSIBLE_ALLOCATION:
        return None  # no machine's memory: a size gone wrong (a bug), raised as such
    where = "the GPU's" if cuda else "the machine's"
    advice = _MEMORY_ADVICE.get(command)
    return UserError(f"{command} ran out of {where} memory" + (f" (an allocation of {asked} failed)" if asked else ""),
                     hint=(f"Lower its use with {advice}; " if advice else "") + "close other programs"
                          + (" or use --device cpu" if cuda else "") + (
                              ". A training stopped before its first checkpoint starts again with the same command "
                              "and new settings; one stopped after it keeps it (`train --resume` goes on with the "
                              "stored settings)" if command == "train" else "") + ".")


def run_folder_missing(path: str | Path) -> UserError:
    """The error for a run folder that is not there: a file of that name is named as one."""
    path = Path(path)
    if path.exists():
        return UserError("this is a file, not a run folder", path=path,
                         hint="Give the folder `uncertsplat train -o` wrote (it holds config.json).")
    return UserError("run folder not found", path=path, hint="Give a folder written by `uncertsplat train`.")
