"""``train --view``: the model in the browser while it trains.

The viewer (``view.server.Viewer``) runs without its render thread: the training thread renders its frames
between two steps (``Trainer.on_step``), so a frame never shows a half-updated model and nothing is
locked. It renders only while the viewer's share of the wall time since training started stays under
``budget`` (5 % by default): with no browser connected a step costs one list lookup; with one, training
slows by about that share (measured in BENCHMARKS.md, "The viewer"). A view that stands still is redrawn
when the model has trained on for ``refresh`` seconds. Every mode of ``uncertsplat view`` works, on the
model as it is at that step (the std modes sample its current posterior).
"""

from __future__ import annotations

import time
from pathlib import Path

from uncertsplat.config import ViewConfig
from uncertsplat.console import console

DEFAULT_BUDGET = 0.05
"""Largest share of the wall time the live viewer may spend rendering."""


class LiveView:
    """Shows the model of a ``Trainer`` in the browser while it trains (see the module docstring).

    Args:
        cfg: the viewer settings (host, port, resolution, samples).
        budget: largest share of the wall time spent rendering for the viewer.
        refresh: seconds after which a still view is redrawn with the model trained since.
    """

    def __init__(self, cfg: ViewConfig, *, budget: float = DEFAULT_BUDGET, refresh: float = 2.0):
        self.cfg = cfg
        self.budget = float(budget)
        self.refresh = float(refresh)
        self.viewer = None
        self.trainer = None
        self.spent = 0.0
        self.frames = 0
        self._t0 = None
        self._renderer_step = -1
        self._shown_at = 0.0

    def attach(self, trainer) -> None:
        """Show ``trainer``'s model from now on (the server starts with the first trainer; an ensemble's later
        members take its place)."""
        from uncertsplat.view.server import Viewer, check_port, require_viser, viewer_url

        self.trainer = trainer
        trainer.on_step = self.step
        self._renderer_step = -1
        if self.viewer is None:
            require_viser()
            check_port(self.cfg.host, self.cfg.port, option="--view-port")
            self.viewer = Viewer(self._renderer(trainer), trainer.scene, self.cfg)
            self.viewer.start(worker=False)
            self._status = self.viewer.server.gui.add_markdown("training starts")
            port = self.viewer.port
            console.print(f"watching the training at [bold]{viewer_url(self.cfg.host, port)}[/] (from another "
                          f"machine: ssh -L {port}:localhost:{port} THIS_HOST); at most {self.budget:.0%} of the "
                          "time goes to the viewer")
        if self._t0 is None:  # the budget runs over the whole command (an ensemble's members one after another)
            self._t0 = time.perf_counter()

    def _renderer(self, trainer):
        from uncertsplat.baselines.runs import LoadedRun
        from uncertsplat.view.frames import FrameRenderer

        run_dir = trainer.run_dir if trainer.run_dir is not None else Path(".")
        loaded = LoadedRun(trainer.model, trainer.cfg, None, trainer.extent, trainer.step, trainer.sh_degree,
                           run_dir, run_dir, near=trainer.near)
        score_cams = trainer.train_cams[list(range(0, len(trainer.train_cams), max(1, len(trainer.train_cams) // 8)))]
        return FrameRenderer(loaded, trainer.scene.scene_scale, trainer.device, score_cameras=score_cams,
                             free_space_cameras=trainer.train_cams, seed=self.cfg.seed)

    def step(self, trainer) -> None:
        """``Trainer.on_step``: serve the connected views while the budget allows."""
        viewer = self.viewer
        if viewer is None or not viewer._views:
            return
        now = time.perf_counter()
        if self.spent > self.budget * (now - self._t0):
            return
        if trainer.step != self._renderer_step:
            if now - self._shown_at > self.refresh:  # redraw still views with the model as it is now
                with viewer._lock:
                    for v in viewer._views.values():
                        v.version += 1
            viewer.renderer = self._renderer(trainer)
            try:
                viewer.offer_modes()  # (the prune preview once Gaussians carry a posterior)
            except Exception as err:  # the panel keeps its modes: nothing of the viewer's may stop the training
                viewer.last_error = f"{type(err).__name__}: {err}"
            self._renderer_step = trainer.step
        with viewer._lock:
            views = list(viewer._views.values())
        pushed = viewer.frames_pushed
        for v in views:  # (a failed frame is said in the panel: the training goes on)
            viewer.serve_or_report(v)
        if viewer.frames_pushed > pushed:
            self._shown_at = time.perf_counter()
            self.frames += viewer.frames_pushed - pushed
            self._status.content = (f"training: step {trainer.step:,} of {trainer.cfg.iterations:,}, "
                                    f"{len(trainer.model):,} Gaussians; viewer {self.share:.1%} of the time")
        self.spent += time.perf_counter() - now

    @property
    def share(self) -> float:
        """The share of the wall time since ``attach`` spent rendering for the viewer."""
        if self._t0 is None:
            return 0.0
        return self.spent / max(time.perf_counter() - self._t0, 1e-9)

    def close(self) -> None:
        if self.viewer is not None:
            self.viewer.stop()
            self.viewer = None


__all__ = ["DEFAULT_BUDGET", "LiveView"]
