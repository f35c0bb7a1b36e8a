"""Stage ``reconstruct``: a folder of photos to an undistorted COLMAP workspace with a health report.

Workspace layout (the COLMAP layout that 3DGS tools read; README, ``uncertsplat reconstruct``)::

    WS/images/                 undistorted PINHOLE images
    WS/sparse/0/*.bin          the model of the undistorted images
    WS/database.db             COLMAP features and matches
    WS/distorted/sparse/0/     the model before undistortion (the kept, largest model)
    WS/distorted/input/        rotated copies, only when some photos carry an EXIF orientation
    WS/reconstruct_report.json written atomically for successful and failed runs
"""

from __future__ import annotations

import contextlib
import math
import shutil
import time
from collections import Counter
from pathlib import Path

from uncertsplat.config import ReconstructConfig
from uncertsplat.console import add_views_args, console, esc, list_names, progress, q, qm
from uncertsplat.errors import Interrupted, UserError
from uncertsplat.io.atomic import (
    atomic_write_bytes,
    atomic_write_json,
    check_output_folder,
    read_json,
    run_lock,
)
from uncertsplat.io.images import IMAGE_EXTENSIONS
from uncertsplat.sfm import reconstruct as sfm
from uncertsplat.sfm.report import (
    EXTEND_DIR,
    FAILED_REPORT_NAME,
    OVERWRITE_MOVING,
    OVERWRITE_OLD,
    OVERWRITE_RESTORING,
    REPORT_NAME,
    UNFINISHED,
    MappingAttempt,
    ModelSummary,
    ReconstructReport,
    load_report,
    write_report,
)

OWN_CAMERAS_DB = "database.own_cameras.db"
"""The copy of the database a photo gets a camera of its own in, mapped from, then put in place of it."""
# What a workspace written by this stage consists of: --overwrite removes these and nothing else.
_OWNED = ("images", "masks", "sparse", "distorted", "database.db", "stereo", ".undistort_tmp", ".extend_tmp", ".extend_done",
          REPORT_NAME, FAILED_REPORT_NAME, OWN_CAMERAS_DB, f"{OWN_CAMERAS_DB}-wal", f"{OWN_CAMERAS_DB}-shm",
          "database.db-wal", "database.db-shm")
OVERWRITE_DONE = ".overwrite_done"
"""``OVERWRITE_OLD`` renamed once the new workspace has finished, then removed."""
OVERWRITE_PLAN = "plan.json"
"""In ``OVERWRITE_MOVING``: the names moved aside and the names the old workspace did not have."""


def _inputs_fingerprint(scan, masks: Path | None) -> str:
    """The fingerprint of a reconstruction's inputs: the photos' (``PhotoScan.fingerprint``), with their masks'
    folder when there is one (other masks are other inputs: a workspace is not reused for them)."""
    if masks is None or not masks.is_dir():
        return scan.fingerprint()
    from uncertsplat.stages.manifest import fingerprint_folder

    return sfm.combined_fingerprint(scan.fingerprint(), fingerprint_folder(masks))


def _recorded_config(recorded: dict, cfg: ReconstructConfig) -> ReconstructConfig | None:
    """A workspace's recorded options as a config (with ``cfg``'s ``overwrite``, no option of a workspace); an option
    added since it was made counts at its default (a workspace from before ``features`` existed was made with "sift",
    the default); None where they no longer read (an option that no longer exists, or a value no longer allowed)."""
    try:
        return type(cfg).model_validate({**recorded, "overwrite": cfg.overwrite})
    except ValueError:
        return None


def _same_options(recorded: dict, cfg: ReconstructConfig) -> bool:
    """Whether a workspace's recorded options are ``cfg``'s (``_recorded_config``)."""
    return _recorded_config(recorded, cfg) == cfg


def _option_changes(recorded: dict, cfg: ReconstructConfig) -> str:
    """The options a workspace was made with that ``cfg`` changes, for the refusal to reuse it ("seed 0 then, 3
    now"); "" where its recorded options cannot be read as a config."""
    then = _recorded_config(recorded, cfg)
    if then is None:
        return ""
    before, now = then.model_dump(mode="json"), cfg.model_dump(mode="json")
    return ", ".join(f"{k} {before[k]} then, {now[k]} now" for k in now if k != "extend" and before[k] != now[k])


def _check_output_path(photos: Path, workspace: Path) -> None:
    """Refuse an output path that is a file, holds the photo folder or lies inside it (before any folder is made).

    Raises:
        UserError: naming which.
    """
    photos_abs, ws_abs = photos.resolve(), workspace.resolve()
    if ws_abs == photos_abs or ws_abs in photos_abs.parents:
        raise UserError("the output folder contains the photo folder; writing there could destroy the photos",
                        path=workspace, hint="Choose an output folder outside the photo folder.")
    if photos_abs in ws_abs.parents:
        raise UserError("the output folder is inside the photo folder", path=workspace,
                        hint="Choose an output folder outside the photo folder.")
    check_output_folder(workspace)


EXIF_NOTE = "EXIF orientation applied to"
"""How the workspace's note on the photos turned upright by their EXIF orientation begins."""


def _exif_note(rotated: list[str]) -> str:
    return (f"{EXIF_NOTE} {len(rotated)} image(s): {list_names(rotated)} (turned upright before feature extraction; "
            "the workspace's images are upright)")


def _folder_changes(existing: ReconstructReport, scan: sfm.PhotoScan, cfg: ReconstructConfig
                    ) -> tuple[list[str], list[str]]:
    """(the photos added since, what changed: the photos added, gone or edited since the workspace ``existing`` was
    made of the folder ``scan`` found them in, and its masks)."""
    added = sorted(set(scan.names) - set(existing.images_found))
    gone = sorted(set(existing.images_found) - set(scan.names))
    changes = ([f"{len(added)} photo(s) added since ({list_names(added)})"] if added else []) + (
        [f"{len(gone)} gone ({list_names(gone)})"] if gone else [])
    hashes = scan.photo_hashes() if existing.photo_sha256 else {}  # (computed already for the fingerprint)
    edited = sorted(n for n, h in hashes.items() if existing.photo_sha256.get(n, h) != h)
    if edited:
        changes.append(f"{list_names(edited)} edited or replaced since")
    then, now = existing.options.get("masks"), cfg.masks
    if (then is None) != (now is None) or (then is not None and Path(then).resolve() != Path(now).resolve()):
        changes.append(f"made {f'with the masks in {then}' if then else 'without masks'}, now "
                       f"{f'with those in {now}' if now is not None else 'without'}")
    if not changes:  # (a mask edited in the same folder; a report from before the photos' hashes)
        changes.append(f"a photo{' or mask' if now is not None else ''} edited or replaced since")
    return added, changes


