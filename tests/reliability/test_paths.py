"""Paths with spaces and non-ASCII characters, relative and absolute; nothing written outside the folder named."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from tests.fixtures import tiny_scene_path  # noqa: F401
from tests.reliability.helpers import FAST, logged_steps, run_cli, snapshot, temp_leftovers

NAMES = ["my scène ☃", "données d'essai", "画像 フォルダ"]


@pytest.mark.parametrize("relative", [True, False], ids=["relative", "absolute"])
def test_train_with_unicode_and_spaces_writes_only_into_the_named_folder(tiny_scene_path, tmp_path, relative):
    root = tmp_path / NAMES[0]
    scene = root / NAMES[1] / "scene"
    shutil.copytree(tiny_scene_path, scene)
    before = snapshot(tmp_path)
    run_rel = Path(NAMES[2]) / "run (1)"
    run = root / run_rel
    if relative:
        res = run_cli("train", Path(NAMES[1]) / "scene", "-o", run_rel, *FAST, "--set", "iterations=3", cwd=root)
    else:
        res = run_cli("train", scene.resolve(), "-o", run.resolve(), *FAST, "--set", "iterations=3", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert logged_steps(run) == [1, 2, 3]
    after = snapshot(tmp_path)
    created = {p for p in after if p not in before}
    changed = {p for p in before if after.get(p) != before[p]}
    prefix = str(run.relative_to(tmp_path))
    assert not changed, f"files outside the run folder changed: {sorted(changed)}"
    assert created and all(p.startswith(prefix + "/") for p in created), sorted(created)
    assert not temp_leftovers(tmp_path)
    info = json.loads((run / "scene.json").read_text(encoding="utf-8"))
    assert Path(info["scene"]) == scene.resolve()  # stored absolute, so later stages find it from anywhere


def test_missing_unicode_path_is_named_in_the_error(tmp_path):
    missing = tmp_path / "pas là ✗" / "scène"
    res = run_cli("train", missing, "-o", tmp_path / "sortie", *FAST)
    assert res.returncode == 2 and "Traceback" not in res.stderr
    assert "pas là ✗" in res.stderr
    assert not (tmp_path / "sortie").exists()


def test_names_near_the_file_system_limit_are_written(tmp_path):
    """A legal name of 220-255 characters made the temporary sibling's name (``.NAME.XXXXXXXX.tmp``) longer than the
    file system's 255 and ended a write in a traceback (prune's only after it had scored and evaluated): the temporary
    name keeps the start and a hash of a long one, whole up to 100 characters."""
    import tempfile

    from uncertsplat.io.atomic import TEMP_STEM, atomic_write_text, temp_stem

    long_name = "n" * 250 + ".json"
    written = atomic_write_text(tmp_path / long_name, "{}\n")
    assert written.read_text(encoding="utf-8") == "{}\n" and [p.name for p in tmp_path.iterdir()] == [long_name]  # no temp left
    assert temp_stem("short") == "short" and len(temp_stem("x" * 255)) == TEMP_STEM
    assert temp_stem("x" * 255) != temp_stem("x" * 254)  # two long names stay apart
    # a folder's staging sibling (prune, synth, reconstruct's model): the same stem
    folder = Path(tempfile.mkdtemp(prefix=f".{temp_stem('d' * 250)}.tmp-host-1-", dir=tmp_path))
    assert folder.is_dir() and len(folder.name) < 255
