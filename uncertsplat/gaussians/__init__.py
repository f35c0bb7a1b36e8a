"""Gaussians: the row-aligned parameter table (``params``), the offset-table layout and prior (``prior``), posterior
samples and KL (``variational``), topology operations (``ops``)."""

from .params import PARAM_SPECS, GaussianModel, init_from_points, memory_per_gaussian
from .prior import TABLE_SPECS, Prior
from .variational import carrier_uncertainty, expected_render_sample, kl_terms, posterior_mean, sample

__all__ = ["PARAM_SPECS", "TABLE_SPECS", "GaussianModel", "Prior", "carrier_uncertainty", "init_from_points",
           "expected_render_sample", "kl_terms", "memory_per_gaussian", "posterior_mean", "sample"]
