"""The PyTorch binning at sizes where float32 index arithmetic would no longer be exact."""

from __future__ import annotations

import pytest
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


def _ellipses(n: int, w: int, h: int, seed: int, aspect: float):
    """n random 2D Gaussians (means, extents of their alpha >= 1/255 ellipse, conics, opacities), elongated up to
    ``aspect`` : 1 at random angles, some far off screen, some tiny."""
    g = torch.Generator().manual_seed(seed)
    means = torch.rand(n, 2, generator=g) * torch.tensor([1.4 * w, 1.4 * h]) - torch.tensor([0.2 * w, 0.2 * h])
    major = 0.3 + torch.rand(n, generator=g) * 0.25 * w
    minor = major / (1 + torch.rand(n, generator=g) * (aspect - 1))
    th = torch.rand(n, generator=g) * torch.pi
    cos, sin = th.cos(), th.sin()
    rot = torch.stack([torch.stack([cos, -sin], -1), torch.stack([sin, cos], -1)], -2)  # [n,2,2]
    cov = rot @ torch.diag_embed(torch.stack([major, minor], -1) ** 2) @ rot.transpose(1, 2)
    inv = torch.linalg.inv(cov.double()).float()
    conics = torch.stack([inv[:, 0, 0], inv[:, 0, 1], inv[:, 1, 1]], -1)
    opac = 0.005 + torch.rand(n, generator=g) * 0.995
    reach = 2 * torch.log((255 * opac).clamp_min(1))  # q <= reach where alpha >= 1/255
    extents = torch.sqrt(reach[:, None] * torch.stack([cov[:, 0, 0], cov[:, 1, 1]], -1)) + 1e-3
    depths = torch.rand(1, n, generator=g) + 0.5
    return means[None], extents[None], torch.ones(1, n, dtype=torch.bool), depths, conics[None], opac


@pytest.mark.parametrize("aspect", [1.0, 50.0, 2000.0])
@pytest.mark.parametrize("tile_size", [4, 16])
def test_binning_keeps_every_pair_whose_alpha_reaches_the_threshold(aspect, tile_size):
    """Dense oracle: a (tile, Gaussian) pair whose alpha >= 1/255 at one of the tile's pixel centres is listed by
    both backends (each row of a box is one run of tiles from its first to its last hit, so thin slanted
    Gaussians at any angle must not lose a tile between two). The two list the same pairs up to 50 : 1; at
    2000 : 1 a few pairs whose ellipse grazes the tile within float rounding of the (margined) limit come out
    either way, the kernel's arithmetic being fused where the tensor ops round each step."""
    w, h, n = 61, 47, 300
    m, e, v, d, con, opac = _ellipses(n, w, h, seed=int(aspect) + tile_size, aspect=aspect)
    got = {b: bin_gaussians(m, e, v, d, w, h, tile_size, con, opac, backend=b) for b in ("torch", "native")}
    a, b = got["torch"], got["native"]
    if aspect <= 50:
        assert torch.equal(a.pair_gauss, b.pair_gauss) and torch.equal(a.pair_tile, b.pair_tile)
    ys, xs = torch.meshgrid(torch.arange(h) + 0.5, torch.arange(w) + 0.5, indexing="ij")
    dx, dy = xs[None] - m[0, :, 0, None, None], ys[None] - m[0, :, 1, None, None]  # [n,h,w]
    q = con[0, :, 0, None, None] * dx * dx + 2 * con[0, :, 1, None, None] * dx * dy + con[0, :, 2, None, None] * dy * dy
    reaches = opac[:, None, None] * torch.exp(-0.5 * q) >= 1 / 255  # [n,h,w]
    tiles_x = -(-w // tile_size)
    tile_of = (ys.long() // tile_size) * tiles_x + xs.long() // tile_size  # [h,w]
    needed = {(int(t), int(g)) for g, yy, xx in reaches.nonzero().tolist() for t in [tile_of[yy, xx]]}
    assert len(needed) > 100
    for bins in got.values():
        listed = set(zip(bins.pair_tile.tolist(), bins.pair_gauss.tolist(), strict=True))
        assert needed <= listed, sorted(needed - listed)[:5]
        if aspect == 1:  # the test is tight (thin ellipses pass between pixel centres that the test's rectangle spans)
            assert len(listed) < 1.5 * len(needed)


def test_both_backends_sort_depths_of_every_magnitude_front_to_back():
    """The native kernel sorts float32 depths by a radix sort of their bits, one byte per pass: depths from 1e-3 to
    1e4 (keys that differ in every byte, the exponent's high bits in the last) must come out front to back in
    every tile, the pairs the PyTorch binning lists in the same order. (The depths of ``_ellipses`` lie in
    [0.5, 1.5): their keys share the top byte, so a sort that skipped it listed the same pairs.)"""
    w, h, n = 61, 47, 300
    m, e, v, _, con, opac = _ellipses(n, w, h, seed=5, aspect=4.0)
    d = 10.0 ** (torch.rand(1, n, generator=torch.Generator().manual_seed(6)) * 7 - 3)
    got = {b: bin_gaussians(m, e, v, d, w, h, 8, con, opac, backend=b) for b in ("torch", "native")}
    a, b = got["torch"], got["native"]
    assert torch.equal(a.pair_gauss, b.pair_gauss) and torch.equal(a.pair_tile, b.pair_tile)
    pair_depth = d[0, b.pair_gauss.long()]
    same_tile = b.pair_tile[1:] == b.pair_tile[:-1]
    assert int(same_tile.sum()) > 1000
    assert bool((pair_depth[1:] >= pair_depth[:-1])[same_tile].all())


def test_more_gaussians_than_the_pair_index_holds():
    """The tile lists index Gaussians as int32: 2^31 cameras x Gaussians is refused with a message."""
    C, N = 2**16, 2**15
    z = torch.zeros(1, 1)
    with pytest.raises(ValueError, match="2\\^31"):
        bin_gaussians(z[..., None].expand(C, N, 2), z[..., None].expand(C, N, 2), z.bool().expand(C, N),
                      z.expand(C, N), 64, 48, 16)
