"""The package's layers: a module never imports a module of a higher layer (issue 17).

Every module under ``uncertsplat/`` is parsed with ``ast``; every import counts, at any depth (function-
level imports and ``TYPE_CHECKING`` blocks included), so a lazy import cannot hide a dependency.
"""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[2] / "uncertsplat"

# The ranking, highest first: a module may import its own layer and the layers below it, never one above.
# Entries are module paths relative to ``uncertsplat`` and match the module and everything under it (the
# longest entry wins), so one package can sit on two layers (``io``). A new package must be placed here.
LAYERS: list[tuple[str, tuple[str, ...]]] = [
    # `python -m uncertsplat`: runs the command line
    ("entry point", ("__main__",)),
    # the command line: parses options, picks the device, calls one stage
    ("cli", ("cli",)),
    # the Python API for poses of one's own: evaluate's predictive (its noise fit and std factor, from stages)
    ("python api", ("predict",)),
    # one module per command: config in, files out (and the pipeline that chains them)
    ("stages", ("stages",)),
    # the browser viewer: renders any loaded run (through baselines) and colours it like the report; choosing
    # the next views scores candidates with a loaded run's posterior or the Fisher baseline's curvature
    ("view and select", ("view", "select")),
    # the speed-accuracy sweep trains and evaluates methods (through baselines)
    ("sweep", ("sweep",)),
    # every training method and the one run loader (baselines: they dispatch on the method, so they sit
    # above the engines they compose), and the HTML report (reads files through schemas)
    ("methods", ("baselines", "report")),
    # training a model into a run folder (uses the image metrics for its held-out PSNR)
    ("train", ("train",)),
    # the evaluation engine and metrics (draw K samples through uncertainty.mc)
    ("eval", ("eval",)),
    # engines over a model: Monte-Carlo maps and per-Gaussian scores, prune masks and policy, densification
    ("engines", ("uncertainty", "prune", "strategy")),
    # scenes as data: COLMAP / Blender / synthetic loaders and their pixels. One layer for both packages:
    # the synthetic generator writes a COLMAP model (data -> sfm) and the loader recognises a synthetic
    # scene (sfm -> data), the only same-layer imports allowed between packages (SAME_LAYER_OK)
    ("scenes", ("sfm", "data")),
    # files that hold Gaussians: PLY (reads and writes a GaussianModel)
    ("model files", ("io.ply",)),
    ("gaussians", ("gaussians",)),
    ("render", ("render",)),
    ("native", ("native",)),
    # the records written to disk (one pydantic model per JSON file)
    ("records", ("schemas",)),
    # what a result was computed with (versions, files' SHA-256: a prune record finds its source run by the model's)
    ("provenance", ("provenance",)),
    # files without models: atomic writes, images, checkpoint containers, the layout of evaluate's maps;
    # the configs; the device choice
    ("files and settings", ("io", "io.atomic", "io.images", "io.checkpoints", "io.maps", "config", "device")),
    # the foundation: shared tensor types, errors, conventions, console output, the version
    ("foundation", ("", "types", "errors", "conventions", "console")),
]

SAME_LAYER_OK = {("data", "sfm"), ("sfm", "data")}
"""Packages of one layer that may import each other (see the "scenes" layer); any other pair must not."""

FORBIDDEN: dict[str, tuple[str, ...]] = {
    # the pure numeric packages take tensors and plain arguments (style rule): never config or files
    "render": ("config", "io", "stages", "cli", "baselines"),
    "gaussians": ("config", "io", "stages", "cli", "baselines"),
    "eval": ("config", "io", "stages", "cli", "baselines", "data", "sfm"),
}
"""Imports refused whatever the layers say (they would be allowed by rank alone)."""

PENDING: set[tuple[str, str]] = set()
"""Known violations awaiting a change in progress: (module, imported module). Remove an entry once fixed
(the test fails on a stale entry, so the list only shrinks)."""


