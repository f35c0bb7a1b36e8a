"""A 3DGS model trained elsewhere as the start of a run (``TrainConfig.init_ply``, ``train --from-ply``).

The informed posterior is built from a trained model and the training views alone (the Fisher of the pixel
likelihood at the posterior mean: ``Trainer.update_posterior``), so any 3DGS model of the scene can get one: its
Gaussians are read from the file (``io.ply.read_standard_ply``), moved into the run's normalised frame, and the
trainer gives the large ones a posterior that renders them as the file does (``ops.spawn``'s ``keep_render``).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from pathlib import Path

import torch

from uncertsplat.errors import UserError
from uncertsplat.gaussians.ops import quat_to_rotmat, rotmat_to_quat
from uncertsplat.gaussians.params import GaussianModel
from uncertsplat.gaussians.prior import empty_tables
from uncertsplat.io.ply import read_standard_ply
from uncertsplat.render.project import points_in_view
from uncertsplat.render.sh import rotate_sh
from uncertsplat.types import Cameras, GaussianSample, SceneData, similarity_scale

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


ALIGNED_RESIDUAL = 0.05
"""A model whose solid Gaussians' distance to the scene's sparse points (``sfm.align``'s residual: the nearest 70 %
of the points' mean distance over the points' radius) is at most this lies on them: read in the scene's source frame
it is kept there, and a frame found by ``init_ply_frame = "align"`` is taken. Models in their right frame measured
0.005 (fern, a plain 3DGS model of 112,664 Gaussians on 3,747 SfM points) to 0.009 (the demo scene); read in a wrong
one, 0.3-1."""
SOLID_OPACITY = 0.5
"""Only Gaussians at least this opaque are placed on the sparse points (SfM points lie on surfaces; faint Gaussians
are where training left fog)."""


def _sparse_points(scene: SceneData) -> torch.Tensor | None:
    """The scene's SfM points [P,3] in the run's frame, or None for random initial points (a scene without a point
    cloud) or too few to place a model on."""
    from uncertsplat.sfm.align import MIN_POINTS

    if not str(scene.source.get("initial_points", "")).endswith("sparse points"):
        return None
    return scene.points if scene.points.shape[0] >= MIN_POINTS else None


def _aligned(path: Path, frame: str, means: torch.Tensor, opacity_logits: torch.Tensor, scene: SceneData
             ) -> tuple[torch.Tensor | None, dict | None, str | None]:
    """(file_from_source [4,4] float64 or None, the alignment's record or None, a note or None) for a foreign file
    read without a transform: ``frame`` "align" finds the frame; "auto" measures how far the Gaussians read in the
    source frame lie from the scene's sparse points and finds a frame only when they do not lie on them."""
    import numpy as np

    from uncertsplat.sfm.align import MIN_FIRMNESS, MIN_POINTS, SLIDE, placement_residual, register_clouds

    points = _sparse_points(scene)
    if means.shape[0] < MIN_POINTS:
        if frame == "align":
            raise UserError(f"init_ply_frame = \"align\" places the model's Gaussians on the scene's sparse points, and "
                            f"the model has {means.shape[0]} (at least {MIN_POINTS} are needed)", path=path,
                            hint="Read it in a frame given: --set init_ply_frame=source|run, or --from-ply-transform "
                            "FILE.")
        return None, None, None
    if points is None:
        if frame == "align":
            raise UserError("init_ply_frame = \"align\" places the model's Gaussians on the scene's sparse points, and "
                            "this scene has none (" + str(scene.source.get("initial_points", "no points")) + ")",
                            path=path, hint="Give the scene's COLMAP model with its points3D (the one the model was "
                            "trained on), or the transform the trainer used: --from-ply-transform FILE.")
        return None, None, None
    solid = torch.sigmoid(opacity_logits) >= SOLID_OPACITY
    cloud = means[solid] if int(solid.sum()) >= MIN_POINTS else means
    cloud_np = cloud.double().cpu().numpy()
    pts = points.double().cpu().numpy()
    file_from_run_source = np.linalg.inv(scene.world_from_source.double().cpu().numpy())
    source_residual = placement_residual(pts, cloud_np, file_from_run_source)
    if frame == "auto" and source_residual <= ALIGNED_RESIDUAL:
        return None, None, None
    began = time.perf_counter()  # (said: train's "done" line times the posterior only)
    reg = register_clouds(pts, cloud_np)
    searched = time.perf_counter() - began
    if frame == "auto" and not (reg.residual <= ALIGNED_RESIDUAL and reg.residual < 0.5 * source_residual):
        # said: the renders' warning that follows would otherwise suggest the search that was just made
        found = (f"nor in the best frame found for them ({reg.residual:.3f}; {ALIGNED_RESIDUAL:g} or less lies on "
                 "them)" if reg.residual > ALIGNED_RESIDUAL else
                 f"and the best frame found for them places them hardly nearer ({reg.residual:.3f})")
        return None, None, (f"the model's Gaussians do not lie on the scene's sparse points as read in the scene's "
                            f"source frame ({source_residual:.3f} of the points' radius from them), {found}: read in "
                            "the source frame; the model may be of another scene or of another mapping of the "
                            "photos (--from-ply-transform FILE gives the trainer's frame)")
    if reg.residual <= ALIGNED_RESIDUAL and reg.firmness < MIN_FIRMNESS:
        # a placement near the points that they do not pin (points on about one plane or line: the model slides
        # along them, turned, shifted and scaled, as near to them as anywhere; a frame taken so was measured twice
        # the scale and turned half round; a model of another scene sharing a room's walls: 1.07-1.14 on the tiny
        # scene, taken before at a residual of 0.026-0.029): its small residual says nothing, so no frame is found
        why = (f"the scene's {pts.shape[0]:,} sparse points do not pin one (slid along them by {SLIDE:.0%} of "
               f"their radius, the found frame leaves them {reg.firmness:.2f}x as far from the Gaussians: they lie on "
               "about one plane or along one line, or the model is of another scene)")
        if frame == "align":
            raise UserError(f"init_ply_frame = \"align\" found a frame that {why}", path=path,
                            hint="Give the transform the trainer used (--from-ply-transform FILE: nerfstudio's "
                            "dataparser_transforms.json), or train the model in the scene's source frame "
                            "(INRIA's 3DGS and gsplat without normalisation write it there).")
        return None, None, (f"the model's Gaussians do not lie on the scene's sparse points as read in the scene's "
                            f"source frame, and a frame found for them cannot be taken: {why}; read in the source frame "
                            "(--from-ply-transform FILE gives the trainer's)")
    file_from_source = torch.from_numpy(reg.dst_from_src @ scene.world_from_source.double().cpu().numpy())
    rot = reg.dst_from_src[:3, :3] / reg.scale
    angle = math.degrees(math.acos(max(-1.0, min(1.0, (float(np.trace(rot)) - 1.0) / 2.0))))
    record = {"file_from_source": file_from_source.tolist(), "residual": reg.residual, "refined_psnr": None,
              "source_residual": source_residual, "points": int(pts.shape[0]), "gaussians": int(cloud_np.shape[0])}
    placed = (f"placed on the scene's {pts.shape[0]:,} sparse points in {searched:.1f} s by a similarity (from the "
              f"run's frame: scale x{reg.scale:.4g}, turned {angle:.1f} degrees; {cloud_np.shape[0]:,} Gaussians "
              f"at least {SOLID_OPACITY} opaque lie {reg.residual:.3f} of the points' radius from them, against "
              f"{source_residual:.3f} read in the scene's source frame)")
    if frame == "auto":
        note = (f"the model's Gaussians do not lie on the scene's sparse points as read in the scene's source frame, so "
                f"its frame was found: {placed}; --set init_ply_frame=source reads it as it is")
    elif reg.residual > ALIGNED_RESIDUAL:
        note = (f"init_ply_frame = \"align\": the best frame found leaves the model off the scene's points ({placed}): "
                "the model may be of another mapping of the photos, or of another scene")
    else:
        note = f"init_ply_frame = \"align\": {placed}"
    return file_from_source, record, note


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
    if record.get("frame") == "aligned":
        return "the frame found by placing its Gaussians on the scene's sparse points"
    return "the scene source's frame" if record.get("frame") == "source" else "the run's frame"


def _in_view(means: torch.Tensor, cams: Cameras) -> torch.Tensor:
    """[N] bool: which of ``means`` [N,3] some camera of ``cams`` has in front of it and inside its image (16
    cameras at a time)."""
    seen = torch.zeros(means.shape[0], dtype=torch.bool)
    for lo in range(0, len(cams), 16):
        seen |= points_in_view(means, cams[lo:lo + 16]).any(0)
    return seen


def _moved(params: dict[str, torch.Tensor], a: torch.Tensor, shift: torch.Tensor, s: float) -> dict[str, torch.Tensor]:
    """The file's parameters moved by x_run = A x_file + shift (A = s R): positions, log-scales, rotations and SH."""
    p = {k: v.clone() for k, v in params.items()}
    p["means"] = (p["means"].double() @ a.T + shift).float()
    p["scales"] = p["scales"] + math.log(s)
    r = a / s
    if not torch.allclose(r, torch.eye(3, dtype=torch.float64), rtol=0, atol=1e-12):  # a turned frame
        q = rotmat_to_quat(r)  # [4]
        p["quats"] = _quat_mul(q.to(p["quats"].dtype).expand_as(p["quats"]), p["quats"])
        p["shN"] = rotate_sh(p["shN"].double(), r).float()
    return p


Refine = Callable[[dict[str, torch.Tensor], int], tuple[torch.Tensor, float, float]]
"""A frame's photometric refinement (``refine_frame`` bound to a run's views): (the Gaussians' parameters in the run's
frame, their SH degree) -> (run_from_run [4,4] float64 that moves them onto the photos, PSNR before, after)."""


REFINE_SCHEDULE = ((0.25, 30), (0.5, 30), (1.0, 40))
"""``refine_frame``'s rounds: (image scale, Adam steps), coarse first: a frame the sparse points left a few pixels off
at full size is under a pixel off at a quarter of it, where the photometric loss still sees the way."""


def refine_frame(params: dict[str, torch.Tensor], sh_degree: int, cams: Cameras,
                 photo: Callable[[int], torch.Tensor], render_rgb: Callable[[GaussianSample, Cameras], torch.Tensor],
                 *, extent: float, mask: Callable[[int], torch.Tensor | None] = lambda i: None,
                 schedule: tuple[tuple[float, int], ...] = REFINE_SCHEDULE) -> tuple[torch.Tensor, float, float]:
    """The similarity (run_from_run [4,4] float64) that moves the Gaussians ``params`` (the file's parameters in the
    run's frame, as ``_moved`` gives them) onto the photos, and the mean PSNR of the views ``cams`` before and after.

    A global turn w, shift v and scale e^sigma about the Gaussians' centre c (x -> c + e^sigma exp([w]x) (x - c) + v,
    sizes x e^sigma, rotations turned by w; the SH colours are left unturned, a fraction of a degree), fitted by Adam
    to the L1 difference between each view's render and ``photo(i)`` [H,W,3] (masked by ``mask(i)`` [H,W,1]), one
    view a step in turn, at each ``schedule`` scale. ``render_rgb(sample, cameras)`` -> [1,H,W,3].
    """
    import torch.nn.functional as F

    from uncertsplat.eval.image import psnr

    dev = params["means"].device
    means = params["means"].detach().double()
    c = means.mean(0)
    base = {k: v.detach() for k, v in params.items()}
    sh = torch.cat([base["sh0"], base["shN"]], dim=1)
    opacities = torch.sigmoid(base["opacities"])
    w = torch.zeros(3, dtype=torch.float64, device=dev, requires_grad=True)
    v = torch.zeros(3, dtype=torch.float64, device=dev, requires_grad=True)
    sigma = torch.zeros(1, dtype=torch.float64, device=dev, requires_grad=True)

    def turn() -> torch.Tensor:
        """[4] wxyz: the turn by the angle |w| about w (its half-angle kept off 0, so differentiable at w = 0)."""
        half = 0.5 * torch.sqrt((w * w).sum() + 1e-24)
        return torch.cat([torch.cos(half)[None], torch.sin(half) * w / (2.0 * half)])

    def sample() -> GaussianSample:
        q_turn = turn()
        r = quat_to_rotmat(q_turn[None])[0]
        grow = torch.exp(sigma)
        moved = c + grow * (means - c) @ r.T + v
        q = _quat_mul(q_turn.to(base["quats"].dtype).expand_as(base["quats"]), base["quats"])
        return GaussianSample(moved.float(), q, base["scales"].exp() * grow.float(), opacities, sh, sh_degree)

    def views_psnr() -> float:
        with torch.no_grad():
            g = sample()
            return sum(float(psnr(render_rgb(g, cams[i])[0].clamp(0, 1), photo(i), mask(i)))
                       for i in range(len(cams))) / len(cams)

    before = views_psnr()
    rates = (1e-3, 1e-3 * extent, 1e-3)  # radians, scene units, log-scale per step at first
    opt = torch.optim.Adam([{"params": [w], "lr": rates[0]}, {"params": [v], "lr": rates[1]},
                            {"params": [sigma], "lr": rates[2]}])
    for stage, (scale, steps) in enumerate(schedule):
        small = cams.scaled(scale) if scale != 1.0 else cams
        for step in range(steps):
            # each stage from half the last's rate down to a tenth of that: one view a step pulls the frame its own
            # way, and a rate that ends high leaves the frame where the last few views pulled it
            for group, rate in zip(opt.param_groups, rates, strict=True):
                group["lr"] = rate * 0.5 ** stage * (1.0 - 0.9 * step / steps)
            i = step % len(cams)
            target = photo(i)
            m = mask(i)
            if scale != 1.0:
                target = F.interpolate(target.permute(2, 0, 1)[None], size=(small.height, small.width),
                                       mode="area")[0].permute(1, 2, 0)
                m = None if m is None else (F.interpolate(m.permute(2, 0, 1)[None].float(),
                                                          size=(small.height, small.width), mode="area")[0]
                                            .permute(1, 2, 0) > 0.999).float()
            diff = (render_rgb(sample(), small[i])[0] - target).abs()
            loss = diff.mean() if m is None else (diff * m).sum() / (m.sum() * 3).clamp_min(1)
            opt.zero_grad()
            loss.backward()
            opt.step()
    after = views_psnr()
    with torch.no_grad():
        r, grow = quat_to_rotmat(turn()[None])[0].cpu(), float(torch.exp(sigma))
        out = torch.eye(4, dtype=torch.float64)
        out[:3, :3] = grow * r
        out[:3, 3] = c.cpu() + v.cpu() - grow * r @ c.cpu()
    if after <= before:  # the photos did not take it further: the points' frame as it was
        return torch.eye(4, dtype=torch.float64), before, before
    return out, before, after


def model_from_ply(path: Path, scene: SceneData, train_cams: Cameras, *, frame: str = "auto",
                   transform: Path | None = None, device: torch.device | str = "cpu", refine: Refine | None = None
                   ) -> tuple[GaussianModel, list[str], dict]:
    """The Gaussians of the 3DGS model in ``path`` as a model without posterior carriers, in the run's frame.

    ``frame``: ``TrainConfig.init_ply_frame``; ``transform``: ``TrainConfig.init_ply_transform`` (``read_transform``:
    the model is in a frame turned, scaled and shifted from the scene's source one; its rotations and SH
    coefficients are turned back with its positions). A frame found on the scene's sparse points (``_aligned``) is
    then fitted to the photos by ``refine`` (the points place a model to a fraction of a degree, which a render
    shows as pixels). Returns (model, notes for the user, a record for ``train_summary.json``: the file, its frame,
    Gaussians read and kept, the share inside some training view).

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
    file_from_source = None if transform is None else read_transform(transform)
    alignment, align_note = None, None
    if transform is None and (frame == "align" or (frame == "auto" and not ply.ours)):
        file_from_source, alignment, align_note = _aligned(path, frame, ply.params["means"], ply.params["opacities"],
                                                           scene)
    a, shift, s, name = _frame(path, ply.ours, "source" if alignment is not None else frame, scene.world_from_source,
                               file_from_source)
    if alignment is not None:
        name = "aligned"
        if refine is not None:
            began = time.perf_counter()
            run_from_run, before, after = refine(_moved(ply.params, a, shift, s), ply.sh_degree)
            fitted = time.perf_counter() - began
            w = scene.world_from_source.double().cpu()
            file_from_source = file_from_source @ torch.linalg.inv(w) @ torch.linalg.inv(run_from_run) @ w
            a, shift, s, _ = _frame(path, ply.ours, "source", scene.world_from_source, file_from_source)
            alignment = {**alignment, "file_from_source": file_from_source.tolist(), "refined_psnr": [before, after]}
            align_note = (f"{align_note}; fitted to the photos: {before:.2f} -> {after:.2f} dB on the views compared "
                          f"({fitted:.1f} s)")
    p = _moved(ply.params, a, shift, s)
    n = p["means"].shape[0]
    # the share inside some training view, over at most IN_VIEW_SAMPLE evenly spaced Gaussians (a statistic: a
    # million Gaussians x 16 cameras in float64 were 0.7 GB of projections); none of them: every one is looked at
    share = _in_view(p["means"][:: max(1, -(-n // IN_VIEW_SAMPLE))], train_cams).float().mean().item()
    if share == 0.0 and n > IN_VIEW_SAMPLE:
        share = sum(int(_in_view(p["means"][lo:lo + IN_VIEW_SAMPLE], train_cams).sum())
                    for lo in range(0, n, IN_VIEW_SAMPLE)) / n
    notes = list(ply.notes) + ([align_note] if align_note else [])
    how = ("in the scene's source frame (moved into the run's normalised one)" if name == "source" else
           "in the run's normalised frame" if name == "run" else
           "in the frame found by placing its Gaussians on the scene's sparse points" if name == "aligned" else
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
              "in_view_share": share, "notes": list(ply.notes) + ([align_note] if align_note else []),
              "alignment": alignment}
    return model, notes, record
