"""Differentiable Gaussian rasterizer: ``render(sample, cameras, ...) -> RenderOutput``."""

from .render import near_plane, render
from .sh import rgb_to_sh, sh_to_rgb

__all__ = ["near_plane", "render", "rgb_to_sh", "sh_to_rgb"]
