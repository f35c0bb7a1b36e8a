"""The viser app of ``uncertsplat view``: a panel, the cameras as frustums and a render loop.

One worker thread renders for every connected browser (a 2-core CPU has no room for more). Each browser's
view has a version, bumped by its camera moves and by every panel change. The worker, for each view:

- while the camera moves (a camera message in the last ``STILL_AFTER`` seconds): renders a preview at a
  resolution chosen so that one frame takes about 1 / ``moving_fps`` seconds (from the measured cost per
  pixel), with ``moving_samples`` posterior samples in the std modes;
- once it stands still: renders the view at full resolution (its long side ``max_side``, the browser's
  aspect) and, in the std modes, keeps adding ``moving_samples`` samples at a time to the same Monte-Carlo
  moments up to ``still_samples``, pushing the refined frame after each step. A camera move in between
  drops the refinement at the next step (one render is never interrupted).

Frames go to the browser as JPEG background images with their depth, so the frustums are hidden behind
surfaces. The colour bar, the frame's size and timing are in the panel. Clicking a camera frustum moves the
view onto that photo and shows the photo in the panel. Nothing is fetched from the internet: viser's
client is served from the installed package and its share button (a tunnel through viser's servers) is
hidden.
"""

from __future__ import annotations

import contextlib
import errno
import html
import io
import math
import socket
import threading
import time
import warnings
from dataclasses import dataclass, field

import numpy as np
import torch

from uncertsplat.config import ViewConfig
from uncertsplat.errors import UserError, require_extra
from uncertsplat.report.colormaps import colorize
from uncertsplat.types import Cameras, SceneData
from uncertsplat.view.frames import (
    STD_MODES,
    VIEW_MODES,
    Frame,
    FrameRenderer,
    StdAccumulator,
    camera_pose,
    viewer_camera,
)

STILL_AFTER = 0.25
"""Seconds without a camera message after which a view counts as still (viser sends one every 20 ms while
the camera moves)."""
MIN_PREVIEW_SIDE = 96
"""The preview's long side never drops below this many pixels."""
THUMBNAIL_WIDTH = 160
PHOTO_WIDTH = 320
_ROLE_COLOURS = {"train": (40, 90, 220), "test": (230, 120, 20), "calibration": (150, 60, 200), "unused": (140, 140, 140)}
"""Frustum colours by the camera's part in the run (``Viewer._role``): blue trained on, orange held out, purple
set aside for the std factor, grey a photo the run did not train on."""
CHOSEN_COLOUR = (30, 170, 70)
"""The frustums of the views ``select-views`` chose (``RUN/select/selection.json``): green, a little larger."""
_ROLE_WORDS = {"train": "training", "test": "held-out", "calibration": "set aside for calibration",
               "unused": "not trained on"}


@dataclass
class ViewState:
    """What the worker knows about one browser's view."""

    client: object  # viser.ClientHandle
    version: int = 0
    moved_at: float = 0.0
    shown_version: int = -1
    shown_full: bool = False
    accumulator: StdAccumulator | None = None
    accumulator_version: int = -1
    frames: int = 0
    last: dict = field(default_factory=dict)


MIN_FOV, MAX_FOV = 0.01, 3.1
SAMPLES_RANGE, SIDE_RANGE, KEEP_RANGE = (2, 128), (128, 2048), (0.5, 1.0)
"""The panel's sliders (still samples K, still resolution, prune keep ratio): their ranges, and what a value a client
sends is clamped to (``_within``)."""
"""Radians: the vertical field of view a client's camera is taken at, at most (a value sent outside it is clamped)."""


def _within(value, lo: float, hi: float, default: float) -> float:
    """A panel or camera value as a number in [``lo``, ``hi``]: viser passes on what a client sends, beyond the
    slider's range too (a resolution of 8192 rendered 8192x8192 in 4 GB; 32768 would need 64 GB; samples of 1e9
    refined without end), or not a number (``default`` then)."""
    try:
        x = float(value)
    except (TypeError, ValueError):
        return float(default)
    return float(default) if x != x else min(max(x, lo), hi)


