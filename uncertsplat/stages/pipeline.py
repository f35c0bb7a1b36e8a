"""``uncertsplat run``: a chain of stages from a TOML pipeline file.

Each stage writes into its own folder under the output (``OUT/<name>``; ``evaluate`` writes into the
run it evaluates, ``RUN/eval``) together with a ``manifest.json``. A stage whose resolved config and
inputs are unchanged since its last successful run is skipped. A stage that must run again moves its
previous output to ``OUT/.previous/<name>`` first, so nothing is lost silently; a train stage interrupted by
Ctrl-C resumes from its checkpoint instead when run again with the same settings and inputs. A failing stage leaves
the outputs of earlier stages intact and the error names the stage.
"""

from __future__ import annotations

import json
import shutil
import time
from functools import partial
from pathlib import Path

from uncertsplat.config import (
    STAGE_CONFIGS,
    STAGE_PATH_KEYS,
    KeyLines,
    PipelineConfig,
    PipelineStage,
    build_config,
    deep_update,
    dotted_keys,
    load_toml,
    parse_override,
    train_config_from,
)
from uncertsplat.console import advice_within, console, q
from uncertsplat.errors import (
    Interrupted,
    NoPosterior,
    StageError,
    UserError,
    naming_overrides,
    out_of_memory,
)
from uncertsplat.io.atomic import lock_holder, run_lock
from uncertsplat.io.folders import PIPELINE_STARTED, is_run
from uncertsplat.stages.manifest import (
    MANIFEST,
    Manifest,
    file_sha256,
    fingerprints,
    hash_config,
    missing_outputs,
    nested_stages,
    output_sizes,
    read_manifest,
    resized_outputs,
    stage_outputs,
    start_manifest,
    write_manifest,
)

_TOP_LEVEL = {"name", "photos", "device"}


def load_pipeline(path: Path, overrides: list[str] | None = None) -> PipelineConfig:
    """Read and validate a pipeline file; ``overrides`` are ``stage.key=value`` or ``photos=...``.

    The first component of an override names a stage (its ``name``, or its kind when unnamed); the
    rest is a key in that stage's config (``train.preset=tiny`` sets the train preset).
    """
    data = load_toml(path)
    base = Path(path).resolve().parent
    photos_given = False
    for text in overrides or []:
        parsed = parse_override(text)
        (head, rest), = parsed.items()
        if head in _TOP_LEVEL:
            data[head] = rest
            photos_given |= head == "photos"
            continue
        stages = data.get("stages", [])
        matches = [s for s in stages if (s.get("name") or s.get("stage")) == head]
        if not matches:
            known = ", ".join(str(s.get("name") or s.get("stage")) for s in stages)
            raise UserError(f"--set {text}: no stage named '{head}' in the pipeline", path=path,
                            hint=f"Stages: {known}; top-level keys: {', '.join(sorted(_TOP_LEVEL))}.")
        if not isinstance(rest, dict):
            raise UserError(f"--set {text}: give a key inside the stage, e.g. {head}.seed=1", path=path)
        for stage in matches:
            if "preset" in rest and stage.get("stage") == "train":  # a train stage's preset sits beside its config
                stage["preset"] = rest.pop("preset")
            stage["config"] = deep_update(stage.get("config", {}), rest)
    names = [str(s.get("name") or s.get("stage")) for s in data.get("stages", []) if isinstance(s, dict)]
    kinds = [str(s.get("stage")) for s in data.get("stages", []) if isinstance(s, dict)]
    with naming_overrides(overrides):
        cfg = build_config(PipelineConfig, data, source=str(path),
                           where=KeyLines(path, replaced=_replaced_keys(names, overrides, kinds)))
    if photos_given and not _reads_photos(cfg):
        from uncertsplat.console import console

        console.print(f"[yellow]note:[/] --set photos is not used: no reconstruct stage of {Path(path).name} starts "
                      "from photos (pipelines/photos.toml does)")
    if cfg.photos is not None and not cfg.photos.is_absolute():
        # typed on the command line: from the current folder; written in the file: from the file's folder (the
        # current folder as a fallback, which is what it was read from before)
        first, second = (Path.cwd(), base) if photos_given else (base, Path.cwd())
        cfg.photos = (first / cfg.photos if (first / cfg.photos).exists() or not (second / cfg.photos).exists()
                      else second / cfg.photos).resolve()
    for stage in cfg.stages:  # a stage's relative path (evaluate's depth_gt): from the current folder, as it always
        # was read, else from the pipeline file's folder (where it failed before: no pipeline's settings change)
        for key in STAGE_PATH_KEYS:
            value = stage.config.get(key)
            if isinstance(value, str) and value and not Path(value).expanduser().is_absolute() \
                    and not Path(value).exists() and (base / value).exists():
                stage.config[key] = str(base / value)
    names = [s.name or s.stage for s in cfg.stages]
    dup = {n for n in names if names.count(n) > 1}
    if dup:
        raise UserError(f"stage names must be unique; repeated: {', '.join(sorted(dup))}", path=path,
                        hint="Give repeated stages a `name`.")
    return cfg


def _replaced_keys(names: list[str], overrides: list[str] | None, kinds: list[str] | None = None) -> set[str]:
    """The pipeline file's keys (dotted from its top: ``stages.2.config.num_samples``) whose values the ``--set``
    ``overrides`` replaced, for the stages called ``names`` (of the stage kinds ``kinds``): an error about one gets no
    line of the file."""
    out: set[str] = set()
    for text in overrides or []:
        (head, rest), = parse_override(text).items()
        if head in _TOP_LEVEL or not isinstance(rest, dict):
            out.add(head)
            continue
        for i, name in enumerate(names):
            if name == head:  # a train stage's preset sits beside its config (synth's is in its config)
                train = kinds is None or kinds[i] == "train"
                out |= {f"stages.{i}.preset" if key == "preset" and train else f"stages.{i}.config.{key}"
                        for key in dotted_keys(rest)}
    return out


