"""What the growth test would measure with the rest re-fitted, on held-out and training views (issue 19).

Trains one scene as 3DGS's densification grows it (the growth test on but with a threshold nothing reaches, and
without its own re-fit, so that the run is the same whatever this script measures), and at every growth test
copies the training three ways: A the whole model, B without the weakest half of the Gaussians that 8 training
views see (``strategy.growth.weakest_half``), C without the youngest half (the last rows: densification appends
what it adds). Each copy trains ``--refit`` steps (its midpoint measured too) with no densification, and the
script records the PSNR of each on the held-out views and on the 8 training views, beside the cost of each half
switched off without a re-fit. The differences A - B against the held-out PSNR a model size reaches at the end of
training (BENCHMARKS.md, "How many Gaussians a scene needs") show which measure, at which threshold, stops each
scene near its knee: BENCHMARKS.md, "The growth test with the rest re-fitted". The copies are plain trainers of
the checkpoint (posterior updates included), as ``train --resume`` would make; the test that landed
(``Trainer._refit_cost``) makes none.

    .venv/bin/python benchmarks/bench_growth_refit.py --scene WS --preset paper --label fern \\
        --set scene.downscale=1.5873 --stop-step 1750

Writes ``benchmarks/results/growth_refit_{label}.json`` after every test and prints one row per test.
"""

from __future__ import annotations

import argparse
import copy
import json
import platform
import tempfile
import time
from dataclasses import replace
from datetime import date
from pathlib import Path

import torch
from _common import RESULTS, add_overwrite_option, refuse_overwrite
from bench_options import scene_folder

from uncertsplat.config import train_config_from
from uncertsplat.errors import Interrupted
from uncertsplat.eval.image import psnr
from uncertsplat.gaussians import ops
from uncertsplat.stages import train as train_stage
from uncertsplat.strategy.densify import DensifyStats
from uncertsplat.strategy.growth import growth_check_due, weakest_half
from uncertsplat.strategy.view_checks import check_views
from uncertsplat.train import trainer as trainer_module
from uncertsplat.uncertainty.scores import blending_weights


@torch.no_grad()
def _psnrs(t, sample, cams, images) -> float:
    """Mean PSNR of ``sample`` rendered by trainer ``t`` over ``cams`` against ``images``."""
    return sum(float(psnr(t.render(sample, cams[i]).rgb[0].clamp(0, 1), images[i])) for i in range(len(cams))) \
        / len(cams)


