"""What a speed-accuracy sweep varies: the spec (TOML), its points and the independent jobs they form.

A spec names a base training config (preset + overrides), a base evaluation config, a ``default``
point and the ``axes`` to vary. ``design = "axes"`` varies one knob at a time around the default
(plus the default itself); ``design = "grid"`` takes the full product. Knobs:

==============  ===========================================  =====================================
knob            sets                                         costs
==============  ===========================================  =====================================
method          ``baselines.METHODS[name]``                  training (ensemble: N x)
iterations      ``iterations`` (schedule scaled, see below)  training time
num_entries     ``variational.num_entries`` (K_table)        memory, a little training time (SGD posterior;
                                                             the informed one stores 1)
num_samples     ``EvalConfig.num_samples`` (K)               evaluation time (linear)
downscale       ``scene.downscale`` (resolution)             everything (about quadratic)
ensemble_size   ``ensemble_size`` (N)                        training time (linear)
spawn_fraction  ``densify.spawn_scale_fraction``             memory (offset tables of carriers)
==============  ===========================================  =====================================

``spawn_fraction`` decides which Gaussians carry a posterior (||scale|| > fraction x extent): larger
values give fewer carriers, hence less table memory and work per step, and leave the small Gaussians
without uncertainty.

``schedule = "scaled"`` (default) scales the densification window (start, until), the spawn and SH
intervals and the opacity reset with the number of iterations (relative to the base config), so a
short run densifies over the same fraction of its steps; the densification *interval* is kept, since
its gradient statistics need about one pass over the training views whatever the run's length (a
scaled interval densifies far more often and the Gaussians explode). ``"fixed"`` keeps the base schedule. Ensemble points always use K = N samples (each member once).

Points that share a training config form one job (train once, evaluate at every K): each job is a
pure function of its dict (``jobs.run_job``), so a cluster engine can run them anywhere.

Scenes and seeds replicate the design: with ``[scenes.NAME]`` tables every point runs on every scene (each
scene a ``path`` that ``train`` reads, a folder of ``photos`` reconstructed once into ``OUT/scenes/NAME``, or a
``synth`` scene generated there; each may set its own preset, train and evaluate keys over the spec's), and with
``seeds = [0, 1, 2]`` every point trains once per seed (``TrainConfig.seed`` and ``EvalConfig.seed``). Point ids
then read ``SCENE.POINT_seedS``; the summary's ``table`` gives the mean and spread over the seeds of each point on
each scene, and the Pareto fronts are drawn per scene over those means. Relative paths in the file are read
from the spec file's folder.
"""

from __future__ import annotations

import itertools
import json
import re
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    field_validator,
    model_validator,
)

from uncertsplat.config import (
    EvalConfig,
    KeyLines,
    TrainConfig,
    build_config,
    deep_update,
    dotted_keys,
    format_validation_error,
    refuse_bool_numbers,
    train_config_from,
)
from uncertsplat.errors import UserError, naming_overrides
from uncertsplat.provenance import hash_config

KNOBS = ("method", "iterations", "num_entries", "num_samples", "downscale", "ensemble_size", "spawn_fraction")


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    @field_validator("*", mode="before")
    @classmethod
    def _no_bool_numbers(cls, value, info):
        return refuse_bool_numbers(cls, info.field_name, value)


def _known_method(name: str) -> str:
    from uncertsplat.baselines import METHODS

    if name not in METHODS:
        raise ValueError(f"unknown method {name!r} (methods: {', '.join(METHODS)})")
    return name


# The knobs' types and ranges, shared by a point and the axes' lists (so that a bad axis value is refused, naming
# its key, when the spec is read).
Method = Annotated[str, AfterValidator(_known_method)]
Iterations = Annotated[int, Field(ge=1)]
NumEntries = Annotated[int, Field(ge=1, le=256)]
NumSamples = Annotated[int, Field(ge=1, le=10_000)]
Downscale = Annotated[float, Field(ge=1.0, le=64.0)]
EnsembleSize = Annotated[int, Field(ge=1, le=1000)]
SpawnFraction = Annotated[float, Field(gt=0.0)]


class SweepPoint(_Strict):
    """The knob values of one point (None: the base config's value)."""

    method: Method = "variational"
    iterations: Iterations | None = None
    num_entries: NumEntries | None = None
    num_samples: NumSamples | None = None
    downscale: Downscale | None = None
    ensemble_size: EnsembleSize | None = None
    spawn_fraction: SpawnFraction | None = None