def _stage_config(stage: PipelineStage, where: KeyLines | None = None):
    """A stage's resolved configuration; ``where``: its ``config`` table's lines in the pipeline file."""
    if stage.stage == "train":
        return train_config_from(stage.preset, stage.config, source=f"stage '{stage.name or stage.stage}'",
                                 where=where)
    if stage.preset is not None:
        raise UserError(f"stage '{stage.name or stage.stage}': `preset` applies to train stages only")
    return build_config(STAGE_CONFIGS[stage.stage], stage.config, source=f"stage '{stage.name or stage.stage}'",
                        where=where)


def check_stages(cfg: PipelineConfig, path: Path, overrides: list[str] | None = None) -> list:
    """Every stage's configuration and input, before the first stage runs (a typo in the last stage's keys was
    found only after the stages before it had run: with real photos, after minutes of reconstruction); returns the
    stages' resolved configurations, in order. ``overrides``: the ``--set`` values the stages hold (their keys are
    not named with a line of the file).

    Raises:
        UserError: naming the pipeline file, the stage and the key with its line (or the input that names nothing).
    """
    earlier: list[str] = []
    configs = []
    replaced = _replaced_keys([s.name or s.stage for s in cfg.stages], overrides, [s.stage for s in cfg.stages])
    kinds: dict[str, str] = {}
    evaluated: dict[tuple[str, str], str] = {}  # (the run's stage, split) -> the evaluate stage that writes it
    for i, stage in enumerate(cfg.stages):
        name = stage.name or stage.stage
        try:
            configs.append(_stage_config(stage, KeyLines(path, prefix=f"stages.{i}.config", replaced=replaced)))
        except UserError as err:
            raise UserError(err.message, path=path, hint=err.hint) from None
        if stage.stage == "reconstruct" and getattr(configs[-1], "extend", False):
            # a pipeline moves a stage's earlier output aside before it runs it again: there is no workspace to grow
            raise UserError(f"stage '{name}': extend is a step of its own, not a pipeline setting (the pipeline "
                            "replaces the stage's workspace when its photos change)", path=path,
                            hint=f"Grow the workspace the pipeline wrote with `uncertsplat reconstruct PHOTOS -o "
                                 f"OUT/{name} --extend`, then train its run on with `uncertsplat train OUT/{name} -o "
                                 "RUN --resume --add-views NAMES`.")
        upstream = stage.input if stage.input is not None else (earlier[-1] if earlier else None)
        if upstream in kinds:
            _check_upstream(stage, name, upstream, kinds, path)
            if stage.stage == "evaluate":
                key = (upstream, configs[-1].split)
                if key in evaluated:
                    raise UserError(f"stages '{evaluated[key]}' and '{name}' both evaluate '{upstream}' ({key[1]} "
                                    "views), into the same folder: each run of the pipeline the second would replace "
                                    "the first's evaluation", path=path,
                                    hint="Keep one of them; to compare evaluation settings use `uncertsplat sweep` "
                                         "(its axes), or `uncertsplat evaluate` on a copy of the run.")
                evaluated[key] = name
        if stage.stage == "report" and not any(k in ("train", "prune") for k in kinds.values()):
            # (found when the report's turn came, after the stages before it had run); a report's `input` is not
            # read: a run folder given there (a copied run) was met with "put a train stage before it" alone
            given = f"; its input '{stage.input}' is not read" if stage.input is not None else ""
            raise UserError(f"stage '{name}' needs a train or prune stage before it (a report shows the pipeline's "
                            f"runs{given})", path=path,
                            hint=f"Put a train stage before it, or run `uncertsplat report "
                                 f"{q(stage.input) if stage.input is not None else 'RUN'}` on a run of your own.")
        kinds[name] = stage.stage
        if stage.input is not None and stage.input not in earlier:
            folder = Path(stage.input)
            folder = folder if folder.is_absolute() else Path(path).resolve().parent / folder
            if not folder.exists():
                raise UserError(f"stage '{name}': its input '{stage.input}' is neither an earlier stage nor a folder",
                                path=path, hint=f"Earlier stages: {', '.join(earlier) or 'none'}; a folder is read "
                                                "from the pipeline file's folder.")
        earlier.append(name)
    return configs


_READS = {"reconstruct": ("synth",), "train": ("synth", "reconstruct"), "evaluate": ("train", "prune"),
          "prune": ("train", "prune")}
"""The kinds of stage whose output each kind of stage reads (a report reads every run before it)."""


def _check_upstream(stage: PipelineStage, name: str, upstream: str, kinds: dict[str, str], path: Path) -> None:
    """Refuse a stage whose input (``upstream``, an earlier stage: its ``input``, or the stage before it) is of a
    kind it cannot read, before any stage runs (an evaluate after a report ran synth and train first, then failed
    with 'not a training run')."""
    allowed = _READS.get(stage.stage)
    if allowed is None or kinds[upstream] in allowed:
        return
    fit = [n for n, k in kinds.items() if k in allowed]
    why = "" if stage.input is not None else " (the stage before it: no `input` given)"
    article = "an" if stage.stage[0] in "aeiou" else "a"
    raise UserError(f"stage '{name}' ({stage.stage}) reads '{upstream}'{why}, a {kinds[upstream]} stage; "
                    f"{article} {stage.stage} stage reads the output of a {' or '.join(allowed)} stage", path=path,
                    hint=f'Set input = "{fit[-1]}" in its [[stages]] table.' if fit else
                    f"Put a {' or '.join(allowed)} stage before it.")


