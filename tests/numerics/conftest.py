"""Every rasterizer test in this folder runs once per compositor: the native CPU kernel and PyTorch's."""

from __future__ import annotations

import pytest


@pytest.fixture(autouse=True, params=["native", "torch"])
def rasterizer(request, monkeypatch):
    """Selects the compositor through ``UNCERTSPLAT_RASTERIZER`` for the duration of one test."""
    if request.param == "native":
        device = request.getfixturevalue("device") if "device" in request.fixturenames else None
        if device is not None and device.type != "cpu":
            pytest.skip("the native compositor is CPU-only")
        from uncertsplat import native

        if native.library() is None:
            pytest.skip(f"native compositor unavailable: {native.unavailable_reason()}")
    monkeypatch.setenv("UNCERTSPLAT_RASTERIZER", request.param)
    return request.param
