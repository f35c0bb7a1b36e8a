"""The view-consistency term's share of a large prediction: native lookups against the tensor ops (issue 18).

``Predictor.predict`` of one held-out camera of a run, scaled to each ``--widths`` (its focal length with it), K
samples, three ways in one process, alternated ``--repeats`` times: the term's lookups in the native kernel (the
default on a CPU), the same lookups as tensor ops (``ViewConsistency._lookup_torch``), and the term off (a Predictor
with ``consistency_views = 0``: what the rest of the predictive costs). Also checks that the two lookups give the same
std maps to rounding.

    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/bench_consistency.py demo_out/train [--widths 320 1280] [--label demo]

Writes ``benchmarks/results/consistency_<label>.json`` and prints the Markdown rows for BENCHMARKS.md.
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
    out_path = RESULTS / f"consistency_{args.label}.json"
    refuse_overwrite(out_path, overwrite=args.overwrite)

    from uncertsplat.predict import Predictor
    from uncertsplat.uncertainty.consistency import ViewConsistency

    torch.set_grad_enabled(False)
    pred = Predictor.load(args.run)
    plain = Predictor.load(args.run, cfg=pred._cfg.model_copy(update={"consistency_views": 0}))
    cam = held_out_camera(pred)
    native = ViewConsistency._native

    def tensor_ops(self, points):
        return False

    for p in (pred, plain):  # the first call of each builds what it keeps (renders of the compared views, stacks)
        p.predict(cam, num_samples=1)
    rows = []
    for width in args.widths:
        view = scaled_camera(cam, width)
        times: dict[str, list[float]] = {"native": [], "tensor ops": [], "term off": []}
        stds = {}
        for _ in range(args.repeats):
            for name in times:
                ViewConsistency._native = tensor_ops if name == "tensor ops" else native
                p = plain if name == "term off" else pred
                t0 = time.perf_counter()
                out = p.predict(view, num_samples=args.samples)
                times[name].append(time.perf_counter() - t0)
                stds[name] = out.rgb_std
        ViewConsistency._native = native
        diff = float((stds["native"] - stds["tensor ops"]).abs().max())
        med = {k: statistics.median(v) for k, v in times.items()}
        term_native, term_torch = med["native"] - med["term off"], med["tensor ops"] - med["term off"]
        rows.append({"width": width, "height": view.height, "samples": args.samples, "seconds": times,
                     "median_s": med, "term_s_native": term_native, "term_s_tensor_ops": term_torch,
                     "max_abs_std_difference": diff})
        print(f"| {width}x{view.height} | {args.samples} | {med['native']:.2f} | {med['tensor ops']:.2f} | "
              f"{med['term off']:.2f} | {term_native:.2f} / {term_torch:.2f} (x{term_torch / max(term_native, 1e-9):.1f}) "
              f"| {diff:.1e} | {args.machine} | {date.today()} |", flush=True)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    out_path.write_text(json.dumps({"run": str(args.run), "machine": args.machine, "date": str(date.today()),
                                    "torch": torch.__version__, "camera": cam.image_names[0], "rows": rows},
                                   indent=1), encoding="utf-8")
    print(f"wrote {out_path}")


if __name__ == "__main__":
    main()