def _evaluation_kept(run_dir: Path, cfg, device) -> bool:
    """Whether ``evaluate`` will keep the evaluation already in ``run_dir/eval`` (e.g. ``prune`` evaluated the run it
    wrote with these settings): it is then left in place, not moved to ``.previous``."""
    from uncertsplat.stages import evaluate

    return evaluate.kept_evaluation(run_dir, cfg, device) is not None


INTERRUPTED = "interrupted"
"""A stage's manifest ``error`` after Ctrl-C (a train stage with a checkpoint resumes when run with the same settings
and inputs, as after any other end before it finished)."""


def _has_checkpoint(run_dir: Path) -> bool:
    from uncertsplat.io.checkpoints import list_checkpoints

    return bool(list_checkpoints(run_dir)) or any(list_checkpoints(m) for m in (run_dir / "members").glob("*"))


def _reads_photos(cfg: PipelineConfig) -> bool:
    """Whether a reconstruct stage reads the pipeline's ``photos``: one with no ``input`` and no stage before it (a
    reconstruct after synth reads the synthetic images)."""
    return any(st.stage == "reconstruct" and st.input is None and i == 0 for i, st in enumerate(cfg.stages))


def _finished_output(folder: Path) -> bool:
    """Whether ``folder`` holds a stage's finished output (its manifest says done)."""
    found = read_manifest(folder)
    return found is not None and found.status == "done"


def held_out_change(previous: Path, run_dir: Path, stage: str = "train") -> str | None:
    """A sentence when the run in ``run_dir`` holds out other views than the earlier run kept in ``previous`` (its
    ``.previous`` generation; ``stage`` names the train stage in the advice): the split follows the photos' sorted
    order (``scene.test_every``), so a photo added to or removed from the folder moves it, and the two runs' held-out
    metrics then score other photos. None when either has no readable scene.json or they hold out the same views."""
    from uncertsplat.schemas.scene import RunScene

    try:
        old, now = RunScene.read(previous / "scene.json"), RunScene.read(run_dir / "scene.json")
    except Exception:  # no earlier run (or one from another version): nothing to compare
        return None
    if list(old.test) == list(now.test):
        return None
    present = set(now.train) | set(now.test) | set(now.calibration)
    kept = [n for n in old.test if n in present]  # the earlier held-out photos still in the scene
    kept = kept if len(kept) <= 20 else []  # (longer: too long for a command line)
    gone = [n for n in old.test if n not in set(now.test)]
    added = [n for n in now.test if n not in set(old.test)]

    def names(xs: list[str]) -> str:
        return ", ".join(xs[:5]) + (f" and {len(xs) - 5} more" if len(xs) > 5 else "")

    what = "; ".join(p for p in (f"no longer held out: {names(gone)}" if gone else "",
                                 f"newly held out: {names(added)}" if added else "") if p)
    return (f"this run holds out other views than the previous one ({previous}): {what}. The split follows the photos' "
            "sorted order, so a photo added or removed moves it; the two runs' held-out metrics score different photos "
            "and do not compare" + (f" (to hold out the earlier ones again: --set '{stage}.scene.test_names="
                                     f"{json.dumps(kept)}')." if kept else "."))


STARTED = PIPELINE_STARTED
"""``OUT/.stages_started.json`` (``io.folders.PIPELINE_STARTED``, by which other commands tell a pipeline's output): {name: the manifest key (settings and inputs) it was last started with} of the stages
this pipeline has started in ``OUT`` (``_move_previous`` tells a folder of its own that lost its manifest, a stage
killed before it, from one it never wrote; a train stage killed with ``kill -9`` or ended by a full disk resumes from
its checkpoint when started again with the same key). Before 2026-11-30 a list of names (keys unknown)."""


def _started_keys(root: Path) -> dict[str, str | None]:
    try:
        found = json.loads((root / STARTED).read_text(encoding="utf-8"))
    except (OSError, ValueError, TypeError):
        return {}
    if isinstance(found, list):
        return {str(n): None for n in found}
    return {str(k): (v if isinstance(v, str) else None) for k, v in found.items()} if isinstance(found, dict) else {}


def _started(root: Path) -> set[str]:
    return set(_started_keys(root))


def _mark_started(root: Path, name: str, key: str) -> None:
    from uncertsplat.io.atomic import atomic_write_text

    keys = _started_keys(root)
    if keys.get(name) != key:
        atomic_write_text(root / STARTED, json.dumps({**keys, name: key}, indent=1, sort_keys=True) + "\n")


def _move_previous(out_dir: Path, root: Path, name: str, own: bool = False) -> None:
    """Keep one previous generation of a stage's output instead of deleting it: ``.previous/NAME``. An unfinished
    output (a stage that failed or was stopped) never replaces a finished one there: it goes to
    ``.previous/NAME-unfinished`` instead, so a failed or interrupted run after a good one loses the good one's work
    neither then nor at the next change. A folder without a manifest that is not ``own`` (no stage of this pipeline
    ever ran there) is not the pipeline's: it goes to ``.previous/NAME-not-from-this-pipeline`` (numbered when taken),
    never replaced."""
    if out_dir.exists() and not out_dir.is_dir():  # (iterdir raised NotADirectoryError: a traceback)
        raise UserError(f"a file is where the stage '{name}' writes its folder", path=out_dir,
                        hint="Move or delete that file (or give -o another folder), then run the pipeline again.")
    if not out_dir.exists() or not any(out_dir.iterdir()):
        return
    if not own and not (out_dir / MANIFEST).is_file():
        # no stage of this pipeline ever wrote here (a run trained by hand into OUT/train, notes of the user's): kept
        # apart, under a name no later generation takes (in the rotation, the next change deleted it: a helper's
        # hand-trained run was lost)
        backup = root / ".previous" / f"{name}-not-from-this-pipeline"
        k = 1
        while backup.exists():
            k += 1
            backup = root / ".previous" / f"{name}-not-from-this-pipeline-{k}"
        backup.parent.mkdir(parents=True, exist_ok=True)
        shutil.move(str(out_dir), str(backup))
        console.print(f"  {out_dir} was not written by this pipeline (no {MANIFEST}): moved to {backup}, where it "
                      "stays until you delete it")
        return
    backup = root / ".previous" / name
    if not _finished_output(out_dir) and _finished_output(backup):
        backup = root / ".previous" / f"{name}-unfinished"
    if backup.exists():
        shutil.rmtree(backup)
    backup.parent.mkdir(parents=True, exist_ok=True)
    shutil.move(str(out_dir), str(backup))
    console.print(f"  previous output of '{name}' moved to {backup}")


