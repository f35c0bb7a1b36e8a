"""NLL: closed forms, torch.distributions, KDE bandwidth, the paper formula."""

from __future__ import annotations

import math

import pytest
import torch

from uncertsplat.eval.nll import (
    gaussian_nll,
    kde_bandwidth,
    kde_nll,
    paper_bandwidth,
    paper_nll,
    predictive_nll,
)


def test_gaussian_nll_closed_form(device):
    y = torch.tensor([0.5], device=device)
    mu = torch.tensor([0.3], device=device)
    s = torch.tensor([0.1], device=device)
    # 0.5*log(2 pi 0.01) + 0.04/(0.02)
    expected = 0.5 * math.log(2 * math.pi * 0.01) + 2.0
    assert gaussian_nll(y, mu, s).item() == pytest.approx(expected, rel=1e-5)


def test_gaussian_nll_matches_torch_normal(device):
    g = torch.Generator().manual_seed(0)
    y = torch.rand(4, 5, 3, generator=g, dtype=torch.float64).to(device)
    mu = torch.rand(4, 5, 3, generator=g, dtype=torch.float64).to(device)
    s = (0.01 + torch.rand(4, 5, 1, generator=g, dtype=torch.float64)).to(device)
    ref = -torch.distributions.Normal(mu, s.expand_as(mu)).log_prob(y)
    got = gaussian_nll(y, mu, s, reduction="none")
    assert torch.allclose(got, ref, atol=1e-12)
    assert gaussian_nll(y, mu, s).item() == pytest.approx(ref.mean().item(), rel=1e-12)


def test_gaussian_nll_zero_std_uses_floor(device):
    y = torch.tensor([0.2, 0.2], device=device)
    mu = torch.tensor([0.2, 0.3], device=device)
    v = gaussian_nll(y, mu, torch.zeros(2, device=device), std_floor=1e-3, reduction="none")
    assert torch.isfinite(v).all()
    ref = -torch.distributions.Normal(mu, torch.full_like(mu, 1e-3)).log_prob(y)
    assert torch.allclose(v, ref, rtol=1e-5)
    with pytest.raises(ValueError):
        gaussian_nll(y, mu, torch.zeros(2), std_floor=0.0)


def test_kde_bandwidth_silverman():
    std = torch.tensor([0.0, 0.1, 1.0])
    h = kde_bandwidth(std, 10, floor=1e-3)
    assert h[0].item() == pytest.approx(1e-3)
    assert h[1].item() == pytest.approx(1.06 * 0.1 * 10 ** (-0.2), rel=1e-6)
    # more samples -> narrower kernels
    assert kde_bandwidth(std, 20)[2] < kde_bandwidth(std, 10)[2]


def test_kde_nll_closed_form_single_sample(device):
    # K = 1: std_hat = 0 -> bandwidth = floor -> NLL of N(y; s, floor^2)
    s = torch.tensor([[0.4, 0.5]], device=device, dtype=torch.float64)
    y = torch.tensor([0.41, 0.5], device=device, dtype=torch.float64)
    got = kde_nll(s, y, bandwidth_floor=0.05, reduction="none")
    ref = -torch.distributions.Normal(s[0], 0.05).log_prob(y)
    assert torch.allclose(got, ref, atol=1e-12)


def test_kde_nll_mixture_closed_form(device):
    samples = torch.tensor([[0.0], [1.0], [3.0]], dtype=torch.float64, device=device)
    y = torch.tensor([0.5], dtype=torch.float64, device=device)
    std = samples.std(0)
    h = 1.06 * std * 3 ** (-0.2)
    dens = sum(torch.exp(torch.distributions.Normal(samples[k], h).log_prob(y)) for k in range(3)) / 3
    assert kde_nll(samples, y).item() == pytest.approx(-torch.log(dens).item(), rel=1e-10)