def _prepare_workspace(photos: Path, workspace: Path, cfg: ReconstructConfig, fingerprints: tuple[str, ...],
                       scan: sfm.PhotoScan | None = None) -> ReconstructReport | None:
    """Check the output folder; return an identical finished report to reuse, else make room. Called while holding
    the folder's lock: a run in progress (its report says unfinished) is never cleared by a second one.
    ``fingerprints``: the photos' (``PhotoScan.fingerprint``, then its legacy form); the same photos moved to another
    folder are the same input, and the report then records their new folder. ``scan``: the photos found, by which a
    refusal says how the folder's photos (or masks) changed since the workspace was made of them.

    Raises:
        UserError: the output folder holds something else (another workspace, other files) and
            ``cfg.overwrite`` is off, or the photos live inside the output folder.
    """
    _check_output_path(photos, workspace)
    photos_abs = photos.resolve()
    if not workspace.exists() or not any(p.name != ".lock" for p in workspace.iterdir()):  # (our own lock)
        return None
    existing = None
    try:
        existing = load_report(workspace)
    except UserError:
        existing = None
    same_input = existing is not None and existing.inputs_fingerprint in fingerprints
    if (not cfg.overwrite and same_input and existing.success
            and _same_options(existing.options, cfg)
            and (workspace / "sparse" / "0").is_dir()):
        if existing.photos != str(photos_abs):  # the same photos, moved: the workspace now names their folder
            console.print(f"[yellow]note:[/] the photos were at {existing.photos}; the same photos (by content) are "
                          f"now at {photos_abs}")
            existing.photos = str(photos_abs)
            write_report(workspace, existing)
        return existing
    # Our own failed run on the same photos is redone without asking: there is nothing to lose.
    redo_failed = existing is not None and (existing.photos == str(photos_abs) or same_input) and not existing.success
    if not cfg.overwrite and not redo_failed:
        only_added = True  # (what --extend can take: photos added, nothing else changed)
        if existing is not None:
            what = (f"a workspace made from other photos{' or masks' if cfg.masks is not None else ''} "
                    f"({existing.photos})" if not same_input
                    else "a workspace made with other options"
                    + (f" ({changed})" if (changed := _option_changes(existing.options, cfg)) else ""))
            if not same_input and existing.photos == str(photos_abs) and scan is not None:
                # the same folder, its photos or masks changed since (one added, say): say how, not "other photos"
                added, changes = _folder_changes(existing, scan, cfg)
                only_added = bool(added) and len(changes) == 1
                what = "a workspace made from this folder's photos as they were then: " + "; ".join(changes)
        else:
            what = "other files (not an uncertsplat workspace)"
        # (--extend only adds photos: not offered where some are gone or changed, or the masks)
        grown = (existing is not None and existing.success and existing.photos == str(photos_abs)
                 and (workspace / "distorted" / "sparse" / "0").is_dir() and only_added)
        raise UserError(f"the output folder already holds {what}", path=workspace,
                        hint="Choose another output folder, or pass --overwrite to replace it"
                             + ("; photos added to the folder join the workspace with --extend, every camera there "
                                "kept (a run trained on it can then train on them)." if grown else "."))
    # masks/ is this stage's only when --masks wrote it: masks drawn by hand on the workspace's images stay
    ours = [n for n in _OWNED if n != "masks" or (existing is not None and existing.options.get("masks"))]
    if "masks" not in ours and (workspace / "masks").is_dir() and cfg.masks is None and existing is not None:
        console.print(f"[yellow]note:[/] {esc(str(workspace / 'masks'))} is kept (reconstruct did not make it): its "
                      "masks were drawn on the images the workspace had, which are made again now; check that they "
                      "still fit them")
    # a finished workspace is moved aside, not deleted, until the new one has finished (``_overwrite_kept``): an
    # --overwrite that fails (too few photos registered with the new options), is stopped or killed puts it back.
    # Masks drawn by hand that --masks is to replace go aside with it.
    if existing is not None and existing.success and (workspace / "sparse" / "0").is_dir():
        names = [*ours, *(["masks"] if cfg.masks is not None and "masks" not in ours else [])]
        there = [n for n in names if (workspace / n).exists() or (workspace / n).is_symlink()]
        moving = workspace / OVERWRITE_MOVING
        moving.mkdir()
        # (the names the new run may write, so that putting the old one back removes exactly the new run's files)
        atomic_write_json(moving / OVERWRITE_PLAN, {"moved": there, "absent": [n for n in names if n not in there]})
        for name in there:
            (workspace / name).rename(moving / name)
        moving.rename(workspace / OVERWRITE_OLD)  # (all of it aside: the new run may begin)
        return None
    for name in ours:
        _remove(workspace / name)
    return None


DISK_FULL_BYTES = 64 * 2**20
"""Below this much free space on its disk, an error of COLMAP's in a workspace is taken for a full disk."""


def _free_bytes(folder: Path) -> int | None:
    """The free bytes on the disk that holds ``folder`` (or its nearest existing parent); None where it cannot say."""
    for place in (folder, *folder.parents):
        if place.exists():
            try:
                return shutil.disk_usage(place).free
            except OSError:
                return None
    return None


def _remove(target: Path) -> None:
    """Delete a file, link or folder if it is there."""
    if target.is_dir() and not target.is_symlink():
        shutil.rmtree(target)
    elif target.exists() or target.is_symlink():
        target.unlink()


def _recover_overwrite(workspace: Path) -> str | None:
    """Finish what an --overwrite left (failed, stopped or killed at any point; itself stopped and run again):

    - ``OVERWRITE_MOVING``: stopped while the old files went aside: the new run never began, they go back;
    - ``OVERWRITE_OLD``: the new run began: finished (its report says success; only the last rename was left), the old
      files go; else the new run's files (the plan's names) go, then ``OVERWRITE_RESTORING``;
    - ``OVERWRITE_RESTORING``: the old files go back, each one still there (a stop between two is run again);
    - ``OVERWRITE_DONE``: a finished one's old files, removed.

    Returns "restored" (the old workspace is back), "finished" (the new one stands) or None (nothing left)."""
    shutil.rmtree(workspace / OVERWRITE_DONE, ignore_errors=True)
    moving, old, back = (workspace / n for n in (OVERWRITE_MOVING, OVERWRITE_OLD, OVERWRITE_RESTORING))
    if old.is_dir():
        try:
            report = load_report(workspace)
        except UserError:  # (damaged: not a finished one)
            report = None
        if report is not None and report.success:
            _drop(workspace / OVERWRITE_OLD, workspace / OVERWRITE_DONE)
            return "finished"
        plan = read_json(old / OVERWRITE_PLAN)
        for name in [*plan["moved"], *plan["absent"]]:  # the new run's (the old ones are aside)
            _remove(workspace / name)
        old.rename(back)
    elif moving.is_dir():  # (nothing in place is the new run's: only what went aside comes back)
        moving.rename(back)
    if not back.is_dir():
        return None
    for part in back.iterdir():
        target = workspace / part.name
        if part.name != OVERWRITE_PLAN and not (target.exists() or target.is_symlink()):
            part.rename(target)
    shutil.rmtree(back)
    return "restored"


def _drop(folder: Path, done: Path) -> None:
    """Delete ``folder`` in one step that cannot leave a half: renamed ``done`` first (a leftover ``done`` of an
    earlier one removed), then removed (a kill while it is removed leaves only ``done``, dropped later): ``extend``'s
    staging folder (its report marker and the originals go together), an --overwrite's old workspace."""
    shutil.rmtree(done, ignore_errors=True)
    folder.rename(done)
    shutil.rmtree(done, ignore_errors=True)


@contextlib.contextmanager
def _overwrite_kept(workspace: Path, state: dict):
    """Around a reconstruction in ``workspace`` (inside its lock): an --overwrite's old workspace goes once the new one
    has finished (its report written), and comes back when it fails or is stopped, the new run's report kept as
    ``FAILED_REPORT_NAME`` beside it (what failed, and why); ``state["restored"]`` then says so."""
    try:
        yield
    except BaseException:
        if (workspace / OVERWRITE_MOVING).is_dir() or (workspace / OVERWRITE_OLD).is_dir():
            new = workspace / REPORT_NAME  # (the new run's only once everything old is aside)
            failed = new.read_bytes() if (workspace / OVERWRITE_OLD).is_dir() and new.is_file() else None
            state["restored"] = _recover_overwrite(workspace) == "restored"
            if state["restored"]:
                if failed is not None:
                    with contextlib.suppress(OSError):  # (never in place of the error that stopped the run)
                        atomic_write_bytes(workspace / FAILED_REPORT_NAME, failed)
                console.print(f"[yellow]note:[/] the workspace --overwrite was to replace is back in {workspace}, as "
                              "it was" + (f" (this run's report: {workspace / FAILED_REPORT_NAME})" if failed else ""))
        raise
    if (workspace / OVERWRITE_OLD).is_dir():
        _drop(workspace / OVERWRITE_OLD, workspace / OVERWRITE_DONE)