def _refuse_other_outputs(root: Path) -> None:
    """Refuse an output folder that is another command's output: a pipeline writes one folder per stage into it,
    which would mix with a training run's files or become part of a scene (whose runs then see their scene changed).

    Raises:
        UserError: ``root`` is a training run, a pruned run, or a scene or COLMAP workspace (a file: ``run_lock``).
    """
    if not root.is_dir() or (root / STARTED).is_file():  # (an earlier `uncertsplat run`'s own output, in any state)
        return
    what = None
    if is_run(root):
        what = "a training run" if not (root / "prune.json").is_file() else "a pruned run"
    elif ((root / "sparse").is_dir() and not (root / "sparse" / MANIFEST).is_file()) or any(
            (root / n).is_file() for n in ("transforms.json", "transforms_train.json", "reconstruct_report.json")):
        # (a COLMAP model beside the photos; a stage folder named "sparse" holds its manifest; a folder of photos
        # alone, images/, is a project folder the stages may well be written beside)
        what = "a scene (photos and their cameras)"
    if what is not None:
        raise UserError(f"the output folder holds {what}: the pipeline's stage folders written into it would mix "
                        "with it", path=root,
                        hint="Choose a new folder for -o: the pipeline writes one folder per stage into it.")


def run(pipeline: Path, output: Path, *, overrides: list[str] | None = None, device: str | None = None,
        force: bool = False) -> dict[str, Path]:
    """Run the pipeline into ``output``; returns the output folder of each stage by name."""
    from uncertsplat.device import resolve_device

    pipeline = Path(pipeline)
    cfg = load_pipeline(pipeline, overrides)
    with naming_overrides(overrides):
        stage_configs = check_stages(cfg, pipeline, overrides)
    if cfg.photos is not None and not Path(cfg.photos).is_dir() and _reads_photos(cfg):
        # before any output folder exists: the pipeline's photo folder is a placeholder until the user sets it
        what = "is a file, not a photo folder" if Path(cfg.photos).exists() else "photo folder not found"
        given = any(o.split("=", 1)[0].strip() == "photos" for o in overrides or ())
        # a pipeline shipped with the package is named as the user typed it (its path lies inside the package)
        shipped = Path(__file__).resolve().parents[1] / "pipelines"
        named = pipeline.stem if pipeline.resolve().parent == shipped else q(pipeline)
        raise UserError(f"{what} (the pipeline's `photos`"
                        + ("" if given else ", which names a folder beside the pipeline file until --set photos gives "
                                            "yours") + ")", path=Path(cfg.photos),
                        hint=f"Give your photos: uncertsplat run {named} -o {q(output)} --set photos=/path/to/photos")
    dev = resolve_device(device or cfg.device)
    root = Path(output)
    if cfg.photos is not None and _reads_photos(cfg):
        # (reconstruct refuses a workspace inside its photos, after the pipeline had written its own file there)
        photos = Path(cfg.photos).resolve()
        if photos == root.resolve() or photos in root.resolve().parents:
            raise UserError(f"the output folder is inside the photo folder {q(cfg.photos)}: reconstruct writes no "
                            "workspace among the photos it reads", path=root,
                            hint=f"Choose an output folder outside it, e.g. -o {q(photos.parent / (photos.name + '_out'))}.")
    _refuse_other_outputs(root)

    # one pipeline command per output folder: a second one would move the first one's stage folders (and their
    # locks) to .previous while it writes them
    with run_lock(root, "run"):
        outputs: dict[str, Path] = {}
        kinds: dict[str, str] = {}
        manifests: dict[str, Manifest] = {}
        ran: set[str] = set()  # the stages this run ran (not skipped)
        upstreams: dict[str, str | None] = {}
        previous: str | None = None
        skipped: dict[str, str] = {}  # a stage skipped for want of a posterior: its reason
        run_notes: dict[Path, list[str]] = {}  # what the report says of a run, e.g. that its prune stage was skipped
        t_all = time.perf_counter()
        console.print(f"[bold]pipeline[/] {cfg.name} ({pipeline}) -> {root}  device={dev}")

        for stage, stage_cfg in zip(cfg.stages, stage_configs, strict=True):
            name = stage.name or stage.stage
            upstream = stage.input if stage.input is not None else previous
            if stage.stage != "synth" and stage.stage != "report" and upstream is None and not (
                stage.stage == "reconstruct" and cfg.photos is not None
            ):
                raise UserError(f"stage '{name}' has no input", path=pipeline,
                                hint="Put a stage before it, set `input`, or set `photos` for reconstruct.")
            upstreams[name] = upstream
            if upstream in skipped and stage.stage not in ("synth", "report"):  # (those two read no input stage)
                # a stage that reads a skipped one's output (the demo's evaluation of the pruned model) is skipped
                # too, for the same reason: a quick test still ends with its report
                skipped[name] = skipped[upstream]
                console.print(f"[yellow]warning:[/] stage '{name}' ({stage.stage}) skipped: it reads the output of "
                              f"stage '{upstream}', which was skipped")
                previous = name
                continue
            inputs: dict[str, str] = {}
            # folder inputs by the manifests' earlier hashes: of every file (notes and backups too), and before that
            # of names, sizes and mtimes; then the three of a scene folder with uncertsplat's own outputs inside it
            # counted (``_outputs_inside``: before they were left out)
            earlier: tuple[dict[str, str], ...] = ({}, {}, {}, {}, {})
            renamed: dict[str, str] = {}
            up_path: Path | None = None
            if upstream is not None:
                if upstream in outputs:
                    up_path = outputs[upstream]
                    inputs[upstream] = _made(manifests[upstream])
                else:
                    up_path = Path(upstream)
                    if not up_path.is_absolute():
                        up_path = (pipeline.resolve().parent / up_path)
                    # keyed as the file writes it (a project moved with its pipeline file keeps its key), where
                    # manifests before 2026-11-30 keyed the resolved path: that key is taken too (``renamed``)
                    skip = [root]
                    if stage.stage == "evaluate":  # evaluations go into the run: not an input of the stage
                        from uncertsplat.stages.evaluate import eval_dir

                        # (this stage's and any other's, of the held-out or the training views: another stage, or
                        # an `evaluate --split train` by hand, rewrote one with each call)
                        skip += [eval_dir(up_path, stage_cfg.model_copy(update={"split": s})) for s in ("test", "train")]
                    # a train stage's scene: a run trained into it by hand (SCENE/run), its evaluation, a pipeline's
                    # or a sweep's output there are no files the scene's loader reads, and each retrained the stage
                    # from step 0 (as the sweep's scene fingerprint leaves them out); likewise a run's: a select-views
                    # or evaluation folder made in it by hand is not its model (an ensemble's members are)
                    from uncertsplat.stages.sweep import _outputs_inside

                    inside = []
                    if up_path.is_dir() and stage.stage in ("train", "evaluate", "prune"):
                        inside = [o for o in _outputs_inside(up_path) if stage.stage == "train"
                                  or o.relative_to(up_path).parts[0] != "members"]
                    inputs[upstream], earlier[0][upstream], earlier[1][upstream] = fingerprints(
                        up_path, skip=[*skip, *inside])
                    if inside:
                        for e, value in zip(earlier[2:], fingerprints(up_path, skip=skip), strict=True):
                            e[upstream] = value
                    if str(up_path) != upstream:
                        renamed[upstream] = str(up_path)

            kwargs: dict = {}
            keyed: dict = {}  # settings keyed otherwise than the stage runs with them (a path inside OUT)
            if stage.stage == "synth":
                out_dir = root / name
            elif stage.stage == "reconstruct":
                if up_path is None:
                    up_path = Path(cfg.photos)
                    inputs["photos"], earlier[0]["photos"], earlier[1]["photos"] = fingerprints(up_path, skip=root)
                elif kinds.get(upstream) == "synth":
                    up_path = up_path / "images"
                if stage_cfg.masks is not None and stage_cfg.masks.is_dir():
                    # the photos' masks are an input as the photos are: other masks, another workspace
                    inputs["masks"], earlier[0]["masks"], earlier[1]["masks"] = fingerprints(stage_cfg.masks, skip=root)
                out_dir = root / name
            elif stage.stage == "evaluate":
                from uncertsplat.stages.evaluate import eval_dir

                out_dir = eval_dir(up_path, stage_cfg)
                if upstream not in outputs:  # a run outside the pipeline's folder: evaluate writes into it
                    console.print(f"[yellow]note:[/] stage '{name}' evaluates the run {up_path}, outside {root}: its "
                                  f"evaluation is written there ({out_dir}; an earlier one there goes to "
                                  f"{root / '.previous'})")
                synth = [n for n, k in kinds.items() if k == "synth"]
                # follow the chain back (evaluate <- prune <- train) to the scene the model was trained on
                node = _back_through(upstream, ("prune",), kinds, upstreams)
                trained_on = kinds.get(str(upstreams.get(node)))
                if synth and stage_cfg.depth_gt is None and trained_on == "reconstruct":
                    # SfM on a synthetic scene: the GT depth lives with the generator's output; the evaluate
                    # stage aligns the depth scale (the reconstruction's frame is not the generator's).
                    # (resolved: keyed as -o was typed, `-o /abs/out` after `-o out` ran the stage again)
                    stage_cfg = stage_cfg.model_copy(update={"depth_gt": outputs[synth[0]].resolve() / "depth"})
                    inputs[synth[0]] = _made(manifests[synth[0]])
                    # keyed by the stage it comes from (whose key is an input), so that a project moved elsewhere,
                    # or `-o` given another way, skips it as every other stage
                    keyed["depth_gt"] = f"{synth[0]}/depth"
            elif stage.stage == "report":
                runs = [p for n, p in outputs.items() if kinds[n] in ("train", "prune")]
                if not runs:
                    raise UserError(f"stage '{name}' needs a train or prune stage before it", path=pipeline)
                kwargs["runs"] = runs
                kwargs["notes"] = run_notes
                for n, k in kinds.items():
                    if k in ("train", "prune", "evaluate"):
                        inputs[n] = _made(manifests[n])
                # an evaluation no stage of this pipeline made (an `evaluate RUN` by hand) is read by the report as
                # the stages' are: made, changed or deleted since, the report is made again
                inputs.update(_evaluations_by_hand(outputs, kinds))
                for n, why in skipped.items():  # the report says it: a stage skipped, or no longer, makes it again
                    inputs[n] = "skipped: " + hash_config({"why": why})
                out_dir = root / name
            else:
                out_dir = root / name
                for key, what in (("init_ply", "model file"), ("init_ply_transform", "model's frame")):
                    if stage.stage != "train" or getattr(stage_cfg, key, None) is None:
                        continue
                    from uncertsplat.provenance import file_sha256

                    # the model file (and its frame's) is an input as the scene is: another under the same name
                    # trains again
                    given = Path(getattr(stage_cfg, key)).expanduser()
                    if not given.is_file():  # refused here, before the stage's finished run is moved aside for nothing
                        # (a relative one was looked for from the current folder, then the pipeline file's)
                        where = "" if given.is_absolute() else (f" (looked for from the current folder and from "
                                                                f"{Path(pipeline).parent.absolute()})")
                        raise UserError(f"stage '{name}': its {what} ({key}), {given}, is "
                                        f"{'not a file' if given.exists() else 'missing'}{where}", path=pipeline,
                                        hint=f"Put the file back (or give {key} its new place) and run the "
                                             "pipeline again; the stage's earlier output is left as it is.")
                    inputs[key] = file_sha256(given)

            config_dict = stage_cfg.model_dump(mode="json")
            new = start_manifest(stage.stage, name, config_dict, inputs,
                                 keyed={**config_dict, **keyed} if keyed else None)
            old = read_manifest(out_dir)
            # (a manifest from before such keys, by the settings as run, is taken too: the same project, not moved)
            same_config = old is not None and old.config_hash in {new.config_hash, hash_config(config_dict)}
            unreadable = old is None and (out_dir / MANIFEST).is_file()  # (said below, once it is known what follows)
            taken = [new.input_hashes, *({**new.input_hashes, **e} for e in earlier)]
            taken += [{renamed.get(k, k): v for k, v in d.items()} for d in taken] if renamed else []
            # (manifests from before a stage's input was keyed with when it finished: by its key alone; only for an
            # input stage skipped in this run, not one that ran again with the same key, which is what they miss)
            legacy = [{k: v if k in ran else v.split("@", 1)[0] for k, v in d.items()} for d in taken]
            taken += [d for d in legacy if d not in taken]
            same_inputs = old is not None and old.input_hashes in taken
            changed = None
            if old is not None and old.status == "done" and not force and same_config and same_inputs:
                changed = _changed_output(name, stage.stage, out_dir, old)
                if changed:
                    console.print(f"[yellow]note:[/] {changed}: it runs again")
            elif not force and not unreadable:  # (a first run says nothing; the note above, the output changed)
                why = _why_again(name, out_dir, old, new, same_config, upstream, ran, _started(root))
                if why:  # a stage folder gone, or its input made again, moved a finished output aside unsaid
                    console.print(f"[yellow]note:[/] {why}")
            if (not force and old is not None and old.status == "done" and same_config
                    and same_inputs and not changed):
                console.print(f"[green]skip[/] {name}: unchanged since its last run ({out_dir})")
                outputs[name], kinds[name], manifests[name] = out_dir, stage.stage, old
                previous = name
                continue

            # a folder another process writes (a `train --resume` of the pipeline's run, an evaluate of it) is neither
            # moved aside nor written: the two would mix (a helper's pipeline trained into a run being resumed by hand)
            for folder in dict.fromkeys([out_dir, *([up_path] if stage.stage == "evaluate" and up_path else [])]):
                holder = lock_holder(folder)
                if holder is not None:
                    raise UserError(f"stage '{name}' would replace {folder}, which another uncertsplat process "
                                    f"({holder}) is writing now", path=folder,
                                    hint="Wait for it to finish, then run the pipeline again (a stage whose output was "
                                         "changed by hand runs again, with a note).")
            console.print(f"[bold cyan]stage[/] {name} ({stage.stage}) -> {out_dir}")
            # a training that did not finish with these settings and inputs goes on from its checkpoint: stopped
            # (Ctrl-C), failed (a full disk), or killed before it could say so (kill -9, the OOM killer: its folder
            # has no manifest of this start, but the pipeline recorded the start's key)
            unfinished = (old is None or old.status != "done") and (
                (old is not None and same_config and same_inputs)
                or _started_keys(root).get(name) in (new.key, new.model_copy(update={"input_hashes": legacy[0]}).key))
            resume = not force and stage.stage == "train" and unfinished and _has_checkpoint(out_dir)
            again = (_made_again("train", out_dir, new) or _trained_elsewhere(out_dir, up_path)) if resume else None
            if again:  # trained on by hand since (`train --resume --iterations`), or a copy's run: not this stage's
                console.print(f"[yellow]note:[/] {again}: it is not resumed; '{name}' runs again")
                resume = False
            if unreadable:
                console.print(f"[yellow]note:[/] {out_dir / MANIFEST} cannot be read (damaged or from another "
                              f"version), so '{name}' runs again; " + (
                                  "its training resumes from its checkpoint (started with these settings and inputs)"
                                  if resume else f"its present output is kept under {root / '.previous'}"))
            if resume:
                kwargs["resume"] = True
                console.print(f"  resuming '{name}' from its checkpoint (it did not finish with these settings and "
                              "inputs)")
            elif not (stage.stage == "evaluate" and _evaluation_kept(up_path, stage_cfg, dev)):
                # a stage of its own killed before its manifest, and an evaluation a prune stage wrote (RUN/eval), take
                # the rotation
                _move_previous(out_dir, root, name if stage.stage != "evaluate" else f"{name}-eval",
                               own=stage.stage == "evaluate" or name in _started(root))
            _mark_started(root, name, new.key)
            t0 = time.perf_counter()
            # the stage's advice in the pipeline's words: its own keys, and an evaluation's or prune's advice about the
            # training that made its run as that train stage's keys (printed notes and the errors below alike)
            node = _back_through(upstream, ("prune", "evaluate"), kinds, upstreams)
            advice = partial(pipeline_advice, name, type(stage_cfg).model_fields, others=(
                {"train": (node, STAGE_CONFIGS["train"].model_fields)}
                if node is not None and kinds.get(node) == "train" and stage.stage != "train" else None))
            try:
                console.rewrite = advice
                try:
                    _run_stage(stage.stage, stage_cfg, up_path, out_dir, dev, kwargs)
                finally:
                    console.rewrite = None
            except KeyboardInterrupt:
                _finish(out_dir, new, "failed", t0, INTERRUPTED)
                raise
            except Interrupted as err:  # a stage stopped by Ctrl-C that kept its work (train's checkpoint, ...)
                _finish(out_dir, new, "failed", t0, INTERRUPTED)
                again = ("training resumes from its checkpoint" if stage.stage == "train" and _has_checkpoint(out_dir)
                         else "this one starts over (its folder kept under .previous/)")
                raise Interrupted(f"stage '{name}' ({stage.stage}) interrupted: {err.message}",
                                  hint=f"Run the same pipeline command again: the stages that finished are skipped and "
                                       f"{again}.") from None
            except NoPosterior as err:
                # a prune of a run its settings left without a posterior (a short test run of a photos pipeline): the
                # stages after it go on (those that read its output skipped too), so the pipeline still ends with its
                # report, which says why this one did not run; what to change is the training's (its length), said in
                # the words of the stage that trains it
                text = (pipeline_advice(upstream, STAGE_CONFIGS["train"].model_fields, f"{err.path}: {err.message}")
                        if kinds.get(upstream) == "train" else advice(err.render()))
                _finish(out_dir, new, "skipped", t0, err.render())
                skipped[name] = text
                run_notes.setdefault(up_path, []).append(f"the pipeline's stage '{name}' did not run: {text}")
                console.print(f"[yellow]warning:[/] stage '{name}' ({stage.stage}) skipped: {text}")
                previous = name
                continue
            except UserError as err:
                _finish(out_dir, new, "failed", t0, err.render())
                raise StageError(f"stage '{name}' ({stage.stage}) failed: {advice(err.render())}") from None
            except Exception as err:  # an unexpected fault: still say which stage, keep earlier outputs
                _finish(out_dir, new, "failed", t0, f"{type(err).__name__}: {err}")
                memory = out_of_memory(err, stage.stage)
                if memory is not None:  # the machine's limit, not a fault: what lowers the stage's use, in its keys
                    raise StageError(f"stage '{name}' ({stage.stage}) failed: {advice(memory.render())}") from None
                raise StageError(
                    f"stage '{name}' ({stage.stage}) failed with an internal error: {type(err).__name__}: {err}",
                    hint="Earlier stages' outputs are intact; re-run with --debug for the traceback and report it.",
                ) from err
            _finish(out_dir, new, "done", t0)
            console.print(f"  [green]done[/] {name} in {time.perf_counter() - t0:.1f} s")
            if stage.stage == "train":
                moved = held_out_change(root / ".previous" / name, out_dir, name)
                if moved:
                    console.print(f"[yellow]note:[/] {moved}")
            outputs[name], kinds[name], manifests[name] = out_dir, stage.stage, new
            ran.add(name)
            previous = name

        console.print(f"[bold green]pipeline finished[/] in {time.perf_counter() - t_all:.1f} s"
                      + (f" ({', '.join(repr(n) for n in skipped)} skipped: see above)" if skipped else ""))
        reports = [p for n, p in outputs.items() if kinds[n] == "report"]
        for r in reports:
            console.print(f"report: {r / 'index.html'}")
        return outputs


