"""Damaged files: checkpoints, PLY, run JSON files and COLMAP models, truncated or with flipped bits.

Each case is detected (checksum or structural validation) and reported as a ``UserError`` that names the
file; ``--resume`` falls back to the previous good checkpoint and says so.
"""

from __future__ import annotations

import json
import random
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from tests.fixtures import tiny_scene_path  # noqa: F401
from tests.reliability.helpers import ROOT, env, flip_bit, temp_leftovers, truncate
from uncertsplat.config import train_config_from
from uncertsplat.errors import UserError
from uncertsplat.io.checkpoints import CorruptCheckpoint, checkpoint_path, list_checkpoints, load_checkpoint

SMALL = {"iterations": 6, "checkpoint_every": 2, "keep_checkpoints": 5, "eval_every": 100000, "log_every": 1,
         "scene": {"downscale": 4.0, "max_points": 150}, "densify": {"start": 100000}}


def small_config(**extra):
    data = json.loads(json.dumps(SMALL))
    data.update(extra)
    return train_config_from("tiny", data)


@pytest.fixture(scope="module")
def small_run(tiny_scene_path, tmp_path_factory) -> Path:
    """A finished 6-step run with checkpoints at steps 2, 4 and 6 (read-only: copy before damaging)."""
    from uncertsplat.stages import train

    out = tmp_path_factory.mktemp("corruption") / "run"
    train.run(tiny_scene_path, out, small_config(), device=torch.device("cpu"))
    return out


def _copy(run: Path, tmp_path: Path) -> Path:
    dst = tmp_path / "run"
    shutil.copytree(run, dst)
    return dst


# --------------------------------------------------------------------------------------- checkpoints
def _damages(size: int, rng: random.Random) -> list[tuple[str, object]]:
    cases: list[tuple[str, object]] = [("empty", 0.0), ("truncated to 8 bytes", 8), ("truncated to header", 44)]
    cases += [(f"truncated at {f:.0%}", f) for f in (0.1, 0.5, 0.9, 0.999)]
    cases += [(f"bit flip at byte {o}", ("flip", o)) for o in (0, 7, 9, 12, 20, 43, 44)]
    cases += [(f"bit flip at byte {o}", ("flip", o)) for o in rng.sample(range(44, size), 25)]
    cases += [("garbage", "garbage"), ("a foreign torch file", "foreign")]
    return cases


def _apply(path: Path, damage) -> None:
    if damage == "garbage":
        path.write_bytes(bytes(random.Random(1).randrange(256) for _ in range(4096)))
    elif damage == "foreign":
        torch.save({"weights": torch.zeros(3)}, path)
    elif isinstance(damage, tuple):
        flip_bit(path, damage[1], bit=damage[1] % 8)
    elif isinstance(damage, int):
        path.write_bytes(path.read_bytes()[:damage])
    else:
        truncate(path, damage)


def test_every_damaged_checkpoint_is_detected_and_named(small_run, tmp_path):
    src = checkpoint_path(small_run, 6)
    cases = _damages(src.stat().st_size, random.Random(0))
    assert len(cases) >= 35
    for what, damage in cases:
        p = tmp_path / "step_000006.pt"
        shutil.copyfile(src, p)
        _apply(p, damage)
        with pytest.raises(CorruptCheckpoint) as err:
            load_checkpoint(p)
        assert str(p) in str(err.value), what