class SweepAxes(_Strict):
    """Values to try per knob (an empty list leaves the knob at the default)."""

    method: list[Method] = []
    iterations: list[Iterations] = []
    num_entries: list[NumEntries] = []
    num_samples: list[NumSamples] = []
    downscale: list[Downscale] = []
    ensemble_size: list[EnsembleSize] = []
    spawn_fraction: list[SpawnFraction] = []


class SweepScene(_Strict):
    """One scene of a multi-scene sweep (``[scenes.NAME]``): exactly one of ``path``, ``photos`` or ``synth``."""

    path: Path | None = None
    """A scene or ``reconstruct`` workspace, as ``train`` reads it."""
    photos: Path | None = None
    """A folder of photos: ``reconstruct`` runs once (in the driver) into ``OUT/scenes/NAME``."""
    reconstruct: dict[str, Any] = {}
    """ReconstructConfig keys for ``photos``."""
    synth: dict[str, Any] | None = None
    """SynthConfig keys: the synthetic scene is generated into ``OUT/scenes/NAME``."""
    train_preset: str | None = None
    """The preset of this scene's points (None: the spec's ``train_preset``)."""
    train: dict[str, Any] = {}
    """TrainConfig keys over the spec's ``train`` (e.g. ``{ scene = { downscale = 2.0 } }``)."""
    evaluate: dict[str, Any] = {}
    """EvalConfig keys over the spec's ``evaluate``."""
    default: dict[str, Any] = {}
    """Knobs over the spec's ``[default]`` on this scene (e.g. ``{ iterations = 3000 }``): the axes vary around it."""

    @model_validator(mode="after")
    def _one_source(self) -> SweepScene:
        given = [k for k in ("path", "photos", "synth") if getattr(self, k) is not None]
        if len(given) != 1:
            raise ValueError(f"a scene needs exactly one of path, photos or synth (got {', '.join(given) or 'none'})")
        if self.reconstruct and self.photos is None:
            raise ValueError("`reconstruct` keys only apply to a `photos` scene")
        unknown = sorted(set(self.default) - set(SweepPoint.model_fields))
        if unknown:
            import difflib

            close = [c for k in unknown for c in difflib.get_close_matches(k, KNOBS, n=1, cutoff=0.6)]
            guess = f"did you mean {' or '.join(close)}? " if close else ""
            raise ValueError(f"unknown knob(s) in `default`: {', '.join(unknown)} ({guess}knobs: {', '.join(KNOBS)})")
        return self


_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_-]*$")


class SweepSpec(_Strict):
    """A sweep (``pipelines/tradeoff.toml``; ``uncertsplat sweep SPEC -o OUT``)."""

    name: str = "sweep"
    scene: Path | None = None
    """Scene folder; None generates the synthetic scene of ``synth`` into OUT/scene (single-scene sweeps)."""
    scenes: dict[str, SweepScene] = {}
    """Named scenes: every point runs on each (then ``scene`` and ``synth`` are not used)."""
    seeds: list[int] = []
    """Training and evaluation seeds: every point runs once per seed (empty: the configs' own seed, once)."""
    synth: dict[str, Any] = {"preset": "demo", "seed": 0}
    """SynthConfig keys used when ``scene`` is not given."""
    train_preset: str | None = "demo"
    train: dict[str, Any] = {}
    """TrainConfig keys over the preset (the base of every point)."""
    evaluate: dict[str, Any] = {}
    """EvalConfig keys (the base of every point; save_maps is ignored: sweeps write no maps)."""
    design: Literal["axes", "grid"] = "axes"
    schedule: Literal["scaled", "fixed"] = "scaled"
    default: SweepPoint = SweepPoint()
    axes: SweepAxes = SweepAxes()
    pareto_x: str = "time"
    pareto_y: list[str] = ["ause_mae", "nll"]

    @field_validator("scenes")
    @classmethod
    def _scene_names(cls, v: dict[str, SweepScene]) -> dict[str, SweepScene]:
        for name in v:
            if not _NAME.match(name):
                raise ValueError(f"scene name {name!r}: use letters, digits, '_' and '-' (it names folders and ids)")
        return v

    @field_validator("pareto_x", "pareto_y")
    @classmethod
    def _pareto_metrics(cls, v: str | list[str]) -> str | list[str]:
        from uncertsplat.sweep.pareto import TABLE_KEYS

        unknown = [m for m in ([v] if isinstance(v, str) else v) if m not in TABLE_KEYS]
        if unknown:
            raise ValueError(f"unknown metric {', '.join(map(repr, unknown))}; the table's metrics are "
                             f"{', '.join(TABLE_KEYS)}")
        return v

    @field_validator("seeds")
    @classmethod
    def _seed_values(cls, v: list[int]) -> list[int]:
        if any(s < 0 for s in v) or len(set(v)) != len(v):
            raise ValueError(f"seeds must be distinct and non-negative, got {v}")
        return v

    @model_validator(mode="after")
    def _one_scene_source(self) -> SweepSpec:
        if self.scenes and self.scene is not None:
            raise ValueError("give either `scene` or `[scenes.NAME]` tables, not both")
        for name, entry in self.scenes.items():
            try:
                SweepPoint(**{**self.default.model_dump(), **entry.default})
            except ValueError as err:
                raise ValueError(f"scenes.{name}.default: {err}") from None
        return self

    def on_scene(self, scene: str | None) -> SweepSpec:
        """This spec with ``[default]`` as it is on ``scene`` (its ``default`` knobs over the spec's)."""
        if scene is None or not self.scenes[scene].default:
            return self
        point = SweepPoint(**{**self.default.model_dump(), **self.scenes[scene].default})
        return self.model_copy(update={"default": point})

    def scene_names(self) -> list[str | None]:
        """The scenes every point runs on (``[None]``: the single ``scene`` / ``synth`` scene)."""
        return list(self.scenes) or [None]

    def seed_values(self) -> list[int | None]:
        """The seeds every point runs with (``[None]``: the configs' own seed)."""
        return list(self.seeds) or [None]


