"""Our Adam (``train.adam``): the dense step in one native call, and the sparse updates (``TrainConfig.sparse_updates``)."""

from __future__ import annotations

import copy

import pytest
import torch
from torch import nn

from tests.e2e.test_train_resume import assert_same_parameters, toy_config, toy_scene
from uncertsplat import native
from uncertsplat.io.checkpoints import decode, encode
from uncertsplat.train.adam import Adam, adam_rows
from uncertsplat.train.trainer import Trainer

BACKENDS = ["torch", pytest.param("native", marks=pytest.mark.skipif(native.library() is None,
                                                                     reason="native kernels unavailable"))]


def _params(seed: int = 0, shapes=((50, 3), (50, 15, 3), (50,))):
    g = torch.Generator().manual_seed(seed)
    return [nn.Parameter(torch.randn(s, generator=g)) for s in shapes]


def _grads(params, seed: int, rows: torch.Tensor | None = None):
    """Random gradients; with ``rows``, zero outside them (what a render gives a Gaussian it never drew)."""
    g = torch.Generator().manual_seed(seed)
    for p in params:
        p.grad = torch.randn(p.shape, generator=g)
        if rows is not None:
            mask = torch.zeros(p.shape[0], dtype=torch.bool)
            mask[rows] = True
            p.grad[~mask] = 0


def _groups(params, lr=1e-2):
    return [{"params": [p], "lr": lr, "name": f"t{i}"} for i, p in enumerate(params)]


NATIVE = pytest.mark.skipif(native.library() is None, reason="native kernels unavailable")


