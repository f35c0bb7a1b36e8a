"""Where a sweep's jobs run: this machine's cores (``local``) or a Ray cluster (``ray``).

Both take the jobs of ``sweep.spec.make_jobs`` and hand every finished job's records (``sweep.jobs.run_job``)
to ``on_records`` in the driver, which alone appends them to ``sweep.jsonl``. Both retry: a job whose worker
died (killed, out of memory) or whose records failed is run again, up to ``retries`` more times, and then its
records are kept as failed with the last error. The other jobs go on meanwhile.

- ``local``: one job at a time in this process (``jobs = 1``), else a process pool of fresh processes (one
  per job, one torch thread each). Needs nothing beyond the package.
- ``ray``: every job is a Ray task asking for ``cpus_per_job`` CPUs and ``gpus_per_job`` GPUs (the job gets as
  many torch threads). ``address`` None starts a local Ray instance with this machine's cores; ``"auto"`` (or
  ``ray://...``) joins a running cluster, whose workers must reach the scene and the output folder at the same
  paths (a shared filesystem). Ray is an optional dependency (``pip install 'uncertsplat[ray]'``).

Ctrl-C cancels what has not finished (the local Ray instance is shut down, or the tasks on a joined cluster
cancelled; the pool's workers stopped) and leaves the finished records in ``sweep.jsonl``.
"""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import threading
import traceback
from collections.abc import Callable, Iterator
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from multiprocessing import get_context

from uncertsplat.errors import Interrupted, UserError, require_extra

EXECUTORS = ("local", "ray")

OnRecords = Callable[[list[dict]], None]
OnStart = Callable[[dict], None]


def failed_records(job: dict, error: str, stage: str = "worker") -> list[dict]:
    """One failed record per point of ``job`` (the job's worker died, or every retry failed)."""
    return [{"id": p["id"], "hash": p["hash"], "job": job["job_id"], "knobs": p["knobs"], "method": job["method_label"],
             "scene": job.get("scene_name"), "seed": job.get("seed"),
             "is_default": p["is_default"], "status": "failed", "stage": stage, "error": error}
            for p in job["points"]]


def _retry_needed(records: list[dict]) -> bool:
    return any(r.get("status") != "ok" for r in records)


def _with_attempts(records: list[dict], attempts: int) -> list[dict]:
    for r in records:
        r["attempts"] = attempts
    return records


def _settle(job: dict, recs: list[dict], attempt: int, retries: int, resubmit: Callable[[dict], None],
            on_records: OnRecords) -> None:
    """Run ``job`` again when its records failed and retries are left, else report them with the attempt count."""
    if _retry_needed(recs) and attempt <= retries:
        resubmit(job)
    else:
        on_records(_with_attempts(recs, attempt))


