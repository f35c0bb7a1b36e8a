"""Why one std cannot be calibrated at every interval width: the shape of the z-scores of an evaluation.

``evaluate``'s calibration error compares the coverage of |error| <= k std (k = 0.5 ... 3) with a Gaussian's.
That needs z = error / std to be N(0, 1) at every k, not only its variance to be 1. This reads a run's held-out
maps (``RUN/eval/maps/*.exr``, written by ``evaluate``) and images and measures how far the z-scores are from a
Gaussian, and what the best possible rescaling of the std could reach, with oracles fitted on the scored views
themselves (so they bound what any rescaling fitted elsewhere could do):

- the kurtosis of z (3 for a Gaussian) and, by decile of the predicted std, the ratio RMS error / mean std
  (1 everywhere for a std whose spread across pixels is right) and the kurtosis within the decile;
- the calibration error with the single factor of maximum likelihood and with the factor that minimises it;
- with one factor per decile (maximum likelihood, and the calibration-optimal one);
- with ``--components``: the predictive is rendered again with the pixel noise and with the resolution term
  left out, and the two terms and the rest are weighted by the maximum-likelihood weights (a grid), fitted on the
  views set aside for calibration and, as an oracle, on the scored views;
- the Student-t predictive with the same std (``eval.tails``): the calibration error and NLL at nu = 3, 4, 5 and
  at the nu ``evaluate`` fitted (``degrees_of_freedom`` in the report), and the oracle nu of the scored views'
  z-scores divided by their RMS (what ``fit_dof`` would give on them).

    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/bench_calibration_shape.py RUN [--components] [--tag NAME]

Writes ``benchmarks/results/calibration_shape_{tag}.json``. Errors and stds are pooled over the views'
pixels and channels (``evaluate`` averages its calibration table over views; the two differ in the third digit).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import platform
from datetime import date
from functools import partial
from pathlib import Path

import numpy as np
import torch
from _common import add_overwrite_option, refuse_overwrite

from uncertsplat.baselines import load_run
from uncertsplat.config import EvalConfig
from uncertsplat.data.dataset import load_view_set, photo_turns, turned_back
from uncertsplat.eval import tails
from uncertsplat.eval.calibration import DEFAULT_KS, calibration
from uncertsplat.io.images import read_exr
from uncertsplat.io.maps import map_stem
from uncertsplat.schemas.metrics import EvalReport

ROOT = Path(__file__).resolve().parents[1]
DECILES = 10


def cal_err(e: torch.Tensor, s: torch.Tensor) -> float:
    return calibration(e, s).calibration_error


def nll(e: torch.Tensor, s: torch.Tensor) -> float:
    return float((0.5 * (e / s).square() + s.log()).mean() + 0.5 * math.log(2 * math.pi))


def kurtosis(z: torch.Tensor) -> float:
    return float(z.pow(4).mean() / z.square().mean().square())


def best_factor(e: torch.Tensor, s: torch.Tensor) -> tuple[float, float]:
    """(factor, calibration error): the factor on a log grid over [e^-1.5, e^1.5] that minimises it."""
    grid = torch.exp(torch.linspace(-1.5, 1.5, 61)).tolist()
    return min(((a, cal_err(e, s * a)) for a in grid), key=lambda t: t[1])


def shape(e: torch.Tensor, s: torch.Tensor) -> dict:
    z = e / s
    ml = float(z.square().mean().sqrt())
    edges = torch.quantile(s[:: max(1, s.numel() // 1_000_000)], torch.linspace(0, 1, DECILES + 1, dtype=s.dtype))
    b = (torch.bucketize(s, edges[1:-1]))
    rows, s_ml, s_cal = [], s.clone(), s.clone()
    for d in range(DECILES):
        m = b == d
        zd = z[m]
        ratio = float(zd.square().mean().sqrt())
        rows.append({"decile": d, "mean_std": float(s[m].mean()), "rms_error": float(e[m].square().mean().sqrt()),
                     "ratio": ratio, "kurtosis": kurtosis(zd), "coverage_1std": float((zd.abs() <= 1).double().mean())})
        s_ml[m] = s[m] * ratio
        s_cal[m] = s[m] * best_factor(e[m], s[m])[0]
    f_cal, c_cal = best_factor(e, s)
    return {"pixels": int(e.numel()), "calibration_error": cal_err(e, s), "nll": nll(e, s), "kurtosis": kurtosis(z),
            "ml_factor": ml, "calibration_error_ml_factor": cal_err(e, s * ml), "nll_ml_factor": nll(e, s * ml),
            "calibration_optimal_factor": f_cal, "calibration_error_optimal_factor": c_cal,
            "calibration_error_per_decile_ml": cal_err(e, s_ml),
            "calibration_error_per_decile_optimal": cal_err(e, s_cal), "deciles": rows}


def student_t(e: torch.Tensor, s: torch.Tensor, fitted: float | None) -> dict:
    """The Student-t predictive with std ``s``: calibration error and NLL per nu (3, 4, 5 and ``evaluate``'s)."""
    rows = []
    for dof in sorted({3.0, 4.0, 5.0} | ({fitted} if fitted is not None else set())):
        rows.append({"dof": dof, "fitted_by_evaluate": dof == fitted,
                     "calibration_error": calibration(e, s, dof=dof).calibration_error,
                     "nll": float(tails.nll(e, torch.zeros_like(e), s, dof).mean())})
    z = e / s
    return {"oracle_dof": tails.fit_dof(z / z.square().mean().sqrt()), "rows": rows}


def read_maps(run: Path, report: EvalReport, scene) -> tuple[torch.Tensor, torch.Tensor]:
    """Pooled (error, std) of the evaluated views, std at ``report.std_floor``."""
    names = list(scene.cameras.image_names)
    views = load_view_set(scene, [names.index(n) for n in report.image_names], depth=False)
    turns = photo_turns(scene)  # the maps of a turned photo lie as the photo does
    errs, stds = [], []
    for j, name in enumerate(report.image_names):
        d = read_exr(run / "eval" / "maps" / f"{map_stem(name, report.image_names)}.exr")
        mean = torch.from_numpy(np.stack([d[f"rgb_mean.{c}"] for c in "RGB"], -1)).double()
        std = torch.from_numpy(np.stack([d[f"rgb_std.{c}"] for c in "RGB"], -1)).double()
        k = turns.get(name, 0)
        valid = (torch.ones(mean.shape[:2], dtype=torch.bool) if views.masks is None
                 else turned_back(views.masks[j][..., 0], k))
        errs.append((mean.clamp(0, 1) - turned_back(views.images[j].double(), k))[valid].reshape(-1))
        stds.append(std.clamp_min(report.std_floor)[valid].reshape(-1))
    return torch.cat(errs), torch.cat(stds)


def components(run: Path, device: torch.device) -> dict:
    """The pixel noise, the resolution term and the rest of the predictive on the set-aside and the scored views,
    and the maximum-likelihood weights of the three (a grid)."""
    from uncertsplat.eval.engine import predictive_terms, scored_sampler, split_indices, view_seed
    from uncertsplat.stages.residual_cache import fitted_residual
    from uncertsplat.uncertainty.mc import mc_render

    cfg = EvalConfig()
    loaded = load_run(run, device)
    scene = loaded.load_scene()
    train_views = partial(load_view_set, scene, depth=False)
    residual = fitted_residual(loaded, scene.scene_scale, scene.split["train"], cfg, device, load_views=train_views,
                               write=False, calibration_indices=scene.split.get("calibration", ()))
    sampler, _ = scored_sampler(partial(loaded.sampler, scene.scene_scale, device), residual, scene.cameras,
                                scene.split, cfg, device, load_views=train_views)
    variants = {"full": (sampler, cfg), "no_noise": (dataclasses.replace(sampler, residual=None), cfg),
                "no_resolution": (sampler, cfg.model_copy(update={"resolution": 0.0}))}

    def parts(indices):
        views = train_views(indices)
        var = {k: [] for k in variants}
        err = []
        for j, i in enumerate(views.indices):
            cam = views.cameras[[j]].to(device)
            for k, (s, c) in variants.items():
                gen = torch.Generator(device=device).manual_seed(view_seed(c.seed, i))
                maps, _ = mc_render(s.sample_fn, s.render_fn, cam, c.num_samples, gen,
                                    **predictive_terms(s, c, cam, depth=False))
                var[k].append(maps.rgb_std[0].cpu().double().square().reshape(-1))
                if k == "full":
                    err.append((maps.rgb_mean[0].cpu().clamp(0, 1) - views.images[j]).double().reshape(-1))
        full = torch.cat(var["full"])
        noise = (full - torch.cat(var["no_noise"])).clamp_min(0)
        res = (full - torch.cat(var["no_resolution"])).clamp_min(0)
        return torch.cat(err), (full - noise - res).clamp_min(0), noise, res

    floor = cfg.std_floor ** 2

    def std(p, a, b):
        return (p[1] + a * p[2] + b * p[3]).clamp_min(floor).sqrt()

    grid = torch.exp(torch.linspace(-3, 1.5, 31)).tolist()

    def fit(p):
        return min(((a, b) for a in grid for b in grid), key=lambda w: nll(p[0], std(p, *w)))

    test = parts(split_indices(scene.split, cfg))
    out = {"variance_shares": {"noise": float(test[2].sum() / (test[1] + test[2] + test[3]).sum()),
                               "resolution": float(test[3].sum() / (test[1] + test[2] + test[3]).sum())}}
    rows = {"as evaluated": (1.0, 1.0)}
    if scene.split.get("calibration"):
        rows["weights fitted on the set-aside views"] = fit(parts(list(scene.split["calibration"])))
    rows["weights fitted on the scored views (oracle)"] = fit(test)
    out["rows"] = [{"weights": name, "noise": a, "resolution": b, "nll": nll(test[0], std(test, a, b)),
                    "calibration_error": cal_err(test[0], std(test, a, b)),
                    "ml_factor": float((test[0] / std(test, a, b)).square().mean().sqrt())}
                   for name, (a, b) in rows.items()]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run", type=Path, help="a run evaluated with maps (RUN/eval/maps)")
    ap.add_argument("--components", action="store_true", help="render the predictive's terms again (slow)")
    ap.add_argument("--tag", default="demo", help="results go to calibration_shape_<tag>.json")
    ap.add_argument("--machine", default=platform.processor() or platform.machine())
    add_overwrite_option(ap)
    args = ap.parse_args()
    path = ROOT / "benchmarks" / "results" / f"calibration_shape_{args.tag}.json"
    refuse_overwrite(path, overwrite=args.overwrite)
    torch.set_num_threads(2)
    report = EvalReport.read(args.run / "eval" / "metrics.json")
    scene = load_run(args.run, torch.device("cpu")).load_scene()
    e, s = read_maps(args.run, report, scene)
    out = {"run": str(args.run), "date": str(date.today()), "machine": args.machine, "ks": list(DEFAULT_KS),
           "evaluate_calibration_error": report.mean.calibration_error, "evaluate_std_scale": report.std_scale,
           **shape(e, s), "student_t": student_t(e, s, report.degrees_of_freedom)}
    if args.components:
        out["components"] = components(args.run, torch.device("cpu"))
    print(json.dumps(out, indent=1))
    path.write_text(json.dumps(out, indent=1) + "\n")
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
