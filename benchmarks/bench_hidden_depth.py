"""What the depth term of the hidden surface points costs a prediction (issue 18, ``EvalConfig.hidden_depth``).

``Predictor.predict`` of one held-out camera of a run, scaled to each ``--widths`` (its focal length with it), K
samples, with and without the term (``hidden_depth = false``), alternated ``--repeats`` times in one process; the
fraction of the view's pixels that get the term. Also the term's bound: ``ViewConsistency._free_gap`` of
``GAP_POINTS`` points (what any view's march costs at most, however much of it no photo saw), on the same run's
compared views.

    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/bench_hidden_depth.py demo_out/train [--widths 320 1280] [--label demo]

Writes ``benchmarks/results/hidden_depth_<label>.json`` and prints the Markdown rows for BENCHMARKS.md.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from datetime import date

import torch
from _common import RESULTS, add_prediction_options, held_out_camera, refuse_overwrite, scaled_camera


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_prediction_options(ap, "demo")
    args = ap.parse_args()
    out_path = RESULTS / f"hidden_depth_{args.label}.json"
    refuse_overwrite(out_path, overwrite=args.overwrite)

    from uncertsplat.predict import Predictor
    from uncertsplat.uncertainty import consistency

    torch.set_grad_enabled(False)
    pred = Predictor.load(args.run)
    plain = Predictor.load(args.run, cfg=pred._cfg.model_copy(update={"hidden_depth": False}))
    cam = held_out_camera(pred)
    for p in (pred, plain):  # the first call of each builds what it keeps (renders of the compared views)
        p.predict(cam, num_samples=1)
    rows = []
    for width in args.widths:
        view = scaled_camera(cam, width)
        times: dict[str, list[float]] = {"term on": [], "term off": []}
        depth_std = {}
        for _ in range(args.repeats):
            for name in times:
                p = plain if name == "term off" else pred
                t0 = time.perf_counter()
                out = p.predict(view, num_samples=args.samples)
                times[name].append(time.perf_counter() - t0)
                depth_std[name] = out.depth_std
        given = float((depth_std["term on"] > depth_std["term off"] * (1 + 1e-6)).float().mean())
        med = {k: statistics.median(v) for k, v in times.items()}
        rows.append({"width": width, "height": view.height, "samples": args.samples, "seconds": times,
                     "median_s": med, "fraction_with_term": given})
        print(f"| {width}x{view.height} | {args.samples} | {med['term on']:.2f} | {med['term off']:.2f} | "
              f"x{med['term on'] / med['term off']:.2f} | {100 * given:.1f} % | {args.machine} | {date.today()} |",
              flush=True)

    # the bound: GAP_POINTS points marched, whatever the view (points spread over the scene's bounding box)
    term = pred._sampler.consistency
    if term is None:
        raise SystemExit(f"{args.run}: its evaluation settings have no view-consistency term (consistency_views = 0), "
                         "so no hidden points' depth term; nothing to time")
    means = pred._sampler.det_sample.means if pred._sampler.det_sample is not None else term.sample.means
    lo, hi = means.min(0).values, means.max(0).values
    gen = torch.Generator().manual_seed(0)
    points = lo + (hi - lo) * torch.rand(consistency.GAP_POINTS, 3, generator=gen)
    z = (points - cam.centers[0]).norm(dim=-1)
    bound = []
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        term._free_gap(points, z, cam, torch.arange(consistency.GAP_POINTS))  # (at the cap: every point marched)
        bound.append(time.perf_counter() - t0)
    print(f"march of GAP_POINTS = {consistency.GAP_POINTS} points x {consistency.GAP_SAMPLES} samples against "
          f"{len(term.cameras)} compared views: {statistics.median(bound):.2f} s")
    out_path.parent.mkdir(parents=True, exist_ok=True)
    out_path.write_text(json.dumps({"run": str(args.run), "machine": args.machine, "date": str(date.today()),
                                    "torch": torch.__version__, "camera": cam.image_names[0], "rows": rows,
                                    "bound": {"points": consistency.GAP_POINTS, "samples": consistency.GAP_SAMPLES,
                                              "compared_views": len(term.cameras), "seconds": bound}},
                                   indent=1), encoding="utf-8")
    print(f"wrote {out_path}")


if __name__ == "__main__":
    main()
