"""Training renders over a random colour (``TrainConfig.random_background``): a new colour each step from its own
stream, the scene's background everywhere else, nothing random for transparent training images, exact resume."""

from __future__ import annotations

from dataclasses import replace

import torch

from tests.e2e.test_train_resume import assert_resume_is_exact, toy_config, toy_scene
from uncertsplat.config import TrainConfig
from uncertsplat.train.trainer import Trainer


def _trainer(transparent: bool = False, **extra) -> Trainer:
    scene, tr, te = toy_scene()
    if transparent:
        scene = replace(scene, source=dict(scene.source, transparent=True))
    return Trainer(scene, toy_config(**extra), tr, te)


def _backgrounds(t: Trainer, steps: int) -> list:
    """The ``background`` argument of every render during ``steps`` training steps and one evaluation."""
    seen: list = []
    render = t.render

    def wrapped(g, cams, background=None):
        seen.append(None if background is None else background.detach().clone())
        return render(g, cams, background=background)

    t.render = wrapped
    for _ in range(steps):
        t.train_step()
    seen.append("evaluate")
    t.evaluate(max_views=1)
    return seen


class TestRandomBackground:
    def test_each_step_renders_over_a_new_colour_and_evaluation_over_the_scenes(self):
        t = _trainer(iterations=10, random_background=True)
        assert t.random_background
        seen = _backgrounds(t, 3)
        cut = seen.index("evaluate")
        colours = seen[:cut]
        assert len(colours) == 3 and all(c is not None and c.shape == (3,) for c in colours)
        assert all(bool(((c >= 0) & (c <= 1)).all()) for c in colours)
        assert not torch.equal(colours[0], colours[1]) and not torch.equal(colours[1], colours[2])
        assert seen[cut + 1:] and all(b is None for b in seen[cut + 1:])  # the scene's background

    def test_off_by_default(self):
        assert TrainConfig().random_background is False
        t = _trainer(iterations=10)
        assert not t.random_background
        assert all(b is None or b == "evaluate" for b in _backgrounds(t, 2))

    def test_transparent_images_keep_their_background(self):
        """Their background is data: a random colour behind them would be fitted as if the photos showed it."""
        t = _trainer(transparent=True, iterations=10, random_background=True)
        assert not t.random_background
        assert all(b is None or b == "evaluate" for b in _backgrounds(t, 2))

    def test_changes_training_and_resume_is_exact(self):
        full = assert_resume_is_exact(toy_config(random_background=True), until=13)
        scene, tr, te = toy_scene()
        plain = Trainer(scene, toy_config(), tr, te)
        plain.fit()
        assert not torch.equal(full.model.params["means"], plain.model.params["means"])