def load_spec(path: Path, overrides: list[str] | None = None) -> SweepSpec:
    """Read a sweep TOML (``key=value`` overrides as for ``--set``) into a validated ``SweepSpec``."""
    from uncertsplat.config import load_toml, parse_override

    data = load_toml(path)
    base = Path(path).resolve().parent  # paths written in the file are read from its folder (as in pipelines)

    def anchored(v):
        return str(base / v) if isinstance(v, str) and not Path(v).is_absolute() else v

    if "scene" in data:
        data["scene"] = anchored(data["scene"])
    scenes = data.get("scenes")
    if scenes == {}:  # written but empty: the sweep would silently run on the synthetic demo scene
        raise UserError("the spec's [scenes] table names no scene", path=path,
                        hint="Add [scenes.NAME] tables (each with path, photos or synth), or remove [scenes].")
    for entry in (scenes.values() if isinstance(scenes, dict) else ()):  # not a table: the validation says so
        if isinstance(entry, dict):
            for key in ("path", "photos"):
                if key in entry:
                    entry[key] = anchored(entry[key])
    replaced: set[str] = set()
    for o in overrides or []:
        parsed = parse_override(o)
        replaced |= dotted_keys(parsed)
        data = deep_update(data, parsed)
    where = KeyLines(path, replaced=replaced)
    given = [k for k in ("scene", "scenes") if data.get(k)]
    if given and "synth" in data and (given[0] in replaced or any(k.startswith(given[0] + ".") for k in replaced)):
        data.pop("synth")  # a scene set with --set replaces the file's synthetic one, as --scene does
    elif given and "synth" in data:  # written in the file together: one would be left unused without a word
        line = where.line("synth")
        raise UserError(f"the spec gives both `{given[0]}` and `synth`" + (f" (line {line})" if line else "")
                        + ": `synth` generates the scene when the spec names none, so it would not be used",
                        path=path, hint=f"Remove `synth`, or `{given[0]}` to sweep the synthetic scene.")
    empty = [f"axes.{k}" for k, v in (data.get("axes") or {}).items() if v == []]
    empty += ["seeds"] if data.get("seeds") == [] else []
    if empty:
        from uncertsplat.console import console

        console.print(f"[yellow]note:[/] {', '.join(empty)} = [] "
                      + ("leave" if len(empty) > 1 else "leaves") + " the knob at its default, as leaving "
                      + ("them" if len(empty) > 1 else "it") + " out does (seeds = []: the configs' own seed, once)")
    with naming_overrides(overrides):
        spec = build_config(SweepSpec, data, source=str(path), where=where)
        check_base_configs(spec, str(path), where)
    return spec


