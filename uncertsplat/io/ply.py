"""PLY files of a trained model.

``point_cloud.ply`` (``write_point_cloud_ply``): the standard 3DGS layout that viewers open
(x y z nx ny nz f_dc_0..2 f_rest_0.. opacity scale_0..2 rot_0..3; log-scales, opacity logits, f_rest
channel-major as in 3DGS), holding the *posterior mean* (offsets, multipliers and gates baked in), plus
extra float properties per Gaussian: ``uncertainty_position`` (RMS position std, world units),
``uncertainty_scale`` (mean multiplier width), ``uncertainty_gate`` (gate-logit std),
``uncertainty_switch_off`` (the chance a posterior sample switches the Gaussian mostly off: ``prune``'s ``gate``
score) and ``has_posterior`` (0/1). Viewers ignore properties they do not know.

``read_standard_ply``: a model in that standard layout written by another tool (INRIA's 3DGS, gsplat, nerfstudio's
export, SuperSplat's uncompressed PLY, Mip-Splatting's ``filter_3D`` folded in), for ``train --from-ply``.

``variational.ply`` (``write_variational_ply`` / ``read_variational_ply``): round-trips everything.
Element ``vertex`` holds the *stored* parameters in the same standard names (so it opens in viewers
too, without the posterior) plus ``has_posterior``; element ``offset`` holds one row per table entry
(P x K rows, carrier-major in table-row order) with ``owner`` (the Gaussian index), ``entry`` (0..K-1)
and the raw table columns ``pos_spread_raw_0..2 pos_loc_0..2 scale_width_raw_0..2 scale_left_0..2
gate_spread_raw_0 gate_loc_0``. Only carriers have rows (no NaN padding). Header comments
``uncertsplat key=value`` carry num_entries, sh_degree, variant, extent, step.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from plyfile import PlyData, PlyElement

from uncertsplat.errors import UserError
from uncertsplat.gaussians.params import GaussianModel
from uncertsplat.gaussians.prior import TABLE_SPECS
from uncertsplat.gaussians.variational import carrier_uncertainty, posterior_mean
from uncertsplat.io.atomic import atomic_write

POINT_CLOUD_COMMENT = "uncertsplat point_cloud posterior-mean"
"""The header comment of ``write_point_cloud_ply``'s files: their Gaussians are in the run's normalised frame."""


def _rest_count(sh_degree: int) -> int:
    return 3 * ((sh_degree + 1) ** 2 - 1)


def _standard_fields(means, log_scales, quats, opacity_logits, sh0, shN) -> dict[str, np.ndarray]:
    n = means.shape[0]
    cols: dict[str, np.ndarray] = {}
    m = means.detach().cpu().float().numpy()
    for i, a in enumerate("xyz"):
        cols[a] = m[:, i]
    for a in ("nx", "ny", "nz"):
        cols[a] = np.zeros(n, np.float32)
    dc = sh0.detach().cpu().float().reshape(n, 3).numpy()
    for i in range(3):
        cols[f"f_dc_{i}"] = dc[:, i]
    rest = shN.detach().cpu().float().transpose(1, 2).reshape(n, -1).numpy()  # [N,3*(B-1)] channel-major
    for i in range(rest.shape[1]):
        cols[f"f_rest_{i}"] = rest[:, i]
    cols["opacity"] = opacity_logits.detach().cpu().float().numpy()
    s = log_scales.detach().cpu().float().numpy()
    for i in range(3):
        cols[f"scale_{i}"] = s[:, i]
    q = quats.detach().cpu().float().numpy()
    for i in range(4):
        cols[f"rot_{i}"] = q[:, i]
    return cols


def _vertex(cols: dict[str, np.ndarray], n: int, name: str = "vertex") -> PlyElement:
    dtype = [(k, "f4" if v.dtype.kind == "f" else "i4") for k, v in cols.items()]
    arr = np.empty(n, dtype=dtype)
    for k, v in cols.items():
        arr[k] = v
    return PlyElement.describe(arr, name)


def _write(path: Path, elements: list[PlyElement], comments: list[str]) -> Path:
    ply = PlyData(elements, text=False, byte_order="<", comments=comments)
    return atomic_write(path, lambda f: ply.write(f))


def write_point_cloud_ply(path: str | Path, model: GaussianModel, *, variant: str = "ours", extent: float = 1.0,
                          temperature: float = 0.2, sh_degree: int | None = None) -> Path:
    """Viewer-compatible PLY of the posterior mean with extra per-Gaussian uncertainty properties.

    Not the expected render (``variational.expected_render_sample``): its position blur needs a per-view
    opacity correction that a standard viewer cannot apply. ``sh_degree``: the SH degree the model renders with
    (the run's active one; None: every band it stores): the ``f_rest_*`` of the bands above it are left out (a run
    shorter than the first band test stores degree 3 whose higher bands are all 0: 45 zero columns a viewer read as
    degree 3).
    """
    with torch.no_grad():
        pm = posterior_mean(model, variant=variant, extent=extent, temperature=temperature)
        op = pm.opacities.clamp(1e-7, 1 - 1e-7)
        shN = model.params["shN"]  # [N,B-1,3]
        if sh_degree is not None:
            shN = shN[:, : (int(sh_degree) + 1) ** 2 - 1]
        cols = _standard_fields(pm.means, pm.scales.clamp_min(1e-30).log(), pm.quats, torch.log(op / (1 - op)),
                                model.params["sh0"], shN)
        unc = carrier_uncertainty(model, variant=variant, extent=extent)
    for k in ("position", "scale", "gate", "switch_off"):
        cols[f"uncertainty_{k}"] = unc[k].cpu().float().numpy()
    cols["has_posterior"] = (model.posterior_row >= 0).cpu().float().numpy()
    return _write(Path(path), [_vertex(cols, len(model))], [POINT_CLOUD_COMMENT])


def set_vertex_properties(path: str | Path, cols: dict[str, np.ndarray]) -> None:
    """Set float properties of the ``vertex`` element of a PLY file: a property it has is replaced in place (its
    position kept), a new one appended; the file is rewritten atomically."""
    ply = PlyData.read(str(path))
    v = ply["vertex"].data
    dtype = v.dtype.descr + [(k, "f4") for k in cols if k not in v.dtype.names]
    arr = np.empty(len(v), dtype=dtype)
    for name in v.dtype.names:
        arr[name] = v[name]
    for k, c in cols.items():
        arr[k] = np.asarray(c, dtype=arr.dtype[k])
    others = [e for e in ply.elements if e.name != "vertex"]
    new = PlyData([PlyElement.describe(arr, "vertex"), *others], text=False, byte_order="<", comments=ply.comments)
    atomic_write(Path(path), lambda f: new.write(f))


def write_variational_ply(path: str | Path, model: GaussianModel, *, meta: dict | None = None) -> Path:
    """Everything needed to rebuild ``model`` exactly (see the module docstring for the layout)."""
    p = model.params
    cols = _standard_fields(p["means"], p["scales"], p["quats"], p["opacities"], p["sh0"], p["shN"])
    cols["has_posterior"] = (model.posterior_row >= 0).cpu().to(torch.int32).numpy()
    P, K = model.num_carriers, model.num_entries
    owner = model.carrier_index().cpu()  # [P] in table-row order
    off: dict[str, np.ndarray] = {
        "owner": owner.repeat_interleave(K).to(torch.int32).numpy(),
        "entry": torch.arange(K).repeat(P).to(torch.int32).numpy(),
    }
    for spec in TABLE_SPECS:
        t = model.tables[spec.name].detach().cpu().float().reshape(P * K, spec.width).numpy()
        for j in range(spec.width):
            off[f"{spec.name}_{j}"] = t[:, j]
    info = {"num_entries": K, "sh_degree": model.sh_degree, **(meta or {})}
    elements = [_vertex(cols, len(model)), _vertex(off, P * K, "offset")]
    # a checksum of the binary data, so a flipped bit in a value is detected on reading, not rendered
    info["sha256"] = _data_digest(elements)
    comments = ["uncertsplat variational 1"] + [f"uncertsplat {k}={v}" for k, v in info.items()]
    return _write(Path(path), elements, comments)


_STANDARD = ("x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
             "rot_0", "rot_1", "rot_2", "rot_3")


@dataclass(frozen=True)
class StandardPly:
    """A 3DGS model read by ``read_standard_ply``.

    Attributes:
        params: the stored parameters as ``PARAM_SPECS`` names them (means [N,3], log-scales [N,3], quats [N,4]
            wxyz as written (not normalised), opacity logits [N], sh0 [N,1,3], shN [N,B-1,3]), float32 on the CPU.
        sh_degree: the SH degree its ``f_rest_*`` count gives.
        ours: written by uncertsplat's ``write_point_cloud_ply`` (in a run's normalised frame).
        notes: what was done to the file's values on reading (rows dropped, a 3D filter folded in), for the user.
    """

    params: dict[str, torch.Tensor]
    sh_degree: int
    ours: bool
    notes: tuple[str, ...]


def read_standard_ply(path: str | Path) -> StandardPly:
    """Read a 3DGS model in the standard PLY layout (see the module docstring) that another tool wrote.

    Rows with a value that is not finite in float32 (a double beyond its range included), or a rotation of zero
    length, are dropped (with a note): a NaN would render as nothing in that tool and poison every sum here. Mip-Splatting's ``filter_3D`` (a 3D smoothing filter
    of that size, folded into each Gaussian at render time) is folded in as that renderer does: the variance
    ``filter^2`` added to each axis and the opacity scaled by the square root of the ratio of the determinants.

    Raises:
        UserError: a file that cannot be read, a point cloud or another layout (compressed, variational.ply), a
            property missing, an ``f_rest_*`` count of no SH degree, no usable Gaussian.
    """
    path = Path(path)
    try:
        ply = PlyData.read(str(path))
    except Exception as err:
        raise UserError(f"cannot read the PLY file ({err})", path=path,
                        hint="Give a 3DGS model as the tool that trained it wrote it (point_cloud.ply).") from None
    names = [e.name for e in ply.elements]
    if "offset" in names and any(c.startswith("uncertsplat variational") for c in ply.comments):
        raise UserError("this is a run's variational.ply, which holds the posterior's tables", path=path,
                        hint="Its run needs no import: `uncertsplat evaluate` that run folder directly (or give "
                        "its point_cloud.ply).")
    if "chunk" in names:
        raise UserError("a compressed PLY (SuperSplat's or splat-transform's chunked layout)", path=path,
                        hint="Write it uncompressed first (SuperSplat: export as PLY, not compressed PLY; "
                        "`splat-transform in.compressed.ply out.ply`).")
    if "vertex" not in names:
        raise UserError(f"no vertex element (the file holds {', '.join(names) or 'no element'})", path=path,
                        hint="Give a 3DGS model in the standard layout (x y z f_dc_* f_rest_* opacity scale_* rot_*).")
    v = ply["vertex"].data
    have = set(v.dtype.names or ())
    missing = [k for k in _STANDARD if k not in have]
    if missing:
        what = ("a point cloud (positions and colours), not a 3DGS model" if {"x", "y", "z"} <= have
                and not ({"opacity", "scale_0"} & have) else f"missing the properties {', '.join(missing)}")
        raise UserError(f"{what}: a 3DGS model has {' '.join(_STANDARD[:7])} scale_* rot_* and f_rest_*", path=path,
                        hint="Give the model file a 3DGS trainer wrote (e.g. point_cloud/iteration_30000/"
                        "point_cloud.ply of INRIA's code), not the sparse points.")
    rest = sorted((k for k in have if k.startswith("f_rest_")), key=lambda k: int(k[7:]) if k[7:].isdigit() else -1)
    degrees = {_rest_count(d): d for d in range(5)}
    if len(rest) not in degrees:
        raise UserError(f"{len(rest)} f_rest_* properties, which is the count of no SH degree (0, 9, 24, 45 for "
                        "degrees 0-3)", path=path, hint="The file is not in the standard 3DGS layout.")
    if [k[7:] for k in rest] != [str(i) for i in range(len(rest))]:
        # the count of a degree, numbered otherwise (a gap): "the count of no SH degree" said of 9 was wrong
        raise UserError(f"{len(rest)} f_rest_* properties not numbered f_rest_0 to f_rest_{len(rest) - 1} "
                        f"({', '.join(rest[:3])}{', ...' if len(rest) > 3 else ''})", path=path,
                        hint="The file is not in the standard 3DGS layout.")
    degree = degrees[len(rest)]
    if degree > 3:
        raise UserError(f"SH degree {degree}: the renderer evaluates degrees 0-3", path=path)
    n = len(v)

    def col(*keys):  # [n,len(keys)] float64 (some tools write doubles; the checks below see their values)
        return np.stack([np.asarray(v[k], dtype=np.float64) for k in keys], axis=-1) if keys else np.zeros((n, 0))

    means, log_scales, quats = col("x", "y", "z"), col("scale_0", "scale_1", "scale_2"), col(*_STANDARD[10:])
    logits, dc, fr = col("opacity")[:, 0], col("f_dc_0", "f_dc_1", "f_dc_2"), col(*rest)
    notes = []
    if "filter_3D" in have:  # Mip-Splatting: the 3D filter folded into the scales and the opacity
        f2 = col("filter_3D")[:, 0] ** 2  # [n]
        with np.errstate(all="ignore"):
            rel = f2[:, None] * np.exp(-2.0 * log_scales)  # [n,3] filter^2 / variance
            # in logs: log r = log sqrt(det / det'), and the new logit log(r o) - log(1 - r o) with 1 - r o written
            # (1 - r) + r (1 - o); as r x sigmoid, an opaque Gaussian (logit ~37 and up) that the filter barely
            # changes made 1 - r o = 0, an infinite logit, and a very transparent one log(0): both left out as "not
            # finite" though the file's values were
            log_r = -0.5 * np.log1p(rel).sum(axis=1)  # [n] <= 0
            log_o = -np.logaddexp(0.0, -logits)  # log sigmoid(logit)
            log_not_o = -np.logaddexp(0.0, logits)  # log (1 - sigmoid(logit))
            logits = log_r + log_o - np.logaddexp(np.log(-np.expm1(log_r)), log_r + log_not_o)
            log_scales = log_scales + 0.5 * np.log1p(rel)
        notes.append("Mip-Splatting's filter_3D folded into the scales and opacities (its 2D filter is not "
                     "modelled: the renders may differ slightly from Mip-Splatting's)")
    with np.errstate(over="ignore"):  # the values as stored (float32): a double beyond its range became inf there
        stored = np.concatenate([means, log_scales, quats, logits[:, None], dc, fr], axis=1).astype(np.float32)
    good = np.isfinite(stored).all(axis=1) & (np.linalg.norm(quats, axis=1) > 0)
    if not good.all():
        notes.append(f"{int((~good).sum()):,} of the {n:,} Gaussians have a value that is not finite (or a "
                     "rotation of zero length) and were left out")
    if not good.any():
        raise UserError(f"no Gaussian has finite values (of {n:,})" if n else "the file holds no Gaussian", path=path)

    def t(a):
        return torch.from_numpy(np.ascontiguousarray(a[good], dtype=np.float32))

    m = int(good.sum())
    b = len(rest) // 3
    params = {"means": t(means), "scales": t(log_scales), "quats": t(quats), "opacities": t(logits),
              "sh0": t(dc).reshape(m, 1, 3),
              # f_rest is channel-major (all of red's bases, then green's, then blue's), as write_point_cloud_ply
              "shN": t(fr).reshape(m, 3, b).transpose(1, 2).contiguous()}
    return StandardPly(params, degree, POINT_CLOUD_COMMENT in ply.comments, tuple(notes))


def _data_digest(elements) -> str:
    import hashlib

    h = hashlib.sha256()
    for e in elements:
        h.update(np.ascontiguousarray(e.data).astype(e.data.dtype.newbyteorder("<")).tobytes())
    return h.hexdigest()


def _parse_meta(comments: list[str]) -> dict:
    meta = {}
    for c in comments:
        if c.startswith("uncertsplat ") and "=" in c:
            k, v = c[len("uncertsplat "):].split("=", 1)
            meta[k.strip()] = v.strip()
    return meta


def _damaged_hint(path: Path) -> str:
    """What writes a damaged (cut short) ``variational.ply`` again: "early end-of-file" alone said neither that the
    file is damaged nor what to do. A run with checkpoints writes it again on ``train --resume`` once it is gone (a
    finished run with the file in place has nothing to do), bit for bit; a pruned run has none (``prune`` wrote it)."""
    import json

    from uncertsplat.console import q

    run = path.parent
    said = "The file is damaged (cut short: a copy or a write that did not finish?). "
    if (run / "prune.json").is_file():
        return said + "`uncertsplat prune` wrote it: prune the source run again into a new folder."
    if any((run / "ckpts").glob("*.pt")):
        try:
            scene = json.loads((run / "scene.json").read_text(encoding="utf-8"))["scene"]
        except (OSError, ValueError, KeyError, TypeError):
            scene = "SCENE"
        return said + (f"Move it aside (or delete it), then `uncertsplat train {q(scene)} -o {q(run)} --resume` "
                       "writes it again from the run's last checkpoint; or train the run again.")
    return said + "Train the run again (it has no checkpoint to write it from), or copy the file again from its source."


def read_variational_ply(path: str | Path, device: torch.device | str = "cpu") -> tuple[GaussianModel, dict]:
    """Rebuild the model written by ``write_variational_ply``; returns (model, header metadata)."""
    path = Path(path)
    try:
        ply = PlyData.read(str(path))
    except Exception as err:
        raise UserError(f"cannot read the PLY file ({err})", path=path, hint=_damaged_hint(path)) from None
    meta = _parse_meta(list(ply.comments))
    names = [e.name for e in ply.elements]
    if "vertex" not in names or "offset" not in names or "num_entries" not in meta:
        raise UserError("not a variational.ply written by uncertsplat (missing elements or metadata)", path=path,
                        hint="Use the variational.ply of a run folder; point_cloud.ply has no offset tables.")
    if "sha256" in meta and _data_digest([ply["vertex"], ply["offset"]]) != meta["sha256"]:
        raise UserError("checksum mismatch: the PLY file is corrupted", path=path,
                        hint="Restore it from a copy, or re-create it from the run's checkpoints with "
                        "`uncertsplat train ... --resume`.")
    v = ply["vertex"].data
    n = len(v)
    sh_degree, K = int(meta["sh_degree"]), int(meta["num_entries"])

    def col(data, *keys):
        return torch.from_numpy(np.stack([np.asarray(data[k], dtype=np.float32) for k in keys], axis=-1))

    nrest = _rest_count(sh_degree)
    params = {
        "means": col(v, "x", "y", "z"),
        "scales": col(v, "scale_0", "scale_1", "scale_2"),
        "quats": col(v, "rot_0", "rot_1", "rot_2", "rot_3"),
        "opacities": torch.from_numpy(np.asarray(v["opacity"], dtype=np.float32)),
        "sh0": col(v, "f_dc_0", "f_dc_1", "f_dc_2").reshape(n, 1, 3),
        "shN": (col(v, *[f"f_rest_{i}" for i in range(nrest)]).reshape(n, 3, nrest // 3).transpose(1, 2)
                if nrest else torch.zeros(n, 0, 3)),
    }
    o = ply["offset"].data
    P = len(o) // K
    owner = torch.from_numpy(np.asarray(o["owner"], dtype=np.int64)).reshape(P, K)[:, 0] if P else torch.zeros(0, dtype=torch.long)
    row = torch.full((n,), -1, dtype=torch.long)
    row[owner] = torch.arange(P)
    tables = {}
    for spec in TABLE_SPECS:
        keys = [f"{spec.name}_{j}" for j in range(spec.width)]
        tables[spec.name] = col(o, *keys).reshape(P, K, spec.width) if P else torch.zeros(0, K, spec.width)
    dev = torch.device(device)
    model = GaussianModel({k: t.contiguous().to(dev) for k, t in params.items()},
                          {k: t.contiguous().to(dev) for k, t in tables.items()}, row.to(dev), sh_degree, K)
    try:
        model.check()
    except ValueError as err:
        raise UserError(f"the PLY file is inconsistent ({err})", path=path) from None
    return model, meta
