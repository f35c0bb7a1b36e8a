"""A CUDA device emulated on the CPU, to check that tensor code keeps to the device of its inputs.

uncertsplat runs on CPU and CUDA with the device taken from the inputs, but most development machines (and the
CI) have no GPU, and a CPU tensor that slips into a CUDA computation only fails on a GPU. ``fake_cuda()`` makes a
CPU-only torch pretend to have one CUDA device: a tensor put "on CUDA" (``device="cuda"``, ``.to("cuda")``,
``.cuda()``, ``torch.load(map_location="cuda")``) stays a CPU tensor but is tagged, reports ``device == cuda:0``
and ``is_cuda``, and its results are tagged in turn. A ``TorchFunctionMode`` sees every torch call and records what
real CUDA would refuse:

- an op mixing a CUDA tensor with a CPU tensor of one dimension or more (a 0-dim CPU tensor is allowed, as a
  scalar, as on real CUDA; so are ``copy_``, ``.to``, and a CPU index into a CUDA tensor);
- a CPU tensor indexed by a CUDA index, an advanced-index assignment of a value on the other device;
- a random draw whose generator is on the other device than the tensor drawn
  (``torch.Generator(device=...)`` remembers the device it was made for);
- ``.numpy()``, ``np.asarray`` or ``data_ptr()`` of a CUDA tensor (host access, or a CPU kernel given device
  memory).

``torch.cuda.is_available()`` is True inside, and the memory and synchronisation calls the code uses are stubs, so
``resolve_device("auto"|"cuda")`` gives the fake device and the CUDA branches of the code run (with PyTorch
kernels: the native ones are CPU kernels).

What it cannot check: numerics (every kernel is the CPU one: no TF32, no atomics, no different reduction order),
nondeterminism, memory use and out-of-memory (``torch.cuda.memory_allocated`` and its kin answer 0, so a test of
CUDA peak memory passes without measuring anything), CUDA kernels and streams, CUDA's generator streams (a CUDA
draw here gives the CPU draw's numbers), and ops run in other threads: a ``TorchFunctionMode`` is per thread, so
work in a thread pool or a background thread is neither checked nor tagged. The autograd engine runs backward
passes without the mode too, so the ``backward`` of a custom ``torch.autograd.Function`` is not checked (the
gradients it leaves in ``.grad`` or returns from ``torch.autograd.grad`` are tagged after the fact). Tensors read
back with ``torch.load`` without a ``map_location`` come back untagged (CPU) even when they were saved from CUDA,
and ``isinstance(g, torch.Generator)`` is False inside for a generator made before (``torch.Generator`` is
replaced).

Each finding is recorded once per kind and innermost project line; ``FakeCuda.report()`` lists them. Under pytest,
``--device fake-cuda`` (conftest.py) installs this for the session and fails the run on any finding.
"""

from __future__ import annotations

import contextlib
import dataclasses
import sys
import traceback
from collections.abc import Iterator
from pathlib import Path

import pytest
import torch
import torch.utils._pytree as pytree
from torch.overrides import TorchFunctionMode

FAKE_CUDA = torch.device("cuda", 0)


class _NotCapturing:
    """The stream ``torch.accelerator.current_stream`` answers: a CUDA build of torch (not a CPU one) asks it whether a
    CUDA graph is being captured before an optimiser's step, which reached for a driver the emulator has not."""

    def is_capturing(self) -> bool:
        return False

FAKE_FREE_BYTES = 80 * 2**30
"""What ``torch.cuda.mem_get_info`` answers (free and total): a device with room for any test's model."""
_CPU = torch.device("cpu")
_TAG = "_fake_cuda"  # the attribute on a tensor that says it is "on CUDA"
_ROOT = Path(__file__).resolve().parents[1]
_THIS = str(Path(__file__).resolve())
_ACTIVE: list[FakeCuda] = []  # the emulators entered and not yet left, innermost last

