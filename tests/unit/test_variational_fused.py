"""The fused training path (``sample_with_kl``: one autograd node over the offset tables whose backward is
written by hand, with the KL terms from the native kernel) against the plain path (``sample`` + ``kl_terms``):
the same sample, the same KL terms and the same gradients, for both variants.

How the two are made comparable: both draw their random numbers through ``variational._draw`` in one order
(subset, eps, u, eta) from the generator, so one seed gives both paths the same table entries and noise; the
test also checks that both leave the generator in the same state. The fused node exists only for float32 CPU
tensors (the native KL kernel is float32), so the reference is the plain path on a float64 copy of the model
(pure PyTorch formulas, as float64 never takes the native kernel), and, as a second reference at the same
precision, the plain path in float32 with ``UNCERTSPLAT_RASTERIZER=torch``.

Tolerances, per tensor: sample values and gradients within a relative L2 error of 1e-5 and elementwise
within 1e-5 x the tensor's largest magnitude; KL terms within rel 1e-5 + abs 1e-6 nats (at the prior they are
~1e-7 in float32 instead of 0). Measured worst cases over the cases below: against float64, values and
gradients 8e-7 (relative L2 and elementwise), KL terms 1.0e-6 relative; against the float32 PyTorch path,
values and gradients 3e-7, KL terms 2.2e-6 relative (that path's own float32 mean; the fused node averages the
subset by strided adds and the native kernel sums in double over blocks).

One case is compared with the float32 reference only: the "paper" variant exactly at the prior, where its L1
scale term sits on the kinks of |l - (1 - w_p)| and |l + w - 1|. Whether those differences round to 0, +tiny or
-tiny depends on the precision, and the gradient of |x| there is 0, +1 or -1 accordingly: a property of the L1
term, not of the fused path.
"""

from __future__ import annotations

import pytest
import torch

from uncertsplat import native
from uncertsplat.gaussians.params import GaussianModel
from uncertsplat.gaussians.variational import Prior, kl_terms, random_model, sample, sample_with_kl

REL, ELEM, KL_ABS = 1e-5, 1e-5, 1e-6
SAMPLE_FIELDS = ("means", "quats", "scales", "opacities", "sh")
KL_FIELDS = ("position", "scale", "gate")
EXTENT = 3.0


@pytest.fixture(autouse=True)
def needs_native():
    if native.library() is None:
        pytest.skip(f"native kernels unavailable: {native.unavailable_reason()}")


def _copy(model: GaussianModel, dtype: torch.dtype) -> GaussianModel:
    return GaussianModel({k: v.detach().to(dtype).clone() for k, v in model.params.items()},
                         {k: v.detach().to(dtype).clone() for k, v in model.tables.items()},
                         model.posterior_row.clone(), model.sh_degree, model.num_entries)


def _run(model: GaussianModel, prior: Prior, subset_size: int, *, fused: bool, seed: int = 7):
    """Values, KL terms, gradients of every parameter and the generator state after the draws.

    The loss weights every sample output and every KL term differently (float64 weights drawn from their own
    generator, the same for both paths), so a gradient sent to the wrong place or the wrong term shows."""
    gen = torch.Generator().manual_seed(seed)
    if fused:
        s, kl = sample_with_kl(model, gen, prior, subset_size=subset_size, extent=EXTENT)
    else:
        s = sample(model, gen, subset_size=subset_size, variant=prior.variant, extent=EXTENT,
                   temperature=prior.temperature)
        kl = kl_terms(model, prior)
    state = gen.get_state()
    wgen = torch.Generator().manual_seed(99)
    loss = 0.0
    values = {}
    for name in SAMPLE_FIELDS:
        t = getattr(s, name)
        values[name] = t.detach().double()
        loss = loss + (t * torch.randn(t.shape, generator=wgen, dtype=torch.float64).to(t.dtype)).sum()
    for i, name in enumerate(KL_FIELDS):
        values[f"kl_{name}"] = kl[name].detach().double()
        loss = loss + (1.5 + i) * kl[name]
    values["kl_total"] = kl["total"].detach().double()
    loss.backward()
    grads = {k: (p.grad if p.grad is not None else torch.zeros_like(p)).double() for k, p in model.parameters().items()}
    return values, grads, state, kl["position"].grad_fn


def _differences(got: dict, ref: dict) -> dict[str, tuple[float, float]]:
    """name -> (relative L2 error, largest elementwise error / largest reference magnitude)."""
    out = {}
    for k, r in ref.items():
        g = got[k]
        assert g.shape == r.shape, k
        if r.numel() == 0:
            out[k] = (0.0, 0.0)
            continue
        scale = r.abs().max().clamp_min(1e-30)
        out[k] = (((g - r).norm() / r.norm().clamp_min(1e-30)).item(), ((g - r).abs().max() / scale).item())
    return out


