"""Two writers on one run folder: the second refuses clearly; a lock left by a dead process is taken over;
processes racing for one folder (also for a stale lock) never both hold it.
(The CLI case, a second `train` while one trains, is in test_interrupt.py.)"""

from __future__ import annotations

import contextlib
import json
import subprocess
import sys

import pytest

from tests.fixtures import tiny_scene_path  # noqa: F401
from tests.reliability.helpers import ROOT, env
from tests.run_fixtures import tiny_run_path  # noqa: F401
from uncertsplat.errors import UserError
from uncertsplat.io.atomic import lock_holder, run_lock

_HOLD = """
import sys, time
from uncertsplat.io.atomic import run_lock
print("holding", flush=True)
with run_lock(sys.argv[1], "test"):
    print("locked", flush=True)
    sys.stdin.readline()
"""


def test_live_holder_refuses_second_writer_with_its_pid(tmp_path):
    with _held_by_another_process(tmp_path) as holder:
        with pytest.raises(UserError) as err:
            with run_lock(tmp_path, "second"):
                pass
        msg = str(err.value)
        assert f"PID {holder.pid}" in msg and str(tmp_path) in msg and "another uncertsplat process" in msg
        assert (tmp_path / ".lock").read_text(encoding="utf-8").split()[0] == str(holder.pid)  # untouched by the refusal
    assert not (tmp_path / ".lock").exists()
    with run_lock(tmp_path):  # free again
        pass


@pytest.mark.parametrize("content", ["999999 train\n", "", "garbage", "1 init\n"])
def test_stale_lock_is_taken_over(tmp_path, content):
    """A lock file nobody holds (dead PID, empty, garbage, even a live unrelated PID) is taken over."""
    (tmp_path / ".lock").write_text(content)
    with run_lock(tmp_path, "train") as lock:
        import os

        assert lock.read_text(encoding="utf-8").split()[0] == str(os.getpid())
    assert not (tmp_path / ".lock").exists()


