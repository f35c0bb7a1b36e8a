"""Adam over named parameter groups (one tensor each): every row each step, or only the rows a step touched.

The dense step (``TrainConfig.sparse_updates = "dense"``, the default) updates every element, as
``torch.optim.Adam``; on CPU float32 it is one native call for all the groups (``native/csrc/optim.cpp``,
``us_adam_multi_f32``) on the kernels' threads, which also checks the gradients for NaN/Inf in the same call
(``step_if_finite``), instead of one kernel per group, the Python around each, and a separate pass over every
gradient for the check, with the bits of torch's fused Adam on x86 CPUs (its AVX2 kernel; BENCHMARKS.md, "One
Adam call for every group").

A view sees part of the model; with dense Adam every other Gaussian still gets an update (its momentum
keeps moving it) and its moments decay. With ``rows`` only the given rows (the Gaussians with a footprint in the
step's views, and their offset-table rows) are updated (``TrainConfig.sparse_updates``):

- ``"visible"``: the other rows' parameters and moments are left exactly as they are (the selective Adam of
  fast 3DGS trainers);
- ``"lazy"``: as ``"visible"``, but when a row comes back after k skipped steps its moments are first
  multiplied by beta1^k and beta2^k, what k dense steps with zero gradients would have left of them (the
  parameter updates those steps would have made are not replayed). Needs one step number per row
  (``last_step``, 8 bytes per row and tensor).

Bias correction uses each group's own step count, as torch's Adam. The state layout is torch's Adam's (``step``,
``exp_avg``, ``exp_avg_sq``, plus ``last_step`` for lazy), so checkpoints of either optimiser load into the
other, and ``gaussians.ops`` edits the rows of every moment together with the parameters.

On CPU float32 the sparse update is one native kernel per tensor that reads and writes only the selected rows;
elsewhere it is gathered, updated and scattered with torch ops (same arithmetic), the dense update too
(``train.optim.make_optimizer`` gives torch's fused Adam instead where the native kernels do not run).
"""

from __future__ import annotations

import ctypes
import math
from collections.abc import Collection

import torch
from torch import Tensor

from uncertsplat import native


