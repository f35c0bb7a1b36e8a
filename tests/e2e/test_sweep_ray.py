"""Sweeps on Ray (``sweep.executors``): a local Ray instance of 2 CPUs, no network.

The retry rules are tested with stand-in jobs (a function that raises, one that kills its worker), so they
take seconds; one real sweep on the tiny scene checks that Ray gives the local executor's records.
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import pytest

from tests.fixtures import default_sigint, tiny_scene, tiny_sweep_spec
from uncertsplat.errors import UserError
from uncertsplat.stages import sweep
from uncertsplat.sweep.executors import run_local, run_ray

ray = pytest.importorskip("ray", reason="the ray extra (pip install 'uncertsplat[ray]')")

SPEC = tiny_sweep_spec("ray-sweep", """num_samples = [1, 3, 5]
iterations = [8, 16]""")


@pytest.fixture(scope="module")
def local_ray():
    import shutil
    import tempfile

    # a short ASCII folder of its own: ray's sockets fail under a long or non-ASCII TMPDIR (a CI's)
    temp = tempfile.mkdtemp(prefix="rc", dir="/tmp")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, configure_logging=False, _temp_dir=temp)
    yield
    ray.shutdown()
    shutil.rmtree(temp, ignore_errors=True)


def _job(name: str) -> dict:
    return {"job_id": name, "method_label": "stand-in",
            "points": [{"id": f"{name}-p", "hash": name, "knobs": {}, "is_default": False}]}


def _ok(job: dict) -> list[dict]:
    p = job["points"][0]
    return [{"id": p["id"], "hash": p["hash"], "job": job["job_id"], "knobs": {}, "method": "stand-in",
             "is_default": False, "status": "ok"}]


class TestRetries:
    @pytest.mark.parametrize("executor", ["local", "ray"])
    def test_a_failing_point_is_retried_then_recorded_failed_while_the_others_finish(self, executor, local_ray,
                                                                                       tmp_path):
        calls = tmp_path / "calls"
        calls.mkdir()

        def run_job(job):
            (calls / f"{job['job_id']}-{len(list(calls.glob(job['job_id'] + '-*')))}").touch()
            if job["job_id"] == "bad":
                p = job["points"][0]
                return [{"id": p["id"], "hash": p["hash"], "job": "bad", "knobs": {}, "method": "stand-in",
                         "is_default": False, "status": "failed", "stage": "train", "error": "ValueError: boom"}]
            return _ok(job)

        got: list[dict] = []
        jobs = [_job("a"), _job("bad"), _job("b")]
        if executor == "ray":
            run_ray(jobs, address=None, cpus_per_job=1, gpus_per_job=0, retries=2, on_records=got.extend,
                    run_job=run_job)
        else:
            run_local(jobs, jobs=1, retries=2, on_records=got.extend, run_job=run_job)
        by_job = {r["job"]: r for r in got}
        assert by_job["a"]["status"] == by_job["b"]["status"] == "ok"
        assert by_job["bad"]["status"] == "failed" and "boom" in by_job["bad"]["error"]
        assert by_job["bad"]["attempts"] == 3 and by_job["a"]["attempts"] == 1
        assert len(list(calls.glob("bad-*"))) == 3

    def test_a_killed_worker_is_retried(self, local_ray, tmp_path):
        marker = tmp_path / "killed-once"

        def run_job(job):
            if not marker.exists():
                marker.touch()
                os._exit(1)  # the worker dies mid-point (as when the OOM killer takes it)
            return _ok(job)

        got: list[dict] = []
        run_ray([_job("a")], address=None, cpus_per_job=1, gpus_per_job=0, retries=1, on_records=got.extend,
                run_job=run_job)
        assert got[0]["status"] == "ok" and got[0]["attempts"] == 2

    def test_a_worker_that_always_dies_is_recorded_failed(self, local_ray):
        def run_job(job):
            os._exit(1)

        got: list[dict] = []
        run_ray([_job("a")], address=None, cpus_per_job=1, gpus_per_job=0, retries=1, on_records=got.extend,
                run_job=run_job)
        assert got[0]["status"] == "failed" and got[0]["stage"] == "worker" and got[0]["attempts"] == 2

    def test_a_request_the_cluster_cannot_meet(self, local_ray):
        with pytest.raises(UserError, match="would never run"):
            run_ray([_job("a")], address=None, cpus_per_job=1, gpus_per_job=1, retries=0, on_records=list,
                    run_job=_ok)


def test_without_ray_one_message_with_the_install_command(monkeypatch, tmp_path):
    monkeypatch.setitem(sys.modules, "ray", None)
    spec = tmp_path / "spec.toml"
    spec.write_text(SPEC)
    with pytest.raises(UserError, match=r"pip install 'uncertsplat\[ray\]'"):
        sweep.run(spec, tmp_path / "out", device="cpu", executor="ray")
    assert not (tmp_path / "out" / "sweep.jsonl").exists()


def test_ray_gives_the_local_executors_records(local_ray, tmp_path_factory, tmp_path):
    scene = tiny_scene(tmp_path_factory.getbasetemp() / "shared_scenes")
    spec = tmp_path / "spec.toml"
    spec.write_text(SPEC)
    local = sweep.run(spec, tmp_path / "local", jobs=1, device="cpu", scene=scene)
    on_ray = sweep.run(spec, tmp_path / "ray", device="cpu", scene=scene, executor="ray")
    assert local.num_points == on_ray.num_points == 4 and on_ray.num_failed == 0
    a = {r.id: r for r in local.records}
    b = {r.id: r for r in on_ray.records}
    assert a.keys() == b.keys()
    for k in a:
        assert b[k].executor == "ray" and a[k].executor == "local"
        # the same seeds give the same numbers (the native kernels do not depend on the thread count)
        for key in ("psnr", "ause_mae", "nll", "num_gaussians"):
            assert getattr(b[k], key) == pytest.approx(getattr(a[k], key), rel=1e-4, abs=1e-6), (k, key)
    # re-running skips every finished point
    again = sweep.run(spec, tmp_path / "ray", device="cpu", scene=scene, executor="ray")
    lines = (tmp_path / "ray" / "sweep.jsonl").read_text(encoding="utf-8").splitlines()
    assert len(lines) == 4 and again.num_points == 4
    assert all(json.loads(line)["status"] == "ok" for line in lines)
    assert Path(tmp_path / "ray" / "pareto.png").is_file()


CTRL_C_SPEC = """
name = "ray-ctrl-c"
seeds = [0, 1, 2, 3]
train_preset = "tiny"
train = {{ eval_every = 1000, checkpoint_every = 1000, log_every = 1000 }}
evaluate = {{ max_views = 1, num_samples = 2 }}
[default]
method = "variational"
iterations = {iterations}
downscale = 4.0
"""


def test_ctrl_c_cancels_the_ray_jobs_and_keeps_the_finished_records(tmp_path_factory, tmp_path):
    """A real `uncertsplat sweep --executor ray` subprocess, Ctrl-C once the first records are written: exit 130
    without a traceback, every line of sweep.jsonl a whole record, no Ray process of its own left; the same
    command then runs only the points that were missing."""
    import signal
    import subprocess
    import tempfile
    import time

    if not Path("/proc/self/cmdline").is_file():
        pytest.skip("reads the process table from /proc")
    scene = tiny_scene(tmp_path_factory.getbasetemp() / "shared_scenes")
    spec = tmp_path / "spec.toml"
    spec.write_text(CTRL_C_SPEC.format(iterations=200))
    out = tmp_path / "out"
    ray_tmp = tempfile.mkdtemp(prefix="rc", dir="/tmp")  # Ray's sockets need a short path
    env = {**os.environ, "RAY_TMPDIR": ray_tmp, "OMP_NUM_THREADS": "1"}
    cmd = [sys.executable, "-m", "uncertsplat.cli", "sweep", str(spec), "-o", str(out), "--scene", str(scene),
           "--device", "cpu", "--executor", "ray", "--jobs", "2", "--retries", "0"]
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            start_new_session=True, preexec_fn=default_sigint)
    log = out / "sweep.jsonl"
    t0 = time.monotonic()
    while time.monotonic() - t0 < 240 and proc.poll() is None:
        if log.is_file() and log.read_text(encoding="utf-8").strip():
            break
        time.sleep(0.2)
    assert proc.poll() is None, proc.communicate()[0][-3000:]
    assert log.is_file(), "no record within 240 s"
    proc.send_signal(signal.SIGINT)
    output = proc.communicate(timeout=120)[0]
    assert proc.returncode == 130, output[-3000:]
    assert "interrupted" in output and "Traceback" not in output, output[-3000:]
    lines = log.read_text(encoding="utf-8").splitlines()
    assert 1 <= len(lines) < 4
    recs = [json.loads(line) for line in lines]  # every line a whole record
    assert all(r["status"] == "ok" and r["executor"] == "ray" for r in recs)
    time.sleep(2.0)

    def ray_processes() -> list[str]:  # processes of this sweep's Ray instance (its temp dir is on their command line)
        found = []
        for f in Path("/proc").glob("[0-9]*/cmdline"):
            try:
                cmdline = f.read_bytes().replace(b"\0", b" ").decode(errors="replace")
            except OSError:
                continue  # gone meanwhile
            if ray_tmp in cmdline:
                found.append(cmdline[:120])
        return found

    assert not ray_processes()
    # the same command (here on the local executor: the records do not depend on it) runs only the rest
    done = {r["id"] for r in recs}
    again = sweep.run(spec, out, jobs=2, device="cpu", scene=scene)
    ids = [json.loads(line)["id"] for line in log.read_text(encoding="utf-8").splitlines()]
    assert len(ids) == 4 and len(set(ids)) == 4 and again.num_failed == 0
    assert set(ids[: len(done)]) == done


def test_an_unreachable_cluster_is_named_before_any_scene_is_made(monkeypatch, tmp_path):
    """`--address` of a cluster that is not there: one message with what to do, and no synthetic scene generated
    first (it took 15 s and was left behind in the output folder). Ray's connection is a stand-in that fails as
    ``ray.init`` does without a cluster (this module's own local instance stays up)."""
    def no_cluster(*args, **kwargs):
        raise ConnectionError("Could not find any running Ray instance")

    monkeypatch.setattr(ray, "is_initialized", lambda: False)
    monkeypatch.setattr(ray, "init", no_cluster)
    spec = tmp_path / "spec.toml"
    spec.write_text(SPEC)
    with pytest.raises(UserError, match="cannot reach the Ray cluster at 'auto'"):
        sweep.run(spec, tmp_path / "out", device="cpu", executor="ray", address="auto")
    assert not (tmp_path / "out" / "scene").exists()