# ops that move a tensor between devices, or accept a tensor of the other device by design (a cross-device copy,
# a CPU index into a CUDA tensor): never a mix
_MOVES = frozenset({"to", "cuda", "cpu", "type_as", "new_tensor", "copy_"})
_CROSS_DEVICE_OK = frozenset({"__getitem__", "__setitem__", "index_put_", "index_put"})
# torch code that makes tensors in C++, out of the mode's sight, and mixes them with the caller's: gradcheck's
# undefined gradients (UndefinedGrad) come out as CPU tensors, a mix of the emulator's making, not the code's
_BLIND_SPOTS = ("torch/autograd/gradcheck.py",)
_HOST_ACCESS = {"numpy": "numpy() of a CUDA tensor", "__array__": "np.asarray of a CUDA tensor",
                "data_ptr": "data_ptr() of a CUDA tensor (a CPU kernel given device memory?)"}
_PROPERTIES = {
    torch._C.TensorBase.__dict__["device"]: lambda t: FAKE_CUDA if is_fake_cuda(t) else _CPU,
    torch._C.TensorBase.__dict__["is_cuda"]: lambda t: is_fake_cuda(t),
    torch._C.TensorBase.__dict__["is_cpu"]: lambda t: not is_fake_cuda(t),
}


def is_fake_cuda(x: object) -> bool:
    """Whether ``x`` is a tensor on the emulated CUDA device."""
    return isinstance(x, torch.Tensor) and getattr(x, _TAG, False)


def _tag(t: torch.Tensor, on_cuda: bool) -> torch.Tensor:
    setattr(t, _TAG, on_cuda)
    return t


def _is_cuda_device(d: object) -> bool:
    # an int device is a CUDA ordinal, as in torch's own ``.to(0)``
    if isinstance(d, int) and not isinstance(d, bool):
        return True
    return isinstance(d, (str, torch.device)) and torch.device(d).type == "cuda"


@dataclasses.dataclass(frozen=True)
class Finding:
    """One place where real CUDA would fail: the kind of mix, the torch op, the project frames (innermost last)
    and the test that first ran into it."""

    kind: str
    op: str
    where: tuple[str, ...]
    test: str = ""

    def __str__(self) -> str:
        where = " <- ".join(reversed(self.where)) or "(no project frame: torch or a third-party library)"
        return f"[{self.kind}] {self.op} at {where}" + (f" (first in {self.test})" if self.test else "")


class FakeCudaGenerator(torch._C.Generator):
    """``torch.Generator`` inside ``fake_cuda()``: a CPU generator that remembers the device it was made for, so
    that a draw with it for a tensor of the other device is found."""

    def __new__(cls, device: str | torch.device = "cpu"):
        return super().__new__(cls)

    def __init__(self, device: str | torch.device = "cpu"):
        device = torch.device(device)
        self._device = FAKE_CUDA if device.type == "cuda" else _CPU

    @property
    def device(self) -> torch.device:
        """The device it was made for (the real generator is always a CPU one)."""
        return self._device


class FakeCuda:
    """The findings of one ``fake_cuda()``; ``test`` names what runs now (the pytest plugin sets it)."""

    def __init__(self):
        self.findings: dict[tuple[str, str], Finding] = {}
        self.counts: dict[tuple[str, str], int] = {}
        self.test = ""

    def record(self, kind: str, func: object) -> None:
        """Record a finding at the calling project line (once per kind and line, counted)."""
        if _ACTIVE[-1] is not self:
            # an emulator inside another (a test of this tool under --device fake-cuda): the outer one sees the
            # inner one's calls again, and they are the inner one's to judge
            return
        where = _project_frames()
        key = (kind, where[-1] if where else getattr(func, "__name__", str(func)))
        self.counts[key] = self.counts.get(key, 0) + 1
        if key not in self.findings:
            self.findings[key] = Finding(kind, getattr(func, "__name__", str(func)), where, self.test)

    def report(self) -> str:
        """The findings, one a line, with how often each was met; empty when there are none."""
        return "\n".join(f"{finding} x{self.counts[key]}" for key, finding in self.findings.items())