def test_lock_of_a_sigkilled_process_is_taken_over(tmp_path):
    holder = subprocess.Popen([sys.executable, "-c", _HOLD, str(tmp_path)], env=env(), cwd=ROOT,
                              stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    assert holder.stdout.readline().strip() == "holding"
    assert holder.stdout.readline().strip() == "locked"
    holder.kill()
    holder.wait(timeout=60)
    assert (tmp_path / ".lock").exists()
    with run_lock(tmp_path):
        pass


_RACE = """
import json, os, sys, time
from uncertsplat.errors import UserError
from uncertsplat.io.atomic import run_lock
folder, start = sys.argv[1], float(sys.argv[2])
while time.time() < start:
    time.sleep(0.001)
for _ in range(20):
    try:
        with run_lock(folder, "race"):
            t0 = time.time()
            time.sleep(0.02)
            print(json.dumps([t0, time.time()]), flush=True)
    except UserError:
        time.sleep(0.003)
"""


def test_racing_processes_never_hold_the_lock_together(tmp_path):
    import time

    (tmp_path / ".lock").write_text("999999 stale\n")  # they also race to take over a stale lock
    start = time.time() + 3.0
    procs = [subprocess.Popen([sys.executable, "-c", _RACE, str(tmp_path), str(start)], env=env(), cwd=ROOT,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for _ in range(4)]
    spans = []
    for p in procs:
        out, errs = p.communicate(timeout=120)
        assert p.returncode == 0, errs
        spans += [json.loads(line) for line in out.splitlines()]
    assert len(spans) >= 4
    spans.sort()
    for (a0, a1), (b0, b1) in zip(spans, spans[1:], strict=False):
        assert b0 >= a1, f"two holders at once: {a0}-{a1} and {b0}-{b1}"
    assert not (tmp_path / ".lock").exists()


@contextlib.contextmanager
def _held_by_another_process(folder):
    """``folder``'s lock held by a live process (``_HOLD``) for the duration."""
    holder = subprocess.Popen([sys.executable, "-c", _HOLD, str(folder)], env=env(), cwd=ROOT,
                              stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "holding"
        assert holder.stdout.readline().strip() == "locked"
        yield holder
    finally:
        holder.communicate("\n", timeout=60)


def test_a_second_pipeline_on_one_output_folder_is_refused(tmp_path):
    """`uncertsplat run` holds its output folder: a second one there (which moved the first one's stage folders,
    their locks with them, to .previous while it trained) is refused before it touches anything; an output path
    that is a file, or lies under one, is named as such."""
    from uncertsplat.stages import pipeline

    out = tmp_path / "out"
    (out / "train").mkdir(parents=True)
    (out / "train" / "kept.txt").write_text("the first run's")
    with _held_by_another_process(out), pytest.raises(UserError, match="another uncertsplat process"):
        pipeline.run(ROOT / "pipelines" / "smoke.toml", out)
    assert (out / "train" / "kept.txt").read_text(encoding="utf-8") == "the first run's" and not (out / ".previous").exists()
    (tmp_path / "afile").write_text("")
    with pytest.raises(UserError, match="the output path is a file, not a folder"):
        pipeline.run(ROOT / "pipelines" / "smoke.toml", tmp_path / "afile")
    with pytest.raises(UserError, match="cannot create the folder: .*afile is a file"):
        pipeline.run(ROOT / "pipelines" / "smoke.toml", tmp_path / "afile" / "out")


def test_prune_refuses_a_run_in_training(tiny_run_path, tmp_path):  # noqa: F811
    """A run that a live process holds (a training going on) is not pruned: its model is about to change."""
    import shutil

    from uncertsplat.config import PruneConfig
    from uncertsplat.stages import prune

    run = tmp_path / "run"
    shutil.copytree(tiny_run_path, run)
    with _held_by_another_process(run) as holder:
        assert lock_holder(run) == f"PID {holder.pid}, test"
        with pytest.raises(UserError, match=rf"another uncertsplat process \(PID {holder.pid}, test\) is working on this run"):
            prune.run(run, tmp_path / "out", PruneConfig(keep_ratio=0.9, num_samples=2), "cpu")
    assert not (tmp_path / "out").exists()
    # a reader takes no lock: none held, none made (a read-only run can be pruned, two prunes of one run both run)
    assert lock_holder(run) is None and lock_holder(tmp_path / "nowhere") is None
    prune.run(run, tmp_path / "out", PruneConfig(keep_ratio=0.9, num_samples=2, score_views=2, score_samples=2,
                                               render_views=1, dry_run=True), "cpu")
    assert not (run / ".lock").exists()


def test_a_training_that_is_starting_is_not_taken_for_a_failed_start(tiny_scene_path, tmp_path):  # noqa: F811
    """Until its first step a starting run holds only config.json and scene.json, as a start that failed does: a
    second `train` there is refused by the folder's lock and deletes nothing."""
    import torch

    from uncertsplat.config import train_config_from
    from uncertsplat.stages import train

    run = tmp_path / "run"
    run.mkdir()
    (run / "config.json").write_text("{}")
    (run / "scene.json").write_text("{}")
    cfg = train_config_from("tiny", None, ["iterations=2", "scene.downscale=4.0"])
    with _held_by_another_process(run), pytest.raises(UserError, match="another uncertsplat process"):
        train.run(tiny_scene_path, run, cfg, torch.device("cpu"))
    assert (run / "config.json").read_text(encoding="utf-8") == "{}" and (run / "scene.json").read_text(encoding="utf-8") == "{}"


def test_the_lock_refusal_names_the_holder_s_command(tmp_path):
    with _held_by_another_process(tmp_path) as holder, pytest.raises(UserError) as err:
        with run_lock(tmp_path, "second"):
            pass
    assert f"(PID {holder.pid}, test)" in str(err.value) and "Wait for it to finish" in err.value.hint


def test_a_pipeline_does_not_replace_a_stage_folder_another_process_writes(tmp_path, monkeypatch):
    """`train --resume` of the pipeline's run by hand, then `uncertsplat run` with a changed setting: the pipeline
    moved the run to .previous and trained its own into the same path while the other kept writing there (their
    stats.jsonl interleaved, a config of 300 steps beside a summary of 6000). Refused before anything moves."""
    from uncertsplat.stages import pipeline as pl

    def fake(kind, cfg, up_path, out_dir, device, kwargs):
        out_dir.mkdir(parents=True, exist_ok=True)
        (out_dir / "out.txt").write_text(kind)

    monkeypatch.setattr(pl, "_run_stage", fake)
    p = tmp_path / "p.toml"
    p.write_text('name = "t"\ndevice = "cpu"\n[[stages]]\nstage = "synth"\nconfig = { preset = "tiny" }\n'
                 '[[stages]]\nstage = "train"\npreset = "tiny"\n')
    out = tmp_path / "out"
    pl.run(p, out)
    with _held_by_another_process(out / "train") as holder:
        with pytest.raises(UserError, match=rf"stage 'train' would replace .*train, which another uncertsplat "
                                            rf"process \(PID {holder.pid}, test\) is writing now"):
            pl.run(p, out, overrides=["train.iterations=9"])
        assert (out / "train" / "out.txt").is_file() and not (out / ".previous" / "train").exists()
    pl.run(p, out, overrides=["train.iterations=9"])  # free again: the stage runs, the earlier run kept aside
    assert (out / ".previous" / "train" / "out.txt").is_file()


def test_a_sweep_neither_trains_into_nor_deletes_a_run_another_process_writes(tmp_path, monkeypatch):
    """A sweep found a run of its own extended by hand (another config.json) and removed it with shutil.rmtree,
    while that `train --resume` was still writing it: a run another process holds is left alone (the point fails,
    said), and one of other settings is moved aside, not deleted."""
    import uncertsplat.baselines as baselines
    from uncertsplat.config import train_config_from
    from uncertsplat.sweep import jobs

    run = tmp_path / "runs" / "variational_x"
    run.mkdir(parents=True)
    (run / "config.json").write_text(json.dumps({"iterations": 6000}))
    job = {"run_dir": str(run), "job_id": "variational_x", "scene": str(tmp_path),
           "train_config": json.loads(train_config_from("tiny").model_dump_json())}
    with _held_by_another_process(run) as holder:
        with pytest.raises(UserError, match=rf"another uncertsplat process \(PID {holder.pid}, test\) holds this "
                                            "point's run now"):
            jobs._train(job, "cpu")
    assert json.loads((run / "config.json").read_text(encoding="utf-8")) == {"iterations": 6000}
    # a finished run of the sweep's own settings that another process only reads (an evaluate holds its lock too) is
    # reused as before
    done = tmp_path / "runs" / "variational_done"
    done.mkdir()
    (done / "config.json").write_text(json.dumps(job["train_config"]))
    (done / "train_summary.json").write_text("{}")
    monkeypatch.setattr(jobs.TrainSummary, "read", classmethod(lambda cls, path: "the finished summary"))
    with _held_by_another_process(done):
        assert jobs._train({**job, "run_dir": str(done)}, "cpu") == ("the finished summary", False, None)
    monkeypatch.undo()

    class Trained(Exception):
        pass

    def fake_train(*args, **kwargs):
        raise Trained

    monkeypatch.setattr(baselines, "train_run", fake_train)
    with pytest.raises(Trained):
        jobs._train(job, "cpu")
    assert json.loads((run.parent / "variational_x.replaced" / "config.json").read_text(encoding="utf-8")) == {"iterations": 6000}
    run.mkdir()  # changed by hand again: the earlier replaced run stays
    (run / "config.json").write_text(json.dumps({"iterations": 7000}))
    with pytest.raises(Trained):
        jobs._train(job, "cpu")
    assert json.loads((run.parent / "variational_x.replaced" / "config.json").read_text(encoding="utf-8")) == {"iterations": 6000}
    assert json.loads((run.parent / "variational_x.replaced2" / "config.json").read_text(encoding="utf-8")) == {"iterations": 7000}