def run_local(todo: list[dict], *, jobs: int, retries: int, on_records: OnRecords,
              on_start: OnStart | None = None, run_job: Callable[[dict], list[dict]] | None = None) -> None:
    """Run ``todo`` on this machine (see the module docstring)."""
    if run_job is None:
        from uncertsplat.sweep.jobs import run_job
    if jobs == 1 or len(todo) <= 1:
        for job in todo:
            for attempt in range(1, retries + 2):
                if on_start:
                    on_start(job)
                try:
                    recs = run_job(job)
                except Interrupted:
                    raise
                except Exception as err:  # run_job reports its own failures; this is a bug or an interrupt-free crash
                    recs = failed_records(job, f"{type(err).__name__}: {err}\n{traceback.format_exc(limit=4)}")
                if not _retry_needed(recs) or attempt == retries + 1:
                    on_records(_with_attempts(recs, attempt))
                    break
        return
    for job in todo:
        job["threads"] = 1  # jobs share the cores: oversubscribing threads only slows them all
    ctx = get_context("spawn")  # no fork of a process holding torch threads
    workers = min(jobs, len(todo))
    # the sweep stops: each worker's training stops as on Ctrl-C (_worker_stops_quietly_on_ctrl_c); a raw shared
    # flag, polled: an Event's set() waits for every waiter to wake, and hung on a worker that had exited
    stop = ctx.RawValue("b", 0)
    with ProcessPoolExecutor(max_workers=workers, mp_context=ctx, max_tasks_per_child=1,
                             initializer=_worker_stops_quietly_on_ctrl_c, initargs=(stop, os.getpid())) as pool:
        attempts: dict[str, int] = {}
        futures = {}
        waiting = list(todo)

        def submit(job: dict) -> None:
            attempts[job["job_id"]] = attempts.get(job["job_id"], 0) + 1
            if on_start:
                on_start(job)
            # the pool starts its workers in the thread that submits (and in its manager thread, which the first
            # submit starts): with SIGINT blocked there, they start with it blocked (_sigint_blocked)
            with _sigint_blocked():
                futures[pool.submit(_run_in_worker, run_job, job)] = job

        def fill() -> None:
            # a job is handed to the pool only when a worker is free: the pool's own queue cannot be taken back,
            # and on Ctrl-C a queued job started a whole training in a worker spawned after the signal
            while waiting and len(futures) < workers:
                submit(waiting.pop(0))

        try:
            fill()
            while futures:
                done, _ = wait(list(futures), return_when=FIRST_COMPLETED)
                for fut in done:
                    job = futures.pop(fut)
                    try:
                        recs = fut.result()
                    except (Interrupted, SystemExit):  # a worker's job stopped on a signal: the sweep stops too
                        raise KeyboardInterrupt from None
                    except Exception as err:  # the worker died (e.g. out of memory, killed)
                        recs = failed_records(job, f"{type(err).__name__}: {err}")
                    _settle(job, recs, attempts[job["job_id"]], retries, submit, on_records)
                fill()
        except KeyboardInterrupt:
            for fut in futures:
                fut.cancel()
            stop.value = 1
            # wait for the workers, which stop at once (a training one after its step and checkpoint): without the
            # wait the pool's manager thread failed on the pool it was still adjusting (a traceback)
            pool.shutdown(wait=True, cancel_futures=True)
            raise


@contextlib.contextmanager
def _sigint_blocked() -> Iterator[None]:
    """SIGINT blocked in this thread for the duration (a Ctrl-C meanwhile is delivered when it ends).

    A process, and a thread, started meanwhile inherits the block, so a pool worker starting then cannot die of a
    Ctrl-C before ``_worker_stops_quietly_on_ctrl_c`` sets it up: a worker that exits without a job's result marks
    the pool broken, and the pool then kills every other worker (SIGTERM), one writing its training's checkpoint
    after that same Ctrl-C included (the resume then went back to the last periodic checkpoint)."""
    if not hasattr(signal, "pthread_sigmask"):  # (not POSIX)
        yield
        return
    old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


def _worker_stops_quietly_on_ctrl_c(stop=None, driver: int | None = None) -> None:
    """Ctrl-C reaches every process of the terminal's group, pool workers included. A worker *between jobs* (idle,
    or just started) ignores it: had it exited, the pool, seeing a worker die without a job's result, would have
    marked itself broken and killed every other worker (SIGTERM), among them those writing their training's
    checkpoint after the same Ctrl-C; the driver ends idle workers itself when it shuts the pool down. While a job
    runs (``_run_in_worker``) Ctrl-C ends it quietly: SystemExit(130), sent back as the job's outcome (an idle
    worker printed KeyboardInterrupt's traceback). A training job installs its own handler while it trains (the step
    finishes, a checkpoint is written, then it stops) and restores the job's after.

    The worker starts with SIGINT blocked (``_sigint_blocked``): it is ignored here first, then unblocked, so a
    Ctrl-C that came while the worker started is dropped.

    ``stop`` (a shared flag of the driver's, ``RawValue``): set to 1 when the sweep stops for any reason the workers
    did not see (Ctrl-C to the driver alone, ``kill -INT``), it stops the worker's training the same way
    (``train.trainer.STOP_REQUESTED``) without a second signal, which would act mid-step after the terminal's
    first.

    The driver gone without a word (``kill -9``, the OOM killer): its workers were left waiting for jobs forever
    (and a training one trained on to its end). The same watch sees the worker's parent change, stops a training
    the same way (its checkpoint written, so the next sweep resumes it) and ends the worker once no job runs.
    ``driver``: the driver's PID, passed in: a worker still starting when the driver died read its new parent as its
    own and waited forever."""
    import time

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if hasattr(signal, "pthread_sigmask"):
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
    parent = os.getppid() if driver is None else driver

    def watch() -> None:
        while True:
            time.sleep(0.1)
            orphaned = os.getppid() != parent
            if orphaned and not _BUSY.is_set():
                os._exit(1)
            if orphaned or (stop is not None and stop.value):
                from uncertsplat.train.trainer import STOP_REQUESTED  # (torch: imported only when needed)

                STOP_REQUESTED.set()

    threading.Thread(target=watch, daemon=True, name="sweep-stop").start()