def _copy(t, step: int, refit: int, remove=None) -> tuple[dict, int]:
    """A copy of trainer ``t`` at ``step`` (without the rows ``remove``), trained ``refit`` steps without
    densification; its held-out and training-view PSNRs after refit // 2 and refit steps, and its size."""
    cfg = t.cfg.model_copy(deep=True)
    cfg.densify.until = step
    c = trainer_module.Trainer(t.scene, cfg, t.train_images, t.test_images, run_dir=None,
                               state=copy.deepcopy(t.state_dict()), near=t.near)
    c.bench_copy = True
    if remove is not None:
        ops.remove(c.model, c.optimizer, remove)
        c.densifier.stats = DensifyStats.zeros(len(c.model), c.model.device)
    views = check_views(len(t.train_idx), t.cfg.densify.growth_check_views)
    out = {}
    for m in (refit // 2, refit):
        c.fit(until=step + m)
        out[f"test{m}"] = c.evaluate()["psnr"]
        out[f"train{m}"] = _psnrs(c, c.mean_sample(), c.train_cams[views], c.photos(views))
    return out, len(c.model)


def instrumented(rows: list[dict], refit: int, stop_step: int, out: Path, meta: dict):
    """``Trainer.check_growth`` that measures the copies before the test (the copies' own tests are left alone)
    and stops the run after ``stop_step``."""
    original = trainer_module.Trainer.check_growth

    def check_growth(self, step):
        if getattr(self, "bench_copy", False):
            return original(self, step)
        if self.densifier.grow and growth_check_due(step, self.cfg.densify, self.cfg.iterations):
            t0 = time.perf_counter()
            n = len(self.model)
            views = check_views(len(self.train_idx), self.cfg.densify.growth_check_views)
            g = self.mean_sample()
            with torch.enable_grad():
                weights = blending_weights(g, self.train_cams[views], render_fn=self.render)
            weak = weakest_half(weights)
            young = torch.zeros(n, dtype=torch.bool)
            young[n - n // 2:] = True
            base = _psnrs(self, g, self.test_cams, self.test_images)

            def without(off):
                return _psnrs(self, replace(g, opacities=torch.where(off, torch.zeros_like(g.opacities),
                                                                     g.opacities)), self.test_cams, self.test_images)

            weak0, young0 = without(weak), without(young)
            a, _ = _copy(self, step, refit)
            b, nb = _copy(self, step, refit, weak)
            c, nc = _copy(self, step, refit, young)
            row = {"step": step, "gaussians": n, "test_psnr": base, "weak_cost_no_refit": base - weak0,
                   "young_cost_no_refit": base - young0, "whole": a, "without_weakest": b, "without_youngest": c,
                   "gaussians_without_weakest": nb, "gaussians_without_youngest": nc,
                   "seconds": time.perf_counter() - t0}
            rows.append(row)
            print(f"step {step:5d}  N {n:8,d}  weakest half after {refit} steps: held out "
                  f"{a[f'test{refit}'] - b[f'test{refit}']:6.3f} dB, training views "
                  f"{a[f'train{refit}'] - b[f'train{refit}']:6.3f} dB", flush=True)
            out.write_text(json.dumps({**meta, "tests": rows}, indent=1))
        check = original(self, step)
        if step >= stop_step:
            self._stop = True
        return check

    trainer_module.Trainer.check_growth = check_growth


def scene_arguments(ap: argparse.ArgumentParser) -> None:
    """The options of a script that trains one scene on a preset with overrides (this one, bench_refit_steps.py)."""
    ap.add_argument("--scene", required=True, help="workspace, or tiny / synthetic-demo (generated)")
    ap.add_argument("--preset", default=None)
    ap.add_argument("--label", required=True)
    ap.add_argument("--set", nargs="*", default=[], dest="overrides", help="config overrides key=value")
    ap.add_argument("--device", default="cpu")
    add_overwrite_option(ap)


def train_scene(scene: str, cfg, device: str) -> None:
    """Train ``scene`` (``bench_options.scene_folder``) on ``cfg`` into a temporary folder; a stop ends it quietly."""
    with tempfile.TemporaryDirectory() as tmp:
        folder = scene_folder(scene, Path(tmp))
        try:
            train_stage.run(folder, Path(tmp) / "run", cfg, torch.device(device))
        except Interrupted:
            pass


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    scene_arguments(ap)
    ap.add_argument("--refit", type=int, default=200, help="steps each copy trains (its half measured too)")
    ap.add_argument("--stop-step", type=int, default=2000)
    args = ap.parse_args()
    out = RESULTS / f"growth_refit_{args.label}.json"
    refuse_overwrite(out, overwrite=args.overwrite)
    meta = {"label": args.label, "scene": str(args.scene), "preset": args.preset, "overrides": args.overrides,
            "refit": args.refit, "machine": platform.processor() or platform.machine(), "torch": torch.__version__,
            "date": date.today().isoformat()}
    rows: list[dict] = []
    instrumented(rows, args.refit, args.stop_step, out, meta)
    cfg = train_config_from(args.preset, None, [*args.overrides, "densify.growth_min_gain_db=1e-6",
                                                "densify.growth_refit_steps=0"])
    RESULTS.mkdir(parents=True, exist_ok=True)
    train_scene(args.scene, cfg, args.device)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