def _assert_close(got_vals, got_grads, ref_vals, ref_grads, what):
    for k, v in ref_vals.items():
        if k.startswith("kl_"):
            assert abs(got_vals[k].item() - v.item()) <= REL * abs(v.item()) + KL_ABS, (what, k, got_vals[k], v)
    for k, (rel, elem) in {**_differences({k: v for k, v in got_vals.items() if not k.startswith("kl_")},
                                          {k: v for k, v in ref_vals.items() if not k.startswith("kl_")}),
                           **_differences(got_grads, ref_grads)}.items():
        assert torch.isfinite(got_grads.get(k, got_vals.get(k))).all(), (what, k)
        assert rel <= REL and elem <= ELEM, (what, k, rel, elem)


# (Gaussians, K entries, subset size M, carrier fraction, table perturbation in raw units)
CASES = {
    "subset_of_carriers": (300, 10, 2, 0.5, 0.3),
    "one_entry": (300, 1, 2, 0.5, 0.3),  # K = 1: M clamps to 1, every sample uses entry 0
    "subset_is_all_entries": (300, 4, 4, 0.6, 0.3),  # M = K
    "subset_larger_than_table": (200, 3, 7, 1.0, 1.5),  # M > K clamps to K; every Gaussian a carrier
    "one_carrier": (30, 5, 2, 0.03, 0.3),  # P = 1 (checked below)
    "far_from_the_prior": (200, 6, 3, 0.7, 2.5),
    "no_carriers": (50, 10, 2, 0.0, 0.3),  # P = 0: the fused call falls back to the plain path
}


@pytest.mark.parametrize("variant", ["ours", "paper"])
@pytest.mark.parametrize("case", list(CASES))
def test_fused_path_matches_the_plain_path(monkeypatch, variant, case):
    n, k, m, fraction, perturb = CASES[case]
    prior = Prior(variant=variant)
    base = random_model(n, torch.Generator().manual_seed(5), num_entries=k, carrier_fraction=fraction, prior=prior,
                        perturb_tables=perturb, extent=EXTENT)
    if case == "one_carrier":
        assert base.num_carriers == 1
    monkeypatch.setenv("UNCERTSPLAT_RASTERIZER", "auto")
    fused = _run(_copy(base, torch.float32), prior, m, fused=True)
    ref64 = _run(_copy(base, torch.float64), prior, m, fused=False)
    monkeypatch.setenv("UNCERTSPLAT_RASTERIZER", "torch")
    ref32 = _run(_copy(base, torch.float32), prior, m, fused=False)

    # the fused node was used (or, with no carriers, deliberately not)
    assert (type(fused[3]).__name__ == "_FusedTablesBackward") == (base.num_carriers > 0)
    # the same draws: the generator ends in the same state on every path
    assert torch.equal(fused[2], ref64[2]) and torch.equal(fused[2], ref32[2])
    _assert_close(fused[0], fused[1], ref64[0], ref64[1], "fused vs float64 plain")
    _assert_close(fused[0], fused[1], ref32[0], ref32[1], "fused vs float32 plain (torch)")


@pytest.mark.parametrize("variant", ["ours", "paper"])
def test_fused_path_matches_at_the_prior(monkeypatch, variant):
    """Tables exactly at the prior (KL = 0): a fresh carrier set, as right after spawning."""
    prior = Prior(variant=variant)
    base = random_model(200, torch.Generator().manual_seed(6), num_entries=10, carrier_fraction=1.0, prior=prior,
                        extent=EXTENT)
    monkeypatch.setenv("UNCERTSPLAT_RASTERIZER", "auto")
    fused = _run(_copy(base, torch.float32), prior, 2, fused=True)
    monkeypatch.setenv("UNCERTSPLAT_RASTERIZER", "torch")
    ref32 = _run(_copy(base, torch.float32), prior, 2, fused=False)
    ref64 = _run(_copy(base, torch.float64), prior, 2, fused=False)
    assert type(fused[3]).__name__ == "_FusedTablesBackward"
    _assert_close(fused[0], fused[1], ref32[0], ref32[1], "fused vs float32 plain (torch)")
    for k in KL_FIELDS:
        assert abs(fused[0][f"kl_{k}"].item()) <= KL_ABS, k
    if variant == "ours":  # smooth everywhere: the float64 reference applies too
        _assert_close(fused[0], fused[1], ref64[0], ref64[1], "fused vs float64 plain")


