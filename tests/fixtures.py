"""Shared test fixtures: the tiny synthetic scene, generated once per test session.

Use it from any test module with::

    from tests.fixtures import tiny_scene_path  # noqa: F401

    def test_something(tiny_scene_path):
        scene = load_scene(tiny_scene_path, SceneConfig())

Tests must treat the scene folder as read-only (it is shared by every test of the session); copy it
(``shutil.copytree``) before modifying anything.
"""

from __future__ import annotations

from pathlib import Path

import pytest

_CACHE: dict[tuple[Path, int], Path] = {}


def tiny_sweep_spec(name: str, axes: str) -> str:
    """A sweep spec of a few seconds a point on the tiny scene: the default point and the ``[axes]`` lines given."""
    return f"""
name = "{name}"
train_preset = "tiny"
train = {{ eval_every = 1000, checkpoint_every = 1000, log_every = 10 }}
evaluate = {{ max_views = 1 }}
[default]
method = "variational"
iterations = 16
num_entries = 4
num_samples = 3
downscale = 4.0
ensemble_size = 2
[axes]
{axes}
"""


def tiny_scene(tmp_root: Path, seed: int = 0) -> Path:
    """Generate the ``tiny`` synthetic scene under ``tmp_root`` (once per process and seed) and return it."""
    from uncertsplat.config import SynthConfig
    from uncertsplat.data.synthetic import generate_scene, is_synthetic_scene

    key = (Path(tmp_root).resolve(), seed)
    if key in _CACHE and is_synthetic_scene(_CACHE[key]):
        return _CACHE[key]
    out = Path(tmp_root) / f"tiny_seed{seed}"
    if not is_synthetic_scene(out):
        generate_scene(out, SynthConfig(preset="tiny", seed=seed), overwrite=True)
    _CACHE[key] = out
    return out


@pytest.fixture(scope="session")
def tiny_scene_path(tmp_path_factory) -> Path:
    """Path of the tiny synthetic scene (24 views, 128x96, GT depth, COLMAP model), shared read-only."""
    return tiny_scene(tmp_path_factory.getbasetemp() / "shared_scenes")


def default_sigint() -> None:
    """``preexec_fn`` for a subprocess a test will Ctrl-C: SIGINT back to its default action.

    A shell starts background jobs (``make test &``, ``nohup``) with SIGINT ignored, their children inherit that,
    and Python then installs no KeyboardInterrupt handler, so the child would never see the test's Ctrl-C."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_DFL)


def fail_png_write(monkeypatch, nth: int) -> list:
    """Make ``io.images.write_png`` raise ``OSError("disk full")`` at its ``nth`` call (the others write); returns
    the list of the paths it was called with."""
    import uncertsplat.io.images as images

    real, calls = images.write_png, []

    def failing(path, pixels):
        calls.append(path)
        if len(calls) == nth:
            raise OSError("disk full")
        return real(path, pixels)

    monkeypatch.setattr(images, "write_png", failing)
    return calls
