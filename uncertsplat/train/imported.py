"""A 3DGS model trained elsewhere as the start of a run (``TrainConfig.init_ply``, ``train --from-ply``).

The informed posterior is built from a trained model and the training views alone (the Fisher of the pixel
likelihood at the posterior mean: ``Trainer.update_posterior``), so any 3DGS model of the scene can get one: its
Gaussians are read from the file (``io.ply.read_standard_ply``), moved into the run's normalised frame, and the
trainer gives the large ones a posterior that renders them as the file does (``ops.spawn``'s ``keep_render``).
"""

from __future__ import annotations

import math
from pathlib import Path

import torch

from uncertsplat.errors import UserError
from uncertsplat.gaussians.ops import rotmat_to_quat
from uncertsplat.gaussians.params import GaussianModel
from uncertsplat.gaussians.prior import empty_tables
from uncertsplat.io.ply import read_standard_ply
from uncertsplat.render.project import points_in_view
from uncertsplat.render.sh import rotate_sh
from uncertsplat.types import Cameras, SceneData, similarity_scale

IN_VIEW_SAMPLE = 100_000
"""The most Gaussians the in-view share (``MIN_IN_VIEW``) is measured over."""
MIN_IN_VIEW = 0.5
"""Below this share of the model's Gaussians inside some training view, ``train`` warns that the model and the
scene may be in different frames (a real capture's model holds some background no view frames, rarely half)."""


def read_transform(path: Path) -> torch.Tensor:
    """``file_from_source`` [4,4] float64 of ``TrainConfig.init_ply_transform``: the similarity that took the scene's
    source coordinates into the model file's (x_file = s R x_source + t).

    Read from nerfstudio's ``dataparser_transforms.json`` (``transform`` [3x4] and ``scale``: x_file = scale x
    (transform [x_source; 1])), or a JSON object ``{"file_from_source": [[4x4]]}``, or a bare 4x4 list.

    Raises:
        UserError: a file that cannot be read or holds none of these.
    """
    import json

    path = Path(path).expanduser()
    hint = ("Give nerfstudio's dataparser_transforms.json (next to the trained model's config.yml), or a JSON file "
            "{\"file_from_source\": [[...], [...], [...], [0, 0, 0, 1]]}.")
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as err:
        raise UserError(f"cannot read the frame's transform ({err})", path=path, hint=hint) from None
    try:
        if isinstance(data, dict) and "transform" in data:
            m = torch.eye(4, dtype=torch.float64)
            m[:3] = torch.tensor(data["transform"], dtype=torch.float64).reshape(3, 4)
            m[:3] *= float(data.get("scale", 1.0))
        else:
            raw = data["file_from_source"] if isinstance(data, dict) else data
            m = torch.tensor(raw, dtype=torch.float64).reshape(4, 4)
    except (KeyError, TypeError, ValueError, RuntimeError) as err:
        raise UserError(f"no transform in the file ({type(err).__name__}: {err})", path=path, hint=hint) from None
    if not bool(torch.isfinite(m).all()) or not torch.allclose(m[3], torch.tensor([0.0, 0, 0, 1], dtype=m.dtype)):
        raise UserError("the transform is not a finite 4x4 matrix whose last row is 0 0 0 1", path=path, hint=hint)
    return m


def _frame(path: Path, ours: bool, frame: str, world_from_source: torch.Tensor,
           file_from_source: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor, float, str]:
    """(A [3,3], shift [3], s, the frame's name), float64, that move the file's Gaussians into the run's frame:
    x_run = A x_file + shift with A = s R (R a proper rotation), log-scales + log s, rotations turned by R."""
    if file_from_source is None and (frame == "run" or (frame == "auto" and ours)):
        return torch.eye(3, dtype=torch.float64), torch.zeros(3, dtype=torch.float64), 1.0, "run"
    run_from_file = world_from_source.double().cpu()
    if file_from_source is not None:
        run_from_file = run_from_file @ torch.linalg.inv(file_from_source.double().cpu())
    a, shift = run_from_file[:3, :3], run_from_file[:3, 3]
    det = float(torch.linalg.det(a))
    s = similarity_scale(run_from_file)
    r = a / s if s > 0 else a
    if det <= 0 or not torch.allclose(r @ r.T, torch.eye(3, dtype=torch.float64), rtol=0, atol=1e-6):
        raise UserError("the model's frame is not a turned, scaled and shifted copy of the scene's (the transform "
                        + ("mirrors it" if det < 0 else "shears or squashes it") + ")", path=path,
                        hint="Check init_ply_transform: a similarity x_file = s R x_source + t, R a rotation.")
    return a, shift.clone(), s, "source" if file_from_source is None else "transform"