def resized_note(groups: dict[tuple[int, int], list[str]], max_side: int) -> str | None:
    """The note for photos (``PhotoScan.size_groups``) larger than ``max_side`` pixels on their longest side, which
    feature extraction and undistortion shrink to it: the workspace's images, and so every ``scene.downscale`` of
    ``train``, start from that size, not the photos'. None when every photo fits."""
    big = {size: names for size, names in groups.items() if max(size) > max_side}
    if not big:
        return None
    count = sum(len(n) for n in big.values())
    w, h = max(big, key=max)
    f = max_side / max(w, h)
    return (f"{count} photo(s) larger than max_image_size ({max_side} px on the longest side; up to {w}x{h}) are "
            f"resized to it in the workspace's images ({round(w * f)}x{round(h * f)}), and `train`'s scene.downscale "
            f"divides that size (the paper preset's 1/8 trains at about {round(w * f / 8)}x{round(h * f / 8)}, "
            "undistortion crops a few pixels); "
            "--max-image-size N keeps more pixels (slower SfM and training)")


def disagreement_note(summaries: list[dict], kept: int, needed: float) -> str:
    """The note for a kept mapping run that no other run of its options confirms (``sfm.agreeing`` False): every run,
    and the runs that did agree among themselves, with why they were not kept."""
    def label(a: dict) -> str:
        return f"seed {a['seed']}{' (relaxed)' if a['relaxed'] else ''}"

    runs = "; ".join(f"{label(a)}: {a['num_images']} images, {a['num_observations']} observations, focal {_focals(a)}"
                     for a in summaries)
    pairs = [(i, j) for i in range(len(summaries)) for j in range(i + 1, len(summaries))
             if summaries[i]["relaxed"] == summaries[j]["relaxed"] and sfm.attempts_agree(summaries[i], summaries[j])]
    text = (f"no other mapping run of the same options found the kept run's geometry ({label(summaries[kept])}, which "
            "explains the most feature observations of the runs that registered enough images)")
    if pairs:
        i, j = pairs[0]
        a = summaries[i]
        why = (f"registered {a['num_images']} images, fewer than needed ({math.ceil(needed)}, --min-registered)"
               if a["num_images"] < needed else "explain fewer feature observations")
        text += f"; {label(a)} and {label(summaries[j])} agree with each other but {why}"
    return (f"{text} ({runs}). Check the poses (train warns when it cannot fit its own views) or raise "
            "--mapping-attempts")


def far_registration_note(far: dict[str, float], counts: dict[str, int]) -> str:
    """The note naming the photos left out as registered far outside the capture on few points
    (``sfm.far_weak_registrations``: name -> distance in median photo distances; ``counts``: their observations)."""
    return ("left out of the model: " + list_names([f"{n} ({r:.0f}x the median photo's distance from the capture's "
                                                    f"middle, on {counts.get(n, 0)} points)" for n, r in far.items()])
            + ": a pose on so few points so far outside the capture is not where the photo was taken (a mirrored or "
              "edited photo, or one of another scene); trained on, it would grow a ghost scene and shrink the run's "
              "frame. If it is a real photo from far away, add photos between it and the others")


def weak_registration_note(weak: dict[str, int], cfg: ReconstructConfig) -> str:
    """The note naming the weakly registered photos (``sfm.weakly_registered``: name -> feature observations); it
    suggests only the matching options this run did not use."""
    options = ([] if cfg.features == "dsp-sift" else ["--features dsp-sift"]) + (
        [] if cfg.guided_matching else ["--set guided_matching=true"])
    return ("weakly registered (their poses rest on fewer than a fifth of the median photo's feature observations): "
            + list_names([f"{n} ({c})" for n, c in weak.items()]) + "; "
            + (f"photos far apart match better with {' '.join(options)}, or add " if options else "add ")
            + "photos between these and their neighbours")


OWN_CAMERA = "a photo that does not fit the camera it shares"
OWN_CAMERA_ROUNDS = 3
"""At most this many photos get a camera of their own (``sfm.focal_outliers``), one per mapping again."""


def own_camera_note(odd: dict[str, float], shared: str, model) -> str:
    """The note for the photos ``sfm.focal_outliers`` found (name -> own / shared focal length); ``shared``: the
    shared camera's focal length before (``_focals``); ``model``: the model mapped again with their own cameras, or
    None when that registered fewer photos and the model before was kept."""
    each = ", ".join(f"{name} {100 * (r - 1):+.0f} %" for name, r in odd.items())
    what = (f"{OWN_CAMERA} with the other photos of its size: {each} (the focal length each fits alone, against "
            f"the others'; a crop saved at full size, a digital zoom or another camera), which bends every photo's "
            f"focal length towards its own (shared: {shared})")
    if model is None:
        return (what + "; mapped again with a camera of its own, fewer photos registered, so the model where it "
                "shares the camera is kept: leave such photos out, or run with --per-image-camera")
    own = {model.image(i).camera_id for i in model.reg_image_ids() if model.image(i).name in odd}
    used = {model.image(i).camera_id for i in model.reg_image_ids()} - own
    px = ", ".join(f"{model.cameras[c].mean_focal_length():.0f}" for c in sorted(own))
    now = ", ".join(f"{model.cameras[c].mean_focal_length():.0f}" for c in sorted(used))
    return what + (f"; mapped again with a camera of its own ({px} px): the others' focal length is now {now} px"
                   if own else "; mapped again with a camera of its own, it did not register (the others' focal "
                   f"length is now {now} px)")


def registration_hints(model_sizes: list[int], matcher: str, n: int, cfg: ReconstructConfig) -> list[str]:
    """What to try when too few of the ``n`` photos registered: the causes this run shows first (mapping split the
    photos into groups of ``model_sizes`` images; images made smaller than features need), then the general ones."""
    hints = []
    if len(model_sizes) > 1:  # the photos form groups that share too few matches
        hints.append(f"mapping split the photos into {len(model_sizes)} groups ({', '.join(map(str, model_sizes))} "
                     "images; reconstruct_report.json: models): add photos that link the groups")
    if cfg.max_image_size < 800:
        hints.append(f"raise --max-image-size (now {cfg.max_image_size} px: small images give few features)")
    hints += ["take more photos with more overlap between neighbours", "use sharper images (no motion blur)"]
    if matcher == "exhaustive" and n > 50:
        hints.append("for video frames try --matcher sequential")
    elif matcher == "sequential":
        hints.append("for unordered photos try --matcher exhaustive")
    hints.append(f"or lower --min-registered (now {cfg.min_registered})")
    return hints


def _model_facts(report: ReconstructReport, model) -> None:
    """The kept model's points, reprojection error, track length, observations and cameras into ``report``."""
    stats = sfm.model_stats(model)
    for key in ("num_points3d", "mean_reprojection_error", "mean_track_length", "mean_observations_per_image",
                "num_observations"):
        setattr(report, key, stats[key])
    report.cameras = sfm.camera_summaries(model)


