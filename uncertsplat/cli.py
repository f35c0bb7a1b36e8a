"""The ``uncertsplat`` command line: thin Typer commands over the ``stages`` run() functions.

The device is chosen here, once (``--device auto|cpu|cuda``); user errors are printed as one paragraph
without a traceback (``--debug`` shows it).
"""

from __future__ import annotations

import contextlib
import errno
import functools
import sys
from pathlib import Path
from typing import Annotated

# numpy before any torch: torch's C start-up imports numpy and swallows an error raised there, so a Ctrl-C landing
# in that import was lost (the command ran on, or failed later with torch half set up); imported here, in Python,
# the interrupt stops the command
import numpy  # noqa: F401, I001
import typer
from rich.text import Text
from typer.core import TyperGroup

from uncertsplat import __version__
from uncertsplat.config import STAGE_PATH_KEYS as _PATH_KEYS
from uncertsplat.console import console, q, qm
from uncertsplat.errors import Interrupted, UserError, WriteFailed, out_of_memory


def _plain_output() -> bool:
    """Whether stderr is a log, a pipe or a dumb terminal, where our messages are plain lines never broken at a width
    (``console``)."""
    return not console.is_terminal or console.is_dumb_terminal


class _Group(TyperGroup):
    """Typer's command group, with its usage errors (an option misspelt, ``--iterations abc``) printed as our errors
    are outside a terminal: ``error: ...`` on one line and the usage; Typer's box-drawn panel, wrapped at 80 columns,
    stays in a terminal."""

    def _plain_usage_error(self, err: typer.TyperException):
        # (no arguments at all: its "error" is the help, printed as Typer prints it)
        if type(err).__name__ == "NoArgsIsHelpError" or not _plain_output():
            raise err
        ctx = getattr(err, "ctx", None)
        console.print(Text.assemble(("error:", "bold red"), " ", err.format_message()), soft_wrap=True)
        if ctx is not None:
            usage = ctx.get_usage()
            if ctx.command.get_help_option(ctx) is not None:
                usage += f"\nTry '{ctx.command_path} {ctx.help_option_names[0]}' for help."
            console.print(Text(usage), soft_wrap=True)
        raise typer.Exit(err.exit_code) from None

    def make_context(self, *args, **kwargs):  # noqa: D102
        try:
            return super().make_context(*args, **kwargs)
        except typer.TyperException as err:  # (Typer's own click: its ClickException and usage errors)
            self._plain_usage_error(err)

    def invoke(self, ctx):  # noqa: D102  (a command's own arguments are parsed in here)
        try:
            return super().invoke(ctx)
        except typer.TyperException as err:  # (Typer's own click: its ClickException and usage errors)
            self._plain_usage_error(err)