def _quat_mul(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """[...,4] wxyz: the rotation b then a (Hamilton product a b)."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack([aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                        aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw], dim=-1)


def frame_phrase(record: dict) -> str:
    """How an imported model's frame was read, for a sentence ("read in ..."): ``record`` is ``model_from_ply``'s
    (``train_summary.json`` ``imported``)."""
    if record.get("frame") == "transform":
        return f"the frame {Path(str(record.get('transform'))).name} takes the scene's source frame to"
    return "the scene source's frame" if record.get("frame") == "source" else "the run's frame"


def _in_view(means: torch.Tensor, cams: Cameras) -> torch.Tensor:
    """[N] bool: which of ``means`` [N,3] some camera of ``cams`` has in front of it and inside its image (16
    cameras at a time)."""
    seen = torch.zeros(means.shape[0], dtype=torch.bool)
    for lo in range(0, len(cams), 16):
        seen |= points_in_view(means, cams[lo:lo + 16]).any(0)
    return seen


def model_from_ply(path: Path, scene: SceneData, train_cams: Cameras, *, frame: str = "auto",
                   transform: Path | None = None, device: torch.device | str = "cpu"
                   ) -> tuple[GaussianModel, list[str], dict]:
    """The Gaussians of the 3DGS model in ``path`` as a model without posterior carriers, in the run's frame.

    ``frame``: ``TrainConfig.init_ply_frame``; ``transform``: ``TrainConfig.init_ply_transform`` (``read_transform``:
    the model is in a frame turned, scaled and shifted from the scene's source one; its rotations and SH
    coefficients are turned back with its positions). Returns (model, notes for the user, a record for
    ``train_summary.json``: the file, its frame, Gaussians read and kept, the share inside some training view).

    Raises:
        UserError: the file (``read_standard_ply``), a frame that cannot be applied, or no Gaussian in front of any
            training camera (the model and the scene do not belong together).
    """
    path = Path(path).expanduser()
    if not path.is_file():
        raise UserError("no such file" if not path.exists() else "not a file", path=path,
                        hint="Give the PLY file of a trained 3DGS model (e.g. point_cloud/iteration_30000/"
                        "point_cloud.ply of INRIA's code).")
    ply = read_standard_ply(path)
    a, shift, s, name = _frame(path, ply.ours, frame, scene.world_from_source,
                               None if transform is None else read_transform(transform))
    p = {k: v.clone() for k, v in ply.params.items()}
    p["means"] = (p["means"].double() @ a.T + shift).float()
    p["scales"] = p["scales"] + math.log(s)
    r = a / s
    if not torch.allclose(r, torch.eye(3, dtype=torch.float64), rtol=0, atol=1e-12):  # a turned frame
        q = rotmat_to_quat(r)  # [4]
        p["quats"] = _quat_mul(q.to(p["quats"].dtype).expand_as(p["quats"]), p["quats"])
        p["shN"] = rotate_sh(p["shN"].double(), r).float()
    n = p["means"].shape[0]
    # the share inside some training view, over at most IN_VIEW_SAMPLE evenly spaced Gaussians (a statistic: a
    # million Gaussians x 16 cameras in float64 were 0.7 GB of projections); none of them: every one is looked at
    share = _in_view(p["means"][:: max(1, -(-n // IN_VIEW_SAMPLE))], train_cams).float().mean().item()
    if share == 0.0 and n > IN_VIEW_SAMPLE:
        share = sum(int(_in_view(p["means"][lo:lo + IN_VIEW_SAMPLE], train_cams).sum())
                    for lo in range(0, n, IN_VIEW_SAMPLE)) / n
    notes = list(ply.notes)
    how = ("in the scene's source frame (moved into the run's normalised one)" if name == "source" else
           "in the run's normalised frame" if name == "run" else
           f"in the frame {Path(transform).name} takes the scene's source frame to")
    if share == 0.0:
        raise UserError(f"none of the model's {n:,} Gaussians lies in front of a training camera and inside its image "
                        f"(read {how}): the model and the scene do not belong together", path=path,
                        hint="Give the scene the model was trained on (its COLMAP model, not one mapped again: "
                        "another mapping has another frame); for a point_cloud.ply of uncertsplat, "
                        "--set init_ply_frame=run.")
    if share < MIN_IN_VIEW:
        notes.append(f"only {share:.0%} of the model's Gaussians lie inside some training view (read {how}): if its "
                     "renders below are poor, the model and the scene's cameras are in different frames "
                     "(--set init_ply_frame=source|run; a trainer that normalises its world: --from-ply-transform) or "
                     "it was trained on another mapping of the photos")
    dev = torch.device(device)
    params = {k: v.contiguous().to(dev) for k, v in p.items()}
    model = GaussianModel(params, empty_tables(1, device=dev, dtype=torch.float32),
                          torch.full((n,), -1, dtype=torch.long, device=dev), ply.sh_degree, 1)
    record = {"path": str(path.resolve()), "frame": name, "gaussians": n, "sh_degree": ply.sh_degree,
              "transform": None if transform is None else str(Path(transform).expanduser().resolve()),
              "in_view_share": share, "notes": list(ply.notes)}
    return model, notes, record
