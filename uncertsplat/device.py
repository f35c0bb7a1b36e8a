"""Device selection: the only place that turns ``auto|cpu|cuda`` into a torch.device."""

from __future__ import annotations

import re

import torch

from uncertsplat.errors import UserError


def resolve_device(name: str | torch.device) -> torch.device:
    """Map ``auto|cpu[:0]|cuda[:n]`` or a torch.device to a torch.device; a clear error when CUDA is asked for but absent
    (a ``torch.device("cuda")`` too: torch itself would only fail at the first tensor put there, with an
    AssertionError).

    Raises:
        UserError: CUDA asked for without a CUDA device, an unknown device name or type.
    """
    if isinstance(name, torch.device):
        if name.type == "cuda" and not torch.cuda.is_available():
            raise _no_cuda(str(name))
        return torch.device("cpu") if name.type == "cpu" else name  # (cpu:0 is the CPU: runs record "cpu")
    if not isinstance(name, str):
        raise UserError(f"the device must be a name or a torch.device, got {type(name).__name__} {name!r}",
                        hint="Use auto, cpu or cuda.")
    name = name.lower()
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if re.fullmatch(r"cpu(:\d+)?", name):  # (torch names the one CPU device cpu:0 too; its tensors say "cpu")
        return torch.device("cpu")
    if re.fullmatch(r"cuda(:\d+)?", name):
        if not torch.cuda.is_available():
            raise _no_cuda(name)
        return torch.device(name)
    raise UserError(f"unknown device '{name}'", hint="Use auto, cpu, cuda or cuda:N (N: the GPU's index).")


def _no_cuda(asked: str) -> UserError:
    # one text for the command line (--device) and for Python (a device argument), which both come here
    return UserError(f"the device '{asked}' was requested but no CUDA device is available (torch "
                     f"{torch.__version__}{' was built without CUDA' if torch.version.cuda is None else ''})",
                     hint="Use the device cpu or auto (--device cpu on the command line, device=\"cpu\" in Python).")