def _made(manifest: Manifest) -> str:
    """A stage as the input of a later one: its key and when it finished, so that a stage run again with the same key
    (a file of its output deleted, ``--force``) makes the stages after it run again: on CUDA, where training is not
    bitwise repeatable, its model is another, which they were skipped for (the same bits on the CPU)."""
    return f"{manifest.key}@{manifest.finished_at!r}"


def _back_through(node: str | None, through: tuple[str, ...], kinds: dict[str, str],
                  upstreams: dict[str, str | None]) -> str | None:
    """The first stage up the chain from ``node`` (itself included) whose kind is not in ``through``: the train stage
    behind an evaluation of a pruned run, or a stage given as a folder (None where the chain ends)."""
    while node is not None and kinds.get(node) in through:
        node = upstreams.get(node)
    return node


def _evaluations_by_hand(outputs: dict[str, Path], kinds: dict[str, str]) -> dict[str, str]:
    """{"RUN_STAGE/EVAL_FOLDER": the SHA-256 of its metrics.json} for each evaluation a report of the pipeline's runs
    reads (``RUN/eval``, ``RUN/eval-train``, ...) that none of the pipeline's evaluate stages wrote."""
    staged = {p.resolve() for n, p in outputs.items() if kinds[n] == "evaluate"}
    found: dict[str, str] = {}
    for n, run_dir in outputs.items():
        if kinds[n] not in ("train", "prune"):
            continue
        for metrics in sorted([run_dir / "eval" / "metrics.json", *run_dir.glob("eval-*/metrics.json")]):
            if metrics.is_file() and metrics.parent.resolve() not in staged:
                found[f"{n}/{metrics.parent.name}"] = file_sha256(metrics)
    return found


