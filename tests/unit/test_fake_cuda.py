"""The CUDA emulator (tests/fake_cuda.py, ``--device fake-cuda``): it finds each device mix real CUDA refuses,
passes what real CUDA accepts, and puts torch back as it was."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from torch.overrides import _get_current_function_mode_stack

from tests.fake_cuda import FAKE_CUDA, fake_cuda, is_fake_cuda
from uncertsplat.device import resolve_device


@pytest.fixture
def emulated():
    """A fresh emulator inside the test, even when the session runs under ``--device fake-cuda``: the planted
    defects are recorded in this one, not in the session's (whose findings would fail the run)."""
    with fake_cuda() as fake:
        yield fake


def _kinds(fake) -> list[str]:
    return [finding.kind for finding in fake.findings.values()]


def test_clean_code_passes_and_tensors_report_the_cuda_device(emulated):
    """0-dim CPU tensors are scalars to CUDA ops (as on real CUDA); copies across, a CPU index into a CUDA tensor
    and a CUDA generator for a CUDA draw are fine too."""
    dev = resolve_device("cuda")
    assert resolve_device("auto") == dev and resolve_device("cpu") == torch.device("cpu")
    gen = torch.Generator(device=dev).manual_seed(0)
    x = torch.randn(4, 3, device=dev, generator=gen, requires_grad=True)
    assert x.device == FAKE_CUDA and x.is_cuda and not x.is_cpu and x.get_device() == 0
    y = (x * torch.tensor(2.0)).sum(0) + torch.ones(3).to(dev)
    assert y.device == FAKE_CUDA and y.cpu().device == torch.device("cpu") and y.device == FAKE_CUDA
    picked = x[torch.tensor([0, 2])]  # a CPU index into a CUDA tensor
    assert picked.device == FAKE_CUDA
    x.detach()[torch.tensor([1])] = torch.zeros(1, 3, device=dev)
    torch.zeros(3, device=dev).copy_(torch.arange(3.0))
    (grad,) = torch.autograd.grad(y.sum(), x)
    assert grad.device == FAKE_CUDA
    assert torch.nn.Parameter(torch.zeros(2, device=dev)).device == FAKE_CUDA
    assert y.detach().cpu().numpy().shape == (3,)
    assert emulated.findings == {}


def test_cpu_and_cuda_tensors_in_one_op_are_found(emulated):
    cuda, cpu = torch.ones(3, device="cuda"), torch.ones(3)
    for _ in range(2):
        assert (cuda + cpu).device == FAKE_CUDA  # the CPU computes it; a GPU would raise
    torch.stack([cuda, cpu])
    assert _kinds(emulated) == ["CUDA and CPU tensors in one op"] * 2
    add, stack = emulated.findings.values()
    # one finding per kind and project line, counted; it names the line of this file that mixed
    assert (add.op, stack.op) == ("add", "stack") and add.where[-1].startswith("tests/unit/test_fake_cuda.py:")
    assert add.test == "" and " x2" in emulated.report().splitlines()[0]


def test_a_cpu_generator_drawing_for_a_cuda_tensor_is_found(emulated):
    torch.randn(3, device="cuda", generator=torch.Generator().manual_seed(0))
    torch.ones(3, device="cuda").normal_(generator=torch.Generator().manual_seed(0))
    torch.rand(3, generator=torch.Generator(device="cuda"))
    assert _kinds(emulated) == ["CPU generator drawing for a CUDA tensor"] * 2 + [
        "CUDA generator drawing for a CPU tensor"]


def test_host_access_to_a_cuda_tensor_is_found(emulated):
    x = torch.ones(3, device="cuda")
    x.numpy()
    np.asarray(x)
    x.data_ptr()
    assert _kinds(emulated) == ["numpy() of a CUDA tensor", "np.asarray of a CUDA tensor",
                                "data_ptr() of a CUDA tensor (a CPU kernel given device memory?)"]


def test_indexing_across_devices_is_found(emulated):
    cpu, cuda = torch.zeros(4), torch.zeros(4, device="cuda")
    cpu[torch.tensor([0, 1], device="cuda")]
    cuda[torch.tensor([0, 1])] = torch.ones(2)
    assert _kinds(emulated) == ["CPU tensor indexed by a CUDA index",
                                "advanced-index assignment of a value on the other device"]


def test_loading_to_cuda_and_moving_keep_the_device():
    with fake_cuda() as fake:
        x = torch.arange(3.0)
        moved = x.to("cuda")
        assert moved.device == FAKE_CUDA and x.device == torch.device("cpu")  # .to() copies, the CPU one stays
        assert x.to(moved).device == FAKE_CUDA and moved.to(torch.float64).device == FAKE_CUDA
        assert x.cuda().device == FAKE_CUDA and moved.to(x).device == torch.device("cpu")
    assert fake.findings == {}


def test_leaving_puts_torch_back(tmp_path):
    """As it was before, also when the session itself runs under ``--device fake-cuda``."""
    before = (torch.Generator, torch.load, torch.autograd.grad, torch.nn.Parameter.__dict__["__new__"],
              torch.cuda.is_available(), len(_get_current_function_mode_stack()))
    with fake_cuda():
        x = torch.ones(2, device="cuda")
        torch.save({"x": x}, tmp_path / "x.pt")
        assert is_fake_cuda(torch.load(tmp_path / "x.pt", map_location="cuda")["x"])
        assert torch.cuda.is_available()
    after = (torch.Generator, torch.load, torch.autograd.grad, torch.nn.Parameter.__dict__["__new__"],
             torch.cuda.is_available(), len(_get_current_function_mode_stack()))
    assert after == before


def test_a_session_with_a_finding_fails_and_lists_it(tmp_path):
    """``--device fake-cuda``: tests that pass but mix devices still fail the run, with the list at the end."""
    (tmp_path / "test_planted.py").write_text(
        "import torch\n\n\n"
        "def test_mixes(device):\n"
        "    assert (torch.ones(2, device=device) + torch.ones(2)).device == device\n")
    root = Path(__file__).resolve().parents[2]
    run = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "conftest", "-p", "no:cacheprovider",
                          "-p", "no:xdist", "--device", "fake-cuda", "--rootdir", str(tmp_path), str(tmp_path)],
                         cwd=root, capture_output=True, text=True, timeout=300)
    assert run.returncode == 1, run.stdout + run.stderr
    assert "1 passed" in run.stdout and "fake CUDA: code that would fail on a real GPU" in run.stdout
    assert "[CUDA and CPU tensors in one op] add" in run.stdout and "test_planted.py::test_mixes" in run.stdout
