"""What the growth test sees, on the views it trains on and on views set aside, as a model grows (issue 19).

Trains one scene with the growth test on but a threshold no half reaches (``densify.growth_min_gain_db=1e-6``), so
the model grows as 3DGS's densification takes it, and at every test records, beside what the test measured on its
views (``densify.growth_reserve_views`` of them set aside from training, or training views when 0), the same
halving cost on ``growth_check_views`` of the views the model trains on. The run stops after ``--stop-step``
(the tests happen while densifying). With the held-out PSNR against model size (BENCHMARKS.md, "How many
Gaussians a scene needs") this shows which cost, at which threshold, stops each scene near its knee.

    .venv/bin/python benchmarks/bench_growth.py --scene WS --preset paper --label fern \\
        --set scene.downscale=1.5873 --reserve 2 --stop-step 3000

Writes ``benchmarks/results/growth_{label}.json`` and prints one row per test.
"""

from __future__ import annotations

import argparse
import json
import platform
import tempfile
import time
from datetime import date
from pathlib import Path

import torch
from _common import add_overwrite_option, refuse_overwrite
from bench_options import scene_folder

from uncertsplat.config import train_config_from
from uncertsplat.errors import Interrupted
from uncertsplat.stages import train as train_stage
from uncertsplat.strategy.growth import halving_cost_db, weakest_half
from uncertsplat.strategy.view_checks import check_views
from uncertsplat.train import trainer as trainer_module
from uncertsplat.uncertainty.scores import blending_weights

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"


def instrumented(rows: list[dict], stop_step: int):
    """``Trainer.check_growth`` that also measures the halving cost on the trained views and stops the run after
    ``stop_step``."""
    original = trainer_module.Trainer.check_growth

    @torch.no_grad()
    def check_growth(self, step):
        check = original(self, step)
        if check is not None:
            trained = self.trained_views()
            views = [trained[k] for k in check_views(len(trained), self.cfg.densify.growth_check_views)]
            cams, images = self.train_cams[views], self.photos(views)
            g = self.mean_sample()
            with torch.enable_grad():
                weights = blending_weights(g, cams, render_fn=self.render)
            cost, quality = halving_cost_db(g, weakest_half(weights), cams, images,
                                            lambda s, cam: self.render(s, cam).rgb)
            rows.append({**check.model_dump(), "trained_cost_db": round(cost, 4), "trained_psnr_db": round(quality, 4),
                         "trained_views": len(views), "trained_seen": int((weights > 0).sum())})
            print(f"step {step:5d}  N {check.gaussians:8,d}  set aside {check.cost_db:7.3f} dB (PSNR "
                  f"{check.psnr_db:6.2f})  trained {cost:7.3f} dB (PSNR {quality:6.2f})", flush=True)
        if step >= stop_step:
            self._stop = True
        return check

    trainer_module.Trainer.check_growth = check_growth


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", required=True, help="workspace, or tiny / synthetic-demo (generated)")
    ap.add_argument("--preset", default=None)
    ap.add_argument("--label", required=True)
    ap.add_argument("--set", nargs="*", default=[], dest="overrides", help="config overrides key=value")
    ap.add_argument("--reserve", type=int, default=2, help="densify.growth_reserve_views")
    ap.add_argument("--stop-step", type=int, default=3000)
    ap.add_argument("--device", default="cpu")
    add_overwrite_option(ap)
    args = ap.parse_args()
    out = RESULTS / f"growth_{args.label}.json"
    refuse_overwrite(out, overwrite=args.overwrite)
    device = torch.device(args.device)
    rows: list[dict] = []
    instrumented(rows, args.stop_step)
    cfg = train_config_from(args.preset, None, [*args.overrides, "densify.growth_min_gain_db=1e-6",
                                                f"densify.growth_reserve_views={args.reserve}"])
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        scene = scene_folder(args.scene, Path(tmp))
        try:
            train_stage.run(scene, Path(tmp) / "run", cfg, device)
        except Interrupted:
            pass
    result = {"label": args.label, "scene": str(args.scene), "preset": args.preset, "overrides": args.overrides,
              "reserve": args.reserve, "stop_step": args.stop_step, "tests": rows,
              "seconds": time.perf_counter() - t0, "machine": platform.processor() or platform.machine(),
              "torch": torch.__version__, "threads": torch.get_num_threads(), "date": date.today().isoformat()}
    RESULTS.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