def test_kde_nll_far_target_finite(device):
    samples = torch.zeros(10, 4, device=device)
    y = torch.full((4,), 1.0, device=device)
    v = kde_nll(samples, y, reduction="none")
    assert torch.isfinite(v).all() and (v > 1e4).all()  # (1/1e-3)^2/2 = 5e5, not inf


def test_kde_gaussian_data_close_to_gaussian_nll():
    # Many samples from N(0, 1): the KDE NLL of N(0,1) targets approaches the true NLL.
    g = torch.Generator().manual_seed(1)
    samples = torch.randn(2000, 200, generator=g, dtype=torch.float64)
    y = torch.randn(200, generator=g, dtype=torch.float64)
    true = gaussian_nll(y, torch.zeros_like(y), torch.ones_like(y)).item()
    assert kde_nll(samples, y).item() == pytest.approx(true, abs=0.1)


def test_paper_nll_depends_on_resolution_ours_does_not():
    g = torch.Generator().manual_seed(3)
    samples = 0.5 + 0.05 * torch.randn(10, 8, 8, 3, generator=g, dtype=torch.float64)
    y = 0.5 + 0.05 * torch.randn(8, 8, 3, generator=g, dtype=torch.float64)
    std = samples.std(0)
    assert torch.allclose(paper_bandwidth(std, 64), 1.06 * std * 64**0.2 + 1e-5)
    # The same view at 4x the resolution (each pixel repeated 4x4): identical per-pixel statistics.
    up_s = samples.repeat_interleave(4, dim=1).repeat_interleave(4, dim=2)
    up_y = y.repeat_interleave(4, dim=0).repeat_interleave(4, dim=1)
    ours, ours_up = kde_nll(samples, y).item(), kde_nll(up_s, up_y).item()
    assert ours_up == pytest.approx(ours, rel=1e-9)
    paper, paper_up = paper_nll(samples, y).item(), paper_nll(up_s, up_y).item()
    # bandwidth x 16^(1/5) = 1.74 -> NLL grows by about log(1.74) = 0.55
    assert paper_up > paper + 0.3


def test_kde_in_chunks_is_the_whole_stacks_to_the_bit(monkeypatch):
    """The KDE's temporaries over the whole [K,...] stack took three times the samples' memory (K = 64 at 1600x1200
    ran out of memory); it works over chunks of the elements: the same values (to the bit in one chunk, as every
    image under 4M / K values is; a chunk's tail may take torch's scalar exp: an ulp)."""
    import math

    from uncertsplat.eval import nll

    gen = torch.Generator().manual_seed(0)
    samples, target = torch.rand(7, 5, 9, 3, generator=gen), torch.rand(5, 9, 3, generator=gen)
    h = nll.kde_bandwidth(samples.std(dim=0, unbiased=True), 7)
    z = (target.unsqueeze(0) - samples) / h.unsqueeze(0)
    whole = torch.logsumexp(-0.5 * z.square(), dim=0) - math.log(7) - torch.log(h) - nll._LOG_SQRT_2PI
    assert torch.equal(nll._kde_log_density(samples, target, h), whole)
    monkeypatch.setattr(nll, "KDE_CHUNK", 7 * 4)  # chunks of 4 elements, the last one shorter (135 = 33 x 4 + 3)
    torch.testing.assert_close(nll._kde_log_density(samples, target, h), whole, rtol=1e-6, atol=1e-6)
    assert torch.equal(nll.kde_nll(samples, target, bandwidth=0.05, reduction="none"),
                       -nll._kde_log_density(samples, target, torch.full_like(target, 0.05)))


