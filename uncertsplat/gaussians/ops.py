"""Every topology change of a ``GaussianModel``, keeping all rows aligned.

Each operation updates, together: the per-Gaussian parameters, ``posterior_row``, the offset tables
and the Adam state rows (``exp_avg``, ``exp_avg_sq``) of every tensor it touches. New rows start with
zero moments (as in 3DGS); kept rows keep theirs. Parameters are replaced by new ``nn.Parameter``
objects (the optimiser's param groups are updated in place), so callers must re-read
``model.params[...]`` after an operation.

The optimiser may be ``None`` (e.g. when editing a loaded model for pruning).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from uncertsplat.gaussians.params import GaussianModel
from uncertsplat.gaussians.prior import Prior, prior_rows
from uncertsplat.gaussians.variational import absorbed_opacity_logit, expected_gate

# row-aligned optimiser state (``last_step``: train.adam's lazy decay; new rows get 0, harmless since their
# moments are 0)
_MOMENTS = ("exp_avg", "exp_avg_sq", "max_exp_avg_sq", "last_step")


def _replace(optimizer: torch.optim.Optimizer | None, old: nn.Parameter, data: Tensor, edit) -> nn.Parameter:
    """New parameter ``data`` in ``old``'s place in the optimiser; each of its row-aligned moments ``m`` becomes
    ``edit(m)``."""
    new = nn.Parameter(data.detach().contiguous(), requires_grad=old.requires_grad)
    if optimizer is None:
        return new
    for group in optimizer.param_groups:
        for i, p in enumerate(group["params"]):
            if p is old:
                group["params"][i] = new
                state = optimizer.state.pop(old, None)
                if state:
                    for key in _MOMENTS:
                        if key in state:
                            state[key] = edit(state[key])
                    optimizer.state[new] = state
                return new
    raise KeyError("parameter not found in the optimiser")


def _swap(optimizer: torch.optim.Optimizer | None, old: nn.Parameter, data: Tensor, keep: Tensor | None,
          n_new: int) -> nn.Parameter:
    """New parameter ``data``; its moments are ``old_moment[keep]`` (all rows when None) + ``n_new`` zero rows."""

    def edit(m: Tensor) -> Tensor:
        m = m if keep is None else m[keep]
        return torch.cat([m, torch.zeros((n_new, *m.shape[1:]), dtype=m.dtype, device=m.device)], dim=0)

    return _replace(optimizer, old, data, edit)


def _edit_rows(store: dict[str, Tensor], optimizer, keep: Tensor | None, new: dict[str, Tensor] | None) -> None:
    """rows = old[keep] ++ new for every tensor of ``store`` (in place), with the Adam rows alongside."""
    n_new = 0 if new is None else next(iter(new.values())).shape[0]
    if keep is None and n_new == 0:
        return
    for name, old in list(store.items()):
        kept = old.detach() if keep is None else old.detach()[keep]
        data = kept if n_new == 0 else torch.cat([kept, new[name].to(kept)], dim=0)
        store[name] = _swap(optimizer, old, data, keep, n_new)


def _edit(model: GaussianModel, optimizer, *, keep: Tensor | None, new_params: dict[str, Tensor] | None,
          table_keep: Tensor | None, new_tables: dict[str, Tensor] | None, posterior_row: Tensor) -> None:
    """The one primitive: rows = old[keep] ++ new, for the Gaussians and (separately) the tables."""
    _edit_rows(model.params, optimizer, keep, new_params)
    _edit_rows(model.tables, optimizer, table_keep, new_tables)
    model.posterior_row = posterior_row


def remove(model: GaussianModel, optimizer, mask: Tensor) -> None:
    """Delete the Gaussians where ``mask`` [N] bool is True, with their table rows and Adam rows."""
    mask = mask.to(model.device, torch.bool)
    if not bool(mask.any()):
        return
    keep = (~mask).nonzero().flatten()
    rows = model.posterior_row[keep]
    table_keep = torch.sort(rows[rows >= 0]).values  # kept table rows, in their old order
    new_row = torch.full_like(rows, -1)
    carriers = rows >= 0
    new_row[carriers] = torch.searchsorted(table_keep, rows[carriers])
    _edit(model, optimizer, keep=keep, new_params=None, table_keep=table_keep, new_tables=None, posterior_row=new_row)


def append(model: GaussianModel, optimizer, params: dict[str, Tensor], tables: dict[str, Tensor] | None = None,
           carriers: Tensor | None = None) -> None:
    """Add Gaussians ``params`` (name -> [n,...]); ``carriers`` [n] bool marks the new rows that own the
    given ``tables`` rows (name -> [c,K,D], c = carriers.sum(), in order)."""
    n = next(iter(params.values())).shape[0]
    if n == 0:
        return
    P = model.num_carriers
    new_rows = torch.full((n,), -1, dtype=torch.long, device=model.device)
    if carriers is not None and bool(carriers.any()):
        c = int(carriers.sum())
        new_rows[carriers.to(model.device)] = torch.arange(P, P + c, device=model.device)
    else:
        tables = None
    row = torch.cat([model.posterior_row, new_rows])
    _edit(model, optimizer, keep=None, new_params=params, table_keep=None, new_tables=tables, posterior_row=row)


def clone(model: GaussianModel, optimizer, mask: Tensor) -> None:
    """Duplicate the Gaussians in ``mask``; clones of carriers get a copy of the parent's table rows."""
    src = mask.to(model.device, torch.bool).nonzero().flatten()
    if src.numel() == 0:
        return
    params = {k: v.detach()[src] for k, v in model.params.items()}
    rows = model.posterior_row[src]
    carriers = rows >= 0
    tables = {k: v.detach()[rows[carriers]] for k, v in model.tables.items()}
    append(model, optimizer, params, tables, carriers)


