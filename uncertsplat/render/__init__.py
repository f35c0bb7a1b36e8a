"""Differentiable Gaussian rasterizer: ``render(sample, cameras, ...) -> RenderOutput``."""

from .render import render
from .sh import rgb_to_sh, sh_to_rgb

__all__ = ["render", "rgb_to_sh", "sh_to_rgb"]
