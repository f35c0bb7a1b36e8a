"""Why the offset tables stay at the prior: the data gradient on the posterior spreads against the KL's.

On a trained run, for S random training views, the gradient of the image loss (the training loss without the
KL) with respect to the entry-averaged raw spreads of every carrier (position, gate, scale width), one
posterior sample per view as in training. Reports per column group:

* ``snr``: |mean| / std over the S steps, per element (median, 90th percentile). Pure noise gives a median of
  about 0.674 / sqrt(S) (``snr_noise_floor``).
* ``shrink_fraction``: elements whose mean gradient says "a smaller spread lowers the loss".
* for the position spread, ``equilibrium_shrink``: the relative spread reduction at which the KL gradient
  (averaged over the P x K x 3 table elements, weight ``variational.kl_weight``) cancels the mean data
  gradient that reaches one table entry per step (the averaged gradient / K), i.e. where the training
  objective has its optimum: delta = mean / K x n_elements / (2 x kl_weight).

``--antithetic`` averages each view's gradient over the noise and its negation (eps, 1 - u, -eta), which
cancels the first-order noise term. Results: ``benchmarks/results/posterior_gradients_{label}.json``.

    .venv/bin/python benchmarks/bench_posterior_gradients.py RUN --steps 40 --label synthetic-demo [--antithetic]
"""

from __future__ import annotations

import argparse
import json
import math
import platform
from datetime import date
from pathlib import Path

import torch
from _common import add_overwrite_option, refuse_overwrite

RESULTS = Path(__file__).resolve().parent / "results"
COLUMNS = ("pos_spread_raw", "gate_spread_raw", "scale_width_raw")


def measure(run: Path, steps: int, antithetic: bool, seed: int = 0) -> dict:
    from uncertsplat.baselines import load_run
    from uncertsplat.data.dataset import load_images
    from uncertsplat.gaussians import variational as V
    from uncertsplat.render import near_plane, render
    from uncertsplat.train.losses import total_loss

    loaded = load_run(run)
    scene = loaded.load_scene()
    train = list(scene.split["train"])
    images, cams = load_images(scene, train), scene.cameras[train]
    model, prior, cfg = loaded.model, loaded.prior, loaded.config
    for p in model.parameters().values():
        p.requires_grad_(False)
    averaged = {k: v.detach().mean(1) for k, v in model.tables.items()}  # [P,D]: the subset M = K
    gen = torch.Generator().manual_seed(seed)
    bg = torch.tensor(cfg.scene.background, dtype=torch.float32)
    kw = {"variant": prior.variant, "extent": loaded.extent, "temperature": prior.temperature,
          "sh_degree": loaded.sh_degree}
    grads: dict[str, list[torch.Tensor]] = {k: [] for k in COLUMNS}
    for _ in range(steps):
        view = int(torch.randint(len(train), (1,), generator=gen))
        draws = V._draw(model, gen, model.num_entries)
        leaf = {k: v.clone().requires_grad_(k in COLUMNS) for k, v in averaged.items()}
        variants = [draws]
        if antithetic:
            variants.append(V._Draws(draws.idx, draws.subset, -draws.eps, 1.0 - draws.u, -draws.eta))
        loss = 0.0
        for d in variants:
            out = render(V._sample_from(model, d, leaf, **kw), cams[[view]], background=bg,
                         near=near_plane(scene.scene_scale), tile_size=cfg.tile_size)
            loss = loss + total_loss(out.rgb, images[[view]], None, ssim_lambda=cfg.ssim_lambda,
                                     kl_weight=0.0)["loss"] / len(variants)
        loss.backward()
        for k in COLUMNS:
            grads[k].append(leaf[k].grad.detach().clone())
    result: dict = {"run": str(run), "steps": steps, "antithetic": antithetic, "carriers": model.num_carriers,
                    "num_entries": model.num_entries, "kl_weight": cfg.variational.kl_weight,
                    "snr_noise_floor": 0.674 / math.sqrt(steps)}
    q = torch.tensor([0.5, 0.9, 0.99])
    for k, lst in grads.items():
        g = torch.stack(lst)  # [S,P,D]
        mean, std = g.mean(0), g.std(0)
        snr = (mean.abs() / std.clamp_min(1e-30)).flatten()
        sub = torch.randperm(snr.numel(), generator=torch.Generator().manual_seed(0))[:1_000_000]
        entry = {"snr_q50": float(snr[sub].quantile(0.5)), "snr_q90": float(snr[sub].quantile(0.9)),
                 "shrink_fraction": float((mean > 0).float().mean())}
        if k == "pos_spread_raw":
            n_el = model.num_carriers * model.num_entries * 3
            delta = (mean / model.num_entries * n_el / (2.0 * max(cfg.variational.kl_weight, 1e-30))).flatten()
            entry["equilibrium_shrink_q50_q90_q99"] = [float(x) for x in delta[sub].quantile(q)]
        result[k] = entry
    return result


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run", type=Path)
    ap.add_argument("--steps", type=int, default=40)
    ap.add_argument("--antithetic", action="store_true")
    ap.add_argument("--label", default="run")
    ap.add_argument("--machine", default=None)
    add_overwrite_option(ap)
    args = ap.parse_args()
    path = RESULTS / f"posterior_gradients_{args.label}{'_antithetic' if args.antithetic else ''}.json"
    refuse_overwrite(path, overwrite=args.overwrite)
    res = measure(args.run, args.steps, args.antithetic)
    res.update({"machine": args.machine or platform.processor() or platform.machine(), "date": date.today().isoformat()})
    RESULTS.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(res, indent=2) + "\n")
    print(json.dumps(res, indent=2))


if __name__ == "__main__":
    main()
