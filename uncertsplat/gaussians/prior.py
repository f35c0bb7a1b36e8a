"""The offset-table layout and the prior: which table columns hold which posterior parameter.

Every posterior carrier (a Gaussian with ``posterior_row >= 0``) owns one row of each table in
``TABLE_SPECS``, a [P,K,D] tensor of K entries:

===================  =  ================================================================  =========
table                D  parameter                                                         lr group
===================  =  ================================================================  =========
``pos_spread_raw``   3  position spread a: sigma = softplus(a)                            means
``pos_loc``          3  position location b: mu = b                                       means
``scale_width_raw``  3  multiplier width c: w = clamp(softplus(c), MIN_WIDTH, MAX_WIDTH)  scales
``scale_left``       3  multiplier left edge d: the scale multiplier is U[d, d + w]       scales
``gate_spread_raw``  1  gate spread e: tau = softplus(e)                                  opacities
``gate_loc``         1  gate location f: nu = f                                           opacities
===================  =  ================================================================  =========

How a sample uses them is ``gaussians.variational``'s business; this module only says what the
columns are, what a fresh row at the prior holds (``prior_rows``) and what the prior is (``Prior``,
plain numbers: ``gaussians/`` never imports config; ``train.trainer.prior_from_config`` builds one
from a ``TrainConfig``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import torch
from torch import Tensor

Variant = Literal["ours", "paper"]


@dataclass(frozen=True)
class TableSpec:
    """One offset-table column group: name, width D (table is [P,K,D]), and base learning-rate key."""

    name: str
    width: int
    lr: str


TABLE_SPECS: tuple[TableSpec, ...] = (
    TableSpec("pos_spread_raw", 3, "means"),
    TableSpec("pos_loc", 3, "means"),
    TableSpec("scale_width_raw", 3, "scales"),
    TableSpec("scale_left", 3, "scales"),
    TableSpec("gate_spread_raw", 1, "opacities"),
    TableSpec("gate_loc", 1, "opacities"),
)
TABLE_NAMES: tuple[str, ...] = tuple(s.name for s in TABLE_SPECS)

MIN_WIDTH, MAX_WIDTH = 0.01, 100.0


@dataclass(frozen=True)
class Prior:
    """The prior and its table initialisation (plain numbers: ``gaussians/`` never imports config).

    Attributes:
        position_std: sigma_p, in units of the extent (ours) or world units (paper).
        scale_width: w_p: the multiplier prior is U[1 - w_p, 1].
        gate_mean, gate_std: the gate-logit prior N(nu_p, tau_p^2).
        temperature: T of the gate.
        variant: "ours" or "paper".
    """

    position_std: float = 0.00248
    scale_width: float = 0.1
    gate_mean: float = 2.0
    gate_std: float = 1.996
    temperature: float = 0.2
    variant: Variant = "ours"

    @property
    def scale_mean(self) -> float:
        """The prior multiplier's mean, ``mean_multiplier(scale_width)``."""
        return mean_multiplier(self.scale_width)


def mean_multiplier(scale_width: float) -> float:
    """The mean 1 - w_p / 2 of the scale-multiplier prior U[1 - w_p, 1]: what a Gaussian at the prior scales its
    base scale by on average (a spawned carrier's and an informed update's base scale absorb it)."""
    return 1.0 - 0.5 * scale_width


def inverse_softplus(y: float | Tensor) -> float | Tensor:
    """x with softplus(x) = y (y > 0), stable for tiny and huge y."""
    if isinstance(y, Tensor):
        return y + torch.log(-torch.expm1(-y))
    return y + math.log(-math.expm1(-y))


def empty_tables(num_entries: int, *, device=None, dtype=torch.float32) -> dict[str, Tensor]:
    """Tables with zero rows (P = 0)."""
    return {s.name: torch.zeros(0, num_entries, s.width, device=device, dtype=dtype) for s in TABLE_SPECS}


def prior_rows(n: int, num_entries: int, prior: Prior, *, device=None, dtype=torch.float32) -> dict[str, Tensor]:
    """``n`` new table rows [n,K,D] at the prior: every KL term is 0 for them, but the scale term of the paper
    variant with K != 10 entries.

    The multiplier width starts at w_p (ours; the KL is then 0 for any K) or at 1/K (paper, as the
    original code; equal to w_p only for the default K = 10: with other K its scale term does not start at 0);
    the interval's left edge is 1 - w_p for both.
    """
    k = num_entries
    width = prior.scale_width if prior.variant == "ours" else 1.0 / k
    width = min(max(width, MIN_WIDTH), MAX_WIDTH)

    def full(d, v):
        return torch.full((n, k, d), float(v), device=device, dtype=dtype)

    return {
        "pos_spread_raw": full(3, inverse_softplus(prior.position_std)),
        "pos_loc": full(3, 0.0),
        "scale_width_raw": full(3, inverse_softplus(width)),
        "scale_left": full(3, 1.0 - prior.scale_width),
        "gate_spread_raw": full(1, inverse_softplus(prior.gate_std)),
        "gate_loc": full(1, prior.gate_mean),
    }


__all__ = ["MAX_WIDTH", "MIN_WIDTH", "TABLE_NAMES", "TABLE_SPECS", "Prior", "TableSpec", "Variant",
           "empty_tables", "inverse_softplus", "mean_multiplier", "prior_rows"]
