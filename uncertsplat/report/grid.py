"""Grids of image panels for the report, composed as pixels (no plotting library).

The per-view figures are images side by side with a title each and a colour bar beside some: laid out by matplotlib
they took 0.55-0.75 s each on the 2-core CPU (the demo report draws 15 of them), composed here directly in about a
tenth of that. The text uses the DejaVu Sans that matplotlib ships, so they match the report's plots.

``grid_png(rows, ...)``: rows of ``Panel`` (an image, a title, an optional ``ColourBar``), an optional label left of
each row and a title above the grid; returns PNG bytes.
"""

from __future__ import annotations

import io
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

MIN_WIDTH = 240
"""Panels narrower than this are enlarged by a whole factor (nearest neighbour: pixels stay pixels)."""
MAX_WIDTH = 480
"""Panels wider than this are reduced (area average)."""
PAD = 8
BAR_WIDTH = 12
TITLE_SIZE = 13
LABEL_SIZE = 12
TICK_SIZE = 11


@dataclass(frozen=True)
class ColourBar:
    """A vertical colour bar: the colour map from ``low`` (bottom) to ``high`` (top) and tick labels at fractions of
    its height (0: bottom)."""

    cmap: str
    ticks: tuple[tuple[float, str], ...]


@dataclass(frozen=True)
class Panel:
    """One image of a grid: ``image`` [H,W,3] uint8 (None: "n/a"), ``title`` above it, ``bar`` beside it."""

    title: str
    image: np.ndarray | None
    bar: ColourBar | None = None


def value_bar(cmap: str, vmin: float, vmax: float, *, below: bool = False, above: bool = False) -> ColourBar:
    """A bar for values from ``vmin`` to ``vmax`` (three ticks). ``below`` / ``above``: the map has values past that
    end, drawn in its colour: the end's label reads "≤" / "≥" (matplotlib's extended colour bar, in words)."""
    mid = 0.5 * (vmin + vmax)
    return ColourBar(cmap, ((0.0, ("≤" if below else "") + _num(vmin)), (0.5, _num(mid)),
                            (1.0, ("≥" if above else "") + _num(vmax))))


def rank_bar(cmap: str) -> ColourBar:
    """A bar for rank-coloured images: low, median, high."""
    return ColourBar(cmap, ((0.0, "low"), (0.5, "median"), (1.0, "high")))


def _num(v: float) -> str:
    return f"{v:.3g}"


@lru_cache(maxsize=8)
def _font(size: int):
    from PIL import ImageFont

    try:
        import matplotlib

        path = matplotlib.get_data_path() + "/fonts/ttf/DejaVuSans.ttf"
        return ImageFont.truetype(path, size)
    except (OSError, ImportError):  # no FreeType or no matplotlib font: Pillow's own
        return ImageFont.load_default()