def quat_to_rotmat(quats: Tensor) -> Tensor:
    """[N,4] wxyz (any norm) -> [N,3,3]."""
    w, x, y, z = torch.nn.functional.normalize(quats, dim=-1).unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], dim=-1).reshape(*quats.shape[:-1], 3, 3)


def rotmat_to_quat(R: Tensor) -> Tensor:
    """[4] unit quaternion (w, x, y, z), w >= 0, of the rotation matrix ``R`` [3,3] (float64): the inverse of
    ``quat_to_rotmat`` (from the largest of the four diagonal combinations, so no division by a small number)."""
    R = R.double()
    m = [1.0 + R[0, 0] + R[1, 1] + R[2, 2], 1.0 + R[0, 0] - R[1, 1] - R[2, 2],
         1.0 - R[0, 0] + R[1, 1] - R[2, 2], 1.0 - R[0, 0] - R[1, 1] + R[2, 2]]
    k = max(range(4), key=lambda i: float(m[i]))
    r = torch.sqrt(m[k].clamp_min(0.0)) * 2.0  # 4 x the largest component
    if k == 0:
        q = torch.stack([r / 4, (R[2, 1] - R[1, 2]) / r, (R[0, 2] - R[2, 0]) / r, (R[1, 0] - R[0, 1]) / r])
    elif k == 1:
        q = torch.stack([(R[2, 1] - R[1, 2]) / r, r / 4, (R[0, 1] + R[1, 0]) / r, (R[0, 2] + R[2, 0]) / r])
    elif k == 2:
        q = torch.stack([(R[0, 2] - R[2, 0]) / r, (R[0, 1] + R[1, 0]) / r, r / 4, (R[1, 2] + R[2, 1]) / r])
    else:
        q = torch.stack([(R[1, 0] - R[0, 1]) / r, (R[0, 2] + R[2, 0]) / r, (R[1, 2] + R[2, 1]) / r, r / 4])
    q = q / q.norm()
    return -q if q[0] < 0 else q


def split(model: GaussianModel, optimizer, mask: Tensor, generator: torch.Generator, *, scales: Tensor,
          prior: Prior, n: int = 2, factor: float = 1.6, carry: bool = True, keep_render: bool = False) -> None:
    """Replace each Gaussian in ``mask`` by ``n`` children (3DGS split), all carrying a posterior.

    With ``carry=False`` (plain 3DGS: ``method != "variational"``) a child carries a posterior only when
    its parent does, so a model without posteriors keeps none.

    Children are placed at the parent's position plus a draw from N(0, R diag(scales)^2 R^T) and get the
    parent's log-scale minus log(factor). ``scales`` [N,3] are the linear scales the decision used (the
    posterior mean), so no fresh posterior sample is involved. A child copies its parent's table rows, or
    gets new rows at the prior when the parent had none; with ``keep_render`` (variant "ours") such a child's
    base opacity and scale absorb the prior's expected gate and mean multiplier, as ``spawn``'s do, so that its
    posterior mean renders it as 3DGS's split would (else the prior dims it by 17 % and shrinks it by 5 % more
    than its sibling of a parent with a posterior).
    """
    src = mask.to(model.device, torch.bool).nonzero().flatten()
    if src.numel() == 0:
        return
    p = {k: v.detach() for k, v in model.params.items()}
    m = src.numel()
    noise = torch.randn((n, m, 3), generator=generator, device=generator.device).to(model.device)
    rot = quat_to_rotmat(p["quats"][src])  # [M,3,3]
    local = noise * scales.detach()[src][None]  # [n,M,3]
    offsets = torch.einsum("mij,nmj->nmi", rot, local)  # [n,M,3]
    children = {k: v[src].repeat(n, *([1] * (v.ndim - 1))) for k, v in p.items()}
    children["means"] = (p["means"][src][None] + offsets).reshape(n * m, 3)
    children["scales"] = children["scales"] - math.log(factor)
    parent_rows = model.posterior_row[src].repeat(n)
    if keep_render and carry:  # (with carry False a child of a parent without rows gets none)
        _absorb_prior(children, parent_rows < 0, prior)
    fresh = prior_rows(n * m, model.num_entries, prior, device=model.device, dtype=model.dtype)
    tables = {}
    for k, v in model.tables.items():
        rows = fresh[k]
        has = parent_rows >= 0
        if bool(has.any()):
            rows[has] = v.detach()[parent_rows[has]]
        tables[k] = rows
    carriers = torch.ones(n * m, dtype=torch.bool, device=model.device)
    if not carry:
        carriers = parent_rows >= 0
        tables = {k: v[carriers] for k, v in tables.items()}
    append(model, optimizer, children, tables, carriers)
    parents = torch.zeros(len(model), dtype=torch.bool, device=model.device)
    parents[src] = True
    remove(model, optimizer, parents)