app = typer.Typer(
    cls=_Group,
    name="uncertsplat",
    help="Photos to a calibrated uncertainty report for variational multi-scale 3D Gaussian Splatting.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)

_STATE = {"debug": False, "process": False}  # process: the command is the whole process (entrypoint)


def _streams_that_cannot_fail() -> None:
    """Output in an encoding without the characters we (and rich's help layout: its ellipsis) print, e.g. under
    PYTHONIOENCODING=ascii or a latin-1 locale: a character the stream cannot hold is written as a replacement
    instead of failing the command with UnicodeEncodeError."""
    for stream in (sys.stdout, sys.stderr):
        enc = (getattr(stream, "encoding", None) or "").lower().replace("-", "").replace("_", "")
        if enc and enc != "utf8" and hasattr(stream, "reconfigure"):
            with contextlib.suppress(ValueError, OSError):
                stream.reconfigure(errors="backslashreplace")


_streams_that_cannot_fail()

DeviceOpt = Annotated[str, typer.Option("--device", help="auto (CUDA if available), cpu or cuda.")]
SetOpt = Annotated[
    list[str] | None,
    typer.Option("--set", help="Override a config key: key=value, dots for nested keys (repeatable)."),
]
ConfigOpt = Annotated[Path | None, typer.Option(
    "--config", help="TOML file with this stage's config (or a config.json an output folder holds).")]


def resolve_device(name: str):
    """Resolve ``--device`` (see ``uncertsplat.device``); imported here so that ``--help`` does not load torch."""
    from uncertsplat.device import resolve_device as _resolve

    return _resolve(name)


_ENVIRONMENT_ERRNOS = {errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EROFS, errno.EACCES, errno.EPERM}


_INTERRUPTED = {
    "prune": "nothing was written (the output folder appears only when prune has finished); the same command "
             "prunes again",
    "report": "the page was not written; the same command writes the report (its figures again too)",
    "select_views": "no selection was written; the same command scores the candidates again",
    "run_pipeline": "the stages that finished are kept (each has a manifest.json); the same command skips them and "
                    "runs the rest",
    "view": "the viewer stopped",
}
"""What Ctrl-C leaves, by command (function name), for those that do not say it themselves (evaluate and synth say it
by what is on disk: ``_evaluation_stopped``, ``_synth_stopped``)."""


def _evaluation_stopped(run: Path, cfg) -> Interrupted:
    """What a Ctrl-C in ``evaluate`` left: its maps go to a staging folder (removed) and are put in place with
    metrics.json once every view is scored, so an earlier evaluation stays whole; one fixed text said "this evaluation
    has no metrics.json" beside an intact earlier one."""
    from uncertsplat.stages.evaluate import eval_dir

    out = eval_dir(run, cfg)
    if (out / "metrics.json").is_file():
        return Interrupted("evaluate stopped before it finished; the evaluation already here is kept whole (its "
                           "metrics.json and maps: the new maps went to a staging folder, now removed)", path=out,
                           hint="The same command evaluates again.")
    return Interrupted("evaluate stopped before it finished: no metrics.json was written (it is written last), so no "
                       "command takes this folder for a finished evaluation", path=out if out.is_dir() else run,
                       hint="The same command evaluates again.")


def _synth_stopped(out: Path, held: bool) -> Interrupted:
    """What a Ctrl-C in ``synth`` left in ``out`` (``held``: it held files before, a scene replaced with --overwrite).
    The scene is rendered into a temporary folder, removed on a stop, and moved into ``out`` once finished: one fixed
    text said "the scene folder is unfinished ... --overwrite" where no folder was left and the plain command works."""
    from uncertsplat.io.folders import holds_files

    if not holds_files(out):
        return Interrupted("synth stopped before the scene was finished: nothing was written (it is rendered into a "
                           "temporary folder, moved into place once finished)", path=out,
                           hint="The same command writes the scene.")
    if held:
        return Interrupted("synth stopped before the new scene was finished: the folder holds what it held before "
                           "(the scene is rendered into a temporary folder, moved into place once finished)", path=out,
                           hint="The same command writes the scene.")
    return Interrupted("synth stopped while it moved the finished scene into place: the folder holds part of it",
                       path=out, hint="The same command with --overwrite writes it again.")


def _run_begun(kwargs: dict) -> bool:
    """Whether ``train``'s output folder (``kwargs["output"]``) holds its config: the training began there, and the
    same command is refused without --resume."""
    return (Path(kwargs["output"]) / "config.json").is_file()


def _space_advice(command: str, kwargs: dict) -> str | None:
    """What works after a full disk (or quota) stopped ``command``, where the writer's "free some space or choose
    another output folder, then run again" does not: ``evaluate`` writes into the run (it has no output folder to
    choose), and a ``train`` whose run folder holds its config is refused when run again without --resume. None: the
    writer's advice works."""
    if command == "evaluate":
        return ("Free some space on that disk, then run the same command again (evaluate writes into the run folder); "
                "or copy the run folder to a disk with room and evaluate the copy.")
    if command == "train" and kwargs.get("output") is not None and _run_begun(kwargs):
        return ("Free some space, then run the same command again" + ("" if kwargs.get("resume") else " with --resume")
                + " (from its last checkpoint, where it has one); or choose another output folder (-o) for a new run.")
    return None


def _d_flag(model: str, field: str, on: str, off: str) -> str:
    """``_d`` for an on/off flag pair: the name of the flag the field's default stands for."""
    import uncertsplat.config as configs

    return f"\\[default: {on if getattr(configs, model).model_fields[field].default else off}]"


def _d(model: str, field: str, extra: str = "") -> str:
    """The ``[default: X]`` of an option whose value comes from a stage config's field (the option itself defaults
    to None so that a --config file or --set can give it), for its help text."""
    import uncertsplat.config as configs

    # (escaped: the help is rich markup, where a bare [default: X] reads as a tag and vanishes)
    return f"\\[default: {getattr(configs, model).model_fields[field].default}{extra}]"


def _ignore_further_interrupts() -> None:
    """After a Ctrl-C has been handled (what was kept is said, the command exits): a second one, pressed while the
    interpreter shuts down, printed torch's atexit traceback over the message. The work is saved by then."""
    import signal

    if not (_STATE["process"] or Path(sys.argv[0]).name == "uncertsplat"):  # (the console script's process)
        return  # called from Python (a test, a notebook): its Ctrl-C stays its own
    with contextlib.suppress(ValueError):  # (not the main thread: nothing to change)
        signal.signal(signal.SIGINT, signal.SIG_IGN)


def _handle_errors(fn):
    """Turn UserError into a one-paragraph message and exit code 2; Ctrl-C (and an Interrupted error: the work
    stopped on a signal, what was done kept) into exit code 130."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except UserError as err:
            if _STATE["debug"]:  # the traceback, then the exit code of a user error, as without --debug
                console.print_exception()
                raise typer.Exit(130 if isinstance(err, Interrupted) else 2) from None
            if isinstance(err, WriteFailed) and err.space:
                err.hint = _space_advice(fn.__name__, kwargs) or err.hint
            # the message as plain text: a path or value in it must not be read as markup or an emoji code
            label = ("interrupted:", "bold yellow") if isinstance(err, Interrupted) else ("error:", "bold red")
            if isinstance(err, Interrupted):
                _ignore_further_interrupts()
            console.print(Text.assemble(label, " ", err.render()), soft_wrap=True)
            raise typer.Exit(130 if isinstance(err, Interrupted) else 2) from None
        except KeyboardInterrupt:
            _ignore_further_interrupts()
            # (train, sweep and reconstruct say what they kept themselves, as an Interrupted error)
            said = _INTERRUPTED.get(fn.__name__)
            console.print(Text.assemble(("interrupted", "yellow"), f": {said}" if said else ""), soft_wrap=True)
            raise typer.Exit(130) from None
        except (MemoryError, RuntimeError) as err:
            # memory that ran out: what lowers this command's use, not the allocator's traceback
            memory = out_of_memory(err, fn.__name__.rstrip("_").replace("_", "-"))
            if _STATE["debug"] or memory is None:
                raise
            console.print(Text.assemble(("error:", "bold red"), " ", memory.render()), soft_wrap=True)
            raise typer.Exit(2) from None
        except OSError as err:
            # the environment, not a bug: disk full, quota, file too large, read-only or forbidden folder
            if _STATE["debug"] or err.errno not in _ENVIRONMENT_ERRNOS:
                raise
            where = f"{err.filename}: " if err.filename else ""
            space = err.errno in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)
            # (--resume only for a run folder that holds its config: before it, train starts over and --resume fails)
            advice = (space and _space_advice(fn.__name__, kwargs)) or (
                ("Free some space or choose another output folder" if space
                 else "Choose an output folder you can write to") + ", then run again" + (
                    " (--resume continues the training run)" if fn.__name__ == "train" and (
                        kwargs.get("output") is None or _run_begun(kwargs)) else "") + ".")
            console.print(Text.assemble(("error:", "bold red"), f" {where}{err.strerror}. {advice}"), soft_wrap=True)
            raise typer.Exit(2) from None

    return wrapper


def _plain_warnings() -> None:
    """Our own warnings (e.g. the native kernels' fallback) as one line, ``warning: ...``, like the commands' notes:
    Python's format added the file, the line number and the source line that raised it. Others keep theirs."""
    import warnings

    package = str(Path(__file__).resolve().parent)
    default = warnings.showwarning
    if getattr(default, "_uncertsplat", False):
        return

    def show(message, category, filename, lineno, file=None, line=None):
        if str(filename).startswith(package):
            print(f"warning: {message}", file=file or sys.stderr)
        else:
            default(message, category, filename, lineno, file, line)

    show._uncertsplat = True
    warnings.showwarning = show


def _version_callback(value: bool):
    if value:
        typer.echo(f"uncertsplat {__version__}")
        raise typer.Exit()


@app.callback()
def main(
    version: Annotated[
        bool, typer.Option("--version", callback=_version_callback, is_eager=True, help="Show the version.")
    ] = False,
    debug: Annotated[bool, typer.Option("--debug", help="Show tracebacks for errors.")] = False,
):
    """uncertsplat: reconstruct, train, evaluate, prune and report uncertainty for 3DGS."""
    _STATE["debug"] = debug
    if not debug:
        _plain_warnings()


_STAGE_TABLES = ("synth", "reconstruct", "train", "evaluate", "prune", "report", "select", "view")


def _config_file(path: Path) -> dict:
    """A --config file's keys (TOML, or JSON for a ``.json`` file: the config.json an output folder holds, given back
    to run the same settings again); one that holds a single stage table (``[train]``) is refused with the fix."""
    import json

    from uncertsplat.config import load_toml
    from uncertsplat.schemas.identify import what_file_is

    if Path(path).suffix.lower() == ".json" and Path(path).is_file():
        try:
            data = json.loads(Path(path).read_text(encoding="utf-8"))
        except (ValueError, UnicodeDecodeError) as err:
            raise UserError(f"not a valid JSON file ({err})", path=path) from None
        if not isinstance(data, dict):
            raise UserError("a --config file holds the command's keys as one object", path=path)
        data = _settings_inside(data)
    else:
        data = load_toml(path)
    if len(data) == 1 and next(iter(data)) in _STAGE_TABLES and isinstance(next(iter(data.values())), dict):
        (table,) = data
        raise UserError(f"the file holds a [{table}] table, but a --config file holds the command's keys at its top "
                        f"level (e.g. `iterations = 7000`, not under [{table}])", path=path,
                        hint=f"Remove the [{table}] line; a pipeline file (`uncertsplat run`) is where stages are "
                             "tables.")
    what = what_file_is(data)
    if what is not None and ("schema_version" in data or what == "a sweep spec"):
        # a record a command wrote (train_summary.json, metrics.json) or a sweep spec: not settings (each key was
        # refused in turn, or a record's values read as settings: "ensemble_size: Input should be a valid integer")
        sweep = what == "a sweep spec"
        raise UserError(f"this is {what}, not a command's --config file", path=path,
                        hint=f"Run it with `uncertsplat sweep {q(path)} -o OUT`." if sweep else
                        "Give the command's own config.json (e.g. RUN/config.json for train, RUN/eval/config.json for "
                        "evaluate), or a TOML file with its keys (the command's --help lists them).")
    if isinstance(data.get("stages"), list):  # a whole pipeline given to one command
        raise UserError("this is a pipeline file (it lists [[stages]]), not one command's --config file", path=path,
                        hint=f"Run it with `uncertsplat run {q(path)}`, or copy the keys of one stage's `config = {{...}}` "
                             "into a file of their own for --config.")
    for key in _PATH_KEYS:  # a relative path in the file is read from the file's folder, as a pipeline's photos are
        value = data.get(key)
        if isinstance(value, str) and value and not value.startswith("~") and not Path(value).is_absolute():
            there = Path(path).resolve().parent / value
            # (candidates may be a word, unused or around[:N]: a file only where the file's folder holds one)
            if key != "candidates" or there.exists():
                data[key] = str(there)
    return data


_RECORDS = (("config", "config_hash"), ("options", "images_registered"), ("settings", "chosen"))
"""The records that hold a command's settings under a key of their own, by (that key, a key that tells the record):
a pipeline stage's ``manifest.json``, ``reconstruct_report.json``, ``select-views``' ``selection.json``."""

_SCORE_KEYS = ("width", "height", "noise_std", "params", "note")
"""What ``selection.json``'s ``settings`` holds beside the command's config (what the score used)."""


def _settings_inside(data: dict) -> dict:
    """The settings of a record that holds them under a key (``_RECORDS``; docs/guide.md says `--config` takes them back,
    and the whole record was read as settings: "mapping_attempts: Input should be a valid integer"), else ``data``."""
    for key, tell in _RECORDS:
        if isinstance(data.get(key), dict) and tell in data and "schema_version" in data:
            inside = dict(data[key])
            return {k: v for k, v in inside.items() if k not in _SCORE_KEYS} if key == "settings" else inside
    return data


def _refuse_two_values(explicit: dict, overrides: list[str] | None) -> None:
    """An option given on the command line and again by ``--set`` with another value: which one the user meant is
    not ours to guess (``--set`` won without a word: `--method deterministic --set method=ensemble` trained an
    ensemble)."""
    from uncertsplat.config import parse_override

    # (the options that feed a config default to None, so a value here is one the command line gave)
    given = {k: v for k, v in explicit.items() if v is not None}
    for text in overrides or []:
        for key, value in parse_override(text).items():
            if key not in given or isinstance(value, dict):
                continue
            same = value == given[key] or str(value) == str(given[key]) or (
                isinstance(given[key], Path) and isinstance(value, str) and Path(value) == given[key])
            if not same:
                option = "--" + key.replace("_", "-")
                raise UserError(f"{option} {given[key]} and --set {text.strip()} give {key} two values",
                                hint=f"Give one of them ({option} or --set {key}=...).")


_SHORT = {"num_views": "-n/"}
"""The options with a short form besides their long one (named both ways in an error about their value)."""


def _refuse_other_commands_file(model, data: dict, config_file: Path | None) -> None:
    """A --config file that is another command's configuration (``RUN/config.json``, train's, given to ``evaluate``):
    one sentence, instead of one clause per key (about forty for a training's config)."""
    from uncertsplat.config import STAGE_CONFIGS, config_owner

    foreign = [k for k in data if k not in model.model_fields]
    if config_file is None or len(foreign) < 3 or 2 * len(foreign) < len(data):
        return
    owner = config_owner(data, other_than=model)
    if owner is None:
        return
    from uncertsplat.config import SelectConfig, ViewConfig

    # (select-views' and view's are no pipeline stage's: "settings of `this command`" named neither)
    commands = {**STAGE_CONFIGS, "select-views": SelectConfig, "view": ViewConfig}
    mine = next((name for name, m in commands.items() if m is model), "this command")
    own = {"evaluate": "RUN/eval/config.json", "prune": "PRUNED/prune_config.json", "train": "RUN/config.json",
           "select-views": "OUT/selection.json"}
    name = f"`uncertsplat {mine}`" if mine in commands else mine
    raise UserError(f"this is `uncertsplat {owner}`'s configuration ({len(foreign)} of its keys are not settings of "
                    f"{name}), not {name}'s", path=config_file,
                    hint=f"Give {mine}'s own" + (f" ({own[mine]})" if mine in own else "")
                         + ", or a TOML file with its keys (the command's --help lists them).")


def _stage_config(model, config_file: Path | None, overrides: list[str] | None, explicit: dict):
    """config file < explicit command-line options < --set overrides (the same key from both, with two values, is
    refused: ``_refuse_two_values``)."""
    from uncertsplat.config import KeyLines, build_config, deep_update, dotted_keys, parse_override

    _refuse_two_values(explicit, overrides)
    data = _config_file(config_file) if config_file else {}
    _refuse_other_commands_file(model, data, config_file)
    given = {k: v for k, v in explicit.items() if v is not None}
    data = deep_update(data, given)
    set_keys: set[str] = set()
    replaced = dotted_keys(given)  # the keys an option or --set gave: an error names none of them with a file line
    for o in overrides or []:
        parsed = parse_override(o)
        set_keys.update(parsed)
        replaced |= dotted_keys(parsed)
        data = deep_update(data, parsed)
    # a bad value from an option is named by the option (-n 0: "-n/--num-views", not the config key "num_views")
    names = {k: _SHORT.get(k, "") + "--" + k.replace("_", "-") for k in given if k not in set_keys}
    where = KeyLines(config_file, replaced=replaced) if config_file else None
    return build_config(model, data, source=str(config_file) if config_file else "command line", names=names,
                        where=where)


@app.command()
@_handle_errors
def synth(
    out: Annotated[Path | None, typer.Argument(
        help="Output folder for the generated scene (or -o OUT, as the other commands take it).",
        show_default=False)] = None,
    output: Annotated[Path | None, typer.Option("-o", "--output", help="The same as OUT.", show_default=False)] = None,
    preset: Annotated[str | None, typer.Option(
        help=f"tiny (tests, seconds) or demo (the embedded default). {_d('SynthConfig', 'preset')}")] = None,
    seed: Annotated[int | None, typer.Option(
        help=f"Random seed; the same seed gives the same scene. {_d('SynthConfig', 'seed')}")] = None,
    layout: Annotated[str | None, typer.Option(
        help="colmap (images/ + sparse/0, the default) or blender (transforms_train/test.json + RGBA PNGs, "
        "the NeRF-synthetic layout, no sparse points).")] = None,
    rig: Annotated[str | None, typer.Option(
        help="ring (an orbit at ~22 degrees elevation, the default) or hemisphere (cameras over the upper "
        "hemisphere looking at the centre, as in NeRF-synthetic).")] = None,
    backdrop: Annotated[str | None, typer.Option(
        help="room (objects in a closed room, the default) or transparent (objects only, RGBA with alpha).")] = None,
    overwrite: Annotated[bool, typer.Option(help="Replace an existing scene in OUT.")] = False,
    set_: SetOpt = None,
):
    """Generate a synthetic multi-view scene with GT cameras and depth, as a COLMAP model or a Blender folder."""
    from uncertsplat.config import SynthConfig
    from uncertsplat.io.folders import holds_files
    from uncertsplat.stages import synth as stage

    if out is None and output is None:
        raise UserError("synth needs the folder to write the scene to", hint="uncertsplat synth OUT (or -o OUT)")
    if out is not None and output is not None and out.resolve() != output.resolve():
        raise UserError(f"two output folders given: {q(out)} and -o {q(output)}", hint="Give one of them.")
    out = out if out is not None else output
    explicit = {"preset": preset, "seed": seed, "layout": layout, "rig": rig, "backdrop": backdrop}
    cfg = _stage_config(SynthConfig, None, set_, explicit)
    held = holds_files(out)
    try:
        stage.run(out, cfg, overwrite=overwrite)
    except KeyboardInterrupt:
        raise _synth_stopped(out, held) from None
    # the next command a user types (not printed by the stage: inside `run` the pipeline trains it)
    console.print(f"Next: [bold]uncertsplat train {qm(out)} -o RUN --preset {cfg.preset}[/]")


@app.command()
@_handle_errors
def reconstruct(
    photos: Annotated[Path, typer.Argument(help="Folder of photos (JPEG/PNG/TIFF).")],
    output: Annotated[Path, typer.Option("-o", "--output", help="Workspace folder to write.")],
    matcher: Annotated[str | None, typer.Option(
        help=f"exhaustive, sequential or auto. {_d('ReconstructConfig', 'matcher')}")] = None,
    camera_model: Annotated[str | None, typer.Option(
        help=f"COLMAP camera model estimated by SfM. {_d('ReconstructConfig', 'camera_model')}")] = None,
    single_camera: Annotated[
        bool | None, typer.Option("--single-camera/--per-image-camera", help="Share one camera per image size. "
                                  + _d_flag("ReconstructConfig", "single_camera", "single-camera", "per-image-camera"))
    ] = None,
    max_image_size: Annotated[int | None, typer.Option(
        help=f"Longest image side used. {_d('ReconstructConfig', 'max_image_size')}")] = None,
    features: Annotated[str | None, typer.Option(
        help=f"sift or dsp-sift (matches photos far apart; slower). {_d('ReconstructConfig', 'features')}")] = None,
    min_registered: Annotated[float | None, typer.Option(
        help=f"Minimum registered fraction. {_d('ReconstructConfig', 'min_registered')}")] = None,
    mapping_attempts: Annotated[int | None, typer.Option(
        help="Mapping runs at most (other seeds) until two agree; the best is kept. 1: a single run. "
             f"{_d('ReconstructConfig', 'mapping_attempts')}")] = None,
    seed: Annotated[int | None, typer.Option(help=f"Random seed. {_d('ReconstructConfig', 'seed')}")] = None,
    masks: Annotated[Path | None, typer.Option(
        help="Folder of masks for the photos (IMG_1.jpg.png, IMG_1.jpg or IMG_1.png; black: not the scene): no "
             "features there, and the workspace's masks/ leave those pixels out of training and scoring (with "
             "--extend: the new photos' masks, for a workspace made without them).")] = None,
    # (None when not given: a --config file's value stands; --no-overwrite given overrides the file's true)
    overwrite: Annotated[bool | None, typer.Option("--overwrite/--no-overwrite",
                                                   help="Replace an existing workspace.")] = None,
    extend: Annotated[bool | None, typer.Option(
        "--extend/--no-extend",
        help="Add the photos new in PHOTOS to the workspace, its cameras kept where they are (then `train --resume "
             "--add-views`).")] = None,
    config: ConfigOpt = None,
    set_: SetOpt = None,
):
    """Run COLMAP SfM on PHOTOS and write an undistorted workspace with a health report."""
    from uncertsplat.config import ReconstructConfig
    from uncertsplat.stages import reconstruct as stage

    explicit = dict(matcher=matcher, camera_model=camera_model, single_camera=single_camera,
                    max_image_size=max_image_size, features=features, min_registered=min_registered,
                    mapping_attempts=mapping_attempts, seed=seed, overwrite=overwrite, extend=extend, masks=masks)
    cfg = _stage_config(ReconstructConfig, config, set_, explicit)
    stage.run(photos, output, cfg)


@app.command()
@_handle_errors
def train(
    scene: Annotated[Path, typer.Argument(help="COLMAP workspace, Blender folder (transforms_*.json), nerfstudio folder (transforms.json) or synthetic scene.")],
    output: Annotated[Path, typer.Option("-o", "--output", help="Run folder to write.")],
    preset: Annotated[str | None, typer.Option(help="tiny, demo or paper (see the README).")] = None,
    iterations: Annotated[int | None, typer.Option(
        help=f"Training steps. {_d('TrainConfig', 'iterations', ' without a preset')}")] = None,
    variant: Annotated[str | None, typer.Option(help="ours or paper (the original code's choices).")] = None,
    seed: Annotated[int | None, typer.Option(help=f"Random seed. {_d('TrainConfig', 'seed')}")] = None,
    method: Annotated[str | None, typer.Option(
        help="variational (default), paper, vi-single, deterministic, ensemble or fisher (baselines).")] = None,
    resume: Annotated[bool, typer.Option(help="Continue from the last good checkpoint in OUTPUT.")] = False,
    add_views: Annotated[list[str] | None, typer.Option(
        "--add-views", help="With --resume: image names to add to the training views (repeatable).")] = None,
    from_ply: Annotated[Path | None, typer.Option(
        "--from-ply", help="A 3DGS model trained elsewhere on SCENE (its point_cloud.ply): give it the posterior "
        "without training it (0 steps).")] = None,
    from_ply_transform: Annotated[Path | None, typer.Option(
        "--from-ply-transform", help="With --from-ply: the JSON file of the frame the model was trained in "
        "(nerfstudio's dataparser_transforms.json), for a trainer that normalises its world.")] = None,
    view: Annotated[bool, typer.Option("--view", help="Watch the model train in the browser (needs viser).")] = False,
    view_port: Annotated[int, typer.Option(help="Port of the --view viewer (0 picks a free one).")] = 8080,
    device: DeviceOpt = "auto",
    config: ConfigOpt = None,
    set_: SetOpt = None,
):
    """Train a variational multi-scale 3DGS model (or a baseline, --method) with full-state checkpoints."""
    from uncertsplat.config import TrainConfig
    from uncertsplat.stages import train as stage

    data = _config_file(config) if config else {}
    _refuse_other_commands_file(TrainConfig, data, config)
    explicit = dict(iterations=iterations, variant=variant, seed=seed)
    if from_ply_transform is not None:
        explicit["init_ply_transform"] = from_ply_transform.expanduser().absolute()
    if from_ply is not None:  # (absolute: config.json and a later --resume read it from any folder)
        explicit["init_ply"] = from_ply.expanduser().absolute()
        if iterations is None and "iterations" not in stage.given_keys(None, {}, None, {}, set_):
            # over a --config file's steps too (an option wins over the file, as every option does); steps given
            # on the command line are refused by the config, which says why
            explicit["iterations"] = 0
    _refuse_two_values({**explicit, "method": method}, set_)
    cfg = stage.resolve_config(preset, data, method, explicit, set_, source=str(config) if config else None)
    # with --resume, --iterations means "train on to this many steps" (the stored config wins otherwise)
    view_cfg = None
    if view:
        from uncertsplat.config import ViewConfig, build_config

        view_cfg = build_config(ViewConfig, {"port": view_port}, source="command line")
        from uncertsplat.view.server import check_port

        check_port(view_cfg.host, view_cfg.port, option="--view-port")  # before any run folder is made
    given = stage.given_keys(preset, data, method, explicit, set_) if resume else None
    if resume and iterations is None and "iterations" in stage.given_keys(None, {}, None, {}, set_):
        iterations = cfg.iterations  # `--set iterations=N` means what --iterations N does (a --config file's does not)
    stage.run(scene, output, cfg, device=resolve_device(device), resume=resume,
              extend_to=iterations if resume else None, view=view_cfg, add_views=add_views, given=given)


@app.command()
@_handle_errors
def evaluate(
    run: Annotated[Path, typer.Argument(help="Run folder written by `train`.")],
    split: Annotated[str | None, typer.Option(help=f"test or train. {_d('EvalConfig', 'split')}")] = None,
    num_samples: Annotated[int | None, typer.Option(
        help=f"Posterior samples per view (K). {_d('EvalConfig', 'num_samples')}")] = None,
    seed: Annotated[int | None, typer.Option(help=f"Random seed for sampling. {_d('EvalConfig', 'seed')}")] = None,
    depth_gt: Annotated[Path | None, typer.Option(help="Folder of GT depth maps.")] = None,
    depth_scale: Annotated[str | None, typer.Option(
        help="auto (fitted to a --depth-gt folder), scene (its maps are in the scene's own units, e.g. a metric "
        "COLMAP model's) or a factor from the run's depth to GT depth units.")] = None,
    paper_nll: Annotated[bool | None, typer.Option("--paper-nll/--no-paper-nll",
                                                   help="Also report the paper's NLL.")] = None,
    device: DeviceOpt = "auto",
    config: ConfigOpt = None,
    set_: SetOpt = None,
):
    """Render uncertainty maps for held-out views and score them (AUSE, NLL, calibration)."""
    from uncertsplat.config import EvalConfig
    from uncertsplat.stages import evaluate as stage

    ds: object = None
    if depth_scale is not None:
        hint = ("auto estimates it from the GT depth maps; scene takes maps in the scene's own units; a number is "
                "the factor to GT units.")
        try:
            ds = float(depth_scale)
        except ValueError:
            if depth_scale not in ("auto", "scene"):
                raise UserError(f"--depth-scale must be auto, scene or a number, not {depth_scale!r}",
                                hint=hint) from None
            ds = depth_scale
        if isinstance(ds, float) and not (0.0 < ds < float("inf")):  # checked before any view is rendered
            raise UserError(f"--depth-scale must be a positive number, not {depth_scale}", hint=hint)
    explicit = dict(split=split, num_samples=num_samples, seed=seed, depth_gt=depth_gt, depth_scale=ds,
                    paper_nll=paper_nll)
    cfg = _stage_config(EvalConfig, config, set_, explicit)
    if cfg.depth_gt is not None and not cfg.depth_gt.is_absolute():
        # (absolute, as train's --from-ply: RUN/eval/config.json, given back by --config, is read from its own folder)
        cfg = cfg.model_copy(update={"depth_gt": cfg.depth_gt.absolute()})
    try:
        stage.run(run, cfg, device=resolve_device(device))
    except KeyboardInterrupt:
        raise _evaluation_stopped(run, cfg) from None


@app.command()
@_handle_errors
def prune(
    run: Annotated[Path, typer.Argument(help="Run folder written by `train`.")],
    output: Annotated[Path | None, typer.Option("-o", "--output", help="New run folder.")] = None,
    keep_ratio: Annotated[float | None, typer.Option(help="Fraction of Gaussians to keep, in (0, 1].")] = None,
    threshold: Annotated[float | None, typer.Option(help="Remove Gaussians whose score exceeds this.")] = None,
    auto: Annotated[bool | None, typer.Option(
        "--auto/--no-auto", help="Strongest pruning within --tolerance-db of the unpruned PSNR.")] = None,
    tolerance_db: Annotated[float | None, typer.Option(help="PSNR loss --auto may accept, in dB (default 0.1).")] = None,
    score: Annotated[str | None, typer.Option(help="Per-Gaussian score: auto (with --auto or --keep-ratio, on a scene with held-out views: free-space and gate both tried, the one that prunes more within the tolerance kept; free-space alone with --sweep, --threshold or no held-out views), free-space, gate, position, scale, or predictive (for --dry-run and --sweep only: it ranks the Gaussians the image needs most first; see docs/guide.md).")] = None,
    dry_run: Annotated[bool | None, typer.Option("--dry-run/--no-dry-run", help="Report only; write no model.")] = None,
    sweep: Annotated[bool | None, typer.Option("--sweep/--no-sweep", help="Evaluate a range of keep ratios.")] = None,
    device: DeviceOpt = "auto",
    config: ConfigOpt = None,
    set_: SetOpt = None,
):
    """Remove the most uncertain Gaussians (floaters) into a new run and measure the effect."""
    from uncertsplat.config import PruneConfig
    from uncertsplat.stages import prune as stage

    explicit = dict(keep_ratio=keep_ratio, threshold=threshold, auto=auto, tolerance_db=tolerance_db,
                    score=score, dry_run=dry_run, sweep=sweep)
    cfg = _stage_config(PruneConfig, config, set_, explicit)
    if tolerance_db is not None and not cfg.auto:
        raise UserError("--tolerance-db only applies to --auto (the strongest pruning within that PSNR loss)",
                        hint="Add --auto, or leave --tolerance-db out.")
    stage.run(run, output, cfg, device=resolve_device(device))


@app.command()
@_handle_errors
def report(
    runs: Annotated[list[Path], typer.Argument(help="One or more run folders.")],
    output: Annotated[Path, typer.Option("-o", "--output", help="Report folder.")],
    config: ConfigOpt = None,
    set_: SetOpt = None,
):
    """Write a self-contained HTML report with PNG figures."""
    from uncertsplat.config import ReportConfig
    from uncertsplat.stages import report as stage

    cfg = _stage_config(ReportConfig, config, set_, {})
    stage.run(runs, output, cfg)


@app.command("select-views")
@_handle_errors
def select_views(
    run: Annotated[Path, typer.Argument(help="Run folder written by `train`.")],
    candidates: Annotated[str | None, typer.Option(
        help="unused (the scene's images not used yet), around[:N] (viewpoints near the training cameras) or a "
             "file of lines 'NAME QW QX QY QZ TX TY TZ'.")] = None,
    num_views: Annotated[int | None, typer.Option("-n", "--num-views", help="How many views to choose.")] = None,
    score: Annotated[str | None, typer.Option(help="fisher (default), variance, unseen, coverage or random.")] = None,
    output: Annotated[Path | None, typer.Option("-o", "--output", help="Output folder (default RUN/select).")] = None,
    device: DeviceOpt = "auto",
    config: ConfigOpt = None,
    set_: SetOpt = None,
):
    """Rank candidate cameras by how much the model would learn from them: which photo to take next."""
    from uncertsplat.config import SelectConfig
    from uncertsplat.stages import select as stage

    cfg = _stage_config(SelectConfig, config, set_, dict(candidates=candidates, num_views=num_views, score=score))
    stage.run(run, cfg, device=resolve_device(device), output=output)


@app.command()
@_handle_errors
def view(
    run: Annotated[Path, typer.Argument(help="Run folder written by `train` (any method) or `prune`.")],
    host: Annotated[str | None, typer.Option(help="Address to listen on (127.0.0.1: this machine only).")] = None,
    port: Annotated[int | None, typer.Option(help="Port to listen on (default 8080; 0 picks a free one).")] = None,
    device: DeviceOpt = "auto",
    config: ConfigOpt = None,
    set_: SetOpt = None,
):
    """Look at the model and its uncertainty in the browser (RGB, depth, std maps, prune preview, cameras)."""
    from uncertsplat.config import ViewConfig
    from uncertsplat.stages import view as stage

    cfg = _stage_config(ViewConfig, config, set_, dict(host=host, port=port))
    stage.run(run, cfg, device=resolve_device(device))


@app.command()
@_handle_errors
def sweep(
    spec: Annotated[Path, typer.Argument(
        help="Sweep TOML, or the name of one installed with uncertsplat (tradeoff).")],
    output: Annotated[Path, typer.Option("-o", "--output", help="Output folder (runs, sweep.jsonl, pareto.png).")],
    jobs: Annotated[int | None, typer.Option(help="Parallel jobs (default: number of cores; 1 on CUDA).")] = None,
    scene: Annotated[Path | None, typer.Option(help="Scene folder (overrides the spec's).")] = None,
    force: Annotated[bool, typer.Option(help="Measure every point again, those with a record too: each run is "
                                        "trained again (its training time measured now) and evaluated.")] = False,
    executor: Annotated[str, typer.Option(help="local (this machine's cores) or ray (a Ray instance or cluster).")] = "local",
    address: Annotated[str | None, typer.Option(
        help="ray: 'auto' joins a running cluster; left out, a local Ray instance starts.")] = None,
    cpus_per_job: Annotated[float, typer.Option(help="ray: CPUs each job asks for (and its torch threads).")] = 1.0,
    gpus_per_job: Annotated[float, typer.Option(help="ray: GPUs each job asks for.")] = 0.0,
    retries: Annotated[int, typer.Option(help="Runs again a job whose worker died or whose points failed.")] = 1,
    scenes: Annotated[str | None, typer.Option(
        help="Only these of the spec's \\[scenes.NAME], comma-separated (e.g. fern,bonsai).")] = None,
    device: DeviceOpt = "auto",
    set_: SetOpt = None,
):
    """Measure the speed-accuracy trade: train/evaluate each point of a sweep and draw the Pareto front."""
    from uncertsplat.config import shipped_file
    from uncertsplat.schemas.identify import what_file_is
    from uncertsplat.stages import sweep as stage

    only = [s.strip() for s in scenes.split(",") if s.strip()] if scenes else None
    stage.run(shipped_file(spec, "sweep", describe=what_file_is), output, jobs=jobs, device=device, scene=scene, overrides=set_, force=force, executor=executor,
              address=address, cpus_per_job=cpus_per_job, gpus_per_job=gpus_per_job, retries=retries,
              only_scenes=only)


@app.command("run")
@_handle_errors
def run_pipeline(
    pipeline: Annotated[Path, typer.Argument(
        help="Pipeline TOML file, or the name of one installed with uncertsplat (demo, smoke, photos).")],
    output: Annotated[Path, typer.Option("-o", "--output", help="Output folder for all stages.")],
    set_: SetOpt = None,
    device: Annotated[str | None, typer.Option("--device", help="auto, cpu or cuda.")] = None,
    force: Annotated[bool, typer.Option(help="Re-run stages even when unchanged.")] = False,
):
    """Run a chain of stages from a TOML file, skipping stages whose config and inputs are unchanged."""
    from uncertsplat.config import shipped_file
    from uncertsplat.schemas.identify import what_file_is
    from uncertsplat.stages import pipeline as stage

    _refuse_two_values({"device": device}, set_)
    stage.run(shipped_file(pipeline, "pipeline", describe=what_file_is), output, overrides=set_ or [], device=device, force=force)


def entrypoint():  # pragma: no cover
    _STATE["process"] = True
    sys.exit(app())


if __name__ == "__main__":  # pragma: no cover
    entrypoint()