def test_resume_falls_back_to_previous_good_checkpoint_and_says_so(small_run, tmp_path, capsys):
    from uncertsplat.stages import train

    run = _copy(small_run, tmp_path)
    (run / "variational.ply").unlink()
    flip_bit(checkpoint_path(run, 6), 5000)
    truncate(checkpoint_path(run, 4), 0.5)
    capsys.readouterr()
    scene = Path(json.loads((run / "scene.json").read_text(encoding="utf-8"))["scene"])
    train.run(scene, run, small_config(), device=torch.device("cpu"), resume=True)
    err = " ".join(capsys.readouterr().err.split())
    assert "step_000006.pt: checksum mismatch" in err and "step_000004.pt: checksum mismatch" in err, err
    assert "trying the previous checkpoint" in err
    assert "step_000002.pt (step 2)" in err
    # the damaged checkpoints were replaced by good ones as training went on again
    assert [s for s, _ in list_checkpoints(run)] == [2, 4, 6]
    for _, p in list_checkpoints(run):
        load_checkpoint(p)
    stats = [json.loads(line)["step"] for line in (run / "stats.jsonl").read_text(encoding="utf-8").splitlines()]
    assert [s for s in stats if s] == [1, 2, 3, 4, 5, 6]


def test_a_damaged_checkpoint_past_the_model_file_leaves_the_model_file_in_use(small_run, tmp_path, capsys):
    """A run trained on (`--resume --iterations N`) and stopped keeps its newest checkpoint beside the PLY of its
    earlier end; with that checkpoint damaged and none past the PLY left (keep_checkpoints = 1), every command
    refused the run as holding 'neither variational.ply nor a checkpoint'. The PLY is its newest good model."""
    from uncertsplat.baselines import load_run

    run = _copy(small_run, tmp_path)
    shutil.copyfile(checkpoint_path(run, 6), checkpoint_path(run, 8))  # (as keep_checkpoints = 1 leaves it)
    for step in (2, 4, 6):
        checkpoint_path(run, step).unlink()
    flip_bit(checkpoint_path(run, 8), 5000)
    capsys.readouterr()
    loaded = load_run(run)
    assert loaded.source == run / "variational.ply" and loaded.step == 6
    assert "step_000008.pt: checksum mismatch" in " ".join(capsys.readouterr().err.split())


@pytest.mark.parametrize("harm", ["nan", "inconsistent"])
def test_a_checkpoint_past_the_model_file_without_a_usable_model_leaves_the_model_file_in_use(small_run, tmp_path,
                                                                                               capsys, harm):
    """A checkpoint past the PLY whose checksum is good but whose model is not usable (a NaN, tables that do not fit
    the parameters: written by other code) was refused, though the PLY beside it is a good model: it is used, with a
    warning naming the checkpoint, as where every checkpoint past it is damaged."""
    from uncertsplat.baselines import load_run
    from uncertsplat.io.checkpoints import load_checkpoint, save_checkpoint

    run = _copy(small_run, tmp_path)
    state = load_checkpoint(checkpoint_path(run, 6))
    state["step"] = 8
    if harm == "nan":
        state["model"]["params"]["means"][0, 0] = float("nan")
    else:
        state["model"]["params"]["means"] = state["model"]["params"]["means"][:-1]
    save_checkpoint(run, 8, state, keep=10)
    capsys.readouterr()
    loaded = load_run(run)
    assert loaded.source == run / "variational.ply" and loaded.step == 6
    err = " ".join(capsys.readouterr().err.split())
    assert "warning:" in err and "step_000008.pt" in err and "the model of step 6" in err


def test_a_short_file_or_another_format_version_is_refused_by_decode():
    """``decode`` itself (not only ``load_checkpoint``, which turns any error into ``CorruptCheckpoint``): the magic
    with a header cut short, and a checksummed payload of another format version, older or newer."""
    import struct

    from uncertsplat.io.checkpoints import MAGIC, VERSION, decode, encode

    good = encode({"step": 3, "x": torch.arange(4)})
    assert decode(good)["step"] == 3
    for short in (MAGIC, MAGIC + b"\x01\x00", good[:43]):
        with pytest.raises(CorruptCheckpoint, match="bad header"):
            decode(short)
    for version in (VERSION - 1, VERSION + 1):
        other = good[:8] + struct.pack("<I", version) + good[12:]
        with pytest.raises(CorruptCheckpoint, match=f"format {version} is not supported"):
            decode(other)


