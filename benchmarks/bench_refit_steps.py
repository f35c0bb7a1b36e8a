"""How many steps the growth test's copies need: its cost read after fewer steps on the same copies (issue 19).

The growth test (``Trainer._refit_cost``) trains two copies of the training ``densify.growth_refit_steps`` steps
(100), the whole model and the model without its weakest half, and compares their renders of the training views.
This script trains a scene on its configuration as ``train`` does and, at every growth test, also reads the
copies' cost after each of ``--lengths`` steps (renders of the same views, which change nothing of the copies), so
every length is read on the very copies the test makes: whether a shorter re-fit would have decided as the
configured one did (cost below ``growth_min_gain_db``, cost above ``growth_skip_factor`` times it), and the copies'
time. The run itself is the configured one (the test decides on its own length).

    .venv/bin/python benchmarks/bench_refit_steps.py --scene tiny --label tiny
    .venv/bin/python benchmarks/bench_refit_steps.py --scene WS --preset paper --label fern \\
        --set scene.downscale=1.5873 --stop-step 1750

Writes ``benchmarks/results/refit_steps_{label}.json`` after every test and prints one row per test.
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import time
import types
from datetime import date
from pathlib import Path

import torch
from _common import RESULTS, refuse_overwrite
from bench_growth_refit import scene_arguments, train_scene

from uncertsplat.config import train_config_from
from uncertsplat.strategy.view_checks import gain_db, sum_squared_error
from uncertsplat.train import trainer as trainer_module


def _finite_or_none(value: float) -> float | None:
    return value if math.isfinite(value) else None


def instrumented(rows: list[dict], lengths: list[int], stop_step: int, out: Path, meta: dict) -> None:
    """``Trainer._refit_cost`` that also reads the copies' squared errors after each of ``lengths`` steps."""
    refit_cost, fork = trainer_module.Trainer._refit_cost, trainer_module.Trainer._fork

    def measured(self, step, off, views, images, masks):
        sse: dict[int, list[float]] = {n: [] for n in lengths}
        reading = [0.0]  # seconds spent reading (not the test's own)

        def forked(self_, step_, remove=None):
            f = fork(self_, step_, remove)
            done = [0]
            train_step = f.train_step

            def counted():
                result = train_step()
                done[0] += 1
                if done[0] in sse:
                    t0 = time.perf_counter()
                    with torch.no_grad():
                        sse[done[0]].append(sum_squared_error(f.mean_sample(), f.train_cams[views], images,
                                                              lambda s, cam: f.render(s, cam).rgb, masks))
                    reading[0] += time.perf_counter() - t0
                return result

            f.train_step = counted
            return f

        self._fork = types.MethodType(forked, self)
        t0 = time.perf_counter()
        try:
            cost = refit_cost(self, step, off, views, images, masks)
        finally:
            del self._fork
        seconds = time.perf_counter() - t0 - reading[0]
        if cost is None:  # a stop came in during the copies: no test (the run stops after this step)
            return cost
        dcfg = self.cfg.densify
        # (a copy that could not train reads +inf: null in the JSON, which has no infinity)
        row = {"step": step, "gaussians": len(self.model), "half": int(off.sum()),
               "configured_steps": dcfg.growth_refit_steps, "cost_db": _finite_or_none(cost),
               "copies_seconds": seconds,
               "costs_db": {str(n): _finite_or_none(gain_db(*v)) for n, v in sse.items() if len(v) == 2},
               "threshold_db": dcfg.growth_threshold_db, "skip_factor": dcfg.growth_skip_factor}
        rows.append(row)
        reads = "  ".join(f"{n}: {c:6.3f}" if c is not None else f"{n}: none" for n, c in row["costs_db"].items())
        print(f"step {step:5d}  N {len(self.model):8,d}  cost after {reads}  (test {cost:.3f} dB, copies "
              f"{seconds:.1f} s)", flush=True)
        out.write_text(json.dumps({**meta, "tests": rows}, indent=1))
        if step >= stop_step:
            self._stop = True
        return cost

    trainer_module.Trainer._refit_cost = measured


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    scene_arguments(ap)
    ap.add_argument("--lengths", type=int, nargs="+", default=[25, 50, 100],
                    help="copy steps after which the cost is read (at most densify.growth_refit_steps)")
    ap.add_argument("--stop-step", type=int, default=10**9, help="stop the run after the test at this step")
    ap.add_argument("--machine", default=platform.processor() or platform.machine())
    args = ap.parse_args()
    out = RESULTS / f"refit_steps_{args.label}.json"
    refuse_overwrite(out, overwrite=args.overwrite)
    cfg = train_config_from(args.preset, None, args.overrides)
    if max(args.lengths) > cfg.densify.growth_refit_steps:
        raise SystemExit(f"--lengths: at most densify.growth_refit_steps ({cfg.densify.growth_refit_steps})")
    meta = {"label": args.label, "scene": str(args.scene), "preset": args.preset, "overrides": args.overrides,
            "lengths": args.lengths, "machine": args.machine, "torch": torch.__version__,
            "date": date.today().isoformat()}
    rows: list[dict] = []
    instrumented(rows, sorted(set(args.lengths)), args.stop_step, out, meta)
    RESULTS.mkdir(parents=True, exist_ok=True)
    train_scene(args.scene, cfg, args.device)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