def _why_again(name: str, out_dir: Path, old: Manifest | None, new: Manifest, same_config: bool,
               upstream: str | None, ran: set[str], started: set[str]) -> str | None:
    """Why the stage ``name``, started before, runs again (its earlier output moved to ``.previous``), or None: its
    folder gone (a project copied without its scene), its settings changed, an input stage that ran again or an input
    that changed. None for a stage never started here, an unfinished one (it resumes or starts over) and a skip."""
    if old is None:
        if upstream in ran and name in started:  # (a nested output, RUN/eval, went to .previous with its run)
            return f"'{name}' runs again: its input '{upstream}' ran again"
        if name in started and not out_dir.exists():
            return f"{out_dir}, where '{name}' wrote its output before, is gone: it runs again"
        return None
    if old.status != "done":
        return None
    if not same_config:
        return f"'{name}' runs again: its settings changed since its last run"
    moved = [k for k, v in new.input_hashes.items() if old.input_hashes.get(k) != v]
    moved += [k for k in old.input_hashes if k not in new.input_hashes]
    if not moved:
        return None
    parts = []
    for which, what in (([k for k in moved if k in ran], "ran again"), ([k for k in moved if k not in ran], "changed")):
        if which:
            parts.append(f"its input{'s' if len(which) > 1 else ''} {', '.join(repr(k) for k in which)} {what}")
    return f"'{name}' runs again: " + "; ".join(parts)


