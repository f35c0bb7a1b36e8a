"""Candidate cameras for ``select-views``: where the next photo could be taken from.

``--candidates`` is one of:

- ``unused``: the scene's images that the run neither trained on nor held out (the active-learning
  protocol: the pool of photos not used yet). Needs a run trained on explicit ``scene.train_names``.
- ``around`` or ``around:N``: N viewpoints (default 32) near the current training cameras: each is a
  training camera (drawn with the seed) moved by up to ``around_radius`` times the median spacing of the
  training cameras, turned to look at the point its source camera looked at (a user extending a capture).
- a file of poses, one per line: ``NAME QW QX QY QZ TX TY TZ``, the camera-from-world rotation (unit
  quaternion, scalar first) and translation as in COLMAP's ``images.txt``, in the coordinates of the scene the
  run was trained on (its COLMAP model or transforms file; ``RUN/scene.json`` records the similarity to the
  run's normalised world); NAME is what comes before the last seven numbers (it may hold spaces). Blank lines
  and lines starting with ``#`` are skipped. The cameras take the
  intrinsics and image size of the run's first training view.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor

from uncertsplat.data.synthetic import look_at
from uncertsplat.errors import UserError
from uncertsplat.gaussians.ops import quat_to_rotmat, rotmat_to_quat
from uncertsplat.render.project import points_in_view
from uncertsplat.types import Cameras, SceneData, similarity_scale

DEFAULT_AROUND = 32


@dataclass(frozen=True)
class Candidates:
    """Candidate cameras and where they came from.

    Attributes:
        cameras: C cameras (world = the run's normalised coordinates), named.
        kind: "unused", "around" or "file".
        scene_indices: for "unused", each candidate's index in the scene (None otherwise).
    """

    cameras: Cameras
    kind: str
    scene_indices: tuple[int, ...] | None = None

    def __len__(self) -> int:
        return len(self.cameras)


def unused_views(scene: SceneData) -> list[int]:
    """Scene indices neither trained on, held out nor set aside for calibration, nor the pose twin of a view held out
    or set aside (``sfm.scene.held_out_twins``: the same picture, which training on would make that view's score one of
    memory)."""
    from uncertsplat.sfm.scene import held_out_twins

    held = [*scene.split.get("test", ()), *scene.split.get("calibration", ())]
    used = set(scene.split.get("train", ())) | set(held)
    free = [i for i in range(len(scene.cameras)) if i not in used]
    found = held_out_twins(scene.cameras, scene.split, free)
    twins = {j for js in found.values() for j in js}
    if twins:  # said, not dropped silently ("only N candidates were there" named none)
        from uncertsplat.console import console

        names = scene.cameras.image_names
        pairs = ", ".join(f"{names[j]} (as {names[h]})" for h, js in found.items() for j in js)
        console.print(f"[yellow]note:[/] left out of the candidates as the same picture as a held-out view: {pairs}")
    return [i for i in free if i not in twins]


def around_views(scene: SceneData, n: int, radius: float, generator: torch.Generator) -> Cameras:
    """``n`` viewpoints near the training cameras (see the module docstring)."""
    train = list(scene.split["train"])
    cams = scene.cameras[train]
    centres = cams.centers.double()
    if len(train) > 1:
        d = torch.cdist(centres, centres) + torch.eye(len(train), dtype=centres.dtype) * 1e30
        spacing = float(d.min(1).values.median())
    else:
        spacing = 0.1 * scene.scene_scale
    world_from_cam = torch.linalg.inv(cams.cam_from_world.double())
    out = []
    for _ in range(n):
        j = int(torch.randint(len(train), (1,), generator=generator))
        offset = torch.randn(3, generator=generator, dtype=torch.float64)
        offset = offset / offset.norm().clamp_min(1e-12) * radius * spacing * float(torch.rand(1, generator=generator))
        # drawn in the camera's axes, not the world's: the candidates of a scene turned are the candidates turned
        # (along the world's axes, a rotated copy of a scene got candidates up to 0.38 of its radius apart)
        offset = world_from_cam[j, :3, :3] @ offset
        forward, up = world_from_cam[j, :3, 2], -world_from_cam[j, :3, 1]
        target = centres[j] + forward * max(float(centres[j].norm()), spacing)  # as far as the scene centre
        out.append(look_at(centres[j] + offset, target, up))
    K = cams.K[[0] * n] if n else cams.K[:0]
    # apart from the scene's photos: a capture that names each photo by its candidate (around_012.png) was offered
    # around_012 again in the next round, and a script writing photos by name would replace the first
    stems = {Path(name).stem for name in scene.cameras.image_names}
    prefix, round_ = "around", 1
    while any(f"{prefix}_{i:03d}" in stems for i in range(n)):
        round_ += 1
        prefix = f"around{round_}"
    names = tuple(f"{prefix}_{i:03d}" for i in range(n))
    return Cameras(torch.stack(out).float() if out else cams.cam_from_world[:0], K, cams.width, cams.height, names)


MAX_AROUND = 10_000
"""``around:N`` at most (every candidate is rendered and scored: 5,000 took 4 s on the tiny scene)."""


def _number(word: str) -> bool:
    try:
        float(word)
    except ValueError:
        return False
    return True


def read_pose_file(path: Path, scene: SceneData, world_from_source: Tensor) -> Cameras:
    """Cameras of a pose file (see the module docstring).

    Raises:
        UserError: naming the file and the line of a malformed pose, or an empty file.
    """
    path = Path(path)
    if path.is_dir():  # (it was "not found": a folder of photos, say, given for the file of their poses)
        raise UserError("--candidates names a folder, not a file of poses", path=path,
                        hint="Give 'unused', 'around[:N]' or a text file of lines 'NAME QW QX QY QZ TX TY TZ' (one "
                             "pose a line, camera-from-world in the scene's own coordinates).")
    if not path.is_file():
        raise UserError("candidate pose file not found" + ("" if path.is_absolute() else f" (looked for {path.resolve()}:"
                                                                  " a relative path is read from the current folder, "
                                                                  "or from the folder of a --config file that gives "
                                                                  "it)"),
                        path=path, hint="Give 'unused', 'around[:N]' or a file of lines 'NAME QW QX QY QZ TX TY TZ'.")
    rows: list[Tensor] = []
    names: list[str] = []
    source_from_world = torch.linalg.inv(world_from_source.double())
    scale = similarity_scale(world_from_source)
    # (utf-8-sig: a file an editor saved with a byte-order mark, whose first name or comment would begin with it)
    for number, line in enumerate(path.read_text(encoding="utf-8-sig", errors="replace").splitlines(), start=1):
        text = line.strip()
        if not text or text.startswith("#"):
            continue
        fields = text.rsplit(None, 7)  # the name is what comes before the 7 numbers: a photo's name may hold spaces
        words = text.split()
        if len(words) >= 10 and words[0].isdigit() and words[8].isdigit() and all(_number(w) for w in words[1:8]):
            # COLMAP's images.txt itself (the file the format is named after): its layout is another
            raise UserError(f"line {number} is in the layout of COLMAP's images.txt (IMAGE_ID QW QX QY QZ TX TY TZ "
                            f"CAMERA_ID NAME, then a line of 2D points), not 'NAME QW QX QY QZ TX TY TZ'", path=path,
                            hint="Write one line 'NAME QW QX QY QZ TX TY TZ' per pose, e.g. from images.txt: awk "
                                 "'!/^#/ && n++ % 2 == 0 {print $10, $2, $3, $4, $5, $6, $7, $8}' images.txt > plan.txt (every "
                                 "other line after the comments is an image's)")
        if len(fields) != 8 or (len(words) > 8 and _number(words[-8])):
            # (a name with spaces ending in a number is a line with a column too many: its numbers would shift)
            raise UserError(f"line {number}: expected 'NAME QW QX QY QZ TX TY TZ' (8 fields), found {len(words)}: "
                            f"{text[:80]!r}", path=path,
                            hint="A name with spaces must not end in a number (IMG 0042.jpg reads; IMG 0042 does not).")
        try:
            values = [float(v) for v in fields[1:]]
        except ValueError:
            raise UserError(f"line {number}: the pose is not 7 numbers: {' '.join(fields[1:])[:80]!r}",
                            path=path) from None
        if not all(math.isfinite(v) for v in values):
            raise UserError(f"line {number}: the pose has a non-finite number", path=path)
        q = torch.tensor(values[:4], dtype=torch.float64)
        if float(q.norm()) < 1e-6:
            raise UserError(f"line {number}: the rotation quaternion is zero", path=path,
                            hint="Write a unit quaternion QW QX QY QZ (e.g. 1 0 0 0).")
        if abs(float(q.norm()) - 1.0) > 1e-3:
            raise UserError(f"line {number}: the rotation quaternion has norm {float(q.norm()):.4g}, not 1", path=path,
                            hint="Normalise it (divide QW QX QY QZ by their norm).")
        cam_from_source = torch.eye(4, dtype=torch.float64)
        cam_from_source[:3, :3] = quat_to_rotmat(q[None])[0]
        cam_from_source[:3, 3] = torch.tensor(values[4:], dtype=torch.float64)
        # world = s R0 source + t0: through source_from_world the camera frame shrinks by 1/s; scaling its rows
        # by s gives a rigid cam_from_world whose depths are in world units
        T = cam_from_source @ source_from_world
        T[:3, :] *= scale
        if not bool(torch.isfinite(T.float()).all()):  # (1e300 passed as finite, became inf / NaN, and ranked first)
            raise UserError(f"line {number}: the camera lies too far away to compute with (translation "
                            f"{max(abs(v) for v in values[4:]):.3g} in the scene's units)", path=path,
                            hint="Check TX TY TZ: the translation of the world-to-camera pose, in the units of the "
                                 "scene's own frame (its COLMAP model's).")
        rows.append(T)
        names.append(fields[0])
    if not rows:
        raise UserError("the candidate pose file holds no pose", path=path,
                        hint="Write one line 'NAME QW QX QY QZ TX TY TZ' per candidate camera.")
    if len(set(names)) != len(names):
        dup = sorted({n for n in names if names.count(n) > 1})
        raise UserError(f"candidate names repeat: {', '.join(dup[:5])}", path=path, hint="Give every pose its own name.")
    first = scene.cameras[[scene.split["train"][0]]]
    return Cameras(torch.stack(rows).float(), first.K.expand(len(rows), 3, 3).clone(), first.width, first.height,
                   tuple(names))


def pose_line(name: str, cam_from_world: Tensor, world_from_source: Tensor) -> str:
    """The camera ``cam_from_world`` [4,4] of the run's normalised world as a line of a ``--candidates`` pose file,
    ``NAME QW QX QY QZ TX TY TZ`` in the scene's own (COLMAP) frame: the inverse of ``read_pose_file``'s mapping.

    The camera's centre is what is kept: it is taken to the scene's frame in float64, and the translation written
    is the one of the rotation the quaternion gives back, with 15 significant digits (UTM northings reach 1e7). Far
    from the scene's origin (a georeferenced scene, translations of 1e6) the float32 rotation's departure from a
    rotation (1e-7) times the translation, and 9 digits, put the centre read back 0.016 of the scene's radius away
    (0.17 at 1e7)."""
    world_from_source = world_from_source.double()
    scale = similarity_scale(world_from_source)
    T = cam_from_world.double()
    centre = -torch.linalg.solve(T[:3, :3], T[:3, 3])  # [3] in the run's world: the matrix's own centre
    source_from_world = torch.linalg.inv(world_from_source)
    centre_source = source_from_world[:3, :3] @ centre + source_from_world[:3, 3]
    q = rotmat_to_quat(T[:3, :3] @ (world_from_source[:3, :3] / scale))
    q = q / q.norm()
    R = quat_to_rotmat(q[None])[0]  # the rotation a reader makes of the quaternion
    values = [*q.tolist(), *(-R @ centre_source).tolist()]
    return " ".join([name, *(f"{v:.15g}" for v in values)])


def seen_fraction(cameras: Cameras, points: Tensor) -> Tensor:
    """[C] the fraction of ``points`` [N,3] (world) in front of each camera and inside its image: a candidate pose
    that sees almost none of the model is most likely given in another convention (camera-to-world, x y z w)."""
    if not len(cameras):
        return torch.zeros(0)
    if not len(points):
        return torch.zeros(len(cameras))
    # one camera at a time: [C,N] float64 projections of a large model for many candidates would not fit
    return torch.cat([points_in_view(points, cameras[[j]]).double().mean(1) for j in range(len(cameras))]).float()


def blind_candidates_note(candidates: Cameras, train: Cameras, points: Tensor) -> str | None:
    """The note for candidates that see under a tenth of what the training views see of ``points`` (median): by
    name, with the fractions, what such a pose means when it faces unexplored space (a robot's path turned away from
    what it saw: the fisher score gives it 0) and the conventions most often mixed up; None when every candidate
    sees the model."""
    seen, ref = seen_fraction(candidates, points), seen_fraction(train, points)
    if not len(seen) or not len(ref):
        return None
    usual = float(ref.median())
    blind = [j for j in range(len(seen)) if float(seen[j]) < 0.1 * usual]
    if not blind:
        return None
    names = candidates.image_names or tuple(f"candidate {j}" for j in range(len(seen)))
    listed = ", ".join(f"{names[j]} {100 * float(seen[j]):.1f} %" for j in blind[:6]) + (", ..." if len(blind) > 6
                                                                                      else "")
    return (f"{len(blind)} of {len(seen)} candidate(s) see almost none of the model ({listed} of its Gaussians in view, "
            f"the training views {100 * usual:.0f} %): where they face what no photo has seen, the model holds nothing "
            "there, and the fisher score measures only the few Gaussians they see (--score variance ranks such views "
            "by their empty rays); "
            "otherwise check the pose file's convention (world-to-camera, the quaternion as w x y z, the scene's "
            "units and frame)")


def candidates_from_spec(spec: str, scene: SceneData, world_from_source: Tensor, *, radius: float,
                         generator: torch.Generator) -> Candidates:
    """The candidates of a ``--candidates`` value (see the module docstring).

    Raises:
        UserError: an unknown spec, no unused view, a bad pose file.
    """
    if spec == "unused":
        idx = unused_views(scene)
        if not idx:
            raise UserError("the run's scene has no unused view: every image is trained on or held out",
                            hint="Use --candidates around[:N] or a file of poses, or train on a subset of the images "
                                 "(--set scene.train_names=[...]).")
        return Candidates(scene.cameras[idx], "unused", tuple(idx))
    if spec == "around" or spec.startswith("around:"):
        try:
            n = int(spec.split(":", 1)[1]) if ":" in spec else DEFAULT_AROUND
        except ValueError:
            n = -1
        if n < 1 or n > MAX_AROUND:  # (10^11 ran on without a word: every candidate is rendered and scored)
            raise UserError(f"--candidates {spec}: N must be a whole number from 1 to {MAX_AROUND:,} (e.g. around:32)")
        return Candidates(around_views(scene, n, radius, generator), "around")
    if Path(spec).suffix or Path(spec).exists():
        return Candidates(read_pose_file(Path(spec), scene, world_from_source), "file")
    raise UserError(f"--candidates {spec!r} is neither 'unused', 'around[:N]' nor a file",
                    hint="Give 'unused' (the scene's images not used yet), 'around:32' (viewpoints near the "
                         "training cameras) or a file of lines 'NAME QW QX QY QZ TX TY TZ'.")


__all__ = ["Candidates", "DEFAULT_AROUND", "around_views", "candidates_from_spec", "read_pose_file", "unused_views"]
