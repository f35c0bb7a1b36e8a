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