def _changed_output(name: str, kind: str, out_dir: Path, manifest: Manifest) -> str | None:
    """Why the finished stage ``name``'s output in ``out_dir`` is not the one it left, or None: a file gone, the
    stage made again by hand with other settings (``_made_again``), or a file of another size (``resized_outputs``)."""

    def files(found: list[str]) -> str:
        return f"{name}'s output {found[0]}" + (f" (and {len(found) - 1} more file(s))" if len(found) > 1 else "")

    owned = nested_stages(out_dir)  # (one walk of the folder for both checks)
    gone = missing_outputs(out_dir, manifest, owned)
    if gone:
        return f"{files(gone)} is gone from {out_dir}"
    again = _made_again(kind, out_dir, manifest)
    if again:
        return again
    resized = resized_outputs(out_dir, manifest, owned)
    if resized:
        return f"{files(resized)} in {out_dir} is not the size the stage left (damaged, or written again since)"
    return None


def pipeline_advice(name: str, fields, text: str, others: dict[str, tuple[str, object]] | None = None) -> str:
    """``text`` (a stage's message) with its advice in a pipeline's words (``console.advice_within``)."""
    return advice_within(name, fields, text, "pipeline", others=others)


def _trained_elsewhere(run_dir: Path, scene: Path | None) -> str | None:
    """Why the unfinished run in ``run_dir`` is not this stage's to resume on ``scene``, or None: it records another
    scene that is still there (a copy of the output folder: train refuses to resume it on the copy's scene, so the
    stage could never finish; a moved project's old scene is gone, and train finds the one beside the run)."""
    from uncertsplat.schemas.scene import RunScene

    try:
        info = RunScene.read_optional(run_dir / RunScene.FILE_NAME)
    except (UserError, OSError):
        return None
    if info is None or scene is None:
        return None
    recorded = Path(info.scene)
    if not recorded.is_dir() or recorded.resolve() == Path(scene).resolve():
        return None
    return f"the run in {run_dir} was trained on {recorded}, which is still there (a copy of another output folder?)"