class TestReductionsAndFloors:
    """The mean over finite, masked elements; the floors of a given bandwidth; the arguments checked; the
    paper formula's closed form."""

    def test_the_mean_leaves_out_non_finite_elements(self, device):
        y = torch.tensor([0.5, float("nan"), float("inf")], dtype=torch.float64, device=device)
        mu = torch.full_like(y, 0.3)
        s = torch.full_like(y, 0.1)
        expected = 0.5 * math.log(2 * math.pi * 0.01) + 2.0  # the first one's (test_gaussian_nll_closed_form)
        assert gaussian_nll(y, mu, s).item() == pytest.approx(expected, rel=1e-12)
        first = predictive_nll(y[:1], mu[:1], s[:1], 5.0).item()
        assert predictive_nll(y, mu, s, 5.0).item() == pytest.approx(first, rel=1e-12)
        nothing = gaussian_nll(y[1:], mu[1:], s[1:])
        assert torch.isnan(nothing)

    def test_predictive_nll_applies_the_mask(self, device):
        g = torch.Generator().manual_seed(4)
        y, mu = torch.rand(2, 3, 4, 3, generator=g, dtype=torch.float64).to(device)
        s = (0.05 + torch.rand(3, 4, 1, generator=g, dtype=torch.float64)).to(device)
        mask = torch.zeros(3, 4, dtype=torch.bool, device=device)
        mask[1:, :2] = True
        for dof in (None, 4.0):
            per = predictive_nll(y, mu, s, dof, reduction="none")
            got = predictive_nll(y, mu, s, dof, mask=mask)
            assert got.item() == pytest.approx(per[mask].mean().item(), rel=1e-12)
            assert got.item() != pytest.approx(per.mean().item(), rel=1e-6)
        assert predictive_nll(y, mu, s, None, mask=mask).item() == pytest.approx(
            gaussian_nll(y, mu, s, mask=mask).item(), rel=1e-12)

    def test_a_given_bandwidth_is_floored(self, device):
        samples = torch.tensor([[0.4, 0.5]], dtype=torch.float64, device=device)  # K = 1
        y = torch.tensor([0.45, 0.9], dtype=torch.float64, device=device)
        for bw in (0.0, 0.01, torch.tensor([0.0, 0.01], dtype=torch.float64, device=device)):
            got = kde_nll(samples, y, bandwidth=bw, bandwidth_floor=0.05, reduction="none")
            ref = -torch.distributions.Normal(samples[0], 0.05).log_prob(y)
            assert torch.allclose(got, ref, atol=1e-12)
        wide = kde_nll(samples, y, bandwidth=torch.tensor([0.01, 0.2], dtype=torch.float64, device=device),
                       bandwidth_floor=0.05, reduction="none")
        ref = -torch.distributions.Normal(samples[0], torch.tensor([0.05, 0.2], dtype=torch.float64,
                                                                   device=device)).log_prob(y)
        assert torch.allclose(wide, ref, atol=1e-12)

    def test_kde_bandwidth_needs_a_sample(self):
        with pytest.raises(ValueError, match="num_samples must be >= 1"):
            kde_bandwidth(torch.tensor([0.1]), 0)
        with pytest.raises(ValueError, match="floor must be > 0"):
            kde_bandwidth(torch.tensor([0.1]), 3, floor=0.0)
        assert kde_bandwidth(torch.tensor([0.1]), 1).item() == pytest.approx(0.106, rel=1e-6)

    def test_paper_nll_closed_form(self, device):
        # K = 3 samples 0, 1, 3 of one pixel: unbiased std sqrt(7/3); bandwidth 1.06 std P^(1/5) + 1e-5
        samples = torch.tensor([0.0, 1.0, 3.0], dtype=torch.float64, device=device).reshape(3, 1, 1, 1)
        y = torch.full((1, 1, 1), 0.5, dtype=torch.float64, device=device)
        for pixels in (None, 32):
            h = 1.06 * math.sqrt(7 / 3) * (1 if pixels is None else 32) ** 0.2 + 1e-5
            kernels = sum(math.exp(-0.5 * ((0.5 - m) / h) ** 2) for m in (0.0, 1.0, 3.0))
            dens = kernels / (3 * h * math.sqrt(2 * math.pi))
            got = paper_nll(samples, y, num_pixels=pixels).item()
            assert got == pytest.approx(-math.log(dens), rel=1e-12)
