"""The PyTorch binning at sizes where float32 index arithmetic would no longer be exact."""

from __future__ import annotations

import torch

from uncertsplat.render.rasterize import bin_gaussians


def _bins(n: int, w: int, h: int, device):
    """n Gaussians that each cover the whole w x h image, listed with 1-pixel tiles (n*w*h pairs)."""
    means2d = torch.tensor([w / 2, h / 2], device=device).expand(1, n, 2)
    extents = torch.tensor([w, h], dtype=torch.float32, device=device).expand(1, n, 2)
    valid = torch.ones(1, n, dtype=torch.bool, device=device)
    depths = torch.arange(n, dtype=torch.float32, device=device)[None] + 1
    return bin_gaussians(means2d, extents, valid, depths, w, h, 1, backend="torch")


def test_more_than_two_to_the_24_pairs(device):
    """Seen on CUDA at 1920x1080 with 500k Gaussians: past 2^24 pairs, pairs landed in tiles past the last."""
    n, w, h = 5, 2000, 1700
    assert n * w * h > 2**24
    bins = _bins(n, w, h, device)
    assert bins.tile_count.numel() == w * h
    assert bool((bins.tile_count == n).all())
    # every tile lists the n Gaussians front to back
    assert torch.equal(bins.pair_tile, torch.arange(w * h, device=device).repeat_interleave(n))
    assert torch.equal(bins.pair_gauss, torch.arange(n, device=device).repeat(w * h))


def test_more_than_two_to_the_24_tiles(device):
    """A tile grid past 2^24 tiles (1-pixel tiles of a 17 Mpixel image) switches to float64 tile indices."""
    w, h = 4200, 4100
    assert w * h > 2**24
    bins = _bins(1, w, h, device)
    assert bins.tile_count.numel() == w * h
    assert bool((bins.tile_count == 1).all())
    assert torch.equal(bins.pair_tile, torch.arange(w * h, device=device))