def test_checkpoints_are_listed_by_step_kept_newest_and_loaded_newest_first(tmp_path, capsys):
    """``list_checkpoints``: only files named ``step_N.pt`` (not a temporary file or a folder of that name), oldest
    first whatever the file system's order; ``save_checkpoint`` keeps the newest ``keep`` and never the file it has
    just written, even when it is older than those (a resumed run saving an earlier step); ``load_latest`` takes
    the newest that loads."""
    from uncertsplat.io.checkpoints import checkpoint_dir, load_latest, save_checkpoint

    run = tmp_path / "run"
    for step in (12, 3, 100, 7):
        save_checkpoint(run, step, {"step": step}, keep=0)
    (checkpoint_dir(run) / "step_000200.pt.tmp").write_bytes(b"partial")
    (checkpoint_dir(run) / "step_000300.pt").mkdir()
    assert [s for s, _ in list_checkpoints(run)] == [3, 7, 12, 100]
    save_checkpoint(run, 50, {"step": 50}, keep=2)
    assert [s for s, _ in list_checkpoints(run)] == [50, 100]
    save_checkpoint(run, 20, {"step": 20}, keep=1)  # older than the newest kept: still there afterwards
    assert [s for s, _ in list_checkpoints(run)] == [20, 100]
    checkpoint_path(run, 100).write_bytes(b"damaged")
    path, state = load_latest(run)
    assert path == checkpoint_path(run, 20) and state["step"] == 20
    assert "trying the previous checkpoint" in capsys.readouterr().err


def test_damaged_run_config_is_reported_not_a_traceback(small_run, tmp_path):
    from uncertsplat.baselines import load_run
    from uncertsplat.stages import train

    run = _copy(small_run, tmp_path)
    scene = Path(json.loads((run / "scene.json").read_text(encoding="utf-8"))["scene"])
    truncate(run / "config.json", 0.5)
    # the advice leads out: neither `train --resume` nor a plain `train` into the run writes the file again (a new
    # user's audit followed "re-run uncertsplat train" in a circle)
    written_once = "written when its training (or prune) starts and read first by every command"
    with pytest.raises(UserError, match="config.json") as err:
        train.run(scene, run, small_config(), device=torch.device("cpu"), resume=True)
    assert written_once in err.value.hint and "new folder" in err.value.hint
    with pytest.raises(UserError, match="config.json") as err:
        load_run(run)
    assert written_once in err.value.hint
    shutil.copyfile(small_run / "config.json", run / "config.json")
    for damage in (lambda p: truncate(p, 0.5), lambda p: p.write_text("{}")):
        damage(run / "scene.json")
        with pytest.raises(UserError, match="scene.json") as err:
            load_run(run)
        assert written_once in err.value.hint and "--config RUN/config.json" in err.value.hint
    assert not (run / ".lock").exists()


# ----------------------------------------------------------------------------------------------- PLY
def test_damaged_variational_ply_is_detected(small_run, tmp_path):
    from uncertsplat.io.ply import read_variational_ply

    src = small_run / "variational.ply"
    model, meta = read_variational_ply(src)
    assert "sha256" in meta
    data = src.read_bytes()
    header = data.index(b"end_header\n") + len(b"end_header\n")
    rng = random.Random(0)
    cases = [("empty", 0.0)] + [(f"truncated at {f:.0%}", f) for f in (0.05, 0.5, 0.99)]
    cases += [(f"bit flip at {o}", ("flip", o)) for o in rng.sample(range(header, len(data)), 20)]
    for what, damage in cases:
        p = tmp_path / "variational.ply"
        shutil.copyfile(src, p)
        _apply(p, damage)
        with pytest.raises(UserError) as err:
            read_variational_ply(p)
        assert str(p) in str(err.value), what