def run(photos: Path, workspace: Path, cfg: ReconstructConfig) -> ReconstructReport:
    """Run SfM on ``photos`` and write an undistorted workspace plus ``reconstruct_report.json``.

    Returns the report. On failure (too few images registered, no overlap) the report is written
    with ``success: false`` first, then a UserError lists the unregistered images and what to try.
    """
    photos, workspace = Path(photos), Path(workspace)
    # an --extend stopped or killed: the workspace as it was (or grown), before any check of it
    if (workspace / EXTEND_DIR).exists() or (workspace / EXTEND_DONE).exists():
        with run_lock(workspace, "reconstruct"):
            _recover_extend(workspace)
    # an --overwrite killed before it finished: the workspace it was replacing, back
    if any((workspace / n).exists() for n in (OVERWRITE_MOVING, OVERWRITE_OLD, OVERWRITE_RESTORING, OVERWRITE_DONE)):
        with run_lock(workspace, "reconstruct"):
            if _recover_overwrite(workspace) == "restored":
                console.print(f"[yellow]note:[/] an earlier --overwrite of {workspace} was stopped before it finished: "
                              "the workspace it was replacing is back")
    if cfg.masks is not None:
        if cfg.masks.resolve() == Path(photos).resolve():
            raise UserError("--masks names the photo folder itself: every photo would be its own mask",
                            path=cfg.masks, hint="Keep the masks in a folder of their own.")
        if not cfg.masks.is_dir():
            raise UserError("the masks folder does not exist" if not cfg.masks.exists() else
                            "--masks needs a folder of masks, one per photo", path=cfg.masks,
                            hint="Give the folder that holds the photos' masks (IMG_1.jpg.png, IMG_1.jpg or IMG_1.png "
                                 "for IMG_1.jpg).")
        cfg = cfg.model_copy(update={"masks": cfg.masks.resolve()})  # (recorded: the same folder from anywhere)
    if cfg.extend:
        return extend(photos, workspace, cfg)
    watch = sfm.Stopwatch()
    t_start = time.perf_counter()
    with watch("scan"):
        scan = sfm.scan_photos(photos, masks=cfg.masks)
        fingerprint = _inputs_fingerprint(scan, cfg.masks)
    _check_output_path(photos, workspace)

    pyv, colv = sfm.versions()
    weak_note = ""  # the photos registered from few points, printed again after the summary
    featureless: list[str] = []  # photos with no keypoint at all (blank, black, out of focus): named with the unregistered
    report = ReconstructReport(
        success=False, photos=str(photos.resolve()), inputs_fingerprint=fingerprint,
        photo_sha256=scan.photo_hashes(), images_found=scan.names, images_unregistered=scan.names, ignored=scan.ignored, notes=list(scan.notes),
        pycolmap_version=pyv, colmap_version=colv,
        options=cfg.model_dump(mode="json", exclude={"overwrite", "extend"}),
    )
    for note in scan.notes:
        console.print(f"[yellow]note:[/] {note}")
    groups = scan.size_groups()
    report.image_sizes = {f"{w}x{h}": len(n) for (w, h), n in groups.items()}
    large = resized_note(groups, cfg.max_image_size)
    if large:
        report.notes.append(large)
        console.print(f"[yellow]note:[/] {large}")
    if len(groups) > 1:
        # train fits them to one size (sfm.scene: scene.photo_sizes); say so before the mapping's minutes
        sizes = "; ".join(f"{k}: {v}" for k, v in sorted(report.image_sizes.items(), key=lambda kv: -kv[1]))
        note = (f"{len(groups)} image sizes found ({sizes})" + ("; one camera per size" if cfg.single_camera else "")
                + ": `train` fits the photos to the most common size (photos of the other orientation turned, "
                "other resolutions of the same shape resized, a few pixels cropped, other shapes left out; "
                "scene.photo_sizes)")
        report.notes.append(note)
        console.print(f"[yellow]note:[/] {note}")
    cameras = scan.camera_groups()
    if cfg.single_camera and len(cameras) > len(groups):  # one size, two lenses: a camera each
        split = {(w, h) for (w, h, lens) in cameras if lens}  # (a size of one lens keeps the key "")
        lenses = "; ".join(f"{w}x{h} {lens}: {len(n)}" for (w, h, lens), n in cameras.items() if (w, h) in split)
        note = (f"photos of one size name several cameras or lenses in their EXIF ({lenses}): one COLMAP camera "
                "each (--per-image-camera gives every photo its own)")
        report.notes.append(note)
        console.print(f"[yellow]note:[/] {note}")

    def fail(message: str, hint: str) -> UserError:
        report.success = False
        report.message = message
        report.stage_seconds = dict(watch.seconds)
        report.total_seconds = round(time.perf_counter() - t_start, 3)
        write_report(workspace, report)
        # (an --overwrite's report is kept beside the workspace it was to replace, which comes back: _overwrite_kept)
        kept = workspace / (FAILED_REPORT_NAME if (workspace / OVERWRITE_OLD).is_dir() else REPORT_NAME)
        return UserError(f"{message} (report: {kept})", path=photos, hint=hint)

    n = len(scan.photos)
    distorted = workspace / "distorted"
    database = workspace / "database.db"
    overwrite = {"restored": False}  # (_overwrite_kept: whether a stop put back the workspace it was replacing)
    try:
        with run_lock(workspace, "reconstruct"), sfm.colmap_logging(), _overwrite_kept(workspace, overwrite):
            reused = _prepare_workspace(photos, workspace, cfg, (fingerprint, scan.legacy_fingerprint()), scan)
            if reused is not None:
                console.print(f"reconstruct: {workspace} already holds this reconstruction ({reused.summary()}); "
                              "nothing to do (pass --overwrite to redo it)")
                return reused
            # the report first, marked unfinished: a run stopped by Ctrl-C leaves a workspace that the same command
            # recognises as its own and starts over in (_prepare_workspace: redo_failed)
            report.message = UNFINISHED
            write_report(workspace, report)
            report.message = ""
            sfm.set_seed(cfg.seed)
            with watch("stage_inputs"):
                image_dir, rotated = sfm.stage_inputs(scan, distorted / "input")
                mask_dir = None
                if cfg.masks is not None:
                    mask_dir = distorted / "masks"
                    without = sfm.stage_masks(scan, cfg.masks, mask_dir)
                    from uncertsplat.sfm.scene import mask_names, masks_note

                    if len(without) == len(scan.photos):

                        raise UserError(f"the folder holds no mask named for any photo ({mask_names(scan.names[0])})",
                                        path=cfg.masks, hint="Name each mask after its photo.")
                    missing = set(without)
                    note = masks_note(scan.names, [None if p in missing else p for p in scan.names],
                                      f"in {cfg.masks}")
                    report.notes.append(note)
                    console.print(f"[yellow]note:[/] {esc(note)}")
            report.rotated = rotated
            if rotated:  # (a phone's portrait photos: said, as the other notes on the photos are)
                report.notes.append(_exif_note(rotated))
                console.print(f"[yellow]note:[/] {esc(report.notes[-1])}")
            matcher = sfm.resolve_matcher(cfg, n)
            pairs = sfm.image_pairs(scan.names, matcher)
            report.matcher = matcher

            with progress() as bar:
                # ---- features
                task = bar.add_task("features", total=n, info="")
                with watch("extract"):
                    keypoints = sfm.extract_features(database, image_dir, cameras, cfg,
                                                     advance=lambda k, s: bar.update(task, advance=k, info=s),
                                                     masks=mask_dir)
                missing = [name for name in scan.names if name not in keypoints]
                if missing:
                    raise fail(f"COLMAP could not read {len(missing)} image(s): {list_names(missing)}",
                               "Re-export these files as JPEG or PNG, or remove them.")
                featureless = sorted(name for name, k in keypoints.items() if k == 0)
                bar.update(task, info=f"{sum(keypoints.values())} keypoints")
                if featureless:
                    report.notes.append(f"no features found in: {list_names(featureless)}")

                # ---- matching
                task = bar.add_task(f"matching ({matcher})", total=len(pairs), info="")
                with watch("match"):
                    report.num_verified_pairs = sfm.match_features(
                        database, pairs, cfg, distorted, advance=lambda k, s: bar.update(task, advance=k, info=s))

                # ---- mapping: runs with other seeds until two agree, relaxed options when too few images register
                needed = cfg.min_registered * n

                def mapping(db: Path, again: str = "") -> tuple[list[sfm.MappingResult], list[dict], int]:
                    results: list[sfm.MappingResult] = []
                    summaries: list[dict] = []  # sfm.attempt_summary of each result, made once
                    for relaxed in (False, True):
                        for attempt in range(cfg.mapping_attempts):
                            seed = cfg.seed + attempt
                            label = (("mapping (relaxed)" if relaxed else "mapping") + again
                                     + (f", seed {seed}" if attempt else ""))
                            task = bar.add_task(label, total=n, info="")
                            with watch("map"):
                                result = sfm.map_incremental(
                                    db, image_dir, distorted / "models", cfg, relaxed, seed=seed,
                                    advance=lambda k, s, t=task: bar.update(t, advance=k, info=s))
                            results.append(result)
                            summaries.append(sfm.attempt_summary(result))
                            bar.update(task, completed=result.num_registered, info=f"{result.num_registered} "
                                       f"registered, {summaries[-1]['num_observations']} observations")
                            if result.best is None:
                                break  # no initial pair: another seed of the same options finds none either
                            if sfm.agreeing(summaries, len(summaries) - 1):
                                break
                        if max(r.num_registered for r in results) >= needed or report.num_verified_pairs == 0:
                            break
                    return results, summaries, sfm.choose_attempt(summaries, needed)

                results, summaries, kept = mapping(database)
                result = results[kept]
                # a photo that does not fit the camera it shares (a crop saved at full size, a digital zoom) bends
                # every photo's focal length towards its own: mapped again with a camera of its own. One photo per
                # round, the farthest out: the bent model put a second bonsai photo 4 % off beside a crop's 8 %, and
                # it fits the shared camera again once the crop has its own
                own: dict[str, float] = {}
                shared, refused = _focals(summaries[kept]), None
                for _ in range(OWN_CAMERA_ROUNDS if cfg.single_camera else 0):
                    found = sfm.focal_outliers(result.best) if result.best is not None else {}
                    if not found:
                        break
                    worst = max(found, key=lambda name: abs(math.log(found[name])))
                    trial = workspace / OWN_CAMERAS_DB  # the database the kept model was mapped from stays
                    shutil.copy2(database, trial)
                    sfm.own_cameras(trial, [worst])
                    again = mapping(trial, ", own camera")
                    if again[0][again[2]].num_registered < result.num_registered:
                        trial.unlink()
                        refused = {worst: found[worst]}
                        break
                    results, summaries, kept = again
                    result = results[kept]
                    trial.replace(database)
                    own[worst] = found[worst]
                if own:
                    report.notes.append(own_camera_note(own, shared, result.best))
                if refused:
                    report.notes.append(own_camera_note(refused, _focals(summaries[kept]), None))
                report.retried_relaxed = any(r.relaxed for r in results)
                report.mapping_attempts = [MappingAttempt(**a, kept=(i == kept)) for i, a in enumerate(summaries)]
                report.mapping_agreed = sfm.agreeing(summaries, kept) \
                    if cfg.mapping_attempts > 1 and result.best is not None else None
                if report.mapping_agreed is False:
                    report.notes.append(disagreement_note(summaries, kept, needed))

            shutil.rmtree(distorted / "models", ignore_errors=True)
            report.models_found = len(result.models)
            report.models = [ModelSummary(index=i, num_images=m.num_reg_images(), num_points3d=m.num_points3D(),
                                          image_names=sfm.registered_names(m), kept=(i == 0))
                             for i, m in enumerate(result.models)]
            best = result.best
            far: dict[str, float] = {}
            if best is not None:
                weak = sfm.weakly_registered(best)
                # a pose on a few points far outside the capture is not where the photo was taken: left out before
                # the model is written, so that no stage trains on it or takes its distance for the rig's size
                far = sfm.far_weak_registrations(best, weak)
                if far:
                    sfm.leave_out(best, list(far))
                    report.notes.append(far_registration_note(far, weak))
                    report.models[0].image_names = sfm.registered_names(best)  # (the kept model, as written)
                    report.models[0].num_images = best.num_reg_images()
                    weak = {k: v for k, v in weak.items() if k not in far}
                    console.print(f"[yellow]warning:[/] {report.notes[-1]}")
            registered = sfm.registered_names(best) if best is not None else []
            report.images_registered = registered
            report.images_unregistered = sorted(set(scan.names) - set(registered))
            report.registered_fraction = len(registered) / n
            if best is not None:
                _model_facts(report, best)
                if weak:
                    weak_note = weak_registration_note(weak, cfg)
                    report.notes.append(weak_note)
            if len(result.models) > 1:
                # COLMAP's later models may re-use photos of the first: only the ones no kept model has are lost
                kept = {im.name for im in result.models[0].images.values() if im.has_pose}
                others = {im.name for m in result.models[1:] for im in m.images.values() if im.has_pose}
                lost = sorted(others - kept)
                report.notes.append(f"mapping made {len(result.models)} models; kept the largest "
                                    f"({result.models[0].num_reg_images()} images), the others hold "
                                    f"{[m.num_reg_images() for m in result.models[1:]]} images"
                                    + (f", {len(lost)} of them in no kept model: {list_names(lost)}" if lost
                                       else ", all of them in the kept model too"))

            if best is None:
                why = ("no image pair shares enough matching features" if report.num_verified_pairs == 0
                       else "no initial image pair could be found")
                raise fail(f"no model could be built: {why}; 0/{n} images registered",
                           "The photos must overlap: take photos of one scene from nearby viewpoints with "
                           "60-80% overlap between neighbours, avoid blur and textureless surfaces.")
            if len(registered) < needed:
                hints = registration_hints([m.num_reg_images() for m in result.models], matcher, n, cfg)
                blank = [name for name in featureless if name in set(report.images_unregistered)]
                if blank:  # no photo of the scene: nothing to match, whatever the options
                    hints = [f"leave out {list_names(blank)} (no features at all: a blank, black or featureless "
                             "photo)", *hints]
                raise fail(f"only {len(registered)}/{n} images registered (below --min-registered "
                           f"{cfg.min_registered}); unregistered: {list_names(report.images_unregistered)}"
                           + (f" ({list_names(blank)}: no features found at all, a blank, black or featureless "
                              "photo)" if blank else ""),
                           "Try: " + "; ".join(hints) + ".")

            model_dir = distorted / "sparse" / "0"
            model_dir.mkdir(parents=True, exist_ok=True)
            best.write(model_dir)
            with console.status(f"undistorting {len(registered)} images"), watch("undistort"):
                report.undistorted_size = sfm.undistort(model_dir, image_dir, workspace, cfg)
                if mask_dir is not None:  # the photos' masks as their images are: undistorted the same way
                    sfm.undistort_masks(model_dir, workspace / "sparse" / "0", mask_dir, workspace / "masks",
                                        skip=without)

            report.ground_truth = _against_ground_truth(photos, workspace)
            report.success = True
            report.message = "" if not report.images_unregistered else (
                f"{len(report.images_unregistered)} image(s) not registered: {list_names(report.images_unregistered)}")
            report.stage_seconds = dict(watch.seconds)
            report.total_seconds = round(time.perf_counter() - t_start, 3)
            write_report(workspace, report)
    except RuntimeError as err:
        # COLMAP's own errors on a full disk ("No registered database factory succeeded", a write that failed): said
        # as the disk, not as COLMAP's traceback
        room = _free_bytes(workspace)
        if room is None or room >= DISK_FULL_BYTES:
            raise
        raise UserError(f"COLMAP failed ({str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__}) "
                        f"with {room / 1e6:.0f} MB left on the disk that holds the workspace: the disk is full",
                        path=workspace, hint="Free some space (or choose an output folder on another disk), then run "
                                             "the same command again.") from None
    except KeyboardInterrupt:
        if overwrite["restored"]:
            raise Interrupted("reconstruct interrupted; the workspace --overwrite was to replace is back as it was",
                              path=workspace, hint="Run the same command again to start over.") from None
        raise Interrupted("reconstruct interrupted; the unfinished workspace is replaced when the same command runs "
                          "again", path=workspace, hint="Run the same command again to start over.") from None
    console.print(f"reconstruct: {report.summary()} -> {workspace}")
    for stage, sec in report.stage_seconds.items():
        console.print(f"  {stage:<13} {sec:8.2f} s")
    if len(report.mapping_attempts) > 1:
        runs = ", ".join(f"seed {a.seed}{' relaxed' if a.relaxed else ''}: {a.num_observations:,} observations"
                         f"{'' if not a.focal_lengths else ' at ' + _focals(a.model_dump())} in {_secs(a.seconds)}"
                         f"{' (kept)' if a.kept else ''}" for a in report.mapping_attempts)
        verdict = {True: "agreed", False: "[yellow]disagreed[/]", None: "one run of these options"}[report.mapping_agreed]
        console.print(f"  mapping runs ({verdict}): {runs}")
    if report.mapping_agreed is False:
        console.print("[yellow]warning:[/] the mapping runs found different geometries; the kept one explains the most "
                      "feature observations (reconstruct_report.json: mapping_attempts)")
    if report.images_unregistered:
        blank = [name for name in featureless if name in set(report.images_unregistered)]
        console.print(f"[yellow]warning:[/] not registered: {list_names(report.images_unregistered)}"
                      + (f" ({list_names(blank)}: no features found at all, a blank, black or featureless photo)"
                         if blank else ""))
    if weak_note:
        console.print(f"[yellow]note:[/] {weak_note}")
    for note in report.notes:
        if note.startswith(OWN_CAMERA):
            console.print(f"[yellow]warning:[/] {note}")
    if report.ground_truth:
        g = report.ground_truth
        console.print(f"  against the synthetic scene's GT cameras: centres {g['centre_error_mean_pct']:.3f} % of the "
                      f"rig radius (max {g['centre_error_max_pct']:.3f} %), rotations {g['rotation_error_mean_deg']:.3f} "
                      f"deg (max {g['rotation_error_max_deg']:.3f}), focal {g['focal_error_mean_pct']:.2f} %")
    return report


