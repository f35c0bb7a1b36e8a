"""Stage ``view``: a run folder -> a local web viewer of the model and its uncertainty (``uncertsplat view``).

``run`` loads any run the other commands read (``baselines.load_run``), checks that the port is free, starts
the viser server (``view.server.Viewer``) and, with ``block``, serves until Ctrl-C. viser is an optional
dependency (``pip install 'uncertsplat[view]'``); without it the command says so and how to install it.
"""

from __future__ import annotations

import contextlib
import signal
import threading
import time
from pathlib import Path

import torch

from uncertsplat.config import PruneConfig, ViewConfig
from uncertsplat.console import console
from uncertsplat.errors import UserError, run_folder_missing
from uncertsplat.view.server import check_port, require_viser, viewer_url


def build(run_dir: Path, cfg: ViewConfig, device: torch.device):
    """The ``Viewer`` of ``run_dir`` (not started).

    Raises:
        UserError: viser missing, a missing or unfinished run folder (the message names the file and the fix).
    """
    from uncertsplat.baselines import load_run
    from uncertsplat.schemas import RunScene
    from uncertsplat.types import similarity_scale
    from uncertsplat.uncertainty.scores import spread_views
    from uncertsplat.view.frames import FrameRenderer
    from uncertsplat.view.server import Viewer

    require_viser()
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise run_folder_missing(run_dir)
    loaded = load_run(run_dir, device)
    loaded.warn_if_unfinished()
    scene = None
    photos = True  # the scene folder's photos are there (not only the cameras its evaluation kept)
    try:
        scene = loaded.load_scene()
    except UserError as err:  # the model is still worth looking at without its photos
        from uncertsplat.stages.predictive_cache import evaluation_predictive

        kept, problem = evaluation_predictive(loaded)
        if kept is not None:  # the cameras, split and normalisation evaluate kept (eval/predictive.pt)
            scene, photos = kept.scene, False
            loaded = loaded.with_scene(scene)  # (the empty-ray term's coverage is rendered from its training cameras)
            console.print(f"[yellow]note:[/] {err.message}: the cameras are those kept in "
                          f"{run_dir / 'eval' / 'predictive.pt'}, without their photos (nor the unseen mode, fitted "
                          "on them)", soft_wrap=True)
        else:
            console.print(f"[yellow]note:[/] no cameras or photos in the viewer, and its std modes leave out the "
                          f"empty-ray term (measured on the training views): {err.render()}", soft_wrap=True)
            # (the term's coverage is rendered from the training cameras: the viewer stopped there with the same error)
            loaded = loaded.with_model(loaded.model, coverage=1.0)
    info = RunScene.read_optional(run_dir / RunScene.FILE_NAME)
    scene_scale = scene.scene_scale if scene is not None else (info.scene_scale if info is not None else 1.0)
    score_cams = free_cams = None
    if scene is not None and scene.split.get("train"):
        defaults = PruneConfig()  # the same views as `prune`, so the preview shows its mask
        score_cams = scene.cameras[spread_views(scene.split["train"], defaults.score_views)]
        free_cams = scene.cameras[spread_views(scene.split["train"], defaults.free_space_views)]
    fit_unseen = None
    if photos and scene is not None and scene.split.get("train"):
        def fit_unseen():
            # the colour posterior as `evaluate` fits it, without the resolution term's shifted renders and the edge
            # term's fit (they only refine the noise of what the photos showed; the colour posterior divides by the
            # whole noise either way)

            from uncertsplat.config import EvalConfig
            from uncertsplat.eval.engine import fit_residual

            console.print("fitting what the training photos showed (the unseen mode, once)...")
            return fit_residual(loaded.sampler(scene_scale, device), scene.split["train"],
                                EvalConfig(resolution=0.0, edge_noise=False), device,
                                load_views=loaded.training_views(scene))
    if scene is not None:
        to_source = scene.depth_to_source
    elif info is not None:  # the scene's units from the run's record of its normalisation
        to_source = 1.0 / similarity_scale(info.world_from_source)
    else:
        to_source = None
    renderer = FrameRenderer(loaded, scene_scale, device, score_cameras=score_cams, free_space_cameras=free_cams,
                             seed=cfg.seed, unseen_field=fit_unseen, depth_to_source=to_source)
    if not photos:  # (the panel would name each missing photo; the frustums are drawn without pictures)
        cfg = cfg.model_copy(update={"thumbnails": False})
    return Viewer(renderer, scene, cfg, chosen=_chosen_views(run_dir) if scene is not None else None)


def _chosen_views(run_dir: Path) -> list:
    """The views ``select-views`` chose for ``run_dir`` into its default folder (``RUN/select/selection.json``), to be
    drawn beside the cameras; none when there is no such file, and a note when it cannot be read."""
    from uncertsplat.schemas import Selection

    path = run_dir / "select" / Selection.FILE_NAME
    if not path.is_file():
        return []
    try:
        chosen = Selection.read(path).chosen
    except UserError as err:
        console.print(f"[yellow]note:[/] the views select-views chose are not shown: {err.render()}", soft_wrap=True)
        return []
    if chosen:
        console.print(f"showing the {len(chosen)} view(s) select-views chose ({path}) as green cameras")
    return chosen


@contextlib.contextmanager
def _sigterm_as_ctrl_c():
    """SIGTERM (`kill`, `timeout`) stops the serving loop as Ctrl-C does; without this the process dies in the
    fatal-signal handler pycolmap's logging installs, which prints a native stack dump. Main thread only."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def stop(_signum, _frame):
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, stop)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def run(run_dir: Path, cfg: ViewConfig, device: torch.device, *, block: bool = True):
    """Serve ``run_dir`` in the browser; returns the started ``Viewer`` when ``block`` is False (the caller
    stops it), else serves until Ctrl-C and returns None.

    Raises:
        UserError: see ``build``; the port in use or not allowed.
    """
    check_port(cfg.host, cfg.port)  # (before the run is loaded: a large model takes a while to be told)
    viewer = build(run_dir, cfg, device)
    try:
        viewer.start()
        if cfg.port and viewer.port != cfg.port:  # taken between our check and viser's bind
            raise UserError(f"port {cfg.port} was taken while the viewer started", hint="Run the command again.")
        r = viewer.renderer
        console.print(f"[bold]view[/] {run_dir}: {r.loaded.size_text()}, modes: {', '.join(r.modes())}, {device}; "
                      f"RGB: {r.rgb_source}")
        console.print(f"open [bold]{viewer_url(cfg.host, viewer.port)}[/] in a browser (from another machine: "
                      f"ssh -L {viewer.port}:localhost:{viewer.port} THIS_HOST); Ctrl-C stops")
        if cfg.host not in ("127.0.0.1", "localhost", "::1"):  # (said where it happens, not only in --help)
            console.print(f"[yellow]warning:[/] listening on {cfg.host}: anyone who can reach port {viewer.port} of "
                          "this machine can see the run's photos, cameras and renders (the viewer has no password)")
        if not block:
            return viewer
        with _sigterm_as_ctrl_c():
            while True:
                time.sleep(0.5)
    except KeyboardInterrupt:  # Ctrl-C (or SIGTERM), whenever it comes: stop cleanly
        block = True
    except BaseException:
        block = True
        raise
    finally:
        if block:
            viewer.stop()
    console.print("viewer stopped")
    return None


__all__ = ["build", "run"]