@NATIVE
class TestDense:
    """The dense step: every group in one native call, with the NaN/Inf check."""

    # sizes with and without a remainder past torch's 8-float vector, one tensor of 45 floats per row (SH), a scalar
    # row, and one large enough (with the rest, 90k floats) that the kernel splits the elements between workers
    # inside a tensor (it gives each at least 32768)
    SHAPES = ((97, 3), (64, 4), (97, 15, 3), (97,), (1, 1), (2851, 15, 2))

    def _pair(self, lr=3e-1):
        a, b = _params(shapes=self.SHAPES), _params(shapes=self.SHAPES)
        ga = [{"params": [p], "lr": lr * (i + 1), "name": f"t{i}"} for i, p in enumerate(a)]
        gb = [{"params": [p], "lr": lr * (i + 1), "name": f"t{i}"} for i, p in enumerate(b)]
        return a, b, torch.optim.Adam(ga, lr=0.0, eps=1e-15, fused=True), Adam(gb, eps=1e-15)

    @pytest.mark.parametrize("threads", [1, 2, 3])
    def test_bit_identical_to_torch_fused_adam(self, threads, monkeypatch):
        """The default optimiser's numbers did not change with it: parameters, moments and step counts equal torch's
        fused Adam's on one thread (as training ran it) to the bit, after steps with different learning rates per
        group, on any number of threads of ours (the elements are split at arbitrary points between them). Bits
        are compared where torch runs its AVX2 kernel (x86 CPUs with AVX2 or AVX-512); elsewhere to a rounding."""
        monkeypatch.setattr(native, "kernel_threads", lambda: threads)
        a, b, theirs, ours = self._pair()
        torch_threads = torch.get_num_threads()
        torch.set_num_threads(1)  # torch splits a tensor between its threads, each part with its own scalar tail
        try:
            for step in range(12):
                _grads(a, step)
                _grads(b, step)
                if step == 6:  # a group without a gradient skips the step (its count too), as in torch
                    a[1].grad = b[1].grad = None
                # one tensor's first moments below float's normal range: torch keeps the denormals
                a[0].grad.mul_(1e-38)
                b[0].grad.mul_(1e-38)
                # rows that never get a gradient (an SH band not switched on yet: the native step skips their cache
                # lines), and some that get one from step 4 on
                for p in (a[2], b[2]):
                    p.grad[: 40 if step < 4 else 20] = 0.0
                    if step >= 8:  # no gradient but moments: momentum still moves them
                        p.grad[40:] = 0.0
                theirs.step()
                assert ours.step_if_finite()
        finally:
            torch.set_num_threads(torch_threads)
        exact = torch.backends.cpu.get_cpu_capability() in ("AVX2", "AVX512")
        for pa, pb in zip(a, b, strict=True):
            for key in ("exp_avg", "exp_avg_sq", "step"):
                x, y = ours.state[pb][key], theirs.state[pa][key]
                assert torch.equal(x, y) if exact else torch.allclose(x, y, rtol=1e-5, atol=1e-7), key
            assert torch.equal(pb.detach(), pa.detach()) if exact else torch.allclose(pb, pa, rtol=1e-5, atol=1e-6)
        assert int(ours.state[b[1]]["step"]) == 11

    def test_a_second_moment_decays_after_the_first_has_underflowed(self):
        """Rows with no gradient whose first moment has reached exactly 0 (it decays by beta1 = 0.9 a step: a float
        underflows after about 900 steps without a gradient) still hold a second moment (beta2 = 0.999), which Adam
        decays every step: the kernel may skip a cache line only where the gradient and *both* moments are 0. After
        steps in that state, moments and parameters equal torch's fused Adam's as in the test above."""
        a, b, theirs, ours = self._pair()
        for step in range(4):
            _grads(a, step)
            _grads(b, step)
            if step >= 1:
                for p, opt in ((a[2], theirs), (b[2], ours)):
                    p.grad[:40] = 0.0
                    opt.state[p]["exp_avg"][:40] = 0.0
            torch_threads = torch.get_num_threads()
            torch.set_num_threads(1)
            try:
                theirs.step()
            finally:
                torch.set_num_threads(torch_threads)
            assert ours.step_if_finite()
        v = ours.state[b[2]]["exp_avg_sq"]
        assert bool((v[:40] > 0).all())
        exact = torch.backends.cpu.get_cpu_capability() in ("AVX2", "AVX512")
        for pa, pb in zip(a, b, strict=True):
            for key in ("exp_avg", "exp_avg_sq"):
                x, y = ours.state[pb][key], theirs.state[pa][key]
                assert torch.equal(x, y) if exact else torch.allclose(x, y, rtol=1e-5, atol=1e-7), key
            assert torch.equal(pb.detach(), pa.detach()) if exact else torch.allclose(pb, pa, rtol=1e-5, atol=1e-6)

    @pytest.mark.parametrize("value", [float("nan"), float("inf"), -float("inf")])
    @pytest.mark.parametrize("where", [(0, (0, 0)), (2, (96, 14, 2)), (4, (0, 0))])
    def test_non_finite_gradient_changes_nothing(self, value, where):
        """One NaN/Inf anywhere (first element, last element of the largest tensor, a one-element tensor): no
        parameter, moment or step count moves, and the step says so; the next finite step proceeds."""
        _, b, _, ours = self._pair()
        _grads(b, 0)
        ours.step_if_finite()
        before = [(p.detach().clone(), {k: v.clone() for k, v in ours.state[p].items()}) for p in b]
        _grads(b, 1)
        tensor, index = where
        b[tensor].grad[index] = value
        assert not ours.step_if_finite()
        for p, (p0, state) in zip(b, before, strict=True):
            assert torch.equal(p.detach(), p0)
            for k, v in state.items():
                assert torch.equal(ours.state[p][k], v), k
        b[tensor].grad[index] = 0.0
        assert ours.step_if_finite()
        assert int(ours.state[b[0]]["step"]) == 2

    def test_moments_of_another_shape_take_the_checked_path(self):
        """The kernels read raw pointers: a state whose moments do not match their parameter (an odd checkpoint) is
        handed to neither; the per-group path refuses it with the shapes."""
        _, b, _, ours = self._pair()
        _grads(b, 0)
        ours.step_if_finite()
        live = [g for g in ours.param_groups if g["params"][0].grad is not None]
        assert ours._dense_native(live)
        ours.state[b[0]]["exp_avg"] = torch.zeros(5, 3)
        assert not ours._dense_native(live)
        with pytest.raises(ValueError, match=r"first moment has shape \(5, 3\), its parameter \(97, 3\)"):
            ours.step_if_finite()

    def test_without_the_check_a_nan_is_applied(self):
        """``step()`` (torch's interface) does not check: the caller decided (the trainer checks through
        ``step_if_finite``)."""
        _, b, _, ours = self._pair()
        _grads(b, 0)
        b[0].grad[0, 0] = float("nan")
        ours.step()
        assert torch.isnan(b[0].detach()[0, 0])

    def test_checkpoints_load_both_ways(self):
        """Our state dict loads into torch's Adam (a CPU run resumed on CUDA) and back, and both continue alike;
        torch's Adam keeps its own options (fused)."""
        from uncertsplat.train.optim import load_optimizer_state

        a, b, theirs, ours = self._pair()
        for step in range(3):
            _grads(b, step)
            ours.step_if_finite()
        for pa, pb in zip(a, b, strict=True):
            pa.data.copy_(pb.detach())
        load_optimizer_state(theirs, copy.deepcopy(ours.state_dict()))  # as read from a file: no shared tensors
        assert all(g["fused"] for g in theirs.param_groups) and theirs.param_groups[2]["lr"] == pytest.approx(0.9)
        _grads(a, 7)
        _grads(b, 7)
        theirs.step()
        ours.step_if_finite()
        exact = torch.backends.cpu.get_cpu_capability() in ("AVX2", "AVX512")
        for pa, pb in zip(a, b, strict=True):
            assert torch.equal(pb.detach(), pa.detach()) if exact else torch.allclose(pb, pa, rtol=1e-5, atol=1e-6)
        back = Adam(ours.param_groups, eps=1e-15)
        load_optimizer_state(back, copy.deepcopy(theirs.state_dict()))
        assert all(torch.equal(back.state[p]["exp_avg_sq"], ours.state[p]["exp_avg_sq"]) for p in b)

    @pytest.mark.parametrize("sparse", [False, True])
    @pytest.mark.parametrize("gradient", ["none", "zeros"])
    def test_an_idle_group_is_skipped_to_the_bit(self, gradient, sparse):
        """``idle``: a group whose gradient (none, or zeros) and moments are zero (SH bands not switched on yet) is
        not read, and the step leaves parameters, moments and step counts as the step over every element would,
        to the bit, also once the group gets gradients; torch's convention (a group without a gradient skips the
        step, its count too) would have given it step 1 there instead of step 5."""
        shapes = ((97, 3), (97, 15, 3), (97,))
        a, b = _params(shapes=shapes), _params(shapes=shapes)
        full, part = Adam(_groups(a), eps=1e-15), Adam(_groups(b), eps=1e-15)
        rows = {"t0": torch.arange(0, 97, 2), "t1": torch.arange(0, 97, 3)} if sparse else None
        for step in range(8):
            _grads(a, step)
            _grads(b, step)
            asleep = step < 4
            if asleep:
                a[1].grad.zero_()
                b[1].grad = None if gradient == "none" else torch.zeros_like(b[1])
            assert full.step_if_finite(rows)
            assert part.step_if_finite(rows, idle=("t1",) if asleep else ())
        for pa, pb in zip(a, b, strict=True):
            for key in ("exp_avg", "exp_avg_sq", "step"):
                assert torch.equal(part.state[pb][key], full.state[pa][key]), key
            assert torch.equal(pb.detach(), pa.detach())
        assert int(part.state[b[1]]["step"]) == 8

    def test_an_idle_group_is_not_read(self):
        """The skip is real: an idle group's gradient (here NaN, which the check refuses otherwise) is neither read
        nor applied; the other groups are updated."""
        params = _params(shapes=((40, 3), (40, 15, 3)))
        opt = Adam(_groups(params), eps=1e-15)
        _grads(params, 0)
        params[1].grad[5, 2, 1] = float("nan")
        before = [p.detach().clone() for p in params]
        assert opt.step_if_finite(idle=("t1",))
        assert torch.equal(params[1].detach(), before[1])
        assert not torch.equal(params[0].detach(), before[0])
        assert not opt.step_if_finite(), "not idle, the NaN is seen and the step refused"
        steps = int(opt.state[params[1]]["step"])
        opt.step(idle=("t1",))  # ``step`` hands ``idle`` on: unchecked, the NaN would be applied
        assert torch.equal(params[1].detach(), before[1]) and int(opt.state[params[1]]["step"]) == steps + 1

    def test_the_trainer_uses_it_on_the_cpu(self):
        """``make_optimizer``'s dense Adam on CPU float32 is ours (one call per step), torch's when the native
        kernels are not used."""
        from uncertsplat.train.optim import make_optimizer

        scene, tr, te = toy_scene()
        t = Trainer(scene, toy_config(iterations=1), tr, te)
        assert isinstance(t.optimizer, Adam)
        rates = {name: 1e-3 for name in t.model.parameters()}
        with pytest.MonkeyPatch.context() as mp:
            mp.setenv("UNCERTSPLAT_RASTERIZER", "torch")
            assert type(make_optimizer(t.model, rates)) is torch.optim.Adam


