"""Space a photo looked through: ``Predictor.seen_free`` against the synthetic scene's exact geometry (issue 18).

A camera inside an object or behind a wall renders confidently (it sees the inside of surfaces the photos saw from
outside), so a planner needs to know which poses the photos showed empty. ``seen_free`` says a point is free when a
training photo's ray passed through it before the surface the model renders there. On a synthetic scene (a run
trained on it with its GT cameras, e.g. ``make demo``'s ``demo_out/train``) the truth is known: points drawn
uniformly in and around the room are labelled occupied (inside an object or outside the room's walls) or free, and
free points the photos actually looked through (the oracle: a training camera whose image holds the point and whose
ray to it meets no surface of the exact scene before it) are told apart from free points no photo saw. Then each
held-out camera is moved along its optical axis to ``--fractions`` of the depth its middle pixel sees (past 1: into
or behind what it looks at), with ``seen_free``, the exact label and the mean RGB std of its render.

    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/bench_free_space.py demo_out/train [--points 20000] [--label demo]

Writes ``benchmarks/results/free_space_<label>.json`` and prints the Markdown rows for BENCHMARKS.md.
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from dataclasses import replace
from datetime import date
from pathlib import Path

import torch
from _common import add_overwrite_option, refuse_overwrite

ROOT = Path(__file__).resolve().parents[1]
TOLERANCE = 0.03
"""As ``consistency.DEPTH_TOLERANCE``: the oracle counts a point as looked through when the exact surface lies more
than this fraction of the distance beyond it."""


def occupied(spec, points: torch.Tensor, objects_only: bool = False) -> torch.Tensor:
    """[P] bool: ``points`` [P,3] (the synthetic scene's frame) inside one of its objects or outside its room (not
    that with ``objects_only``)."""
    from uncertsplat.data.synthetic import CEIL, FLOOR, ROOM

    p = points.double()
    out = torch.zeros(p.shape[0], dtype=torch.bool)
    if spec.room and not objects_only:
        out |= (p[:, 0].abs() > ROOM) | (p[:, 1].abs() > ROOM) | (p[:, 2] < FLOOR) | (p[:, 2] > CEIL)
    for obj in spec.objects:
        c = torch.tensor(obj.center, dtype=torch.float64)
        if obj.kind == "sphere":
            out |= (p - c).norm(dim=-1) < obj.size[0]
        elif obj.kind == "box":
            local = (p - c) @ torch.tensor(obj.rot, dtype=torch.float64)
            out |= (local.abs() < torch.tensor(obj.size, dtype=torch.float64)).all(-1)
        else:  # cylinder: vertical axis through the centre
            d = p - c
            out |= (d[:, :2].norm(dim=-1) < obj.size[0]) & (d[:, 2].abs() < obj.size[1])
    return out


def inside_objects(spec, per_object: int, g: torch.Generator) -> list[tuple[str, torch.Tensor]]:
    """[(object kind and index, [n,3] points drawn uniformly inside it)] for each of the scene's objects: what a
    planner must never take for free space (a pose inside an object renders confidently)."""
    out = []
    for i, obj in enumerate(spec.objects):
        c = torch.tensor(obj.center, dtype=torch.float64)
        r = float(torch.tensor(obj.size, dtype=torch.float64).norm())  # encloses every kind's extent
        one = replace(spec, objects=(obj,), room=False)
        kept = []
        while sum(len(k) for k in kept) < per_object:
            cand = c + r * (2 * torch.rand(4 * per_object, 3, generator=g, dtype=torch.float64) - 1)
            kept.append(cand[occupied(one, cand, objects_only=True)])
        out.append((f"{obj.kind} {i}", torch.cat(kept)[:per_object]))
    return out


def looked_through(spec, points_source: torch.Tensor, points_world: torch.Tensor, cams, centres_source) -> torch.Tensor:
    """[P] bool, the oracle: some camera of ``cams`` (run world) holds the point in its image, in front of it, and its
    ray to the point (from ``centres_source``, the scene's frame) meets the exact scene more than ``TOLERANCE`` of
    the distance beyond it."""
    from uncertsplat.data.synthetic import trace
    from uncertsplat.render.project import project_points

    seen = torch.zeros(points_source.shape[0], dtype=torch.bool)
    for k in range(len(cams)):
        uv, z = project_points(points_world.float(), cams.cam_from_world[k], cams.K[k])
        inside = (z > 1e-9) & (uv[:, 0] >= 0) & (uv[:, 0] <= cams.width) & (uv[:, 1] >= 0) & (uv[:, 1] <= cams.height)
        if not bool(inside.any()):
            continue
        o = centres_source[k].expand(int(inside.sum()), 3).contiguous()
        d = points_source[inside] - o
        dist = d.norm(dim=-1)
        t, _, _ = trace(spec, o, d / dist[:, None])
        idx = inside.nonzero()[:, 0]
        seen[idx] |= t > dist * (1.0 + TOLERANCE)
    return seen


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", type=Path, help="a run trained on a synthetic scene (its GT cameras)")
    ap.add_argument("--points", type=int, default=20000)
    ap.add_argument("--fractions", type=float, nargs="+", default=[0.5, 0.9, 1.05, 1.2, 2.0])
    ap.add_argument("--samples", type=int, default=4, help="posterior samples of the moved cameras' renders")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--object-points", type=int, default=2000, help="points drawn inside each object")
    ap.add_argument("--label", default="demo")
    add_overwrite_option(ap)
    args = ap.parse_args()
    out_path = ROOT / "benchmarks" / "results" / f"free_space_{args.label}.json"
    refuse_overwrite(out_path, overwrite=args.overwrite)

    from uncertsplat.data.synthetic import CEIL, FLOOR, ROOM, make_scene_spec, read_scene_meta, trace
    from uncertsplat.predict import Predictor

    pred = Predictor.load(args.run, "cpu")
    meta = read_scene_meta(Path(pred.scene.source["path"]))
    if meta is None:
        raise SystemExit(f"{args.run}: not trained on a synthetic scene ({pred.scene.source['path']})")
    spec = make_scene_spec(meta.seed, room=meta.backdrop == "room")
    T = pred.scene.world_from_source.double()
    Tinv = torch.linalg.inv(T)

    def to_world(p: torch.Tensor) -> torch.Tensor:
        return p.double() @ T[:3, :3].T + T[:3, 3]

    def to_source(p: torch.Tensor) -> torch.Tensor:
        return p.double() @ Tinv[:3, :3].T + Tinv[:3, 3]

    g = torch.Generator().manual_seed(args.seed)
    lo = torch.tensor([-1.2 * ROOM, -1.2 * ROOM, FLOOR - 1.0], dtype=torch.float64)
    hi = torch.tensor([1.2 * ROOM, 1.2 * ROOM, CEIL + 1.0], dtype=torch.float64)
    pts = lo + (hi - lo) * torch.rand(args.points, 3, generator=g, dtype=torch.float64)  # the scene's frame
    t0 = time.perf_counter()
    free_said = pred.seen_free(pts)
    seconds = time.perf_counter() - t0
    occ = occupied(spec, pts)
    train = pred.scene.cameras[list(pred.scene.split["train"])]
    oracle = looked_through(spec, pts, to_world(pts), train, to_source(train.centers.double()))
    oracle &= ~occ

    def share(mask: torch.Tensor, of: torch.Tensor) -> float | None:
        n = int(of.sum())
        return round(float((mask & of).sum()) / n, 4) if n else None

    points = {
        "points": args.points, "occupied": int(occ.sum()), "free": int((~occ).sum()),
        "free_looked_through": int(oracle.sum()), "said_free": int(free_said.sum()),
        "said_free_of_occupied": share(free_said, occ),
        "said_free_of_looked_through": share(free_said, oracle),
        "said_free_of_free_not_looked_through": share(free_said, ~occ & ~oracle),
        "free_of_said_free": share(~occ, free_said),
        "looked_through_of_said_free": share(oracle, free_said),
        "seconds": round(seconds, 3), "seconds_per_point": seconds / args.points,
    }
    # inside each object (the uniform points hold few of them: most occupied points lie beyond the walls)
    points["said_free_inside_objects"] = {
        name: round(float(pred.seen_free(p).double().mean()), 4) for name, p in inside_objects(spec, args.object_points, g)}

    # held-out cameras moved along their optical axes into or past what their middle pixel sees
    moved = []
    test = list(pred.scene.split["test"])
    cams = pred.scene.cameras
    small = cams.scaled(0.25)
    for i in test:
        cs = to_source(cams.centers[i].double()[None])[0]
        fwd_world = cams.cam_from_world[i, 2, :3].double()
        fwd = (Tinv[:3, :3] @ fwd_world)
        fwd = fwd / fwd.norm()
        t, _, _ = trace(spec, cs[None], fwd[None])
        for f in args.fractions:
            c_new = cs + f * float(t[0]) * fwd
            cw = to_world(c_new[None])[0]
            cfw = cams.cam_from_world[[i]].clone()
            cfw[0, :3, 3] = -(cfw[0, :3, :3].double() @ cw).float()
            cam = small[[i]]
            cam = type(cam)(cfw, cam.K, cam.width, cam.height, (f"{cams.image_names[i]}@{f:g}",))
            out = pred.predict(cam, num_samples=args.samples)
            moved.append({"view": cams.image_names[i], "fraction": f, "occupied": bool(occupied(spec, c_new[None])[0]),
                          "seen_free": bool(out.seen_free[0]), "mean_rgb_std": round(float(out.rgb_std.mean()), 5)})
    by_fraction = {}
    for f in args.fractions:
        rows = [m for m in moved if m["fraction"] == f]
        by_fraction[f"{f:g}"] = {
            "views": len(rows), "occupied": sum(m["occupied"] for m in rows),
            "seen_free": sum(m["seen_free"] for m in rows),
            "seen_free_and_occupied": sum(m["seen_free"] and m["occupied"] for m in rows),
            "mean_rgb_std": round(sum(m["mean_rgb_std"] for m in rows) / max(len(rows), 1), 5)}
    result = {"run": str(args.run), "date": date.today().isoformat(), "machine": platform.processor() or
              platform.machine(), "seed": args.seed, "tolerance": TOLERANCE, "points": points,
              "moved": by_fraction, "moved_views": moved}
    out_path.parent.mkdir(parents=True, exist_ok=True)
    out_path.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps({"points": points, "moved": by_fraction}, indent=2))
    print(f"\n| {args.label} | {points['occupied']:,} / {points['free']:,} | {points['said_free_of_occupied']} | "
          f"{points['said_free_of_looked_through']} | {points['said_free_of_free_not_looked_through']} | "
          f"{points['free_of_said_free']} | "
          + ", ".join(f"{v:.2%}" for v in points["said_free_inside_objects"].values())
          + f" | {1e6 * points['seconds_per_point']:.1f} us |")
    print(f"wrote {out_path}")


if __name__ == "__main__":
    main()
