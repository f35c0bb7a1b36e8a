"""Device selection (``uncertsplat.device.resolve_device``): names and torch.devices alike."""

import pytest
import torch

from uncertsplat.device import resolve_device
from uncertsplat.errors import UserError


def test_cuda_without_a_cuda_device_is_a_user_error_as_a_name_and_as_a_torch_device(monkeypatch):
    """``torch.device("cuda")`` was returned as given, so ``Predictor.load(run, torch.device("cuda"))`` on a CPU-only
    torch failed later with a bare AssertionError; the message fits the command line and Python both."""
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    for asked in ("cuda", "cuda:1", torch.device("cuda"), torch.device("cuda", 0)):
        with pytest.raises(UserError, match="no CUDA device is available") as err:
            resolve_device(asked)
        assert "--device cpu" in str(err.value) and 'device="cpu"' in str(err.value)
    assert resolve_device(torch.device("cpu")) == torch.device("cpu")
    assert resolve_device("auto") == torch.device("cpu") and resolve_device("CPU") == torch.device("cpu")
    with pytest.raises(UserError, match="unknown device 'tpu'"):
        resolve_device("tpu")
    with pytest.raises(UserError, match="must be a name or a torch.device"):
        resolve_device(0)


def test_device_names_torch_takes_and_misspelt_ones(monkeypatch):
    """``cpu:0`` (torch's name of the CPU device) was an unknown device; a misspelt index (``cuda:x``) went to
    ``torch.device`` and ended in its RuntimeError traceback: one message now."""
    assert resolve_device("cpu:0") == torch.device("cpu") and resolve_device("cpu:0").index is None
    assert str(resolve_device(torch.device("cpu", 0))) == "cpu"  # what evaluate records and compares
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert resolve_device("cuda:1") == torch.device("cuda", 1)
    for bad in ("cuda:x", "cuda1", "cpu:", "cpux"):
        with pytest.raises(UserError, match=f"unknown device '{bad}'") as err:
            resolve_device(bad)
        assert "cuda:N" in err.value.hint