def test_fused_path_without_gradients_gives_the_same_values(monkeypatch):
    """Under ``no_grad`` the fused node keeps no gradient buffers; the sample and the draws are unchanged, and
    the KL terms agree to float32 rounding (the kernel's gradient-free loop is compiled separately and may
    round the per-element terms differently: seen 1 ulp of the float32 mean)."""
    monkeypatch.setenv("UNCERTSPLAT_RASTERIZER", "auto")
    prior = Prior()
    model = random_model(100, torch.Generator().manual_seed(8), num_entries=5, perturb_tables=0.4, extent=EXTENT)
    with torch.no_grad():
        s0, kl0 = sample_with_kl(model, torch.Generator().manual_seed(1), prior, subset_size=2, extent=EXTENT)
    s1, kl1 = sample_with_kl(model, torch.Generator().manual_seed(1), prior, subset_size=2, extent=EXTENT)
    assert not kl0["total"].requires_grad and kl1["total"].requires_grad
    for name in SAMPLE_FIELDS:
        assert torch.equal(getattr(s0, name), getattr(s1, name).detach()), name
    for name in (*KL_FIELDS, "total"):
        torch.testing.assert_close(kl0[name], kl1[name].detach(), rtol=1e-6, atol=0.0, msg=name)


class TestMeanGaussiansKernel:
    """A training step's Gaussians from the parameters and the kept table terms (``variational._with_constants``):
    the native pass (``native/csrc/sample.cpp``) against the tensor ops, values and gradients, down to the
    extremes of the logits and log scales, a gate of 0 and 1, and outputs the loss does not use."""

    @staticmethod
    def _params(n: int, g: torch.Generator, extreme: bool) -> dict[str, torch.Tensor]:
        scales = torch.randn(n, 3, generator=g) - 3.0
        logits = 3.0 * torch.randn(n, generator=g)
        if extreme:
            scales[:4] = torch.tensor([-80.0, -20.0, 5.0, 40.0])[:, None]
            logits[:6] = torch.tensor([-100.0, -30.0, -1e-7, 0.0, 30.0, 100.0])
        return {"means": torch.randn(n, 3, generator=g).requires_grad_(), "scales": scales.requires_grad_(),
                "opacities": logits.requires_grad_()}

    @staticmethod
    def _run(params, fn, weights, used=(0, 1, 2)):
        for t in params.values():
            t.grad = None
        out = fn()
        sum((out[i] * weights[i]).sum() for i in used).backward()
        return [o.detach() for o in out] + [params[k].grad for k in ("means", "scales", "opacities")]

    @pytest.mark.parametrize("extreme", [False, True])
    @pytest.mark.parametrize("used", [(0, 1, 2), (1,), (0, 2)])
    def test_matches_the_tensor_ops(self, extreme, used):
        from uncertsplat.gaussians.variational import _MeanGaussians, _with_constants

        g = torch.Generator().manual_seed(11)
        n = 1031  # not a multiple of any vector width
        params = self._params(n, g, extreme)
        offset = 0.01 * torch.randn(n, 3, generator=g)
        factor = torch.rand(n, 3, generator=g) + 0.5
        gate = torch.rand(n, generator=g)
        gate[:2] = torch.tensor([0.0, 1.0])
        weights = [torch.randn(n, 3, generator=g), torch.randn(n, 3, generator=g), torch.randn(n, generator=g)]
        calls = []
        original = _MeanGaussians.apply
        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(_MeanGaussians, "apply", lambda *a: calls.append(1) or original(*a))
            fused = self._run(params, lambda: _with_constants(params, offset, factor, gate), weights, used)
        assert calls, "the native pass did not run"
        reference = self._run(params, lambda: (params["means"] + offset, torch.exp(params["scales"]) * factor,
                                               torch.sigmoid(params["opacities"]) * gate), weights, used)
        for name, a, b in zip(("means", "scales", "opacities", "d means", "d scales", "d opacities"), fused,
                              reference, strict=True):
            if b is None:
                assert a is None or not a.any(), name
                continue
            assert torch.isfinite(a).all(), name
            # 2-3 ulp of float32 (vmath's exp against torch's); below the smallest normal float both are ~0
            torch.testing.assert_close(a, b, rtol=4e-7, atol=1e-37, msg=name)

    def test_other_cases_take_the_tensor_ops(self):
        """float64, a constant that needs a gradient, shapes that only broadcast: the tensor ops."""
        from uncertsplat.gaussians.variational import _MeanGaussians, _with_constants

        g = torch.Generator().manual_seed(3)
        params = self._params(50, g, False)
        offset, factor, gate = torch.zeros(50, 3), torch.ones(50, 3), torch.ones(50)
        calls = []
        original = _MeanGaussians.apply
        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(_MeanGaussians, "apply", lambda *a: calls.append(1) or original(*a))
            _with_constants({k: v.double() for k, v in params.items()}, offset.double(), factor.double(),
                            gate.double())
            _with_constants(params, offset, factor, gate.clone().requires_grad_())
            _with_constants(params, offset, torch.ones(3), gate)
        assert not calls
