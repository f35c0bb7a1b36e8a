"""File layout of ``evaluate``'s per-view maps, shared by their writer and their readers.

``RUN/eval/maps/{map_stem(name)}.exr`` holds the float channels ``EXR_CHANNELS`` of the view whose image
is ``name``, and in its header which predictive ``rgb_std`` is the std of (``EXR_RGB_PREDICTIVE``,
``EXR_RGB_DOF``); the PNG previews next to it are ``{map_stem(name)}_{kind}.png``. ``stages/evaluate.py``
writes them, ``report`` reads them, and ``prune`` names its renders the same way.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

EXR_CHANNELS = ("rgb_mean.R", "rgb_mean.G", "rgb_mean.B", "rgb_std.R", "rgb_std.G", "rgb_std.B",
                "depth_mean.Z", "depth_std.Z")
"""Channels of a view's EXR: MC mean and std of the colour, and of the depth (in the run's world units)."""
EXR_ALPHA_CHANNEL = "alpha.A"
"""Channel of a view's EXR (maps written since 2026-11-29): the samples' mean accumulated opacity, in [0, 1]; low
where a ray meets little of the model (its depth there is mostly the empty-ray term's), to mask such pixels."""
EXR_RGB_PREDICTIVE = "uncertsplat:rgb_predictive"
"""Header attribute: "student-t" or "gaussian", the family of the RGB predictive whose std ``rgb_std`` holds."""
EXR_RGB_DOF = "uncertsplat:rgb_degrees_of_freedom"
"""Header attribute (float, with "student-t"): nu; the central interval of probability p is mean +- w std, w the
unit-variance t's half-width (``eval.tails.half_width``)."""
EXR_DEPTH_TO_SOURCE = "uncertsplat:depth_to_source"
"""Header attribute (float, when the scene knows it): the factor that takes ``depth_mean`` and ``depth_std`` from the
run's normalised units to the scene's own (a COLMAP model's, a synthetic scene's GT depth): 1 / s of ``RUN/scene.json``'s
``world_from_source``."""


def written_depth_to_source(maps_dir: Path) -> float | None:
    """``EXR_DEPTH_TO_SOURCE`` of the first EXR map in ``maps_dir`` (by name): the factor an evaluation wrote its depths
    with; None without a map or without a positive finite factor in it (an unreadable map raises what the reader
    raises)."""
    import math

    from uncertsplat.io.images import read_exr_attribute

    maps = sorted(Path(maps_dir).glob("*.exr")) if Path(maps_dir).is_dir() else []
    got = read_exr_attribute(maps[0], EXR_DEPTH_TO_SOURCE) if maps else None
    return float(got) if isinstance(got, (int, float)) and math.isfinite(got) and got > 0 else None


def map_stem(image_name: str, among: Sequence[str] = ()) -> str:
    """File stem for an image's maps: extension dropped, sub-folders flattened with '__'; where another of the names
    ``among`` (the views whose maps share the folder) has the same stem, the extension is kept as ``_ext``
    (``IMG_1.jpg`` and ``IMG_1.png``: ``IMG_1_jpg``, ``IMG_1_png``): their maps wrote over each other's."""
    stem = _plain_stem(image_name)
    if any(other != image_name and _plain_stem(other) == stem for other in among):
        suffix = Path(image_name).suffix
        return stem + ("_" + suffix[1:] if suffix else "_")
    return stem


def _plain_stem(image_name: str) -> str:
    return str(Path(image_name).with_suffix("")).replace("/", "__").replace("\\", "__")


__all__ = ["EXR_ALPHA_CHANNEL", "EXR_CHANNELS", "EXR_RGB_DOF", "EXR_RGB_PREDICTIVE", "map_stem"]
