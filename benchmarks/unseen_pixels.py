"""Where a synthetic run's unseen pixels are: its held-out pixels by the GT label (observed / unobserved, from GT
depth: ``eval.observed.observed_mask``), with each group's squared error against its predicted variance.

``bench_unseen.py`` gives one ROC AUC per predictive; this says which pixels make the AUC what it is (e.g. "a quarter
of the unobserved pixels have a std below the observed pixels' 90th percentile, and are under-predicted 2.3x"). The
predictive is the one ``evaluate`` scores (K = 10), optionally with ``--set`` overrides of ``EvalConfig``; with
``--against`` another setting is evaluated too and the pixels split by whether the difference between the two
variances is positive (e.g. ``--against consistency_views=0``: where the view-consistency term fired).

    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/unseen_pixels.py RUN [--set k=v ...] [--against k=v ...]

RUN: a run trained by ``bench_unseen.py`` on the synthetic scene (GT depth), e.g. /tmp/unseen/variational.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch


def pixels(run_dir: Path, overrides: dict, device: torch.device) -> dict:
    """Per held-out pixel with GT depth: squared error, predicted variance (mean over channels), the GT label, the
    rendered alpha; and the run's metrics (``bench_unseen.evaluate_run``, K = 10)."""
    from bench_unseen import evaluate_run, observed

    from uncertsplat.config import EvalConfig

    run = evaluate_run(run_dir, device, EvalConfig(num_samples=10, **overrides))
    out = {"err2": [], "var": [], "observed": [], "alpha": []}
    for j, m in enumerate(run["maps"]):
        obs, valid = observed(run, j)
        out["err2"].append((m.rgb_mean - m.gt).square().mean(-1)[valid])
        out["var"].append(m.rgb_std.square().mean(-1)[valid])
        out["observed"].append(obs[valid])
        out["alpha"].append(m.alpha_mean[..., 0][valid])
    out = {k: torch.cat(v) for k, v in out.items()}
    out["metrics"] = run["report"].mean
    out["factor"] = run["std_scale"]
    return out


def describe(name: str, mask: torch.Tensor, p: dict) -> None:
    e, v = p["err2"][mask], p["var"][mask]
    if not mask.any():
        print(f"{name}: no pixels")
        return
    q = v.sqrt().quantile(torch.tensor([0.1, 0.5, 0.9], dtype=v.dtype))
    print(f"{name}: {int(mask.sum())} px, squared error {e.mean():.2e}, variance {v.mean():.2e} (ratio "
          f"{e.mean() / v.mean():.2f}), std q10/q50/q90 {q[0]:.3f} / {q[1]:.3f} / {q[2]:.3f}, alpha "
          f"{p['alpha'][mask].mean():.3f}")


def _pairs(items: list[str]) -> dict:
    from uncertsplat.config import deep_update, parse_override

    out: dict = {}
    for item in items:
        out = deep_update(out, parse_override(item))
    return out


def main() -> None:
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from bench_unseen import roc

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("--set", action="append", default=[], help="EvalConfig key=value")
    ap.add_argument("--against", action="append", default=[], help="EvalConfig key=value of a second evaluation")
    args = ap.parse_args()
    torch.set_num_threads(2)
    device = torch.device("cpu")
    p = pixels(args.run, _pairs(args.set), device)
    m = p["metrics"]
    unobserved = ~p["observed"]
    print(f"PSNR {m.psnr:.2f} NLL {m.nll:.3f} cal. err {m.calibration_error:.3f} factor x{p['factor']:.3f} "
          f"AUC unseen RGB {roc(p['var'].sqrt(), unobserved):.3f}")
    describe("unobserved", unobserved, p)
    describe("observed", p["observed"], p)
    low = unobserved & (p["var"].sqrt() < p["var"][p["observed"]].sqrt().quantile(0.9))
    describe("unobserved below the observed pixels' 90th percentile of std", low, p)
    if args.against:
        other = pixels(args.run, _pairs(args.against), device)
        fired = (p["var"] - other["var"]) > 1e-6
        describe(f"observed, variance above that with {args.against}", p["observed"] & fired, p)
        describe(f"observed, variance not above that with {args.against}", p["observed"] & ~fired, p)


if __name__ == "__main__":
    main()