# ------------------------------------------------------------------------------------- metrics.json
def test_damaged_metrics_json_is_left_out_of_the_report_with_a_note(small_run, tmp_path):
    from uncertsplat.report.loader import load_run

    run = _copy(small_run, tmp_path)
    (run / "eval").mkdir()
    (run / "eval" / "metrics.json").write_text('{"mean": {"psnr": 20.0, "ause_mae": 0.1}, "per_view": {"a')
    (run / "stats.jsonl").write_text((small_run / "stats.jsonl").read_text(encoding="utf-8") + '{"step": 7, "lo')
    data = load_run(run)
    assert data.metrics is None
    notes = " ".join(data.notes)
    assert "metrics.json" in notes and "stats.jsonl" in notes, notes
    (run / "eval" / "metrics.json").write_bytes(b'{"mean": {"psnr": 2\xb0.0}}')  # a flipped high bit
    data = load_run(run)
    assert data.metrics is None and "metrics.json" in " ".join(data.notes)


# ------------------------------------------------------------------------------------- COLMAP model
_COLMAP_FUZZ = r"""
import json, random, shutil, sys
from pathlib import Path
from uncertsplat.config import SceneConfig
from uncertsplat.errors import UserError
from uncertsplat.sfm.scene import load_scene
src, work, n = Path(sys.argv[1]), Path(sys.argv[2]), int(sys.argv[3])
rng = random.Random(0)
cases = []
for f in ("cameras.bin", "images.bin", "points3D.bin"):
    size = (src / "sparse/0" / f).stat().st_size
    # flips are bit positions (byte * 8 + bit): here in the record count of the file
    cases += [(f, "zero", 0), (f, "trunc", size // 2), (f, "trunc", size - 1), (f, "flip", 3 * 8), (f, "flip", 7 * 8 + 6)]
# the track length of the first 3D point, the 2D point count of the first image ("view_000.png")
cases += [("points3D.bin", "flip", (8 + 43 + 4) * 8 + 1), ("images.bin", "flip", (8 + 64 + 13 + 3) * 8 + 2)]
while len(cases) < n:
    f = rng.choice(["cameras.bin", "images.bin", "points3D.bin"])
    size = (src / "sparse/0" / f).stat().st_size
    kind = rng.choice(["trunc", "flip", "flip"])
    cases.append((f, kind, rng.randrange(size) * (8 if kind == "flip" else 1) + rng.randrange(8)))
for i, (f, kind, where) in enumerate(cases):
    dst = work / f"s{i}"
    shutil.copytree(src, dst, ignore=shutil.ignore_patterns("depth", "masks"))
    p = dst / "sparse/0" / f
    data = bytearray(p.read_bytes())
    if kind == "flip":
        data[(where // 8) % len(data)] ^= 1 << (where % 8)
    else:
        data = data[:where]
    p.write_bytes(bytes(data))
    try:
        load_scene(dst, SceneConfig())
        out = {"result": "ok"}
    except UserError as e:
        out = {"result": "error", "names_file": str(dst) in str(e), "message": str(e)}
    except Exception as e:
        out = {"result": "crash", "message": repr(e)}
    print(json.dumps({"file": f, "kind": kind, **out}), flush=True)
    shutil.rmtree(dst)
"""


def test_damaged_colmap_model_is_detected_never_hangs(tiny_scene_path, tmp_path):
    n = 40
    proc = subprocess.run([sys.executable, "-c", _COLMAP_FUZZ, str(tiny_scene_path), str(tmp_path), str(n)],
                          env=env(), cwd=ROOT, capture_output=True, text=True, timeout=240)
    assert proc.returncode == 0, proc.stderr[-3000:]
    rows = [json.loads(line) for line in proc.stdout.splitlines()]
    assert len(rows) == n
    assert not [r for r in rows if r["result"] == "crash"], rows
    assert all(r["names_file"] for r in rows if r["result"] == "error"), rows
    structural = [r for r in rows if r["kind"] in ("zero", "trunc")]
    assert all(r["result"] == "error" for r in structural), structural
    # a flipped bit inside a float (a coordinate, a focal length) cannot be told from a real value; every
    # flip in a count or size is caught: at least the 8 targeted ones
    assert sum(r["result"] == "error" for r in rows if r["kind"] == "flip") >= 8


def test_no_temp_files_left_by_the_fixture_run(small_run):
    assert not temp_leftovers(small_run)
