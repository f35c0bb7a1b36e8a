"""Root pytest configuration: ``--device`` selects where tensor tests run (default cpu)."""

from __future__ import annotations

import os

import pytest

os.environ.setdefault("UNCERTSPLAT_NO_PROGRESS", "1")


def pytest_addoption(parser):
    parser.addoption("--device", action="store", default="cpu", help="torch device for tests: cpu or cuda")


@pytest.fixture(scope="session")
def device(request):
    import torch

    name = request.config.getoption("--device")
    if name.startswith("cuda") and not torch.cuda.is_available():
        pytest.skip("--device cuda given but CUDA is not available")
    return torch.device(name)