EXTEND_DONE = ".extend_done"
"""``EXTEND_DIR`` renamed once nothing in it is needed, then removed."""
_SWAPPED = (Path("distorted") / "sparse" / "0", Path("sparse") / "0", Path("images"), Path("database.db"))


def _swap_in(workspace: Path, stage_dir: Path, report: ReconstructReport, staged_input: bool,
             masks: bool = False) -> None:
    """Move the grown parts from ``stage_dir`` into ``workspace``, each original first to ``stage_dir/old`` (where
    ``_recover_extend`` finds them if this stops half way), the report that names them last, then drop the
    originals. ``masks``: ``stage_dir/masks`` too (``_grown_masks``); a workspace without masks/ before gets a marker
    ``old/NO_MASKS`` first, so that a stop takes the new folder out again."""
    if staged_input:  # rotated copies of EXIF-tagged photos, as `run` keeps them (a superset of the ones there)
        target = workspace / "distorted" / "input"
        if target.exists():
            shutil.rmtree(target)
        (stage_dir / "input").rename(target)
    write_report(stage_dir, report)
    if masks and not (workspace / "masks").exists():
        (stage_dir / "old").mkdir(exist_ok=True)
        (stage_dir / "old" / NO_MASKS).touch()
    for part in (*_SWAPPED, *([Path("masks")] if masks else []), Path(REPORT_NAME)):  # the report last: once it is
        # in, the swap is complete
        aside = stage_dir / "old" / part
        aside.parent.mkdir(parents=True, exist_ok=True)
        if (workspace / part).exists():  # (masks/: absent in a workspace made without them)
            (workspace / part).rename(aside)
        (stage_dir / part).rename(workspace / part)
    _drop(workspace / EXTEND_DIR, workspace / EXTEND_DONE)


