"""A run's model written as another 3DGS tool writes its file (tests of ``train --from-ply``, ``bench_align.py``).

``in_source_frame``: the standard PLY layout in the scene's source frame, without uncertsplat's header comment (as
INRIA's code writes it); ``moved``: such a file moved by a similarity, as a trainer that normalises its world writes
its model (positions, sizes, rotations and SH colours alike).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import torch
from plyfile import PlyData, PlyElement

from uncertsplat.gaussians.ops import rotmat_to_quat
from uncertsplat.render.sh import rotate_sh
from uncertsplat.train.imported import _quat_mul


def in_source_frame(run: Path, out: Path) -> Path:
    """``run``'s point_cloud.ply moved back into the scene's source frame, without uncertsplat's header comment."""
    m = np.asarray(json.loads((run / "scene.json").read_text(encoding="utf-8"))["world_from_source"])
    s, t = float(np.cbrt(abs(np.linalg.det(m[:3, :3])))), m[:3, 3]
    v = PlyData.read(str(run / "point_cloud.ply"))["vertex"].data.copy()
    for i, a in enumerate("xyz"):
        v[a] = (v[a].astype(np.float64) - t[i]) / s
    for i in range(3):
        v[f"scale_{i}"] = v[f"scale_{i}"] - math.log(s)
    PlyData([PlyElement.describe(v, "vertex")], text=False).write(str(out))
    return out


def moved(src: Path, out: Path, file_from_source: torch.Tensor) -> Path:
    """The file ``src`` moved by the similarity ``file_from_source`` [4,4] float64 (x_file = s R x_src + t): positions,
    log-scales + log s, rotations turned by R, SH colours turned with them (``rotate_sh``)."""
    scale = float(torch.linalg.det(file_from_source[:3, :3])) ** (1 / 3)
    r = file_from_source[:3, :3] / scale
    v = PlyData.read(str(src))["vertex"].data.copy()
    xyz = torch.from_numpy(np.stack([v[a] for a in "xyz"], -1).astype(np.float64))
    xyz = xyz @ file_from_source[:3, :3].T + file_from_source[:3, 3]
    for i, a in enumerate("xyz"):
        v[a] = xyz[:, i].numpy()
    for i in range(3):
        v[f"scale_{i}"] = v[f"scale_{i}"] + math.log(scale)
    q = torch.from_numpy(np.stack([v[f"rot_{i}"] for i in range(4)], -1).astype(np.float64))
    q = _quat_mul(rotmat_to_quat(r).expand_as(q), q)
    for i in range(4):
        v[f"rot_{i}"] = q[:, i].numpy()
    rest = sorted((k for k in v.dtype.names if k.startswith("f_rest_")), key=lambda k: int(k[7:]))
    if rest:
        b = len(rest) // 3
        sh = torch.from_numpy(np.stack([v[k] for k in rest], -1).astype(np.float64)).reshape(-1, 3, b).transpose(1, 2)
        sh = rotate_sh(sh, r).transpose(1, 2).reshape(len(v), -1)
        for i, k in enumerate(rest):
            v[k] = sh[:, i].numpy()
    PlyData([PlyElement.describe(v, "vertex")], text=False).write(str(out))
    return out
