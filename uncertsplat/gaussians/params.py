"""Per-Gaussian parameters: one row-aligned table, initialised from sparse points.

``PARAM_SPECS`` lists every per-Gaussian attribute once (name, trailing shape, activation, learning-rate
key); ``TABLE_SPECS`` (in ``prior.py``) does the same for the offset tables of posterior carriers.
``GaussianModel`` holds both plus ``posterior_row`` [N] (long; -1 = no posterior), which maps each
Gaussian to its row in the offset tables. Offset tables hold rows only for posterior carriers ("model
only what a scene requires"), so a scene whose Gaussians are mostly small pays almost nothing for them.

Invariant (checked by ``GaussianModel.check``): the values of ``posterior_row`` that are >= 0 are a
permutation of ``0..P-1``: every table row belongs to exactly one Gaussian.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor, nn

from uncertsplat.gaussians.neighbors import nearest_neighbor_distance
from uncertsplat.gaussians.prior import TABLE_SPECS, empty_tables
from uncertsplat.render.sh import rgb_to_sh


@dataclass(frozen=True)
class ParamSpec:
    """One per-Gaussian attribute.

    Attributes:
        name: key in ``GaussianModel.params``.
        shape: trailing shape per Gaussian; ``None`` entries depend on the SH degree (see ``trailing_shape``).
        activation: how the stored value becomes a renderable one (documentation only: no code reads it).
        lr: key into ``LearningRates`` (the optimiser builds one Adam group per attribute).
    """

    name: str
    shape: tuple
    activation: str
    lr: str


PARAM_SPECS: tuple[ParamSpec, ...] = (
    ParamSpec("means", (3,), "identity", "means"),
    ParamSpec("scales", (3,), "exp", "scales"),  # log of the linear standard deviations
    ParamSpec("quats", (4,), "normalize", "quats"),  # wxyz
    ParamSpec("opacities", (), "sigmoid", "opacities"),  # logits
    ParamSpec("sh0", (1, 3), "identity", "sh0"),  # SH DC
    ParamSpec("shN", (None, 3), "identity", "shN"),  # SH rest: (B - 1) bases
)
PARAM_NAMES: tuple[str, ...] = tuple(s.name for s in PARAM_SPECS)


def num_sh_bases(degree: int) -> int:
    return (degree + 1) ** 2


def trailing_shape(spec: ParamSpec, sh_degree: int) -> tuple[int, ...]:
    """The concrete trailing shape of ``spec`` for a model of maximum SH degree ``sh_degree``."""
    return tuple(num_sh_bases(sh_degree) - 1 if d is None else d for d in spec.shape)


class GaussianModel:
    """Row-aligned per-Gaussian parameters plus the offset tables of posterior carriers.

    Attributes:
        params: name -> ``nn.Parameter`` [N,...] as listed in ``PARAM_SPECS`` (stored, not activated).
        tables: name -> ``nn.Parameter`` [P,K,...] as listed in ``gaussians.prior.TABLE_SPECS``.
        posterior_row: [N] long, the table row of each Gaussian, -1 when it carries no posterior.
        sh_degree: maximum SH degree the coefficients allow.
        num_entries: K, offset-table entries per carrier.
    """

    def __init__(self, params: dict[str, Tensor], tables: dict[str, Tensor], posterior_row: Tensor,
                 sh_degree: int, num_entries: int):
        self.params = {k: v if isinstance(v, nn.Parameter) else nn.Parameter(v) for k, v in params.items()}
        self.tables = {k: v if isinstance(v, nn.Parameter) else nn.Parameter(v) for k, v in tables.items()}
        self.posterior_row = posterior_row
        self.sh_degree = sh_degree
        self.num_entries = num_entries

    # ------------------------------------------------------------------------------------ properties
    def __len__(self) -> int:
        return self.params["means"].shape[0]

    @property
    def num_carriers(self) -> int:
        """P: Gaussians that carry a posterior (= rows of the offset tables)."""
        return next(iter(self.tables.values())).shape[0]

    @property
    def device(self) -> torch.device:
        return self.params["means"].device

    @property
    def dtype(self) -> torch.dtype:
        return self.params["means"].dtype

    def parameters(self) -> dict[str, nn.Parameter]:
        """All trainable tensors by name (per-Gaussian first, then tables)."""
        return {**self.params, **self.tables}

    def carrier_index(self) -> Tensor:
        """[P'] indices of the Gaussians that carry a posterior, ordered by their table row.

        Cached until ``posterior_row`` is replaced or modified in place (every training step asks for it;
        it changes only with the topology)."""
        row = self.posterior_row
        cached = getattr(self, "_carrier_cache", None)
        if cached is not None and cached[0] is row and cached[1] == row._version:
            return cached[2]
        idx = (row >= 0).nonzero().flatten()
        idx = idx[torch.argsort(row[idx])]
        self._carrier_cache = (row, row._version, idx)
        return idx

    def check(self) -> None:
        """Raise ``ValueError`` naming the field when the rows are not aligned (used after loading and by tests).

        Checked: every ``PARAM_SPECS`` attribute is present with shape [N, *trailing shape]; ``posterior_row``
        is a long tensor of shape [N]; every ``TABLE_SPECS`` table is present with shape [P, K, D]; the
        values of ``posterior_row`` that are >= 0 are a permutation of ``0..P-1``. Plain ``if`` tests, so
        the checks also run under ``python -O``.
        """
        missing = [s.name for s in PARAM_SPECS if s.name not in self.params]
        if missing:
            raise ValueError(f"GaussianModel.params lacks {', '.join(missing)} (expected {', '.join(PARAM_NAMES)})")
        n = len(self)
        for spec in PARAM_SPECS:
            t = self.params[spec.name]
            want = (n, *trailing_shape(spec, self.sh_degree))
            if tuple(t.shape) != want:
                raise ValueError(f"GaussianModel.params[{spec.name!r}] has shape {tuple(t.shape)}, expected {want} "
                                 f"(N = {n}, sh_degree = {self.sh_degree})")
        row = self.posterior_row
        if not isinstance(row, Tensor) or row.dtype != torch.long or tuple(row.shape) != (n,):
            got = f"{row.dtype} of shape {tuple(row.shape)}" if isinstance(row, Tensor) else type(row).__name__
            raise ValueError(f"GaussianModel.posterior_row must be a torch.long tensor of shape ({n},), not {got}")
        missing = [s.name for s in TABLE_SPECS if s.name not in self.tables]
        if missing:
            raise ValueError(f"GaussianModel.tables lacks {', '.join(missing)}")
        for spec in TABLE_SPECS:
            if self.tables[spec.name].dim() != 3:
                raise ValueError(f"GaussianModel.tables[{spec.name!r}] has shape {tuple(self.tables[spec.name].shape)}, "
                                 f"expected [P, K, {spec.width}]")
        p = self.num_carriers
        for spec in TABLE_SPECS:
            t = self.tables[spec.name]
            want = (p, self.num_entries, spec.width)
            if tuple(t.shape) != want:
                raise ValueError(f"GaussianModel.tables[{spec.name!r}] has shape {tuple(t.shape)}, expected {want} "
                                 f"(P = {p} carriers, num_entries K = {self.num_entries})")
        rows = row[row >= 0]
        if rows.numel() != p:
            raise ValueError(f"GaussianModel.posterior_row marks {rows.numel()} carriers (values >= 0) but the offset "
                             f"tables have {p} rows")
        if not torch.equal(torch.sort(rows).values, torch.arange(p, device=rows.device)):
            raise ValueError(f"GaussianModel.posterior_row: the values >= 0 are not a permutation of 0..{p - 1} "
                             "(a table row is missing or shared by two Gaussians)")

    def state_dict(self) -> dict:
        return {
            "params": {k: v.detach().clone() for k, v in self.params.items()},
            "tables": {k: v.detach().clone() for k, v in self.tables.items()},
            "posterior_row": self.posterior_row.clone(),
            "sh_degree": self.sh_degree,
            "num_entries": self.num_entries,
        }

    @classmethod
    def from_state_dict(cls, state: dict, device: torch.device | None = None) -> GaussianModel:
        def mv(t):
            return t.to(device) if device is not None else t

        model = cls({k: mv(v) for k, v in state["params"].items()}, {k: mv(v) for k, v in state["tables"].items()},
                    mv(state["posterior_row"]), int(state["sh_degree"]), int(state["num_entries"]))
        model.check()
        return model


# ----------------------------------------------------------------------------------------- initialisation
def _logit(p: float) -> float:
    return math.log(p / (1.0 - p))


def far_points(points: Tensor, *, factor: float, extent: float = 1.0) -> Tensor:
    """[N] bool: points farther from the cloud's (coordinate-wise) median than ``factor`` times the larger of the
    cloud's 90th-percentile distance from it and ``extent``; none when ``factor`` is 0 or fewer than 10 points.

    Both references are robust to the few points they judge: a handful of far points moves neither the median nor
    the 90th percentile, and ``extent`` (the cameras' radius) keeps a point within the cameras' own reach of a small
    cloud from being judged far.
    """
    n = points.shape[0]
    if factor <= 0 or n < 10:
        return torch.zeros(n, dtype=torch.bool, device=points.device)
    p = points.detach().double()
    dist = (p - p.median(0).values).norm(dim=-1)  # [N]
    q90 = dist.kthvalue(max(1, math.ceil(0.9 * n))).values  # (quantile refuses more than 16M elements)
    reach = max(float(q90), float(extent))
    return dist > factor * reach


def init_from_points(points: Tensor, colors: Tensor, *, sh_degree: int, num_entries: int,
                     init_opacity: float = 0.1, extent: float = 1.0) -> GaussianModel:
    """A model with one isotropic Gaussian per point and no posterior carriers yet.

    Args:
        points: [N,3] positions.
        colors: [N,3] RGB in [0, 1].
        sh_degree: maximum SH degree of the coefficients.
        num_entries: K for the (initially empty) offset tables.
        init_opacity: initial opacity of every Gaussian.
        extent: scene extent; only used to give isolated points a sane scale (1e-3 x extent floor).
    """

    points = points.detach().float()
    n = points.shape[0]
    dev = points.device
    dist = nearest_neighbor_distance(points).clamp_min(1e-7 * extent)
    if n == 1:
        dist = torch.full_like(dist, 1e-2 * extent)
    scales = dist.log()[:, None].repeat(1, 3)  # [N,3]
    quats = torch.zeros(n, 4, device=dev)
    quats[:, 0] = 1.0
    opac = torch.full((n,), _logit(init_opacity), device=dev)
    sh0 = rgb_to_sh(colors.detach().float().clamp(0, 1))[:, None, :]  # [N,1,3]
    shN = torch.zeros(n, num_sh_bases(sh_degree) - 1, 3, device=dev)
    params = {"means": points.clone(), "scales": scales, "quats": quats, "opacities": opac, "sh0": sh0, "shN": shN}
    tables = empty_tables(num_entries, device=dev, dtype=points.dtype)
    return GaussianModel(params, tables, torch.full((n,), -1, dtype=torch.long, device=dev), sh_degree, num_entries)


def memory_per_new_gaussian(model: GaussianModel, *, carrier: bool, table_moments: bool = True) -> float:
    """Bytes one more Gaussian of ``model`` takes: its row of every parameter with their two Adam moments, its table
    index and, for a ``carrier``, its offset-table rows (with their two moments where ``table_moments``). Unlike
    :func:`memory_per_gaussian`'s average this does not depend on how many carry a posterior yet (densification's
    split children all do: priced by the average before the first carriers, growth was priced 7x too low)."""
    row = sum(math.prod(t.shape[1:]) * t.element_size() for t in model.params.values())
    table = sum(math.prod(t.shape[1:]) * t.element_size() for t in model.tables.values()) if carrier else 0
    return float(3 * row + model.posterior_row.element_size() + table * (3 if table_moments else 1))


def memory_per_gaussian(model: GaussianModel, *, optimizer_moments: bool = True,
                        table_moments: bool = True) -> dict[str, float]:
    """Bytes per Gaussian: parameters, offset tables (only carriers pay), and Adam moments (2x; of the tables
    only with ``table_moments``: the informed posterior sets its tables without the optimiser).

    Returns a dict with ``params``, ``tables``, ``index`` (posterior_row), ``optimizer`` and ``total``
    bytes per Gaussian (0 for an empty model), plus ``table_bytes_per_carrier``.
    """
    n = max(len(model), 1)
    pbytes = sum(t.numel() * t.element_size() for t in model.params.values())
    tbytes = sum(t.numel() * t.element_size() for t in model.tables.values())
    ibytes = model.posterior_row.numel() * model.posterior_row.element_size()
    obytes = 2 * (pbytes + (tbytes if table_moments else 0)) if optimizer_moments else 0
    per_carrier = sum(math.prod(t.shape[1:]) * t.element_size() for t in model.tables.values())
    return {
        "params": pbytes / n,
        "tables": tbytes / n,
        "index": ibytes / n,
        "optimizer": obytes / n,
        "total": (pbytes + tbytes + ibytes + obytes) / n,
        "table_bytes_per_carrier": float(per_carrier),
    }