NO_MASKS = "NO_MASKS"
"""``_swap_in``'s marker in ``EXTEND_DIR/old``: the workspace had no masks/ before the extension gave it one."""


def _extension_masks(recorded: Path | None, given: Path | None, workspace: Path,
                     registered: list[str]) -> Path | None:
    """The folder ``reconstruct --extend`` reads the photos' masks from: the one the workspace was made with
    (``recorded``, its report's options) while it is there, else ``--masks`` (``given``); None for none.

    Raises:
        UserError: ``given`` is another folder than the workspace's own, which is still there (a workspace reads its
            photos' masks from one folder: later extensions and the reuse of the workspace go by it); for a
            workspace made without masks, ``given`` holds masks of photos already there (``registered``: their
            features were taken without them; only a new reconstruction takes them in), or the workspace has a
            masks/ drawn by hand (reconstruct would own it from then on, and replace it with the next --overwrite).
    """
    from uncertsplat.sfm.scene import mask_file

    if given is not None and recorded is not None and Path(recorded).is_dir() \
            and Path(given).resolve() != Path(recorded).resolve():
        raise UserError(f"--masks {given}: the workspace was made with the masks in {recorded}, and reads the new "
                        "photos' masks from there", path=given,
                        hint=f"Put the new photos' masks into {recorded} and run --extend without --masks.")
    if recorded is not None and Path(recorded).is_dir():
        return Path(recorded)
    if given is None:
        return None
    if recorded is None:
        old = [n for n in registered if mask_file(given, n) is not None]
        if old:
            raise UserError(f"--masks {given} holds masks of {len(old)} photo(s) the workspace was made without masks "
                            f"({list_names(old)}): --extend adds only the new photos' masks", path=given,
                            hint="Reconstruct all the photos with --masks into a new workspace (or --overwrite), or "
                                 "give --extend a folder that holds only the new photos' masks.")
        if (workspace / "masks").is_dir():
            raise UserError("the workspace has a masks/ folder that reconstruct did not make (masks drawn on its "
                            "images): --extend --masks would take it over", path=workspace / "masks",
                            hint="Draw the new photos' masks into it by hand as well, on their images once --extend "
                                 "without --masks has added them.")
    return Path(given)


def _grown_masks(workspace: Path, stage_dir: Path, model_dir: Path, staged: Path, without: list[str],
                 registered: list[str], source: Path) -> None:
    """``stage_dir/masks``: the ``staged`` masks (``sfm.stage_masks``, of every photo) undistorted as their images
    (``sfm.undistort_masks``, from the grown distorted model ``model_dir`` to ``stage_dir/sparse/0``); a photo in
    ``without`` gets none. The photos already there (``registered``) must come out as the workspace has them, as
    their images must: a mask edited or added since in ``source`` (the user's folder) would be a silent change of a
    training view.

    Raises:
        UserError: the masks of photos already in the workspace changed since it was made, naming them.
    """
    out = stage_dir / "masks"
    sfm.undistort_masks(model_dir, stage_dir / "sparse" / "0", staged, out, skip=without)
    out.mkdir(exist_ok=True)

    def content(folder: Path, name: str) -> bytes | None:
        path = folder / f"{name}.png"
        return path.read_bytes() if path.is_file() else None

    changed = [n for n in registered if content(workspace / "masks", n) != content(out, n)]
    if changed:
        raise UserError(f"the masks of {len(changed)} photo(s) already in the workspace changed since it was made "
                        f"({list_names(changed)}): the workspace is unchanged", path=source,
                        hint="Put back the masks as they were, or reconstruct again with them into a new workspace.")


def _recover_extend(workspace: Path) -> bool:
    """Clear what an ``extend`` left (stopped, or killed): once its report was swapped in, the grown workspace is
    complete and only the staging folder goes; before, every part it had moved aside goes back (the grown one in its
    place is dropped), so the workspace is the one it started from. Returns whether the workspace is the grown one."""
    stage_dir = workspace / EXTEND_DIR
    shutil.rmtree(workspace / EXTEND_DONE, ignore_errors=True)  # a finished one's leftovers
    if not stage_dir.exists():
        return False
    grown = (stage_dir / "old" / REPORT_NAME).exists()
    if grown:
        # every part was in when the report's swap began: finish it (killed between its two moves, the workspace had
        # no report at all)
        if (stage_dir / REPORT_NAME).exists() and not (workspace / REPORT_NAME).exists():
            (stage_dir / REPORT_NAME).rename(workspace / REPORT_NAME)
    else:
        if (stage_dir / "old" / NO_MASKS).exists():  # (a masks/ the extension brought in: out again)
            shutil.rmtree(workspace / "masks", ignore_errors=True)
        for part in (*_SWAPPED, Path("masks")):
            aside = stage_dir / "old" / part
            if aside.exists():
                _remove(workspace / part)
                aside.rename(workspace / part)
    _drop(workspace / EXTEND_DIR, workspace / EXTEND_DONE)
    return grown


