"""File layout of ``evaluate``'s per-view maps, shared by their writer and their readers.

``RUN/eval/maps/{map_stem(name)}.exr`` holds the float channels ``EXR_CHANNELS`` of the view whose image
is ``name``; the PNG previews next to it are ``{map_stem(name)}_{kind}.png``. ``stages/evaluate.py``
writes them, ``report`` reads them, and ``prune`` names its renders the same way.
"""

from __future__ import annotations

from pathlib import Path

EXR_CHANNELS = ("rgb_mean.R", "rgb_mean.G", "rgb_mean.B", "rgb_std.R", "rgb_std.G", "rgb_std.B",
                "depth_mean.Z", "depth_std.Z")
"""Channels of a view's EXR: MC mean and std of the colour, and of the depth (in the run's world units)."""


def map_stem(image_name: str) -> str:
    """File stem for an image's maps: extension dropped, sub-folders flattened with '__'."""
    p = Path(image_name)
    return str(p.with_suffix("")).replace("/", "__").replace("\\", "__")


__all__ = ["EXR_CHANNELS", "map_stem"]