class Adam(torch.optim.Optimizer):
    """Adam over named parameter groups (one tensor each) whose ``step`` may take the rows to update.

    Args:
        groups: ``[{"params": [p], "lr": lr, "name": name}, ...]`` as ``train.optim.make_optimizer`` builds them.
        betas, eps: Adam's.
        lazy: decay the moments of skipped rows when they come back (see the module docstring).
    """

    def __init__(self, groups, *, betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-15, lazy: bool = False):
        super().__init__(groups, {"lr": 0.0, "betas": betas, "eps": eps})
        self.lazy = lazy

    def load_state_dict(self, state_dict: dict) -> None:
        """As ``Optimizer.load_state_dict``, which casts every state tensor to its parameter's dtype: the step
        numbers of the lazy decay are made integers again (exact: steps stay far below 2^24)."""
        super().load_state_dict(state_dict)
        for state in self.state.values():
            if "last_step" in state:
                state["last_step"] = state["last_step"].round().to(torch.long).contiguous()

    @torch.no_grad()
    def step(self, closure=None, rows: dict[str, Tensor] | None = None,  # noqa: D417
             idle: Collection[str] = ()):
        """One update of the rows ``rows[group name]`` ([R] long, distinct) of each tensor that has a gradient.

        A group absent from ``rows`` (or ``rows=None``) updates every row. Rows outside the list keep their
        values and moments.

        ``idle``: groups whose gradient (if any) and moments the caller vouches are all zero (SH bands not
        switched on yet), where Adam would change no number: they are not read, but their step count advances as
        under a gradient of zeros, so that their bias correction when they wake is a dense step's (torch skips a
        group without a gradient, its step count too).
        """
        loss = closure() if closure is not None else None
        self.step_if_finite(rows, check_finite=False, idle=idle)
        return loss

    @torch.no_grad()
    def step_if_finite(self, rows: dict[str, Tensor] | None = None, *, check_finite: bool = True,
                       idle: Collection[str] = ()) -> bool:
        """As :meth:`step`; with ``check_finite`` (the default) it updates only when every gradient is finite, and
        returns False (changing nothing, moments and step counts included) when one holds a NaN or Inf."""
        live = [g for g in self.param_groups if g["params"][0].grad is not None and g["name"] not in idle]
        asleep = [g for g in self.param_groups if g["name"] in idle]
        if rows is None and not self.lazy and self._dense_native(live):
            if not self._dense_step(live, check_finite):
                return False
        elif check_finite and not all_finite(g["params"][0].grad for g in live):
            return False
        else:
            self._per_group(live, rows)
        for g in asleep:
            self._state_of(g["params"][0])["step"] += 1
        return True

    def _per_group(self, live: list[dict], rows: dict[str, Tensor] | None) -> None:
        """One native (or torch) call per group: the sparse updates, and the dense step off the native path."""
        for group in live:
            (p,) = group["params"]
            state = self._state_of(p)
            state["step"] += 1
            step = int(state["step"])
            idx = None if rows is None else rows.get(group["name"])
            if idx is None:
                idx = torch.arange(p.shape[0], device=p.device)
            if idx.numel() == 0 or p.numel() == 0:
                continue
            beta1, beta2 = group["betas"]
            adam_rows(p, p.grad, state["exp_avg"], state["exp_avg_sq"], state.get("last_step") if self.lazy else None,
                      idx, step=step, lr=group["lr"], beta1=beta1, beta2=beta2, eps=group["eps"])

    def zero_grad(self, set_to_none: bool = True) -> None:
        """As ``Optimizer.zero_grad``, without its profiler hooks (every training step calls it)."""
        for group in self.param_groups:
            for p in group["params"]:
                if p.grad is None:
                    continue
                if set_to_none:
                    p.grad = None
                else:
                    p.grad.detach_().zero_()

    def _state_of(self, p: Tensor) -> dict:
        state = self.state[p]
        if not state:
            state["step"] = torch.zeros((), dtype=torch.float32)
            state["exp_avg"] = torch.zeros_like(p, memory_format=torch.contiguous_format)
            state["exp_avg_sq"] = torch.zeros_like(p, memory_format=torch.contiguous_format)
        if self.lazy and "last_step" not in state:  # first step, or a checkpoint of dense Adam: nothing owed
            state["last_step"] = torch.full((p.shape[0],), int(state["step"]), dtype=torch.long, device=p.device)
        return state

    def _dense_native(self, live: list[dict]) -> bool:
        """Whether the dense step of these groups is one native call: CPU float32, contiguous, one beta pair, and
        moments (once they exist) of their parameter's shape (the kernel reads raw pointers: a checkpoint's odd
        state takes the per-group path, which refuses it)."""
        if not live or len({(tuple(g["betas"]), g["eps"]) for g in live}) != 1:
            return False
        tensors = [g["params"][0] for g in live] + [g["params"][0].grad for g in live]
        for g in live:
            p, state = g["params"][0], self.state.get(g["params"][0])
            if p.grad.shape != p.shape:
                return False
            if state:
                moments = [state.get("exp_avg"), state.get("exp_avg_sq")]
                if any(m is None or m.shape != p.shape for m in moments):
                    return False
                tensors += moments
        return native.use_for(*tensors, dtypes=(torch.float32,), strict=False) and all(
            t.is_contiguous() for t in tensors)

    def _dense_step(self, live: list[dict], check_finite: bool) -> bool:
        """Every element of every live group in one native call (``us_adam_multi_f32``)."""
        n = len(live)
        params = [g["params"][0] for g in live]
        states = [self._state_of(p) for p in params]
        steps = [int(s["step"]) + 1 for s in states]
        ptrs = ctypes.c_void_p * n
        beta1, beta2 = live[0]["betas"]
        bad = native.library().us_adam_multi_f32(
            n, (ctypes.c_int64 * n)(*(p.numel() for p in params)), ptrs(*(p.data_ptr() for p in params)),
            ptrs(*(p.grad.data_ptr() for p in params)), ptrs(*(s["exp_avg"].data_ptr() for s in states)),
            ptrs(*(s["exp_avg_sq"].data_ptr() for s in states)), (ctypes.c_double * n)(*(g["lr"] for g in live)),
            (ctypes.c_int64 * n)(*steps), beta1, beta2, live[0]["eps"], TORCH_ADAM_VECTOR, int(check_finite),
            native.kernel_threads())
        if bad:
            return False
        for s in states:
            s["step"] += 1
        return True