def check_base_configs(spec: SweepSpec, source: str, lines: KeyLines | None = None) -> None:
    """The spec's ``train_preset``, ``train``, ``evaluate``, ``synth`` and ``reconstruct`` keys (and each scene's) as
    configs, so that a mistake is refused when the spec is read, named where it is in the file (``lines``: its
    lines), rather than when a point's job (or the scene's generation or reconstruction) builds its configs."""
    from uncertsplat.config import TRAIN_PRESETS, ReconstructConfig, SynthConfig

    tables = [(None, "")] + [(name, f"scenes.{name}.") for name in spec.scenes]
    if not spec.scenes and spec.scene is None:  # the single synthetic scene
        build_config(SynthConfig, spec.synth, source=source, key_prefix="synth", where=lines)
    for name, where in tables:
        entry = spec.scenes[name] if name is not None else None
        own_preset = entry is not None and entry.train_preset is not None
        preset = entry.train_preset if own_preset else spec.train_preset
        if preset is not None and preset not in TRAIN_PRESETS:
            key = f"{where if own_preset else ''}train_preset"
            number = lines.line(key) if lines is not None else None
            raise UserError(f"invalid configuration in {source}: {key}"
                            + (f" (line {number})" if number is not None else "")
                            + f": unknown preset '{preset}' (presets: {', '.join(TRAIN_PRESETS)})")
        for key, model in (("synth", SynthConfig), ("reconstruct", ReconstructConfig)):
            table = getattr(entry, key) if entry is not None else None
            if table:
                build_config(model, table, source=source, key_prefix=f"{where}{key}", where=lines)
        for key, own, model in (("train", spec.train, TrainConfig), ("evaluate", spec.evaluate, EvalConfig)):
            data = deep_update(own, getattr(entry, key)) if entry is not None else own
            label = source
            if key == "train" and preset is not None:  # the preset's keys under the table's, as train_config_from
                label = f"{source} (preset {preset})"
                data = deep_update(TRAIN_PRESETS[preset], data)
            try:
                model.model_validate(data)
            except ValidationError as err:
                # a key of the scene's own table is named there; one of the spec's shared table, there
                inner = getattr(entry, key) if entry is not None else {}
                prefix = f"{where}{key}" if entry is not None and _mentions(inner, err) else key
                raise UserError(format_validation_error(err, label, model, key_prefix=prefix, where=lines)) from None


def _mentions(table: dict, err: ValidationError) -> bool:
    """True when the first error's key path starts in ``table``."""
    loc = err.errors()[0]["loc"]
    return bool(loc) and loc[0] in table


def expand_points(spec: SweepSpec) -> list[SweepPoint]:
    """The points of a spec, default first, without duplicates (same knob values)."""
    d = spec.default.model_dump()
    axes = {k: v for k, v in spec.axes.model_dump().items() if v}
    pts: list[dict] = [d]
    if spec.design == "grid" and axes:
        keys = list(axes)
        for combo in itertools.product(*(axes[k] for k in keys)):
            pts.append({**d, **dict(zip(keys, combo, strict=True))})
    else:
        for k, values in axes.items():
            pts += [{**d, k: v} for v in values]
    seen, out = set(), []
    for p in pts:
        key = json.dumps(p, sort_keys=True)
        if key not in seen:
            seen.add(key)
            out.append(SweepPoint(**p))
    return out


def _scaled_schedule(data: dict, base: TrainConfig, iterations: int) -> dict:
    """Scale the step-based schedule of ``base`` to ``iterations`` steps (keys into ``data``)."""
    f = iterations / base.iterations
    dz = base.densify

    def s(v: int) -> int:
        return max(1, round(v * f))

    sched = {"start": s(dz.start) if dz.start else 0, "until": s(dz.until),
             "spawn_interval": s(dz.spawn_interval),
             "opacity_reset_interval": s(dz.opacity_reset_interval) if dz.opacity_reset_interval else 0}
    return deep_update(data, {"iterations": iterations, "sh_degree_interval": s(base.sh_degree_interval),
                              "densify": sched})