def _module_name(path: Path) -> str:
    rel = path.relative_to(PACKAGE).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _modules() -> dict[str, Path]:
    return {_module_name(p): p for p in sorted(PACKAGE.rglob("*.py"))}


def _resolve(name: str, known: dict[str, Path]) -> str:
    """``uncertsplat.a.b`` -> ``a.b`` (root: ""), or the longest prefix that is a module of the package."""
    parts = name.split(".")[1:]
    while parts and ".".join(parts) not in known:
        parts.pop()
    return ".".join(parts)


def _imports(path: Path, module: str, known: dict[str, Path]) -> list[tuple[int, str]]:
    """(line, imported module) of every import of an uncertsplat module in ``path``, at any depth."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    is_package = path.name == "__init__.py"
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(node.lineno, _resolve(a.name, known)) for a in node.names if a.name.split(".")[0] == "uncertsplat"]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = ["uncertsplat", *module.split(".")] if module else ["uncertsplat"]
                base = base if is_package else base[:-1]
                base = base[: len(base) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if target.split(".")[0] != "uncertsplat":
                continue
            for a in node.names:  # `from uncertsplat.x import y` imports the module x.y when there is one
                out.append((node.lineno, _resolve(f"{target}.{a.name}", known)))
    return out


def _entry(module: str) -> tuple[int, str] | None:
    """(layer index, matching entry) of a module: the longest entry that is the module or a prefix of it."""
    best = None
    for i, (_, entries) in enumerate(LAYERS):
        for e in entries:
            if module == e or (e and module.startswith(e + ".")):
                if best is None or len(e) > len(best[1]):
                    best = (i, e)
    return best


def _top(module: str) -> str:
    return module.split(".")[0]


def test_every_module_has_a_layer():
    unplaced = [m for m in _modules() if _entry(m) is None]
    assert not unplaced, f"place these modules in LAYERS (tests/unit/test_layers.py): {unplaced}"


def test_no_module_imports_a_higher_layer():
    known = _modules()
    problems, seen_pending = [], set()
    for module, path in known.items():
        placed = _entry(module)
        if placed is None:
            continue  # test_every_module_has_a_layer reports it
        rank, _ = placed
        for line, target in _imports(path, module, known):
            if _top(target) == _top(module) and target and module:
                continue  # within one package
            t_rank, _ = _entry(target)
            forbidden = any(target == f or target.startswith(f + ".") for f in FORBIDDEN.get(_top(module), ()))
            higher = t_rank < rank
            sideways = (t_rank == rank and target and module and _top(target) != _top(module)
                        and (_top(module), _top(target)) not in SAME_LAYER_OK)
            if not (higher or sideways or forbidden):
                continue
            if (module, target) in PENDING:
                seen_pending.add((module, target))
                continue
            why = ("a forbidden import" if forbidden else
                   f"same layer '{LAYERS[rank][0]}', another package" if sideways else
                   f"layer '{LAYERS[rank][0]}' imports the higher layer '{LAYERS[t_rank][0]}'")
            problems.append(f"uncertsplat/{path.relative_to(PACKAGE)}:{line}: uncertsplat.{module or '__init__'} "
                            f"imports uncertsplat.{target} ({why})")
    stale = PENDING - seen_pending
    assert not problems, "lower layers import higher ones:\n" + "\n".join(problems)
    assert not stale, f"fixed, remove from PENDING in tests/unit/test_layers.py: {sorted(stale)}"


def test_the_ranking_matches_the_issue():
    # cli > stages > sweep / baselines / report > train / eval / prune / uncertainty / strategy > gaussians
    # > render > native (issue 17); the finer ranks above only split those tiers
    order = ["cli", "stages", "sweep", "baselines", "train", "eval", "prune", "gaussians", "render", "native"]
    ranks = [_entry(m)[0] for m in order]
    assert ranks == sorted(ranks)
    assert _entry("report")[0] <= _entry("train")[0] and _entry("uncertainty")[0] == _entry("prune")[0]
    assert _entry("strategy")[0] < _entry("gaussians")[0]