def _called_from(suffixes: tuple[str, ...]) -> bool:
    """Whether the current torch call comes from a file ending in one of ``suffixes`` (before any project
    frame)."""
    frame = sys._getframe(1)
    while frame is not None:
        path = frame.f_code.co_filename
        if path.endswith(suffixes):
            return True
        if path != _THIS and "site-packages" not in path and path.startswith(str(_ROOT)):
            return False
        frame = frame.f_back
    return False


def _project_frames(depth: int = 4) -> tuple[str, ...]:
    # the innermost project lines of the current stack (uncertsplat/ and tests/, not this file nor a virtualenv):
    # the op that mixes is torch's, the line to fix is the project's
    frames = []
    for frame in traceback.extract_stack():
        path = frame.filename
        if path == _THIS or "site-packages" in path or not path.startswith(str(_ROOT)):
            continue
        frames.append(f"{Path(path).relative_to(_ROOT)}:{frame.lineno}")
    return tuple(frames[-depth:])


class _Mode(TorchFunctionMode):
    """Sees every torch call: answers the device properties of tagged tensors, records device mixes, tags
    results. Inside ``__torch_function__`` the mode is off, so the calls made here are plain torch."""

    def __init__(self, state: FakeCuda):
        super().__init__()
        self.state = state

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = dict(kwargs or {})
        name = getattr(func, "__name__", "")
        if name == "__get__":
            prop = _PROPERTIES.get(getattr(func, "__self__", None))
            if prop is not None:
                return prop(args[0])
        if name == "get_device" and is_fake_cuda(args[0]):
            return FAKE_CUDA.index
        if name in _HOST_ACCESS and is_fake_cuda(args[0]):
            self.state.record(_HOST_ACCESS[name], func)

        # where the result goes: True = fake CUDA, False = CPU, None = where the inputs are
        target = None
        if kwargs.get("device") is not None:
            target = _is_cuda_device(kwargs["device"])
            kwargs["device"] = _CPU
        if name == "to":
            args, target = _to_args(args, target)
        if name == "cuda":
            return args[0] if is_fake_cuda(args[0]) else _tag(args[0].clone(), True)
        if name == "cpu":
            return _tag(args[0].clone(), False) if is_fake_cuda(args[0]) else args[0]

        tensors = [a for a in pytree.tree_leaves((args, kwargs)) if isinstance(a, torch.Tensor)]
        on_cuda = any(is_fake_cuda(t) for t in tensors)
        self._check(func, name, args, kwargs, tensors, target if target is not None else on_cuda)

        result = func(*args, **kwargs)
        if target is None:
            target = on_cuda
        if name == "to" and result is args[0] and target != is_fake_cuda(result):
            result = result.clone()  # .to() of a tensor already on the CPU returns it: the copy gets the tag
        inputs = {id(t) for t in tensors}

        def tag_new(x):
            # results that are inputs (in-place ops, a no-op .contiguous()) keep their own tag
            if isinstance(x, torch.Tensor) and id(x) not in inputs:
                _tag(x, target)
            return x

        pytree.tree_map(tag_new, result)
        return result

    def _check(self, func, name, args, kwargs, tensors, draws_on_cuda):
        if name not in _MOVES and name not in _CROSS_DEVICE_OK and any(is_fake_cuda(t) for t in tensors):
            # a 0-dim CPU tensor is a scalar to CUDA ops; anything larger must be on the device (the stack is
            # walked only then: it costs more than the op)
            if any(not is_fake_cuda(t) and t.dim() > 0 for t in tensors) and not _called_from(_BLIND_SPOTS):
                self.state.record("CUDA and CPU tensors in one op", func)
        for gen in pytree.tree_leaves((args, kwargs)):
            if isinstance(gen, torch._C.Generator):
                on = gen.device.type == "cuda"
                if on != draws_on_cuda:
                    self.state.record(f"{'CUDA' if on else 'CPU'} generator drawing for a "
                                      f"{'CUDA' if draws_on_cuda else 'CPU'} tensor", func)
        if name in ("__getitem__", "__setitem__") and not is_fake_cuda(args[0]):
            if any(is_fake_cuda(i) and i.dim() > 0 for i in pytree.tree_leaves(args[1])):
                self.state.record("CPU tensor indexed by a CUDA index", func)
        if name == "__setitem__" and isinstance(args[2], torch.Tensor) and args[2].dim() > 0:
            advanced = any(isinstance(i, torch.Tensor) and i.dim() > 0 for i in pytree.tree_leaves(args[1]))
            if advanced and is_fake_cuda(args[2]) != is_fake_cuda(args[0]):
                self.state.record("advanced-index assignment of a value on the other device", func)