def extend(photos: Path, workspace: Path, cfg: ReconstructConfig) -> ReconstructReport:
    """Register the photos in ``photos`` that ``workspace`` (made by ``run``) does not hold into its model, every
    camera already there kept where it is (``sfm.map_into``: poses and intrinsics held fixed), with the
    workspace's own options (its report's); a run trained on the workspace then trains on them with
    ``train --resume --add-views`` (its frame and held-out views stay). Features and matches are computed for the new
    photos only (each against every photo); the images are undistorted again. The workspace is changed only at the
    end, once the new model is checked (a failure or Ctrl-C before leaves it as it was). Called by ``run`` with
    ``cfg.extend``, once it has undone an extension that was stopped.

    Raises:
        UserError: not a finished workspace of this stage, the photo folder lacks photos the workspace registered,
            no new photo, none of them registered, or a camera already there moved.
    """
    photos, workspace = Path(photos), Path(workspace)
    existing = load_report(workspace) if workspace.is_dir() else None  # (``run`` undid a stopped extension first)
    needed = [workspace / "database.db", workspace / "distorted" / "sparse" / "0", workspace / "sparse" / "0"]
    if existing is None or not existing.success or any(not p.exists() for p in needed):
        held = workspace.is_dir() and any(not p.name.startswith(".") for p in workspace.iterdir())
        if existing is None and held:  # (a synthetic scene, a COLMAP model made elsewhere: never to be overwritten)
            from uncertsplat.io.folders import is_scene

            what = "a scene `reconstruct` did not make" if is_scene(workspace) else "other files"
            hint = ("--extend grows only a workspace `uncertsplat reconstruct` made; reconstruct the photos into a new "
                    f"folder: uncertsplat reconstruct {q(photos)} -o {q(workspace.parent / (workspace.name + '_ws'))}")
            raise UserError(f"--extend needs a finished workspace of `uncertsplat reconstruct`, and the folder holds "
                            f"{what}", path=workspace, hint=hint)
        raise UserError("--extend needs a finished workspace of `uncertsplat reconstruct` (its report, database.db, "
                        "distorted/sparse/0)", path=workspace,
                        hint=f"Reconstruct the photos first: uncertsplat reconstruct {q(photos)} -o {q(workspace)}")
    ws_cfg = ReconstructConfig.model_validate({**existing.options, "num_threads": cfg.num_threads})
    # of copies and photos sharing a name stem the workspace's own are kept (a new copy sorted first took its place)
    masks = _extension_masks(ws_cfg.masks, cfg.masks, workspace, existing.images_registered)
    scan = sfm.scan_photos(photos, prefer=set(existing.images_registered), masks=masks)
    _check_output_path(photos, workspace)
    said = [note for note in scan.notes if note not in existing.notes]
    for note in said:
        console.print(f"[yellow]note:[/] {note}")
    missing = sorted(set(existing.images_registered) - set(scan.names))
    if missing:
        raise UserError(f"{photos} lacks {len(missing)} of the photos the workspace registered ({list_names(missing)})",
                        path=photos, hint="Give the folder the workspace was made from, with the new photos added to "
                                          f"it ({existing.photos}).")
    found_before = set(existing.images_found)
    new = [n for n in scan.names if n not in found_before]
    if not new:
        # (the photos left out as copies or for a shared name; not hidden files, sub-folders or other files)
        left = sorted(n for n in set(scan.ignored) - set(existing.ignored)
                      if not n.startswith(".") and n.lower().endswith(IMAGE_EXTENSIONS))
        # the same photos, other contents: a photo edited or replaced since (said only after a whole extension before)
        edited = (set(scan.names) == set(existing.images_found)  # (a photo left out since changes it too)
                  and existing.inputs_fingerprint not in ("", _inputs_fingerprint(scan, ws_cfg.masks),
                                                          scan.legacy_fingerprint()))
        hashes = scan.photo_hashes() if edited and existing.photo_sha256 else {}
        which = sorted(n for n, h in hashes.items() if existing.photo_sha256.get(n, h) != h)  # (before version 3: none)
        unregistered = sorted(set(scan.names) - set(existing.images_registered))  # (found then, not registered)
        raise UserError(f"no new photo in {photos}: the workspace was made from every one of its {len(scan.names)} "
                        "photos" + (f" ({len(unregistered)} of them not registered then: {list_names(unregistered)}; "
                                    "--extend adds only photos it has not tried)" if unregistered else "")
                        + (f" (left out: {list_names(left)}, copies of a photo or sharing its name"
                           + (": the notes above)" if said else ")") if left else "")
                        + ("; and the folder's photos are not the ones the workspace was made from ("
                           + (f"{list_names(which)} edited or replaced since" if which else
                              "a photo edited or replaced since")
                           + ": --extend keeps the cameras and images already there, so one the workspace registered "
                           "must stay as it was)" if edited else ""),
                        path=photos, hint="Put back the photos the workspace was made from, or reconstruct the folder "
                                          "into a new workspace (and train a new run on it)." if edited else
                        "Put the new photos into the folder beside the others and run this again.")
    console.print(f"[bold]reconstruct --extend[/] {workspace}: {len(new)} new photo(s) ({list_names(new)}) into its "
                  f"{len(existing.images_registered)} registered ones, their cameras fixed; the workspace's options")
    if ws_cfg.masks is not None and masks is None:  # (the masks/ of the photos there stay valid: their cameras and
        # images do not change)
        console.print(f"[yellow]note:[/] the workspace was made with masks from {esc(str(ws_cfg.masks))}, which is no "
                      "longer there; the new photos get none (every pixel of them counts; --masks DIR reads theirs)")
    stage_dir = workspace / EXTEND_DIR
    watch = sfm.Stopwatch()
    t_start = time.perf_counter()
    try:
        with run_lock(workspace, "reconstruct"), sfm.colmap_logging():
            _recover_extend(workspace)  # an earlier --extend killed while it swapped: its originals back first
            stage_dir.mkdir()
            database = stage_dir / "database.db"
            shutil.copy2(workspace / "database.db", database)
            old_model = workspace / "distorted" / "sparse" / "0"
            before = sfm.read_model(old_model)
            is_new = set(new)
            with watch("stage_inputs"):
                image_dir, rotated = sfm.stage_inputs(scan, stage_dir / "input")
                mask_dir, without = None, []
                if masks is not None:  # every photo's masks, as `run` stages them (the ones already there are
                    # undistorted again and compared with the workspace's: _grown_masks)
                    mask_dir = stage_dir / "staged_masks"
                    without = sfm.stage_masks(scan, masks, mask_dir)
                    from uncertsplat.sfm.scene import mask_names, masks_note

                    bare = set(without)
                    if cfg.masks is not None and is_new <= bare:
                        raise UserError(f"the folder holds no mask named for any new photo ({mask_names(new[0])})",
                                        path=masks, hint="Name each mask after its photo.")
                    mask_note = "new photos' " + masks_note(new, [None if n in bare else n for n in new], f"in {masks}")
                    console.print(f"[yellow]note:[/] {esc(mask_note)}")
            known = sfm.database_cameras(database)
            groups = {key: [n for n in names if n in is_new] for key, names in scan.camera_groups().items()}
            # a group's camera is the one most of its photos there use: a photo reconstruct gave a camera of its own
            # (a crop saved at full size) was the first of its group by name, and new photos took its focal length
            cameras = {key: Counter(known[n] for n in names if n in known).most_common(1)[0][0]
                       for key, names in scan.camera_groups().items() if any(n in known for n in names)}
            pairs = [(a, b) for i, a in enumerate(scan.names) for b in scan.names[i + 1:]
                     if a in is_new or b in is_new]
            with progress() as bar:
                task = bar.add_task("features (new photos)", total=len(new), info="")
                with watch("extract"):
                    keypoints = sfm.extract_features(database, image_dir, {k: v for k, v in groups.items() if v},
                                                     ws_cfg, advance=lambda k, i: bar.update(task, advance=k, info=i),
                                                     cameras=cameras, masks=mask_dir)
                unread = [n for n in new if n not in keypoints]
                if unread:
                    raise UserError(f"COLMAP could not read {len(unread)} new photo(s): {list_names(unread)}",
                                    path=photos, hint="Re-export these files as JPEG or PNG, or remove them.")
                task = bar.add_task("matching (new against all)", total=len(pairs), info="")
                with watch("match"):
                    sfm.match_features(database, pairs, ws_cfg, stage_dir,
                                       advance=lambda k, i: bar.update(task, advance=k, info=i))
                task = bar.add_task("registering", total=len(new), info="")
                with watch("map"):
                    grown = sfm.map_into(database, image_dir, old_model, stage_dir / "models", ws_cfg,
                                         advance=lambda k, i: bar.update(task, advance=k, info=i), start=before)
            registered = sfm.registered_names(grown) if grown is not None else []
            added = sorted(set(registered) - set(existing.images_registered))
            if not added:
                raise UserError(f"none of the {len(new)} new photo(s) registered ({list_names(new)}): the workspace is "
                                "unchanged", path=photos,
                                hint="A new photo must overlap the others (share features with photos near it); a "
                                     "photo of another place, blurred or too far from the capture does not register.")
            moved, params = sfm.pose_changes(before, grown)
            if moved > 1e-9 or params > 1e-9:  # fixed frames and cameras: a change is a fault, never kept
                raise UserError(f"registering the new photos moved the cameras already there (pose entries by up to "
                                f"{moved:.3g}, camera parameters by {params:.3g}): the workspace is unchanged",
                                path=workspace, hint="Reconstruct all the photos again into a new workspace (and train "
                                                     "a new run on it).")
            model_dir = stage_dir / "distorted" / "sparse" / "0"
            model_dir.mkdir(parents=True)
            grown.write(model_dir)
            with console.status(f"undistorting {len(registered)} images"), watch("undistort"):
                sizes = sfm.undistort(model_dir, image_dir, stage_dir, ws_cfg)
                if mask_dir is not None:  # the photos' masks undistorted as their images, the ones there unchanged
                    _grown_masks(workspace, stage_dir, model_dir, mask_dir, without, existing.images_registered,
                                 masks)
            # the workspace's images of the photos already there must come out as they were (the run was trained on
            # them): a photo edited since would be a silent change of a training view
            changed = [n for n in existing.images_registered
                       if (workspace / "images" / n).read_bytes() != (stage_dir / "images" / n).read_bytes()]
            if changed:
                raise UserError(f"{len(changed)} photo(s) already in the workspace changed since it was made "
                                f"({list_names(changed)}): the workspace is unchanged", path=photos,
                                hint="Put back the photos as they were, or reconstruct again into a new workspace.")
            report = existing.model_copy(deep=True)
            if masks is not None:  # (the folder later extensions read the new photos' masks from)
                report.options["masks"] = str(masks)
                report.notes.append(mask_note)
            report.inputs_fingerprint = _inputs_fingerprint(scan, masks if masks is not None else ws_cfg.masks)
            report.photo_sha256 = scan.photo_hashes()
            report.photos = str(photos.resolve())
            report.ignored = scan.ignored  # (the scan's notes were printed; the report keeps its first scan's)
            report.images_found = scan.names
            report.images_registered = registered
            report.images_unregistered = sorted(set(scan.names) - set(registered))
            report.registered_fraction = len(registered) / len(scan.names)
            report.undistorted_size = sizes
            report.image_sizes = {f"{w}x{h}": len(n) for (w, h), n in scan.size_groups().items()}
            turned = sorted(set(rotated) - set(report.rotated))
            report.rotated = sorted(set(report.rotated) | set(rotated))
            if turned:  # (the workspace's note names them all; the console the new ones)
                console.print(f"[yellow]note:[/] EXIF orientation applied to {len(turned)} new image(s): "
                              f"{esc(list_names(turned))}")
                report.notes = [n for n in report.notes if not n.startswith(EXIF_NOTE)]
                report.notes.append(_exif_note(report.rotated))
            _model_facts(report, grown)
            not_added = sorted(set(new) - set(added))
            report.notes.append(f"extended with {len(added)} photo(s) ({list_names(added)})"
                                + (f", {len(not_added)} not registered ({list_names(not_added)})" if not_added else "")
                                + f"; the {len(existing.images_registered)} cameras already there kept (poses and "
                                  f"intrinsics fixed) (reconstruct --extend, {time.perf_counter() - t_start:.1f} s)")
            report.total_seconds = round(report.total_seconds + time.perf_counter() - t_start, 3)
            # the workspace's time per stage, every extension's included (as total_seconds)
            report.stage_seconds = {k: round(report.stage_seconds.get(k, 0.0) + watch.seconds.get(k, 0.0), 3)
                                    for k in [*report.stage_seconds, *(k for k in watch.seconds
                                                                       if k not in report.stage_seconds)]}
            _swap_in(workspace, stage_dir, report, image_dir == stage_dir / "input", masks=mask_dir is not None)
    except KeyboardInterrupt:
        grown = _recover_extend(workspace)
        raise Interrupted("reconstruct --extend interrupted " + ("after its last step: the workspace holds the new "
                                                                 "photos" if grown else ": the workspace is as it was"),
                          path=workspace, hint="Run the same command again." if not grown else None) from None
    except BaseException:
        _recover_extend(workspace)
        raise
    console.print(f"reconstruct --extend: {len(added)} of {len(new)} new photo(s) registered ({list_names(added)}); "
                  f"the {len(existing.images_registered)} cameras already there unchanged -> {workspace}")
    if not_added:
        console.print(f"[yellow]warning:[/] not registered: {list_names(not_added)}")
    odd, common = _other_shapes(report, added)
    if odd:
        console.print(f"[yellow]note:[/] {list_names(odd)}: another shape than the workspace's photos ({common[0]}x"
                      f"{common[1]} undistorted): `train` leaves them out of its scene (scene.photo_sizes: a photo of "
                      "that shape in either orientation joins, resized)")
    usable = [n for n in added if n not in odd]
    if usable:
        console.print(f"Next: a run trained on {workspace} trains on them with [bold]uncertsplat train {qm(workspace)} -o "
                      f"RUN --resume {esc(add_views_args(usable))} --iterations N[/] (N: the steps to train to, past "
                      "the run's own: a finished run has none left for them)")
    return report