def _widened(bounds: tuple[int, int], value: int) -> tuple[int, int]:
    """A slider's ``bounds`` widened to hold ``value`` (a setting the config allows beyond the usual range)."""
    return min(bounds[0], int(value)), max(bounds[1], int(value))


def _fit(aspect: float, long_side: int) -> tuple[int, int]:
    """(width, height) with the given aspect (width / height) and long side."""
    long_side = max(int(long_side), 8)
    if aspect >= 1.0:
        return long_side, max(8, round(long_side / aspect))
    return max(8, round(long_side * aspect)), long_side


def colour_bar_html(value_range: tuple[float, float] | None, unit: str, note: str = "") -> str:
    """The panel's colour bar: a turbo gradient with its ends and middle as numbers (like the report's)."""
    if value_range is None:
        return f"<div style='font-size:0.85em'>{html.escape(note)}</div>"
    lo, hi = value_range
    stops = colorize(np.linspace(0.0, 1.0, 11)[None], "fixed", 0.0, 1.0)[0]
    grad = ", ".join(f"rgb({r},{g},{b}) {i * 10}%" for i, (r, g, b) in enumerate(stops.tolist()))
    ticks = "".join(f"<span>{v:.3g}</span>" for v in (lo, 0.5 * (lo + hi), hi))
    return ("<div style='font-size:0.85em'>"
            f"<div>{html.escape(unit)}</div>"
            f"<div style='height:14px;border-radius:3px;background:linear-gradient(to right, {grad})'></div>"
            f"<div style='display:flex;justify-content:space-between'>{ticks}</div>"
            f"<div style='opacity:0.8'>{html.escape(note)}</div></div>")


def require_viser():
    """Import viser, or raise a UserError with the install command."""
    return require_extra("viser", feature="the viewer", extra="view")


HOST_LOOKUP_SECONDS = 5.0
"""How long a host name (not an address) may take to resolve before ``check_port`` gives up on it."""


def _host_address(host: str) -> str:
    """``host`` as an address to bind: an IP address as it is, a name resolved without waiting on a DNS server that
    does not answer (a malformed address such as 999.1.1.1 would otherwise be looked up as a name)."""
    import ipaddress
    import threading

    hint = "Give --host an address of this machine: 127.0.0.1 for it alone, 0.0.0.0 for every interface."
    try:
        return str(ipaddress.ip_address(host))
    except ValueError:
        pass
    if host.replace(".", "").isdigit() or ":" in host:
        raise UserError(f"--host {host} is not a valid IP address", hint=hint)
    found: list = []

    def lookup():
        try:
            infos = socket.getaddrinfo(host, None, type=socket.SOCK_STREAM)
            # the IPv4 address where there is one (localhost's ::1 may be off; the viewer binds the name as given)
            found.append(next((i[4][0] for i in infos if i[0] == socket.AF_INET), infos[0][4][0]))
        except OSError as err:
            found.append(err)

    worker = threading.Thread(target=lookup, daemon=True)
    worker.start()
    worker.join(HOST_LOOKUP_SECONDS)
    if not found:
        raise UserError(f"--host {host}: the name did not resolve within {HOST_LOOKUP_SECONDS:g} s", hint=hint)
    if isinstance(found[0], OSError):
        raise UserError(f"--host {host}: no such host ({found[0].strerror or found[0]})", hint=hint)
    return found[0]


def check_port(host: str, port: int, option: str = "--port") -> None:
    """Raise a clear UserError when ``host:port`` cannot be listened on (viser itself would silently move to
    the next port, and the printed URL would then be wrong for an SSH tunnel set up in advance); with port 0, when
    ``host`` is not an address of this machine. ``option``: the command's name for the port, for the hint."""
    address = _host_address(host)
    family = socket.AF_INET6 if ":" in address else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((address, port))
        except OSError as err:
            if err.errno == errno.EADDRINUSE:
                raise UserError(f"port {port} on {host} is already in use (another viewer or server?)",
                                hint=f"Stop the other program, or choose another port: {option} {port + 1} "
                                     f"({option} 0 picks a free one).") from None
            raise UserError(f"cannot listen on {host}:{port} ({err.strerror})",
                            hint="Check --host (127.0.0.1 for this machine only, 0.0.0.0 for every interface) "
                                 f"and {option} (1024 and above need no privileges).") from None