def point_configs(spec: SweepSpec, point: SweepPoint, scene: str | None = None,
                  seed: int | None = None) -> tuple[TrainConfig, EvalConfig]:
    """The resolved train and eval configs of ``point`` (on the spec's scene ``scene``, with ``seed``)."""
    from uncertsplat.baselines import method_overrides

    entry = spec.scenes[scene] if scene is not None else None
    preset = entry.train_preset if entry is not None and entry.train_preset is not None else spec.train_preset
    train_keys = deep_update(spec.train, entry.train) if entry is not None else spec.train
    if seed is not None:
        train_keys = deep_update(train_keys, {"seed": seed})
    base = train_config_from(preset, train_keys)
    data = json.loads(base.model_dump_json())
    if point.iterations is not None and point.iterations != base.iterations:
        if base.init_ply is not None:  # (0 steps: the scaled schedule divided by them)
            raise UserError(f"the sweep's train settings give a model trained elsewhere (init_ply), which trains no "
                            f"step, and a point asks for {point.iterations} steps",
                            hint="Sweep the iterations of models trained here, or leave the iterations knob out.")
        data = (_scaled_schedule(data, base, point.iterations) if spec.schedule == "scaled"
                else deep_update(data, {"iterations": point.iterations}))
    if point.num_entries is not None:
        data = deep_update(data, {"variational": {"num_entries": point.num_entries}})
    if point.downscale is not None:
        data = deep_update(data, {"scene": {"downscale": point.downscale}})
    if point.ensemble_size is not None:
        data["ensemble_size"] = point.ensemble_size
    if point.spawn_fraction is not None:
        data = deep_update(data, {"densify": {"spawn_scale_fraction": point.spawn_fraction}})
    data = deep_update(data, method_overrides(point.method))  # vi-single's K_table = 1 wins
    tcfg = build_config(TrainConfig, data, source=f"sweep point {point_id(point)}")
    if not tcfg.has_offset_tables:
        # no offset tables: K_table and the spawn rule do not matter, so points differing only in them share a run
        densify = tcfg.densify.model_copy(update={"spawn_scale_fraction": base.densify.spawn_scale_fraction})
        tcfg = tcfg.model_copy(update={"variational": TrainConfig().variational, "densify": densify})
    elif tcfg.posterior == "informed" and point.num_entries is not None:
        # the informed posterior stores one table entry whatever K_table says: its K_table points share a run
        tcfg = tcfg.model_copy(update={"variational": tcfg.variational.model_copy(
            update={"num_entries": base.variational.num_entries})})
    if tcfg.method != "ensemble":
        tcfg = tcfg.model_copy(update={"ensemble_size": TrainConfig().ensemble_size,
                                       "ensemble_members": TrainConfig().ensemble_members})
    edata = deep_update(spec.evaluate, entry.evaluate) if entry is not None else dict(spec.evaluate)
    edata = deep_update(edata, {"save_maps": False} if seed is None else {"save_maps": False, "seed": seed})
    if tcfg.method == "ensemble" and tcfg.ensemble_members == "deterministic":  # K = N: each member once
        edata["num_samples"] = tcfg.ensemble_size
    elif point.num_samples is not None:
        edata["num_samples"] = point.num_samples
    ecfg = build_config(EvalConfig, edata, source=f"sweep point {point_id(point)}")
    return tcfg, ecfg


KNOB_KEYS = {"method": ("train", "method"), "num_entries": ("train", "variational.num_entries"),
              "downscale": ("train", "scene.downscale"), "ensemble_size": ("train", "ensemble_size"),
              "spawn_fraction": ("train", "densify.spawn_scale_fraction"), "num_samples": ("evaluate", "num_samples")}
"""Each knob's key in the spec's ``train`` / ``evaluate`` tables, which ``point_configs`` may replace with the knob's
value (``iterations`` is not among them: the spec's ``train.iterations`` is the schedule the knob's steps scale)."""


def shadowed_settings(spec: SweepSpec) -> list[str]:
    """The spec's ``train`` / ``evaluate`` keys (also a scene's) of a knob that no point of the sweep uses: every
    point resolves (``point_configs``) to the same configs with the key as without it, because the knob's value
    replaces it, as "evaluate.num_samples = 3 (the knob `num_samples`)". They had no effect,
    and the sweep recorded the spec's value as if used. A knob left unset in ``[default]``, the informed posterior's
    one table entry, a point without offset tables: the spec's value is used there, and nothing is named."""
    def pop(table: dict, dotted: str):
        *parents, last = dotted.split(".")
        node: Any = table
        for part in parents:
            if not isinstance(node, dict) or part not in node:
                return None
            node = node[part]
        return node.pop(last, None) if isinstance(node, dict) else None

    def resolved(sp: SweepSpec) -> list[str]:
        return [tcfg.model_dump_json() + ecfg.model_dump_json() for name in sp.scene_names()
                for point in expand_points(sp.on_scene(name)) for tcfg, ecfg in [point_configs(sp, point, name)]]

    base = None
    out: list[str] = []
    places = [(None, "")] + [(name, f"scenes.{name}.") for name in spec.scenes]
    for knob, (where, dotted) in KNOB_KEYS.items():
        for scene, prefix in places:
            data = spec.model_dump()  # (a fresh copy: the key is taken out of it)
            given = pop((data if scene is None else data["scenes"][scene])[where], dotted)
            if given is None or given == getattr(spec.on_scene(scene).default, knob):
                continue  # (the knob's own value given again: nothing lost)
            base = resolved(spec) if base is None else base
            if resolved(type(spec).model_validate(data)) == base:
                out.append(f"{prefix}{where}.{dotted} = {given} (the knob `{knob}`)")
    return out