def _absorb_prior(params: dict[str, Tensor], rows: Tensor, prior: Prior) -> None:
    """In place: the base opacity and scale of the Gaussians ``rows`` [N] bool of ``params`` absorb the prior's
    expected gate and mean multiplier (variant "ours"; the paper's variant is left as it is), so that new table rows
    at the prior leave their posterior-mean render as it was (as every informed update does)."""
    if prior.variant != "ours" or not bool(rows.any()):
        return
    gate = float(expected_gate(torch.tensor(prior.gate_mean), torch.tensor(prior.gate_std), prior.temperature))
    op = params["opacities"]
    op[rows] = absorbed_opacity_logit(torch.sigmoid(op[rows]), gate).to(op.dtype)
    params["scales"][rows] -= math.log(prior.scale_mean)  # the prior's mean multiplier


def spawn(model: GaussianModel, optimizer, mask: Tensor, prior: Prior, keep_render: bool = False) -> int:
    """Give a posterior (new table rows at the prior) to the Gaussians in ``mask`` that have none.

    Returns the number of new carriers. Existing carriers keep their rows. ``keep_render`` (variant "ours"): the
    new carriers' base opacity and scale absorb the prior's expected gate and mean multiplier, so that the
    posterior mean renders them as before (as the informed update does); else the prior dims them by its
    expected gate (17 % with the default prior) and shrinks them by its mean multiplier (5 %).
    """
    new = mask.to(model.device, torch.bool) & (model.posterior_row < 0)
    c = int(new.sum())
    if c == 0:
        return 0
    if keep_render:
        with torch.no_grad():
            _absorb_prior({k: v.data for k, v in model.params.items()}, new, prior)
    P = model.num_carriers
    row = model.posterior_row.clone()
    row[new] = torch.arange(P, P + c, device=model.device)
    tables = prior_rows(c, model.num_entries, prior, device=model.device, dtype=model.dtype)
    _edit(model, optimizer, keep=None, new_params=None, table_keep=None, new_tables=tables, posterior_row=row)
    return c


def truncate_sh(model: GaussianModel, optimizer, degree: int) -> None:
    """Keep only the SH bands up to ``degree`` (drops ``shN`` columns and their Adam moments).

    The bands above ``degree`` average to zero over the sphere of view directions, so dropping them keeps each
    Gaussian's direction-averaged colour. ``model.sh_degree`` becomes ``degree``; a degree at or above the
    current one changes nothing.
    """
    if degree >= model.sh_degree:
        return
    if degree < 0:
        raise ValueError(f"SH degree must be >= 0, got {degree}")
    keep = (degree + 1) ** 2 - 1  # shN columns of degree `degree`
    old = model.params["shN"]
    # last_step (train.adam) is one number per row: it stays
    new = _replace(optimizer, old, old.detach()[:, :keep], lambda m: m[:, :keep].contiguous() if m.dim() > 1 else m)
    model.params["shN"] = new
    model.sh_degree = degree


def reset_opacity(model: GaussianModel, optimizer, max_opacity: float = 0.01) -> None:
    """Clamp opacities to at most ``max_opacity`` and zero their Adam moments (3DGS opacity reset)."""
    old = model.params["opacities"]
    cap = math.log(max_opacity / (1.0 - max_opacity))
    data = old.detach().clamp_max(cap)
    new = _swap(optimizer, old, data, torch.zeros(0, dtype=torch.long, device=model.device), len(model))
    model.params["opacities"] = new