class TestRows:
    @pytest.mark.parametrize("backend", BACKENDS)
    def test_every_row_equals_torch_adam(self, backend, monkeypatch):
        monkeypatch.setenv("UNCERTSPLAT_RASTERIZER", backend)
        a, b = _params(), _params()
        dense = torch.optim.Adam(_groups(a), eps=1e-15)
        sparse = Adam(_groups(b), eps=1e-15)
        for step in range(5):
            _grads(a, step)
            _grads(b, step)
            dense.step()
            sparse.step()
        for pa, pb in zip(a, b, strict=True):
            torch.testing.assert_close(pb, pa, rtol=1e-5, atol=1e-6)
            for key in ("exp_avg", "exp_avg_sq"):
                torch.testing.assert_close(sparse.state[pb][key], dense.state[pa][key], rtol=1e-5, atol=1e-6)

    @pytest.mark.parametrize("backend", BACKENDS)
    @pytest.mark.parametrize("lazy", [False, True])
    def test_rows_outside_the_list_are_untouched_exactly(self, backend, lazy, monkeypatch):
        monkeypatch.setenv("UNCERTSPLAT_RASTERIZER", backend)
        params = _params()
        opt = Adam(_groups(params), lazy=lazy)
        _grads(params, 0)
        opt.step()  # every row has moments now
        before = [(p.detach().clone(), opt.state[p]["exp_avg"].clone(), opt.state[p]["exp_avg_sq"].clone())
                  for p in params]
        rows = torch.tensor([3, 7, 11, 40])
        _grads(params, 1)  # gradients everywhere: rows not listed must still not move
        opt.step(rows={f"t{i}": rows for i in range(len(params))})
        out = torch.ones(50, dtype=torch.bool)
        out[rows] = False
        for p, (p0, m0, v0) in zip(params, before, strict=True):
            assert torch.equal(p.detach()[out], p0[out])
            assert torch.equal(opt.state[p]["exp_avg"][out], m0[out])
            assert torch.equal(opt.state[p]["exp_avg_sq"][out], v0[out])
            assert not torch.equal(p.detach()[rows], p0[rows])

    @pytest.mark.parametrize("rows", [[0, 5, 6, 7, 9, 39, 17], list(range(2, 38))],
                             ids=["few rows (runs)", "most rows (masked sweep)"])
    def test_native_and_torch_paths_agree_with_lazy_decay(self, rows):
        if native.library() is None:
            pytest.skip("native kernels unavailable")
        g = torch.Generator().manual_seed(3)
        tensors = [torch.randn(40, 6, generator=g) for _ in range(4)]
        tensors[3] = tensors[3].abs()  # exp_avg_sq >= 0
        last = torch.randint(0, 5, (40,), generator=g)
        rows = torch.tensor(rows)
        out = {}
        for backend in ("torch", "native"):
            p, gr, m, v = (t.clone() for t in tensors)
            ls = last.clone()
            adam_rows(p, gr, m, v, ls, rows, step=9, lr=0.01, beta1=0.9, beta2=0.999, eps=1e-15, backend=backend)
            out[backend] = (p, m, v, ls)
        for x, y in zip(out["torch"], out["native"], strict=True):
            torch.testing.assert_close(y, x, rtol=2e-6, atol=1e-7)
        others = torch.ones(40, dtype=torch.bool)
        others[rows] = False
        assert (out["native"][3][rows] == 9).all() and torch.equal(out["native"][3][others], last[others])

    @pytest.mark.parametrize("backend", BACKENDS)
    def test_lazy_decay_is_the_dense_decay_of_the_skipped_steps(self, backend, monkeypatch):
        """A row skipped for k steps then updated: its moments equal dense Adam's after k zero-gradient steps."""
        monkeypatch.setenv("UNCERTSPLAT_RASTERIZER", backend)
        a, b = _params(shapes=((6, 4),)), _params(shapes=((6, 4),))
        dense = torch.optim.Adam(_groups(a), eps=1e-15)
        lazy = Adam(_groups(b), eps=1e-15, lazy=True)
        all_rows = {"t0": torch.arange(6)}
        for step in range(6):
            rows = torch.arange(6) if step in (0, 5) else torch.tensor([0, 1])  # rows 2-5 skipped 4 steps
            _grads(a, step, rows)
            _grads(b, step, rows)
            dense.step()
            lazy.step(rows=all_rows if step in (0, 5) else {"t0": rows})
        for key in ("exp_avg", "exp_avg_sq"):
            torch.testing.assert_close(lazy.state[b[0]][key], dense.state[a[0]][key], rtol=1e-5, atol=1e-10)
        assert (lazy.state[b[0]]["last_step"] == 6).all()
        # the parameters differ: dense Adam kept moving the skipped rows by their momentum, lazy did not
        assert not torch.allclose(b[0][2:], a[0][2:])
        torch.testing.assert_close(b[0][:2], a[0][:2], rtol=1e-5, atol=1e-6)

    @pytest.mark.parametrize("backend", BACKENDS)
    @pytest.mark.parametrize("source", ["ours", "torch"])
    def test_lazy_after_a_dense_state_owes_no_decay(self, backend, source, monkeypatch):
        """A dense state (ours, or torch's Adam: a run resumed with ``sparse_updates="lazy"``) loaded into lazy
        Adam: every row was updated at the state's last step, so the next sparse step decays nothing extra; the
        touched rows' moments and values are those of one more dense step, and ``last_step`` starts at the loaded
        step count."""
        from uncertsplat.train.optim import load_optimizer_state

        monkeypatch.setenv("UNCERTSPLAT_RASTERIZER", backend)
        a, b = _params(shapes=((6, 4), (6,))), _params(shapes=((6, 4), (6,)))
        dense = (Adam if source == "ours" else torch.optim.Adam)(_groups(a), eps=1e-15)
        for step in range(3):
            _grads(a, step)
            dense.step()
        for pa, pb in zip(a, b, strict=True):
            pb.data.copy_(pa.detach())
        lazy = Adam(_groups(b), eps=1e-15, lazy=True)
        load_optimizer_state(lazy, copy.deepcopy(dense.state_dict()))  # as read from a checkpoint
        rows = torch.tensor([1, 4])
        _grads(a, 3, rows)
        _grads(b, 3, rows)
        dense.step()
        lazy.step(rows={"t0": rows, "t1": rows})
        others = torch.tensor([0, 2, 3, 5])
        for pa, pb in zip(a, b, strict=True):
            for key in ("exp_avg", "exp_avg_sq"):
                torch.testing.assert_close(lazy.state[pb][key][rows], dense.state[pa][key][rows], rtol=1e-5,
                                           atol=1e-12)
            torch.testing.assert_close(pb.detach()[rows], pa.detach()[rows], rtol=1e-5, atol=1e-6)
            assert int(lazy.state[pb]["step"]) == 4
            assert lazy.state[pb]["last_step"].tolist() == [3, 4, 3, 3, 4, 3]
            # the skipped rows keep the loaded moments (dense Adam decayed them): they owe one step from here
            assert not torch.allclose(lazy.state[pb]["exp_avg"][others], dense.state[pa]["exp_avg"][others])

    def test_empty_row_list_and_no_gradient_change_nothing(self):
        params = _params(shapes=((5, 2),))
        opt = Adam(_groups(params))
        p0 = params[0].detach().clone()
        opt.step()  # no gradient yet
        assert not opt.state
        _grads(params, 0)
        opt.step(rows={"t0": torch.zeros(0, dtype=torch.long)})
        assert torch.equal(params[0].detach(), p0)


