"""Benchmark ``uncertsplat view`` and ``train --view``: milliseconds per frame and the cost of watching training.

Part 1, frames (``--run``, default the demo's run ``demo_out/train``; ``make demo`` writes it): the viewer's
render loop (``Viewer.serve``: render, colour, JPEG-encode and queue the frame) for a stand-in browser of
640x480 at a training camera, per mode: RGB and RGB std with K = 4, moving (the preview resolution the loop
picks for ``moving_fps``, after it has measured the cost per pixel) and still (640x480; std: K = 4, then the
refinement to K = 16). Medians over ``--repeats`` frames; a 2048^3 float32 matmul is timed in the same run
as the reference. Also the render alone under ``sys.settrace`` (how nerfview interrupts a render: a Python
trace function on every line) against without, the reason this viewer does not use nerfview.

Part 2, ``train --view`` (``--train``): the demo preset for ``--steps`` steps on the demo scene, trained three
times in one process: without the viewer, with the viewer and no browser, and with the viewer and a
stand-in browser that moves the camera to the next training view every second (so previews, still frames
and redraws all happen); wall time of each and the ratio.

    .venv/bin/python benchmarks/bench_view.py --run demo_out/train
    .venv/bin/python benchmarks/bench_view.py --run demo_out/train --train --scene demo_out/synth --steps 1500

Writes ``benchmarks/results/view.json`` and prints the rows for BENCHMARKS.md.
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import sys
import threading
import time
from datetime import date
from pathlib import Path
from types import SimpleNamespace

import torch
from _common import add_overwrite_option, refuse_overwrite

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from uncertsplat.config import ViewConfig  # noqa: E402
from uncertsplat.stages import view as view_stage  # noqa: E402
from uncertsplat.view import server as view_server  # noqa: E402
from uncertsplat.view.frames import camera_pose, viewer_camera  # noqa: E402


class Browser:
    """A stand-in browser: viser's camera fields, and a list of the frames it was sent."""

    def __init__(self, scene, i: int, canvas=(640, 480)):
        self.scene_data = scene
        self.client_id = 1
        self.camera = SimpleNamespace(aspect=canvas[0] / canvas[1], image_width=canvas[0], image_height=canvas[1])
        self.frames = 0
        self.scene = SimpleNamespace(set_background_image=self._receive)
        self.look(i)

    def look(self, i: int) -> None:
        c = self.scene_data.cameras[[i]]
        wxyz, pos, fov = camera_pose(c.cam_from_world[0], c.K[0], c.height)
        self.camera.wxyz, self.camera.position, self.camera.fov = wxyz, pos, fov

    def _receive(self, image, **_):
        self.frames += 1


def matmul_ms(repeats: int = 5) -> float:
    a, b = torch.randn(2048, 2048), torch.randn(2048, 2048)
    a @ b
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        a @ b
        times.append(time.perf_counter() - t)
    return 1000 * statistics.median(times)


def bench_frames(run: Path, repeats: int) -> dict:
    viewer = view_stage.build(run, ViewConfig(port=0, thumbnails=False, max_side=640), torch.device("cpu"))
    viewer.start(worker=False)
    scene = viewer.scene
    cam0 = scene.split["train"][0]
    out: dict = {"gaussians": len(viewer.renderer.loaded.model), "matmul_2048_ms": matmul_ms()}
    try:
        for mode in ("rgb", "rgb_std"):
            viewer.set_mode(mode)
            # moving: first calibrate the cost per pixel (as the loop does from its first frames), then time
            b = Browser(scene, cam0)
            state = view_server.ViewState(b, version=0)
            moving = []
            for r in range(repeats + 2):
                state.version += 1
                state.moved_at = time.monotonic()
                viewer.serve(state)
                if r >= 2:
                    moving.append(state.last["seconds"])
            out[f"{mode}_moving"] = {"ms": 1000 * statistics.median(moving), "width": state.last["width"],
                                     "height": state.last["height"], "samples": state.last["samples"]}
            # still: full resolution; the std mode refines K = 4 -> 16 (first step timed, and the whole)
            first, whole = [], []
            for _ in range(repeats):
                state.version += 1
                state.moved_at = time.monotonic() - 10
                t = time.perf_counter()
                viewer.serve(state)
                first.append(state.last["seconds"])
                while not state.shown_full:
                    viewer.serve(state)
                whole.append(time.perf_counter() - t)
            out[f"{mode}_still"] = {"ms_first": 1000 * statistics.median(first), "ms_total": 1000 * statistics.median(whole),
                                    "width": state.last["width"], "height": state.last["height"],
                                    "samples": state.last["samples"]}
        # the render alone, with and without a trace function (nerfview's interruption mechanism)
        cam = viewer_camera(*camera_pose(scene.cameras.cam_from_world[cam0], scene.cameras.K[cam0],
                                         scene.cameras.height), 640, 480)

        def tracer(frame, event, arg):
            return tracer

        plain, traced = [], []
        for _ in range(repeats):
            t = time.perf_counter()
            viewer.renderer.frame(cam, "rgb")
            plain.append(time.perf_counter() - t)
            sys.settrace(tracer)
            try:
                t = time.perf_counter()
                viewer.renderer.frame(cam, "rgb")
                traced.append(time.perf_counter() - t)
            finally:
                sys.settrace(None)
        out["render_rgb_ms"] = 1000 * statistics.median(plain)
        out["render_rgb_traced_ms"] = 1000 * statistics.median(traced)
    finally:
        viewer.stop()
    return out