def point_id(point: SweepPoint, scene: str | None = None, seed: int | None = None) -> str:
    """A readable, file-name-safe id: the scene (if named), method, the knobs that are set and the seed (if set)."""
    parts = [point.method]
    for key, tag in (("iterations", "it"), ("num_entries", "kt"), ("num_samples", "k"), ("downscale", "ds"),
                     ("ensemble_size", "n"), ("spawn_fraction", "sf")):
        if key == "ensemble_size" and point.method != "ensemble":
            continue  # N only matters to ensembles
        v = getattr(point, key)
        if v is not None:
            parts.append(f"{tag}{v:g}" if isinstance(v, float) else f"{tag}{v}")
    if seed is not None:
        parts.append(f"seed{seed}")
    return (f"{scene}." if scene is not None else "") + "_".join(parts)


def make_jobs(spec: SweepSpec, out_dir: Path, scene: Path | dict[str, Path], device: str,
              threads: int | None = None) -> list[dict]:
    """Group the points by scene and training config into independent jobs (plain dicts, JSON-serialisable).

    Args:
        scene: the scene folder of a single-scene spec, or ``{name: folder}`` for each of ``spec.scenes``.

    Each job: ``{"job_id", "scene", "scene_name", "seed", "run_dir", "device", "threads", "train_config",
    "method_label", "points": [{"id", "hash", "knobs", "eval_config", "is_default"}]}``; run folders are
    ``OUT/runs/JOB`` (``OUT/runs/SCENE/JOB`` for named scenes).
    """
    from uncertsplat.baselines import method_label

    folders = dict(scene) if isinstance(scene, dict) else {None: Path(scene)}
    if set(folders) != set(spec.scene_names()):
        raise ValueError(f"scene folders for {sorted(map(str, folders))}, the spec names {spec.scene_names()}")
    points = {name: expand_points(spec.on_scene(name)) for name in spec.scene_names()}
    jobs: dict[str, dict] = {}
    seen: set[str] = set()
    for name, seed, p in ((n, k, p) for n, k in itertools.product(spec.scene_names(), spec.seed_values())
                          for p in points[n]):
        default = points[name][0]
        tcfg, ecfg = point_configs(spec, p, name, seed)
        tdata = json.loads(tcfg.model_dump_json())
        edata = json.loads(ecfg.model_dump_json())
        # a named scene is part of what a point is (the same configs on two scenes are two points); a single-scene
        # spec keeps the hashes it always had, so its sweeps resume
        phash = hash_config({"train": tdata, "eval": edata} if name is None else
                            {"scene": name, "train": tdata, "eval": edata})
        if phash in seen:
            continue  # knobs that do not matter to this method (e.g. N for a variational point)
        seen.add(phash)
        is_default = p == default
        if p.num_samples is not None and p.num_samples != ecfg.num_samples:
            p = p.model_copy(update={"num_samples": ecfg.num_samples})  # the K used (an ensemble's is its N)
        thash = hash_config(tdata)
        label = method_label(tcfg)
        job_id = f"{label}_{thash[:8]}" if name is None else f"{name}.{label}_{thash[:8]}"
        run_dir = Path(out_dir) / "runs" / (job_id if name is None else Path(name) / f"{label}_{thash[:8]}")
        job = jobs.setdefault(job_id, {
            "job_id": job_id, "scene": str(Path(folders[name]).resolve()), "scene_name": name, "seed": seed,
            "run_dir": str(run_dir.resolve()), "device": device, "threads": threads, "train_config": tdata,
            "method_label": label, "points": []})
        job["points"].append({"id": point_id(p, name, seed), "hash": phash,
                              "knobs": p.model_dump(), "eval_config": edata,
                              "is_default": is_default})
    return list(jobs.values())