def _to_args(args: tuple, target: bool | None) -> tuple[tuple, bool | None]:
    """``Tensor.to``'s positional device (or tensor) replaced by the CPU, and where it asked to go."""
    rest = []
    for a in args[1:]:
        if isinstance(a, torch.Tensor):
            target = is_fake_cuda(a)  # every tensor is a CPU one: only the tag tells
        elif isinstance(a, (str, torch.device)) or (isinstance(a, int) and not isinstance(a, bool)):
            target = _is_cuda_device(a)
            a = _CPU
        rest.append(a)
    return (args[0], *rest), target


def _fake_parameter_new(orig_new):
    def new(cls, data=None, requires_grad=True):
        # nn.Parameter(t) is a new tensor made in C++, out of the mode's sight: it takes t's tag
        param = orig_new(cls, data, requires_grad)
        return _tag(param, True) if is_fake_cuda(data) else param

    return new


def _fake_grad(orig_grad):
    def grad(outputs, inputs, *args, **kwargs):
        # the autograd engine makes the gradients out of the mode's sight: each is on its input's device
        grads = orig_grad(outputs, inputs, *args, **kwargs)
        ins = [inputs] if isinstance(inputs, torch.Tensor) else list(inputs)
        for g, x in zip(grads, ins, strict=True):
            if g is not None and is_fake_cuda(x):
                _tag(g, True)
        return grads

    return grad


def _fake_load(orig_load):
    def load(f, map_location=None, *args, **kwargs):
        if not isinstance(map_location, (str, torch.device, int)) or not _is_cuda_device(map_location):
            return orig_load(f, map_location, *args, **kwargs)
        loaded = orig_load(f, _CPU, *args, **kwargs)
        pytree.tree_map(lambda x: _tag(x, True) if isinstance(x, torch.Tensor) else x, loaded)
        return loaded

    return load


@contextlib.contextmanager
def fake_cuda() -> Iterator[FakeCuda]:
    """Emulate one CUDA device on the CPU in this thread until the block ends; yields the ``FakeCuda`` that
    collects the findings. Everything it patches in torch is put back on exit."""
    state = FakeCuda()
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(torch, "Generator", FakeCudaGenerator)
        mp.setattr(torch.nn.Parameter, "__new__", _fake_parameter_new(torch.nn.Parameter.__new__))
        mp.setattr(torch.autograd, "grad", _fake_grad(torch.autograd.grad))
        mp.setattr(torch, "load", _fake_load(torch.load))
        mp.setattr(torch.cuda, "is_available", lambda: True)
        mp.setattr(torch.cuda, "device_count", lambda: 1)
        mp.setattr(torch.cuda, "current_device", lambda: FAKE_CUDA.index)
        mp.setattr(torch.cuda, "get_device_name", lambda device=None: "fake CUDA (tests/fake_cuda.py)")
        for stub in ("synchronize", "reset_peak_memory_stats", "empty_cache", "manual_seed", "manual_seed_all"):
            mp.setattr(torch.cuda, stub, lambda *args, **kwargs: None)
        for zero in ("memory_allocated", "max_memory_allocated", "memory_reserved", "max_memory_reserved"):
            mp.setattr(torch.cuda, zero, lambda device=None: 0)
        mp.setattr(torch.cuda, "mem_get_info", lambda device=None: (FAKE_FREE_BYTES, FAKE_FREE_BYTES))
        if hasattr(torch, "accelerator"):  # a CUDA build of torch asks its stream in Optimizer.step: none is capturing
            mp.setattr(torch.accelerator, "current_stream", lambda device=None: _NotCapturing())
        _ACTIVE.append(state)
        try:
            with _Mode(state):
                yield state
        finally:
            _ACTIVE.remove(state)
