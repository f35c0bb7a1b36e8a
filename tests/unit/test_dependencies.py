"""The package's imports against pyproject.toml's dependencies: a user who installs the package without the
development extra has every module a command imports, and no dependency is installed for nothing."""

from __future__ import annotations

import ast
import importlib.metadata
import re
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

OPTIONAL = {
    "viser": "the `view` extra (`uncertsplat view`, `train --view`), imported through errors.require_extra",
    "ray": "the `ray` extra (`sweep --executor ray`), imported through errors.require_extra",
    "lpips": "LPIPS, found by importlib.util.find_spec and reported unavailable without it (eval.image)",
}
"""Modules the package may import without declaring them as runtime dependencies, and why."""


def _normalised(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def _declared(section: str | None = None) -> set[str]:
    """The distribution names of pyproject.toml's runtime dependencies (or of the optional ``section``)."""
    project = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"]
    specs = project["dependencies"] if section is None else project["optional-dependencies"][section]
    return {_normalised(re.split(r"[<>=!~ \[;]", spec, maxsplit=1)[0]) for spec in specs}


def _imported(root: Path) -> dict[str, list[Path]]:
    """Every top-level module the files under ``root`` import (at any depth of the code, absolute imports only),
    with the files that import it."""
    found: dict[str, list[Path]] = {}
    for path in sorted(root.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            else:
                continue
            for name in names:
                found.setdefault(name.split(".")[0], []).append(path)
    return found


def _third_party(found: dict[str, list[Path]]) -> dict[str, list[Path]]:
    return {m: files for m, files in found.items() if m not in sys.stdlib_module_names and m != "uncertsplat"}


class TestRuntimeDependencies:
    def test_every_module_the_package_imports_is_a_declared_dependency(self):
        """A module imported only by the development extra's packages failed for users: ``sfm.align`` imported
        scipy (the frame search of ``train --from-ply``), which only the ``dev`` extra installed."""
        declared = _declared()
        owners = importlib.metadata.packages_distributions()
        undeclared = {}
        for module, files in _third_party(_imported(ROOT / "uncertsplat")).items():
            if module in OPTIONAL:
                continue
            dists = {_normalised(d) for d in owners.get(module, [])}
            if not dists & declared:
                undeclared[module] = (sorted(dists), sorted(str(f.relative_to(ROOT)) for f in files))
        assert not undeclared, f"imported by the package, not in pyproject.toml's dependencies: {undeclared}"

    def test_every_declared_dependency_is_imported(self):
        """A runtime dependency nothing imports is installed for nothing (tomli-w was, from the first layout on)."""
        owners = importlib.metadata.packages_distributions()
        used = {_normalised(d) for module in _imported(ROOT / "uncertsplat") for d in owners.get(module, [])}
        assert _declared() <= used, sorted(_declared() - used)

    def test_the_optional_modules_come_from_their_extras_and_are_imported_inside_functions(self):
        """An optional module imported when its file is imported would make every command that imports the file
        fail without the extra; the extras named in ``OPTIONAL`` exist in pyproject.toml."""
        assert "viser" in _declared("view") and "ray" in _declared("ray")
        for path in sorted((ROOT / "uncertsplat").rglob("*.py")):
            for node in ast.parse(path.read_text(encoding="utf-8")).body:  # the module's own statements
                if isinstance(node, ast.Import):
                    names = [alias.name.split(".")[0] for alias in node.names]
                elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                    names = [node.module.split(".")[0]]
                else:
                    continue
                assert not set(names) & set(OPTIONAL), f"{path.relative_to(ROOT)} imports {names} at its top"

    def test_the_check_sees_an_import_inside_a_function(self, tmp_path):
        """The walk finds imports at any depth (scipy's was inside a method), and leaves the stdlib out."""
        pkg = tmp_path / "pkg"
        pkg.mkdir()
        (pkg / "a.py").write_text("import os\n\nclass C:\n    def f(self):\n        from scipy.spatial import cKDTree\n"
                                  "        import numpy.linalg as la\n        from . import b\n", encoding="utf-8")
        assert sorted(_third_party(_imported(pkg))) == ["numpy", "scipy"]
