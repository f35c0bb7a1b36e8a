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
from uncertsplat.gaussians.params import GaussianModel
from uncertsplat.gaussians.prior import empty_tables
from uncertsplat.io.ply import read_standard_ply
from uncertsplat.render.project import points_in_view
from uncertsplat.types import Cameras, SceneData

IN_VIEW_SAMPLE = 100_000
"""The most Gaussians the in-view share (``MIN_IN_VIEW``) is measured over."""
MIN_IN_VIEW = 0.5
"""Below this share of the model's Gaussians inside some training view, ``train`` warns that the model and the
scene may be in different frames (a real capture's model holds some background no view frames, rarely half)."""


def _frame(path: Path, ours: bool, frame: str, world_from_source: torch.Tensor) -> tuple[torch.Tensor, float, str]:
    """(shift [3] float64, scale s, the frame's name) that move the file's Gaussians into the run's frame:
    x_run = s x_file + shift, log-scales + log s."""
    if frame == "run" or (frame == "auto" and ours):
        return torch.zeros(3, dtype=torch.float64), 1.0, "run"
    m = world_from_source.double().cpu()
    s = float(torch.linalg.det(m[:3, :3]).abs() ** (1.0 / 3.0))
    if s <= 0 or not torch.allclose(m[:3, :3], s * torch.eye(3, dtype=torch.float64), rtol=0, atol=1e-9 * s):
        raise UserError("the scene's frame turns its source coordinates (world_from_source is not a scale and a "
                        "shift), which a model's view-dependent colours would have to follow", path=path,
                        hint="Give the model in the run's frame (--set init_ply_frame=run), or a scene loaded "
                        "without the turn.")
    return m[:3, 3].clone(), s, "source"


def _in_view(means: torch.Tensor, cams: Cameras) -> torch.Tensor:
    """[N] bool: which of ``means`` [N,3] some camera of ``cams`` has in front of it and inside its image (16
    cameras at a time)."""
    seen = torch.zeros(means.shape[0], dtype=torch.bool)
    for lo in range(0, len(cams), 16):
        seen |= points_in_view(means, cams[lo:lo + 16]).any(0)
    return seen


def model_from_ply(path: Path, scene: SceneData, train_cams: Cameras, *, frame: str = "auto",
                   device: torch.device | str = "cpu") -> tuple[GaussianModel, list[str], dict]:
    """The Gaussians of the 3DGS model in ``path`` as a model without posterior carriers, in the run's frame.

    ``frame``: ``TrainConfig.init_ply_frame``. Returns (model, notes for the user, a record for
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
    shift, s, name = _frame(path, ply.ours, frame, scene.world_from_source)
    p = {k: v.clone() for k, v in ply.params.items()}
    p["means"] = (p["means"].double() * s + shift).float()
    p["scales"] = p["scales"] + math.log(s)
    n = p["means"].shape[0]
    # the share inside some training view, over at most IN_VIEW_SAMPLE evenly spaced Gaussians (a statistic: a
    # million Gaussians x 16 cameras in float64 were 0.7 GB of projections); none of them: every one is looked at
    share = _in_view(p["means"][:: max(1, -(-n // IN_VIEW_SAMPLE))], train_cams).float().mean().item()
    if share == 0.0 and n > IN_VIEW_SAMPLE:
        share = sum(int(_in_view(p["means"][lo:lo + IN_VIEW_SAMPLE], train_cams).sum())
                    for lo in range(0, n, IN_VIEW_SAMPLE)) / n
    notes = list(ply.notes)
    how = ("in the scene's source frame (moved into the run's normalised one)" if name == "source"
           else "in the run's normalised frame")
    if share == 0.0:
        raise UserError(f"none of the model's {n:,} Gaussians lies in front of a training camera and inside its image "
                        f"(read {how}): the model and the scene do not belong together", path=path,
                        hint="Give the scene the model was trained on (its COLMAP model, not one mapped again: "
                        "another mapping has another frame); for a point_cloud.ply of uncertsplat, "
                        "--set init_ply_frame=run.")
    if share < MIN_IN_VIEW:
        notes.append(f"only {share:.0%} of the model's Gaussians lie inside some training view (read {how}): if its "
                     "renders below are poor, the model and the scene's cameras are in different frames "
                     "(--set init_ply_frame=source|run) or it was trained on another mapping of the photos")
    dev = torch.device(device)
    params = {k: v.contiguous().to(dev) for k, v in p.items()}
    model = GaussianModel(params, empty_tables(1, device=dev, dtype=torch.float32),
                          torch.full((n,), -1, dtype=torch.long, device=dev), ply.sh_degree, 1)
    record = {"path": str(path.resolve()), "frame": name, "gaussians": n, "sh_degree": ply.sh_degree,
              "in_view_share": share, "notes": list(ply.notes)}
    return model, notes, record
