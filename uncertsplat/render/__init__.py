"""Differentiable Gaussian rasterizer: ``render(sample, cameras, ...) -> RenderOutput``."""

from .render import near_plane, render
from .sh import rgb_to_sh

__all__ = ["near_plane", "render", "rgb_to_sh"]