_BUSY = threading.Event()
"""Set in a pool worker while it runs a job (``_run_in_worker``): an orphaned worker ends only between jobs."""


def _run_in_worker(run_job: Callable[[dict], list[dict]], job: dict) -> list[dict]:
    """``run_job(job)`` in a pool worker, with Ctrl-C ending it quietly (see ``_worker_stops_quietly_on_ctrl_c``);
    ignored again once it is done, until the worker's next job."""
    signal.signal(signal.SIGINT, _exit_quietly)
    _BUSY.set()
    try:
        return run_job(job)
    finally:
        _BUSY.clear()
        signal.signal(signal.SIGINT, signal.SIG_IGN)


def _exit_quietly(signum, frame) -> None:
    raise SystemExit(130)


def require_ray():
    """Import ray, or raise one UserError with the install command."""
    return require_extra("ray", feature="--executor ray", extra="ray")


RAY_PROBE_SECONDS = 5.0
"""How long ``connect_ray`` waits for a TCP connection to a cluster's address before it calls it unreachable."""

_NOT_REACHED_HINT = ("Start it on the head node (ray start --head) and run the sweep there with --address auto, or "
                     "leave --address out to use this machine only.")


def _host_port(address: str) -> tuple[str, int] | None:
    """(host, port) of a Ray address ``HOST:PORT``, ``ray://HOST:PORT`` or ``[IPv6]:PORT``; None for one without
    a port (``auto``, ``local``), which Ray itself resolves."""
    rest = address.strip().removeprefix("ray://")
    host, sep, port = rest.rpartition(":")
    if not sep or not host or not port.isdigit():
        return None
    return host.strip("[]"), int(port)


def _probe(address: str, timeout: float) -> None:
    """Raise one UserError when nothing answers at ``address``'s host and port within ``timeout`` seconds. Ray's own
    attempt at an unreachable address retries for minutes while its C++ client prints a warning every few seconds
    (2 minutes and 9 warnings without an answer for 127.0.0.1:6399, Ray 2.60)."""
    target = _host_port(address)
    if target is None:
        return
    try:
        with socket.create_connection(target, timeout=timeout):
            pass
    except OSError as err:
        where = f"{target[0]}:{target[1]}"
        reason = (f"no answer at {where} within {timeout:g} s" if isinstance(err, TimeoutError)
                  else f"{(err.strerror or str(err)).lower()} at {where}")
        raise UserError(f"cannot reach the Ray cluster at {address!r} ({reason})", hint=_NOT_REACHED_HINT) from None