def _other_shapes(report: ReconstructReport, names: list[str]) -> tuple[list[str], tuple[int, int]]:
    """(of ``names``, the photos whose undistorted image `train` leaves out of the scene: neither within the size
    tolerance of the workspace's common size nor of its shape, in either orientation (``sfm.scene.size_fit``); that
    size)."""
    from collections import Counter

    from uncertsplat.sfm.scene import common_size, other_orientation, size_fit

    sizes = {n: tuple(wh) for n, wh in (report.undistorted_size or {}).items()}
    if not sizes:
        return [], (0, 0)
    common = common_size(dict(Counter(sizes.values())))

    def fits(w: int, h: int) -> bool:  # as `train` fits it: turned to the scene's orientation first
        if other_orientation(w, h, *common):
            w, h = h, w
        return size_fit(w, h, *common) is not None

    return [n for n in names if n in sizes and not fits(*sizes[n])], common


def _secs(seconds: float) -> str:
    """A mapping run's time: whole seconds, tenths below 10 s (a small scene maps in a fraction of one)."""
    if seconds < 0.05:
        return "< 0.1 s"
    return f"{seconds:.1f} s" if seconds < 10 else f"{seconds:.0f} s"


def _focals(attempt: dict) -> str:
    """The focal lengths of a mapping run's summary, for a note ("813 px" or "813 / 640 px")."""
    f = attempt["focal_lengths"]
    return " / ".join(f"{v:.0f}" for v in f.values()) + " px" if f else "none"


def _against_ground_truth(photos: Path, workspace: Path) -> dict[str, float] | None:
    """Pose accuracy against a synthetic scene's GT cameras when ``photos`` is its ``images/`` folder."""
    from uncertsplat.data.synthetic import is_synthetic_scene

    scene = photos.resolve().parent
    reference = scene / "sparse" / "0"
    if photos.name != "images" or not is_synthetic_scene(scene) or not reference.is_dir():
        return None
    try:
        return sfm.pose_accuracy(workspace / "sparse" / "0", reference)
    except (ValueError, RuntimeError, OSError) as err:  # a damaged GT model must not fail the reconstruction
        console.print(f"[yellow]note:[/] could not compare with the GT cameras in {reference}: {err}")
        return None