# Floats per vector in torch's fused CPU Adam: its AVX2 kernel (an AVX-512 CPU runs it too: torch registers no
# AVX-512 version of it) and its portable one; a tensor's last numel % 8 elements take its scalar loop, whose
# rounding differs in one place, which the native dense step repeats (``native/csrc/optim.cpp``)
TORCH_ADAM_VECTOR = 8


def all_finite(tensors) -> bool:
    """True when no element of the tensors is NaN/Inf. A sum is NaN/Inf as soon as one element is (one pass per
    tensor instead of isfinite's three); it could only also overflow for values near 1e38 / N."""
    sums = [t.sum() for t in tensors if t is not None]
    return bool(torch.isfinite(torch.stack(sums)).all()) if sums else True


@torch.no_grad()
def adam_rows(param: Tensor, grad: Tensor, exp_avg: Tensor, exp_avg_sq: Tensor, last_step: Tensor | None,
              rows: Tensor, *, step: int, lr: float, beta1: float, beta2: float, eps: float,
              backend: str | None = None) -> None:
    """Adam update, in place, of ``param[rows]`` and its moments (``last_step[rows]`` set to ``step`` when given).

    Args:
        param, grad, exp_avg, exp_avg_sq: [N,...] contiguous, same shape.
        last_step: [N] long, the step each row was last updated (lazy decay), or None.
        rows: [R] long, distinct row indices.
        step: this update's step number (>= 1), for the bias correction.
    """
    for name, t in (("gradient", grad), ("first moment", exp_avg), ("second moment", exp_avg_sq)):
        if t.shape != param.shape:  # the kernel reads raw pointers: never hand it a mismatched state
            raise ValueError(f"Adam's {name} has shape {tuple(t.shape)}, its parameter {tuple(param.shape)} (a "
                             "checkpoint of another model?)")
    width = param[0].numel() if param.shape[0] else 0
    if last_step is not None and (last_step.dtype != torch.long or last_step.shape != param.shape[:1]):
        raise ValueError(f"last_step must be a long tensor of shape [{param.shape[0]}], not {last_step.dtype} "
                         f"{tuple(last_step.shape)}")
    tensors = (param, grad, exp_avg, exp_avg_sq)
    if native.use_for(*tensors, backend=backend, dtypes=(torch.float32,), strict=False) and all(
            t.is_contiguous() for t in tensors):
        r = rows.to(torch.long).contiguous()
        native.library().us_adam_rows_f32(
            param.shape[0], r.numel(), width, r.data_ptr(), param.data_ptr(), grad.data_ptr(), exp_avg.data_ptr(),
            exp_avg_sq.data_ptr(), None if last_step is None else last_step.data_ptr(), step, lr, beta1, beta2, eps,
            native.kernel_threads())
        return
    p2, g2, m2, v2 = (t.view(t.shape[0], -1) for t in tensors)
    g = g2.index_select(0, rows)
    m = m2.index_select(0, rows)
    v = v2.index_select(0, rows)
    if last_step is not None:
        skipped = (step - 1 - last_step.index_select(0, rows)).clamp_min(0).to(torch.float64)[:, None]
        m.mul_(torch.pow(torch.tensor(beta1, dtype=torch.float64, device=m.device), skipped).to(m.dtype))
        v.mul_(torch.pow(torch.tensor(beta2, dtype=torch.float64, device=v.device), skipped).to(v.dtype))
        last_step.index_fill_(0, rows, step)
    m.lerp_(g, 1.0 - beta1)
    v.mul_(beta2).addcmul_(g, g, value=1.0 - beta2)
    step_size = lr / (1.0 - beta1**step)
    denom = v.sqrt().div_(math.sqrt(1.0 - beta2**step)).add_(eps)
    p = p2.index_select(0, rows).addcdiv_(m, denom, value=-step_size)
    p2.index_copy_(0, rows, p)
    m2.index_copy_(0, rows, m)
    v2.index_copy_(0, rows, v)