def connect_ray(address: str | None, num_cpus: int | None = None) -> bool:
    """Start a local Ray instance (``address`` None; ``num_cpus`` CPUs, default all) or join the cluster at
    ``address``, unless this process is connected already; True when this call connected. A cluster that cannot be
    reached is one UserError with what to do (``sweep`` calls this before it prepares any scene): an address with a
    port is tried first with a plain TCP connection (``RAY_PROBE_SECONDS``), so a wrong one fails in seconds."""
    ray = require_ray()
    if ray.is_initialized():
        return False
    if address is not None:
        _probe(address, RAY_PROBE_SECONDS)
    kwargs = dict(include_dashboard=False, log_to_driver=False, configure_logging=False)
    try:
        if address is None:
            ray.init(num_cpus=num_cpus, **kwargs)
        else:
            ray.init(address=address, **kwargs)
    except ConnectionError as err:
        raise UserError(f"cannot reach the Ray cluster at {address!r} ({err})", hint=_NOT_REACHED_HINT) from None
    except ValueError as err:  # e.g. a ray:// address without Ray's client package: Ray's message says what to install
        where = f"connect to {address!r}" if address is not None else "start on this machine"
        raise UserError(f"Ray cannot {where}: {err}") from None
    return True


def run_ray(todo: list[dict], *, address: str | None, cpus_per_job: float, gpus_per_job: float, retries: int,
            on_records: OnRecords, on_start: OnStart | None = None, num_cpus: int | None = None,
            run_job: Callable[[dict], list[dict]] | None = None) -> None:
    """Run ``todo`` as Ray tasks (see the module docstring).

    ``num_cpus`` (a local instance only): the CPUs it may use (default: all of this machine's).
    """
    ray = require_ray()
    if run_job is None:
        from uncertsplat.sweep.jobs import run_job
    started_here = connect_ray(address, num_cpus)
    total = ray.cluster_resources()
    if cpus_per_job > total.get("CPU", 0) or gpus_per_job > total.get("GPU", 0):
        if started_here:
            ray.shutdown()
        raise UserError(f"a job asks for {cpus_per_job:g} CPUs and {gpus_per_job:g} GPUs, and the Ray cluster has "
                        f"{total.get('CPU', 0):g} CPUs and {total.get('GPU', 0):g} GPUs in all, so it would never run",
                        hint="Lower --cpus-per-job / --gpus-per-job, or add nodes with those resources.")
    # every retry is the loop's (a dead worker and failed records alike), so a job runs at most retries + 1 times
    task = ray.remote(num_cpus=cpus_per_job, num_gpus=gpus_per_job, max_retries=0)(run_job)
    attempts: dict[str, int] = {}
    pending: dict = {}

    def submit(job: dict) -> None:
        attempts[job["job_id"]] = attempts.get(job["job_id"], 0) + 1
        job = {**job, "threads": max(1, int(cpus_per_job))}
        if on_start:
            on_start(job)
        pending[task.remote(job)] = job

    try:
        for job in todo:
            submit(job)
        while pending:
            # with a timeout: a blocking ray.wait holds Ctrl-C back until the next job ends (minutes for a real
            # job); Python runs the SIGINT handler between the short waits
            done, _ = ray.wait(list(pending), num_returns=1, timeout=0.5)
            for ref in done:
                job = pending.pop(ref)
                try:
                    recs = ray.get(ref)
                except Exception as err:  # the worker died (Ray does not retry it: max_retries=0) or the task raised
                    recs = failed_records(job, f"{type(err).__name__}: {str(err)[:2000]}")
                _settle(job, recs, attempts[job["job_id"]], retries, submit, on_records)
    except KeyboardInterrupt:
        # A local instance of our own is shut down below, which ends its workers. Cancelling their tasks first
        # races with tasks that are just finishing: Ray's core worker then aborts the process ("Tried to
        # complete task that was not pending"), so the user gets a crash instead of a clean stop. On a
        # cluster we joined, the tasks must be cancelled, or they would run on.
        if not (started_here and address is None):
            for ref in pending:
                ray.cancel(ref, force=True)
        raise
    finally:
        if started_here:
            ray.shutdown()


__all__ = ["EXECUTORS", "connect_ray", "failed_records", "require_ray", "run_local", "run_ray"]