def _made_again(kind: str, out_dir: Path, manifest: Manifest) -> str | None:
    """Why the output in ``out_dir`` is no longer the one the finished stage of ``manifest`` made, or None: the run's
    ``config.json`` (train) or the evaluation's ``config.json`` (evaluate; but for the settings that change only what
    it writes, ``OUTPUT_SETTINGS``) records other settings than the stage ran with (an `evaluate --num-samples 4` of
    the pipeline's run, a `train --resume --iterations`)."""
    from uncertsplat.stages.evaluate import OUTPUT_SETTINGS

    if kind not in ("train", "evaluate") or not (out_dir / "config.json").is_file():
        return None
    ignore = set(OUTPUT_SETTINGS) if kind == "evaluate" else set()
    try:
        found = json.loads((out_dir / "config.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return f"{out_dir / 'config.json'} cannot be read"
    if not isinstance(found, dict):
        return f"{out_dir / 'config.json'} is not a config"
    if {k: v for k, v in found.items() if k not in ignore} == {k: v for k, v in manifest.config.items()
                                                                 if k not in ignore}:
        return None
    what = "run" if kind == "train" else "evaluation"
    return (f"the {what} in {out_dir} was made again since with other settings than this stage's (its config.json; "
            f"e.g. `uncertsplat {kind}` run on it by hand)")


def _finish(out_dir: Path, manifest: Manifest, status: str, t0: float, error: str | None = None) -> None:
    manifest.status = status
    manifest.finished_at = time.time()
    manifest.seconds = time.perf_counter() - t0
    manifest.error = error
    manifest.outputs = stage_outputs(out_dir) if status == "done" else []
    manifest.output_sizes = output_sizes(out_dir, manifest.outputs)
    if out_dir.exists() or status == "done":
        write_manifest(out_dir, manifest)


def _run_stage(kind: str, cfg, up_path: Path | None, out_dir: Path, device, kwargs: dict) -> None:
    if kind == "synth":
        from uncertsplat.stages import synth

        synth.run(out_dir, cfg, overwrite=True)
    elif kind == "reconstruct":
        from uncertsplat.stages import reconstruct

        reconstruct.run(up_path, out_dir, cfg.model_copy(update={"overwrite": True}))
    elif kind == "train":
        from uncertsplat.stages import train

        # dispatches on the method; resume: an interrupted run of the same settings and inputs goes on
        train.run(up_path, out_dir, cfg, device=device, resume=kwargs.get("resume", False))
    elif kind == "evaluate":
        from uncertsplat.stages import evaluate

        evaluate.run(up_path, cfg, device=device)
    elif kind == "prune":
        from uncertsplat.stages import prune

        prune.run(up_path, out_dir, cfg, device=device)
    elif kind == "report":
        from uncertsplat.stages import report

        report.run(kwargs["runs"], out_dir, cfg, notes=kwargs.get("notes"))
    else:  # pragma: no cover - the schema forbids it
        raise UserError(f"unknown stage kind {kind}")
