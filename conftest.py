"""Root pytest configuration: ``--device`` selects where tensor tests run (default cpu)."""

from __future__ import annotations

import os

import pytest

os.environ.setdefault("UNCERTSPLAT_NO_PROGRESS", "1")
# OpenMP threads that spin while waiting make torch 10-20x slower when another process shares the
# 2 cores (seen with parallel test workers); passive waiting costs nothing on an idle machine.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


def pytest_addoption(parser):
    parser.addoption("--device", action="store", default="cpu", help="torch device for tests: cpu or cuda")


@pytest.fixture(scope="session")
def device(request):
    import torch

    name = request.config.getoption("--device")
    if name.startswith("cuda") and not torch.cuda.is_available():
        pytest.skip("--device cuda given but CUDA is not available")
    return torch.device(name)
