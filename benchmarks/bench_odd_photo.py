"""One photo that does not fit the camera it shares: what it does to a capture's focal length, and what
``reconstruct``'s check (``sfm.focal_outliers``, a camera of its own, mapped again) gives back.

For each scene, the photos are resized by ``--scale`` and reconstructed twice with the defaults (one camera per image
size): as they are, and with photo ``--index`` cropped to its middle 1/``--zoom`` and saved at the full size (a crop
kept at the original size, or a phone's digital zoom without EXIF). Recorded: the clean capture's focal length, the
shared focal length the cropped capture's first mapping settled in (from the warning), the others' and the crop's
after the check, and the ratio the check measured.

    .venv/bin/python benchmarks/bench_odd_photo.py                       # fern at 1/4, a 1.5x crop: ~1 minute
    .venv/bin/python benchmarks/bench_odd_photo.py --scenes fern bonsai  # bonsai at 1/2, a 1.25x crop too: ~3 min

Writes ``benchmarks/results/odd_photo[-LABEL].json``. Needs ``../shared/datasets/{fern,bonsai}/images``.
"""

from __future__ import annotations

import argparse
import json
import platform
import re
import shutil
import sys
import tempfile
import time
from pathlib import Path

from _common import RESULTS, add_overwrite_option, refuse_overwrite

DATASETS = Path(__file__).resolve().parents[1] / ".." / "shared" / "datasets"
DEFAULTS = {"fern": (4, 1.5, 7), "bonsai": (2, 1.25, 10)}  # scale, zoom, index of the cropped photo


def prepare(src: Path, dst: Path, scale: int, zoom: float | None, index: int) -> str:
    """The photos of ``src`` resized by 1/``scale`` into ``dst``, photo ``index`` cropped by ``zoom`` (None: none)
    and resized back; returns that photo's name."""
    from PIL import Image

    dst.mkdir(parents=True)
    names = sorted(p.name for p in src.iterdir() if p.suffix.lower() in (".jpg", ".jpeg", ".png"))
    for i, name in enumerate(names):
        im = Image.open(src / name)
        im = im.resize((im.width // scale, im.height // scale), Image.LANCZOS)
        if zoom is not None and i == index:
            w, h = im.size
            dx, dy = round(w * (1 - 1 / zoom) / 2), round(h * (1 - 1 / zoom) / 2)
            im = im.crop((dx, dy, w - dx, h - dy)).resize((w, h), Image.LANCZOS)
        im.save(dst / name, quality=95)
    return names[index]


def focal_lengths(workspace: Path) -> dict[str, float]:
    """{photo: focal length in pixels} of the workspace's model before undistortion."""
    import pycolmap

    rec = pycolmap.Reconstruction(workspace / "distorted" / "sparse" / "0")
    return {rec.image(i).name: float(rec.image(i).camera.mean_focal_length()) for i in rec.reg_image_ids()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", nargs="+", default=["fern"], choices=sorted(DEFAULTS))
    ap.add_argument("--label", default="")
    ap.add_argument("--machine", default=platform.processor() or platform.machine())
    add_overwrite_option(ap)
    args = ap.parse_args()
    out = RESULTS / f"odd_photo{'-' + args.label if args.label else ''}.json"
    refuse_overwrite(out, overwrite=args.overwrite)

    from statistics import median

    from uncertsplat.config import ReconstructConfig
    from uncertsplat.stages import reconstruct as stage
    from uncertsplat.stages.reconstruct import OWN_CAMERA

    results = {"machine": args.machine, "date": time.strftime("%Y-%m-%d"), "scenes": {}}
    for scene in args.scenes:
        src = DATASETS / scene / "images"
        if not src.is_dir():
            sys.exit(f"{src} not found (see ../shared/datasets/README.md)")
        scale, zoom, index = DEFAULTS[scene]
        with tempfile.TemporaryDirectory() as tmp:
            tmp = Path(tmp)
            row: dict = {"scale": scale, "zoom": zoom}
            for case, z in (("clean", None), ("cropped", zoom)):
                t0 = time.perf_counter()
                row["cropped_photo"] = prepare(src, tmp / case / "photos", scale, z, index)
                report = stage.run(tmp / case / "photos", tmp / case / "ws", ReconstructConfig(num_threads=2))
                focal = focal_lengths(tmp / case / "ws")
                notes = [n for n in report.notes if n.startswith(OWN_CAMERA)]
                crop = row["cropped_photo"]
                others = [f for n, f in focal.items() if n != crop]
                row[case] = {"registered": len(focal), "photos": len(report.images_found),
                             "others_focal_px": round(median(others), 1), "cropped_focal_px": round(focal.get(crop, 0), 1),
                             "flagged": notes[0] if notes else None, "seconds": round(time.perf_counter() - t0, 1)}
                shared = re.search(r"shared: ([0-9. /]+) px", notes[0]) if notes else None
                row[case]["first_mapping_shared_px"] = shared.group(1) if shared else None
                print(f"{scene} {case}: {row[case]}", flush=True)
            shutil.rmtree(tmp, ignore_errors=True)
        results["scenes"][scene] = row
    out.parent.mkdir(exist_ok=True)
    out.write_text(json.dumps(results, indent=2) + "\n")
    print(f"-> {out}")


if __name__ == "__main__":
    main()