class TestTraining:
    def test_dense_and_sparse_agree_when_every_gaussian_is_visible(self, monkeypatch):
        """The toy scene's Gaussians sit in front of every camera; with no densification the rows a view touches
        are all rows at almost every step, and the parameters follow dense Adam's. (On the native kernels, where
        both run in one kernel: torch's path rounds its fused and per-row updates apart, up to 7e-4 in a few quats.)"""
        from uncertsplat import native

        if native.library() is None:
            pytest.skip("the native CPU kernels are not available on this machine")
        monkeypatch.setenv("UNCERTSPLAT_RASTERIZER", "native")
        scene, tr, te = toy_scene()
        base = {"iterations": 12, "densify": {"start": 1000, "until": 1000, "interval": 10, "spawn_interval": 10**6,
                                              "opacity_reset_interval": 0}}
        dense = Trainer(scene, toy_config(**base, sparse_updates="dense"), tr, te)
        dense.fit()
        sparse = Trainer(scene, toy_config(**base, sparse_updates="visible"), tr, te)
        touched = []
        rows_of = sparse.touched_rows

        def recording(radii):
            touched.append(rows_of(radii))
            return touched[-1]

        sparse.touched_rows = recording
        sparse.fit()
        assert len(touched) == 12
        assert all(len(r["means"]) == len(sparse.model) for r in touched), "the test needs every Gaussian in view"
        for name, p in dense.model.params.items():
            torch.testing.assert_close(sparse.model.params[name], p, rtol=1e-4, atol=1e-5, msg=name)

    @pytest.mark.parametrize("mode", ["visible", "lazy"])
    def test_training_runs_and_resume_restores_the_sparse_state(self, mode):
        scene, tr, te = toy_scene()
        cfg = toy_config(sparse_updates=mode)
        full = Trainer(scene, cfg, tr, te)
        full.fit()
        assert len(full.model) != 150, "densification ran: the optimiser state was edited with the rows"
        part = Trainer(scene, cfg, tr, te)
        part.fit(until=17)
        resumed = Trainer(scene, cfg, tr, te, state=decode(encode(part.state_dict())))
        resumed.fit()
        assert_same_parameters(full.model, resumed.model)
        sa, sb = full.optimizer.state_dict()["state"], resumed.optimizer.state_dict()["state"]
        for i in sa:
            for key in sa[i]:
                torch.testing.assert_close(sb[i][key], sa[i][key], rtol=0, atol=1e-6, msg=f"{i}.{key}")
        if mode == "lazy":
            assert all("last_step" in s for s in sa.values())

    def test_bands_not_switched_on_cost_nothing_and_change_nothing(self, monkeypatch):
        """At SH degree 0 Adam does not read the higher bands (``idle``), which get no gradient at all once the
        step renders the table's two SH tensors (the native SH backward writes none: from the first posterior
        update on, when the model has carriers), yet their step count keeps pace. The parameters and moments of such
        a run equal, to the bit, those of a run in which every step handed Adam a gradient of zeros for the bands
        and Adam updated every element (the way before)."""
        from uncertsplat.render import sh as sh_module

        if native.library() is None:
            pytest.skip("the native CPU kernels are not available on this machine")
        scene, tr, te = toy_scene()
        cfg = toy_config(iterations=24, sh_degree_interval=15)  # degree 0 to step 14, carriers from step 11 on
        seen: list[tuple[int, bool, tuple[str, ...]]] = []
        fast = Trainer(scene, cfg, tr, te)
        update = fast._update

        def recording(loss, radii, idle):
            seen.append((fast.step + 1, fast.model.params["shN"].grad is None, idle))
            return update(loss, radii, idle)

        fast._update = recording
        fast.fit()
        assert [(k, idle) for k, _, idle in seen if k < 15] == [(k, ("shN",)) for k in range(1, 15)], "degree 0"
        assert any(none for k, none, _ in seen if k < 15), "no step rendered the split SH without a band gradient"
        assert all(not none and idle == () for k, none, idle in seen if k >= 15), "degree 1, the model's own"

        backward = sh_module._NativeSH.backward

        def zeros_for_the_bands(ctx, grad):
            out = list(backward(ctx, grad))
            if out[1] is None and len(ctx.saved_tensors) == 4:
                out[1] = torch.zeros_like(ctx.saved_tensors[3])
            return tuple(out)

        monkeypatch.setattr(sh_module._NativeSH, "backward", staticmethod(zeros_for_the_bands))
        monkeypatch.setattr(Trainer, "_idle_sh", lambda self, degree: ())
        slow = Trainer(scene, cfg, tr, te)
        slow.fit()
        for name, p in fast.model.parameters().items():
            q = slow.model.parameters()[name]
            assert torch.equal(p.detach(), q.detach()), name
            mine, theirs = fast.optimizer.state.get(p, {}), slow.optimizer.state.get(q, {})
            assert mine.keys() == theirs.keys(), name  # (the informed tables get no gradient, so no state)
            for key in mine:
                assert torch.equal(mine[key], theirs[key]), f"{name}.{key}"
        assert int(fast.optimizer.state[fast.model.params["shN"]]["step"]) == 24

    @pytest.mark.parametrize("mode", ["dense", "lazy"])
    @pytest.mark.parametrize("bands", ["none", "dropped"])
    def test_a_model_without_higher_bands_keeps_every_step_count(self, bands, mode):
        """A model at SH degree 0 for good (``sh_degree = 0``, or band 1 dropped by its test: ``shN`` [N,0,3]) still
        counts every step for ``shN``, as when each step handed Adam its (empty) gradient: the native SH backward
        gives it none at degree 0, which must not stop its count (the checkpoint's state as before, and as on
        torch's path)."""
        if native.library() is None:
            pytest.skip("the native CPU kernels are not available on this machine")
        scene, tr, te = toy_scene()
        cfg = toy_config(iterations=24, sparse_updates=mode,
                         **({"sh_degree": 0} if bands == "none" else
                            {"sh_degree": 1, "sh_degree_interval": 10, "sh_min_gain_db": 100.0}))
        trainer = Trainer(scene, cfg, tr, te)
        trainer.fit()
        assert trainer.model.sh_degree == 0 and trainer.model.params["shN"].shape[1] == 0
        if bands == "dropped":
            assert [b.kept for b in trainer.sh_bands] == [False]
        steps = {name: int(trainer.optimizer.state[p]["step"]) for name, p in trainer.model.params.items()}
        assert steps == dict.fromkeys(steps, 24), steps

    def test_a_gaussian_outside_every_view_keeps_its_parameters_and_moments(self):
        scene, tr, te = toy_scene()
        cfg = toy_config(sparse_updates="visible", iterations=8,
                         densify={"start": 1000, "until": 1000, "interval": 10, "spawn_interval": 10**6,
                                  "opacity_reset_interval": 0})
        t = Trainer(scene, cfg, tr, te)
        t.fit(until=2)
        with torch.no_grad():  # move Gaussian 0 far behind every camera (the ring looks at the origin from z = 0.6)
            t.model.params["means"][0] = torch.tensor([0.0, 0.0, 500.0])
        before = {n: p.detach()[0].clone() for n, p in t.model.params.items()}
        moments = {n: t.optimizer.state[p]["exp_avg"][0].clone() for n, p in t.model.params.items()}
        t.fit()
        for n, p in t.model.params.items():
            assert torch.equal(p.detach()[0], before[n]), n
            assert torch.equal(t.optimizer.state[p]["exp_avg"][0], moments[n]), n


def test_torch_adam_counts_an_idle_band_without_a_gradient(monkeypatch):
    """``Trainer._update`` with torch's Adam (other devices): an idle group without a gradient (the native SH backward
    at degree 0) is handed zeros, so torch counts its step as ours does (torch skips a tensor without a gradient)."""
    scene, tr, te = toy_scene()
    t = Trainer(scene, toy_config(iterations=1), tr, te)
    params = t.model.parameters()
    t.optimizer = torch.optim.Adam([{"params": [p], "name": n, "lr": 1e-3} for n, p in params.items()])
    monkeypatch.setattr(t, "touched_rows", lambda radii: None)
    for name, p in params.items():
        p.grad = None if name == "shN" else torch.ones_like(p)
    before = params["shN"].detach().clone()
    assert t._update(torch.tensor(1.0), None, ("shN",))
    assert int(t.optimizer.state[params["shN"]]["step"]) == 1, "counted as under a gradient of zeros"
    assert torch.equal(params["shN"].detach(), before)