def viewer_url(host: str, port: int) -> str:
    shown = "localhost" if host in ("0.0.0.0", "127.0.0.1", "::", "::1") else host
    if ":" in shown:  # an IPv6 address: a URL needs it in brackets
        shown = f"[{shown.strip('[]')}]"
    return f"http://{shown}:{port}"


class Viewer:
    """The viewer of one loaded run (``run`` in ``stages.view`` builds and starts it).

    Args:
        renderer: renders the run (``view.frames.FrameRenderer``).
        scene: the scene the run was trained on, for the camera frustums and photos (None: no cameras).
        cfg: the viewer settings.
    """

    def __init__(self, renderer: FrameRenderer, scene: SceneData | None, cfg: ViewConfig, chosen: list | None = None):
        self.renderer = renderer
        self.scene = scene
        self.cfg = cfg
        self.chosen = list(chosen or [])  # ``schemas.ChosenView``s: drawn as frustums of their own (no photo yet)
        self.server = None
        self._views: dict[int, ViewState] = {}
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._worker: threading.Thread | None = None
        self._sec_per_pixel: dict[str, float] = {}  # per mode: measured seconds per pixel and render
        self._locked_range: tuple[float, float] | None = None
        self.frames_pushed = 0
        self.last_error: str | None = None

    # ------------------------------------------------------------------------------------------ lifecycle
    def start(self, worker: bool = True) -> None:
        """Start the server on ``cfg.host:cfg.port`` and (unless ``worker`` is False: a test then calls ``serve``
        itself) the render worker; returns at once."""
        import viser

        # viser prints its own URL box whatever ``verbose`` says; the stage prints ours (with the SSH hint)
        with contextlib.redirect_stdout(io.StringIO()):
            self.server = viser.ViserServer(host=self.cfg.host, port=self.cfg.port, verbose=False)
        self.server.gui.configure_theme(show_share_button=False, control_width="medium")
        self._build_panel()
        self._add_cameras()
        self.server.on_client_connect(self._on_connect)
        self.server.on_client_disconnect(self._on_disconnect)
        if worker:
            self._worker = threading.Thread(target=self._work, name="uncertsplat-view", daemon=True)
            self._worker.start()

    @property
    def port(self) -> int:
        return int(self.server.get_port())

    def stop(self) -> None:
        """Stop the worker and the server."""
        self._stop.set()
        self._wake.set()
        if self._worker is not None:
            self._worker.join(timeout=10)
        if self.server is not None:
            self.server.stop()

    # ------------------------------------------------------------------------------------------ panel
    def _build_panel(self) -> None:
        gui = self.server.gui
        labels, scores = self._choices()
        self._label_to_mode = {VIEW_MODES[m]: m for m in self.renderer.modes()}
        self.gui_mode = gui.add_dropdown("Mode", labels, initial_value=labels[0],
                                         hint="What the view shows: the render, its depth, the posterior's std, or "
                                              "the Gaussians prune would remove.")
        # (a setting beyond a slider's usual range widens it: the config allows what the panel should show)
        self._samples_range = _widened(SAMPLES_RANGE, self.cfg.still_samples)
        self._side_range = _widened(SIDE_RANGE, self.cfg.max_side)
        self.gui_samples = gui.add_slider("Samples (still)", min=self._samples_range[0], max=self._samples_range[1],
                                          step=2,
                                          initial_value=self.cfg.still_samples,
                                          hint="Posterior samples of a still std frame (K); moving frames use "
                                               f"{self.cfg.moving_samples}.")
        self.gui_side = gui.add_slider("Resolution (still)", min=self._side_range[0], max=self._side_range[1], step=32,
                                       initial_value=self.cfg.max_side,
                                       hint="Long side in pixels of a still frame; moving frames are smaller.")
        self.gui_lock = gui.add_checkbox("Lock colour range", initial_value=False,
                                         hint="Keep the current colour range while moving (default: 1st-99th "
                                              "percentile of each frame).")
        with gui.add_folder("Prune preview", expand_by_default=True) as self.gui_prune_folder:
            self.gui_score = gui.add_dropdown("Score", scores, initial_value=scores[0])
            self.gui_keep = gui.add_slider("Keep ratio", min=KEEP_RANGE[0], max=KEEP_RANGE[1], step=0.01,
                                           initial_value=0.9,
                                           hint="Preview of prune --keep-ratio: the removed Gaussians are coloured.")
            self.gui_hide = gui.add_checkbox("Show only what is kept", initial_value=False)
        self.gui_cameras = gui.add_checkbox("Show cameras", initial_value=True)
        self.gui_bar = gui.add_html(colour_bar_html(None, "", ""))
        self.gui_status = gui.add_markdown("waiting for a browser")
        self.gui_photo_title = gui.add_markdown("")
        self.gui_photo = None
        for handle in (self.gui_mode, self.gui_samples, self.gui_side, self.gui_score, self.gui_keep, self.gui_hide):
            handle.on_update(self._on_panel)
        self.gui_lock.on_update(self._on_lock)
        self.gui_cameras.on_update(self._on_show_cameras)
        self._update_visibility()

    def _choices(self) -> tuple[tuple[str, ...], tuple[str, ...]]:
        """(mode labels, prune scores) the panel offers for the current renderer."""
        r = self.renderer
        return (tuple(VIEW_MODES[m] for m in r.modes()),
                tuple(r.score_names() if r.prune_available else ["gate"]))

    def offer_modes(self) -> None:
        """The panel's modes and prune scores made those of the current renderer: ``train --view`` starts before any
        Gaussian carries a posterior and gets a new renderer as the training goes (the prune preview then becomes
        available)."""
        labels, scores = self._choices()
        if tuple(self._label_to_mode) != labels:
            self._label_to_mode = {VIEW_MODES[m]: m for m in self.renderer.modes()}
            self.gui_mode.options = labels  # (viser keeps the value where it is still offered)
        if tuple(self.gui_score.options) != scores:
            self.gui_score.options = scores

    @property
    def mode(self) -> str:
        # (a value no dropdown offers, sent by a client, reads as the first mode: it raised KeyError in every frame)
        return self._label_to_mode.get(self.gui_mode.value, next(iter(self._label_to_mode.values())))

    def set_mode(self, mode: str) -> None:
        """Switch every view to ``mode`` (a ``VIEW_MODES`` key), as choosing it in the panel does."""
        self.gui_mode.value = VIEW_MODES[mode]  # viser calls _on_panel (synchronously) when the value changes

    def _update_visibility(self) -> None:
        mode = self.mode
        self.gui_samples.visible = mode in STD_MODES
        self.gui_prune_folder.visible = mode == "prune"
        self.gui_lock.visible = mode in ("depth", "unseen") + STD_MODES

    def _on_panel(self, _event) -> None:
        self._update_visibility()
        self._locked_range = None
        with self._lock:
            for v in self._views.values():
                v.version += 1
        self._wake.set()

    def _on_lock(self, _event) -> None:
        if not self.gui_lock.value:
            self._on_panel(None)

    def _on_show_cameras(self, _event) -> None:
        for i, h in enumerate(self._frustums):
            h.visible = bool(self.gui_cameras.value) and i != self._hidden

    # ------------------------------------------------------------------------------------------ cameras
    def _add_cameras(self) -> None:
        self._frustums = []
        self._hidden: int | None = None  # the frustum of the camera the view jumped to
        scene = self.scene
        if scene is None:
            return
        cams = scene.cameras
        centres = torch.linalg.inv(cams.cam_from_world.double())[:, :3, 3]  # [C,3]
        # the world's up: the cameras' mean up axis (OpenCV: -y of each camera)
        up = -torch.linalg.inv(cams.cam_from_world.double())[:, :3, 1].mean(0)
        if float(up.norm()) > 1e-6:
            self.server.scene.set_up_direction(tuple((up / up.norm()).tolist()))
        if len(cams) > 1:
            d = torch.cdist(centres, centres) + torch.eye(len(cams), dtype=centres.dtype) * 1e9
            size = 0.5 * float(d.min(1).values.median())
        else:
            size = 0.1 * scene.scene_scale
        self._frustum_size = max(min(size, 0.15 * scene.scene_scale), 1e-3 * scene.scene_scale)
        aspect = cams.width / cams.height
        for i in range(len(cams)):
            wxyz, pos, fov = camera_pose(cams.cam_from_world[i], cams.K[i], cams.height)
            name = cams.image_names[i] if cams.image_names else f"camera_{i}"
            role = self._role(i)  # a photo the run never trained on is no training camera (a gap to fill is grey)
            colour = _ROLE_COLOURS[role]
            h = self.server.scene.add_camera_frustum(
                f"/cameras/{role}/{i:05d}", fov=fov, aspect=aspect,
                scale=self._frustum_size, thickness=1.5, thickness_units="screen", color=colour, wxyz=wxyz,
                position=pos)
            h.on_click(self._click_handler(i, name, wxyz, pos, fov))
            self._frustums.append(h)
        ref = scene.split["train"][0] if scene.split.get("train") else 0  # (a chosen pose's field of view: its)
        for c in self.chosen:
            cfw = torch.tensor(c.cam_from_world, dtype=cams.cam_from_world.dtype)
            wxyz, pos, fov = camera_pose(cfw, cams.K[ref], cams.height)
            h = self.server.scene.add_camera_frustum(
                f"/cameras/chosen/{c.rank:03d}", fov=fov, aspect=aspect, scale=1.5 * self._frustum_size,
                thickness=3.0, thickness_units="screen", color=CHOSEN_COLOUR, wxyz=wxyz, position=pos)
            h.on_click(self._chosen_handler(len(self._frustums), c, wxyz, pos, fov))
            self._frustums.append(h)
        # initial view: behind and above the first training camera, looking where it looks (as far as the scene
        # centre), so its frustum and photo are in sight without covering the render
        first = scene.split["train"][0] if scene.split.get("train") else 0
        _, pos, fov = camera_pose(cams.cam_from_world[first], cams.K[first], cams.height)
        R = torch.linalg.inv(cams.cam_from_world[first].double())[:3, :3].numpy()
        dist = max(float(np.linalg.norm(pos)), 1e-3)
        back = pos - R[:, 2] * 0.5 * dist - R[:, 1] * 0.25 * dist
        self.server.initial_camera.position = tuple(back.tolist())
        self.server.initial_camera.look_at = tuple((pos + R[:, 2] * dist).tolist())
        self.server.initial_camera.up = tuple((-R[:, 1]).tolist())
        self.server.initial_camera.fov = fov
        if self.cfg.thumbnails:
            threading.Thread(target=self._load_thumbnails, name="uncertsplat-thumbnails", daemon=True).start()

    def _role(self, i: int) -> str:
        """The camera's part in the run: "train" (trained on), "test" (held out), "calibration" (set aside for the
        std factor) or "unused" (a photo of the scene the run did not train on: scene.train_names, pose twins)."""
        split = self.scene.split
        for role in ("test", "calibration", "train"):
            if i in set(split.get(role, ())):
                return role
        return "unused"

    def _jump(self, client, i: int, wxyz, pos, fov) -> None:
        """Put ``client``'s view at frustum ``i``'s camera and hide that frustum: standing at the camera, its own
        frustum (and photo) would cover the render (shown again at the next jump)."""
        with client.atomic():
            client.camera.wxyz = wxyz
            client.camera.position = pos
            client.camera.fov = fov
        if self._hidden is not None:
            self._frustums[self._hidden].visible = bool(self.gui_cameras.value)
        self._frustums[i].visible = False
        self._hidden = i

    def _click_handler(self, i: int, name: str, wxyz, pos, fov):
        def on_click(event) -> None:
            self._jump(event.client, i, wxyz, pos, fov)
            self._show_photo(i, name)

        return on_click

    def _chosen_handler(self, i: int, chosen, wxyz, pos, fov):
        """Clicking a chosen view's frustum: the view jumps to it, and the panel says which choice it is (it has no
        photo yet: it is where the next one is to be taken)."""
        def on_click(event) -> None:
            self._jump(event.client, i, wxyz, pos, fov)
            score = "" if chosen.score_when_chosen is None else f", score {chosen.score_when_chosen:.4g}"
            self.gui_photo_title.content = (f"**{html.escape(chosen.name)}**: choice {chosen.rank} of select-views"
                                            f"{score} (no photo yet: take one here)")

        return on_click

    def _read_photo(self, i: int, width: int) -> np.ndarray:
        from uncertsplat.data.dataset import read_photo
        from uncertsplat.io.images import resize_image

        img = read_photo(self.scene, i)
        h = max(1, round(img.shape[0] * width / img.shape[1]))
        return (np.clip(resize_image(img, width, h), 0, 1) * 255 + 0.5).astype(np.uint8)

    def _show_photo(self, i: int, name: str) -> None:
        split = _ROLE_WORDS[self._role(i)]
        try:
            photo = self._read_photo(i, PHOTO_WIDTH)
        except Exception as err:  # a photo moved or unreadable: say so in the panel, keep the viewer running
            self.gui_photo_title.content = f"**{html.escape(name)}** ({split} view): cannot read the photo ({err})"
            return
        self.gui_photo_title.content = f"**{html.escape(name)}** ({split} view)"
        if self.gui_photo is None:
            self.gui_photo = self.server.gui.add_image(photo, label="Photo")
        else:
            self.gui_photo.image = photo

    def _load_thumbnails(self) -> None:
        for i, h in enumerate(self._frustums):
            if self._stop.is_set():
                return
            try:
                h.image = self._read_photo(i, THUMBNAIL_WIDTH)
            except Exception:  # a missing photo keeps its frustum without a picture
                continue

    # ------------------------------------------------------------------------------------------ clients
    def _on_connect(self, client) -> None:
        state = ViewState(client, moved_at=time.monotonic())
        with self._lock:
            self._views[client.client_id] = state

        def on_camera(_camera) -> None:
            with self._lock:
                state.version += 1
                state.moved_at = time.monotonic()
            self._wake.set()

        client.camera.on_update(on_camera)
        self._wake.set()

    def _on_disconnect(self, client) -> None:
        with self._lock:
            self._views.pop(client.client_id, None)

    # ------------------------------------------------------------------------------------------ rendering
    def _work(self) -> None:
        while not self._stop.is_set():
            self._wake.wait(0.05)
            self._wake.clear()
            with self._lock:
                views = list(self._views.values())
            for v in views:
                if self._stop.is_set():
                    return
                self.serve_or_report(v)

    def serve_or_report(self, v: ViewState) -> None:
        """``serve``, a failure shown in the panel instead of raised: a frame too large for the device's memory or a
        client's odd camera must neither stop the viewer nor a training run it watches (``view.live``)."""
        try:
            self.serve(v)
        except Exception as err:
            self.last_error = f"{type(err).__name__}: {err}"
            self.gui_status.content = f"**render failed**: {html.escape(self.last_error)}"
            with self._lock:  # (not tried again until the camera moves)
                v.shown_version, v.shown_full = v.version, True

    def _camera(self, v: ViewState, long_side: int) -> Cameras:
        cam = v.client.camera
        aspect = float(cam.aspect) if cam.aspect and cam.aspect > 0 else 4 / 3
        w, h = _fit(aspect, long_side)
        fov = _within(cam.fov, MIN_FOV, MAX_FOV, 1.0)  # (0 divided by zero; above pi rendered a mirrored frame)
        return viewer_camera(cam.wxyz, cam.position, fov, w, h, self.renderer.device)

    def _full_side(self, v: ViewState) -> int:
        cam = v.client.camera
        canvas = int(max(_within(cam.image_width, 0, 1 << 16, 0), _within(cam.image_height, 0, 1 << 16, 0)))
        side = int(_within(self.gui_side.value, *self._side_range, self.cfg.max_side))
        return min(side, canvas) if canvas > 0 else side

    def _preview_side(self, v: ViewState, mode: str, renders: int) -> int:
        full = self._full_side(v)
        spp = self._sec_per_pixel.get(mode)
        if spp is None:
            return max(MIN_PREVIEW_SIDE, full // 2)
        cam = v.client.camera
        aspect = float(cam.aspect) if cam.aspect and cam.aspect > 0 else 4 / 3
        pixels = (1.0 / self.cfg.moving_fps) / (spp * max(renders, 1))
        side = math.sqrt(pixels * max(aspect, 1 / aspect))
        return int(min(full, max(MIN_PREVIEW_SIDE, side)))

    def serve(self, v: ViewState) -> None:
        """Do the next piece of work for one view (a preview, a full frame or one refinement step)."""
        with self._lock:
            version, moving = v.version, time.monotonic() - v.moved_at < STILL_AFTER
            done = v.shown_version == version and (v.shown_full or moving)
        if done:
            return
        mode = self.mode
        std = mode in STD_MODES
        k_move = self.cfg.moving_samples
        value_range = self._locked_range if self.gui_lock.value else None
        t0 = time.perf_counter()
        if moving:
            cams = self._camera(v, self._preview_side(v, mode, k_move if std else 1))
            frame = self._frame(cams, mode, k_move, value_range)
            full = False
            renders = k_move if std else 1
        elif std:
            if v.accumulator is None or v.accumulator_version != version:
                v.accumulator = self.renderer.std_accumulator(self._camera(v, self._full_side(v)))
                v.accumulator_version = version
            cams = v.accumulator.cameras
            k_total = int(_within(self.gui_samples.value, *self._samples_range, self.cfg.still_samples))
            step = min(k_move, k_total - v.accumulator.count)
            v.accumulator.add(step)
            frame = v.accumulator.frame(mode, value_range)
            full = v.accumulator.count >= k_total
            renders = step
        else:
            cams = self._camera(v, self._full_side(v))
            frame = self._frame(cams, mode, 1, value_range)
            full, renders = True, 1
        seconds = time.perf_counter() - t0
        self._measure(mode, seconds, cams, renders)
        with self._lock:
            if v.version != version:  # the camera moved while rendering: show it anyway (it is close), redo next
                full = False
        self._push(v, frame, cams, seconds, "moving" if moving else "still")
        with self._lock:
            v.shown_version, v.shown_full = version, full

    def _frame(self, cams: Cameras, mode: str, samples: int, value_range) -> Frame:
        keep = _within(self.gui_keep.value, *KEEP_RANGE, 0.9)
        return self.renderer.frame(cams, mode, num_samples=samples, value_range=value_range,
                                   score=str(self.gui_score.value), keep_ratio=keep,
                                   hide_removed=bool(self.gui_hide.value))

    def _measure(self, mode: str, seconds: float, cams: Cameras, renders: int) -> None:
        spp = seconds / max(cams.width * cams.height * max(renders, 1), 1)
        old = self._sec_per_pixel.get(mode)
        self._sec_per_pixel[mode] = spp if old is None else 0.7 * old + 0.3 * spp

    def _push(self, v: ViewState, frame: Frame, cams: Cameras, seconds: float, kind: str) -> None:
        depth = np.where(np.isfinite(frame.depth), frame.depth, 1e3).astype(np.float32)
        with warnings.catch_warnings():
            # the browser may close while its frame renders: viser then warns that the frame is undeliverable
            warnings.filterwarnings("ignore", message="Queued a BackgroundImageMessage on a closed connection")
            v.client.scene.set_background_image(frame.image, format="jpeg", jpeg_quality=self.cfg.jpeg_quality,
                                                depth=depth)
        v.frames += 1
        v.last = {"kind": kind, "width": cams.width, "height": cams.height, "samples": frame.samples,
                  "seconds": seconds, "value_range": frame.value_range}
        self.frames_pushed += 1
        if frame.value_range is not None and self.gui_lock.value and self._locked_range is None:
            self._locked_range = frame.value_range
        self.gui_bar.content = colour_bar_html(frame.value_range, frame.unit, frame.note)
        samples = f", K = {frame.samples}" if self.mode in STD_MODES else ""
        self.gui_status.content = f"{kind}: {cams.width}x{cams.height}{samples}, {seconds * 1000:.0f} ms"


__all__ = ["MIN_PREVIEW_SIDE", "STILL_AFTER", "ViewState", "Viewer", "check_port", "colour_bar_html",
           "require_viser", "viewer_url"]