def _fit(image: np.ndarray) -> np.ndarray:
    """``image`` scaled into [MIN_WIDTH, MAX_WIDTH] wide (see those)."""
    from PIL import Image

    h, w = image.shape[:2]
    if w < MIN_WIDTH:
        k = -(-MIN_WIDTH // max(w, 1))
        return np.repeat(np.repeat(image, k, axis=0), k, axis=1)
    if w > MAX_WIDTH:
        size = (MAX_WIDTH, max(1, round(h * MAX_WIDTH / w)))
        return np.asarray(Image.fromarray(image).resize(size, Image.Resampling.BOX))
    return image


@lru_cache(maxsize=16)
def _gradient(cmap: str, height: int) -> np.ndarray:
    """[height, BAR_WIDTH, 3] uint8: the colour map, top = 1."""
    import matplotlib

    t = np.linspace(1.0, 0.0, height)
    rgb = matplotlib.colormaps[cmap](t, bytes=True)[:, :3]  # [height,3]
    return np.ascontiguousarray(np.broadcast_to(rgb[:, None, :], (height, BAR_WIDTH, 3)))


def _text_width(draw, text: str, font) -> int:
    box = draw.textbbox((0, 0), text, font=font)
    return box[2] - box[0]


def grid_png(rows: list[list[Panel]], title: str = "", row_labels: list[str] | None = None,
             compress_level: int = 2) -> bytes:
    """PNG bytes of ``rows`` of panels (every panel's image is scaled as ``_fit`` does; panels of a column share its
    width), with ``row_labels`` left of the rows and ``title`` above."""
    from PIL import Image, ImageDraw

    fitted = [[None if p.image is None else _fit(np.ascontiguousarray(p.image, dtype=np.uint8)) for p in row]
              for row in rows]
    shapes = [im.shape[:2] for row in fitted for im in row if im is not None]
    ph, pw = (max(s[0] for s in shapes), max(s[1] for s in shapes)) if shapes else (MIN_WIDTH * 3 // 4, MIN_WIDTH)
    probe = ImageDraw.Draw(Image.new("RGB", (1, 1)))
    tick_font, label_font, title_font = _font(TICK_SIZE), _font(LABEL_SIZE), _font(TITLE_SIZE)
    bar_text = max((_text_width(probe, t, tick_font) for row in rows for p in row if p.bar is not None
                    for _, t in p.bar.ticks), default=0)
    bar_space = (PAD // 2 + BAR_WIDTH + 4 + bar_text) if any(p.bar is not None for row in rows for p in row) else 0
    cols = max(len(row) for row in rows)
    cell_w, cell_h = pw + bar_space + PAD, ph + LABEL_SIZE + 10
    left = (max(_text_width(probe, t, label_font) for t in row_labels) + PAD) if row_labels else 0
    top = (TITLE_SIZE + 12) if title else 4
    canvas = Image.new("RGB", (left + cols * cell_w + PAD, top + len(rows) * cell_h + PAD), "white")
    draw = ImageDraw.Draw(canvas)
    if title:
        draw.text(((canvas.width - _text_width(draw, title, title_font)) // 2, 4), title, fill="black",
                  font=title_font)
    for r, row in enumerate(rows):
        y0 = top + r * cell_h
        if row_labels:
            draw.text((PAD // 2, y0 + LABEL_SIZE + 6 + ph // 2), row_labels[r], fill="black", font=label_font,
                      anchor="lm")
        for c, (panel, image) in enumerate(zip(row, fitted[r], strict=True)):
            x0 = left + PAD + c * cell_w
            draw.text((x0 + (pw - _text_width(draw, panel.title, label_font)) // 2, y0 + 2), panel.title,
                      fill="black", font=label_font)
            iy = y0 + LABEL_SIZE + 6
            if image is None:
                draw.rectangle((x0, iy, x0 + pw - 1, iy + ph - 1), outline=(200, 200, 200))
                draw.text((x0 + pw // 2, iy + ph // 2), "n/a", fill=(128, 128, 128), font=label_font, anchor="mm")
                continue
            canvas.paste(Image.fromarray(image), (x0, iy))
            if panel.bar is not None:
                h = image.shape[0]
                bx = x0 + image.shape[1] + PAD // 2
                canvas.paste(Image.fromarray(_gradient(panel.bar.cmap, h)), (bx, iy))
                for frac, text in panel.bar.ticks:
                    ty = iy + round((1.0 - frac) * (h - 1))
                    draw.line((bx + BAR_WIDTH, ty, bx + BAR_WIDTH + 2, ty), fill="black")
                    draw.text((bx + BAR_WIDTH + 4, min(max(ty, iy + TICK_SIZE // 2), iy + h - TICK_SIZE // 2)),
                              text, fill="black", font=tick_font, anchor="lm")
    buf = io.BytesIO()
    canvas.save(buf, format="PNG", compress_level=compress_level)
    return buf.getvalue()


__all__ = ["ColourBar", "Panel", "grid_png", "rank_bar", "value_bar"]