def bench_train(scene: Path, steps: int, tmp: Path) -> dict:
    from uncertsplat.baselines import train_run
    from uncertsplat.config import train_config_from
    from uncertsplat.view.live import LiveView

    cfg = train_config_from("demo", {"iterations": steps, "eval_every": 10 * steps, "checkpoint_every": 10 * steps})
    out = {}
    for name in ("no viewer", "viewer, no browser", "viewer, browser"):
        live = None if name == "no viewer" else LiveView(ViewConfig(port=0, thumbnails=False))
        browser: list = []
        stop = threading.Event()

        watched = name == "viewer, browser"

        def attach(trainer, live=live, browser=browser, stop=stop, watched=watched):
            live.attach(trainer)
            if watched:
                b = Browser(trainer.scene, trainer.train_idx[0])
                state = view_server.ViewState(b, version=1, moved_at=time.monotonic())
                with live.viewer._lock:
                    live.viewer._views[b.client_id] = state
                browser.append(b)

                def move():  # the user clicks through the training views, one a second
                    k = 0
                    while not stop.wait(1.0):
                        k += 1
                        with live.viewer._lock:
                            b.look(trainer.train_idx[k % len(trainer.train_idx)])
                            state.version += 1
                            state.moved_at = time.monotonic()

                threading.Thread(target=move, daemon=True).start()

        t = time.perf_counter()
        try:
            train_run(scene, tmp / name.replace(" ", "_").replace(",", ""), cfg, torch.device("cpu"),
                      on_trainer=attach if live is not None else None)
        finally:
            stop.set()
            if live is not None:
                live.close()
        seconds = time.perf_counter() - t
        out[name] = {"seconds": seconds, "frames": browser[0].frames if browser else 0,
                     "viewer_share": live.share if live is not None else 0.0}
        print(f"{name}: {seconds:.1f} s, {out[name]['frames']} frames", flush=True)
    base = out["no viewer"]["seconds"]
    for v in out.values():
        v["ratio"] = v["seconds"] / base
    return {"steps": steps, "runs": out}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run", type=Path, default=ROOT / "demo_out" / "train")
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--train", action="store_true", help="also measure train --view")
    ap.add_argument("--scene", type=Path, default=ROOT / "demo_out" / "synth")
    ap.add_argument("--steps", type=int, default=1500)
    ap.add_argument("--tmp", type=Path, default=Path("/tmp/bench_view"))
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "view.json")
    add_overwrite_option(ap)
    args = ap.parse_args()
    refuse_overwrite(args.out, overwrite=args.overwrite)
    torch.manual_seed(0)
    res = {"machine": platform.processor() or platform.machine(), "threads": torch.get_num_threads(),
           "date": date.today().isoformat(), "run": str(args.run)}
    res["frames"] = bench_frames(args.run, args.repeats)
    f = res["frames"]
    print(json.dumps(f, indent=1))
    if args.train:
        import shutil

        shutil.rmtree(args.tmp, ignore_errors=True)
        args.tmp.mkdir(parents=True)
        res["train"] = bench_train(args.scene, args.steps, args.tmp)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(res, indent=1) + "\n")
    print(f"wrote {args.out}")
    m = f["matmul_2048_ms"]
    for mode in ("rgb", "rgb_std"):
        mv, st = f[f"{mode}_moving"], f[f"{mode}_still"]
        print(f"| {mode} moving | {mv['width']}x{mv['height']}, K={mv['samples']} | {mv['ms']:.0f} ms "
              f"({mv['ms'] / m:.2f}x matmul) |")
        print(f"| {mode} still | {st['width']}x{st['height']}, K={st['samples']} | first {st['ms_first']:.0f} ms, "
              f"all {st['ms_total']:.0f} ms ({st['ms_first'] / m:.2f}x matmul) |")
    print(f"render alone {f['render_rgb_ms']:.0f} ms, under sys.settrace {f['render_rgb_traced_ms']:.0f} ms "
          f"(x{f['render_rgb_traced_ms'] / f['render_rgb_ms']:.2f})")
    if args.train:
        for name, v in res["train"]["runs"].items():
            print(f"| {name} | {v['seconds']:.1f} s | x{v['ratio']:.3f} | {v['frames']} frames |")


if __name__ == "__main__":
    main()
