"""Stage ``select-views``: a run + candidate cameras -> the next photos to take (``uncertsplat select-views``).

``run`` loads the run (any single-model method; the ``fisher`` score needs the run's Gaussians, which every
run has), builds the candidates (``select.candidates``), scores and chooses them (``select.scores``) and
writes ``OUT/selection.json`` (``schemas.Selection``) and ``OUT/selection.png`` (the cameras seen from above:
used, candidates, the chosen ones numbered). ``OUT`` defaults to ``RUN/select``.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np
import torch

from uncertsplat.config import SelectConfig
from uncertsplat.console import console, count, esc, list_names, q, qm
from uncertsplat.errors import UserError, run_folder_missing


def _plot(path: Path, used: torch.Tensor, cands: torch.Tensor, chosen: list[int], up: torch.Tensor, title: str,
          held: torch.Tensor | None = None, not_drawn: int = 0) -> None:
    """The camera centres on the plane they spread over: candidates, the views used for training, the held-out ones
    (``held``: where the scores are measured, a gap's middle often) and the chosen. Seen from above (on the plane
    normal to ``up``) when the training cameras spread over a level plane (a ring, a walk), from the front when they
    stand on an upright one (a forward-facing grid, which the view from above drew as a line, its chosen views on top
    of each other). ``not_drawn``: candidates ruled out (no camera can stand there) and left off the plot, which the
    legend counts (it said "candidates (3)" of 4)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import MaxNLocator

    from uncertsplat.io.atomic import atomic_write_bytes

    up = up.double() / up.double().norm().clamp_min(1e-12)
    normal, side = up, "above"
    if len(used) >= 3:  # the plane of the training cameras' two widest spreads
        centred = used.double() - used.double().mean(0)
        normal = torch.linalg.svd(centred, full_matrices=True).Vh[2]
        if abs(float(normal @ up)) >= 0.7:
            normal = up
        else:
            side = "the front"
    b = up - (up @ normal) * normal  # the plot's vertical: up, on the plane (for a level plane, any)
    if side == "above" or float(b.norm()) < 0.1:
        b = torch.linalg.cross(normal, torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64))
        if float(b.norm()) < 0.1:
            b = torch.linalg.cross(normal, torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64))
    b = b / b.norm()
    a = torch.linalg.cross(b, normal)

    def xy(p):
        p = p.double()
        return (p @ a).numpy(), (p @ b).numpy()

    fig, ax = plt.subplots(figsize=(6, 6), dpi=110)
    left = f"; {not_drawn} ruled out, not drawn" if not_drawn else ""
    ax.scatter(*xy(cands), s=14, c="0.6", label=f"candidates ({len(cands)}{left})")
    if len(used):
        ax.scatter(*xy(used), s=22, c="tab:blue", label=f"used ({len(used)})")
    if held is not None and len(held):
        ax.scatter(*xy(held), s=22, c="tab:orange", marker="s", label=f"held out ({len(held)})")
    if chosen:
        cx, cy = xy(cands[chosen])
        ax.scatter(cx, cy, s=60, c="tab:red", marker="*", label=f"chosen ({len(chosen)})")
        for k, (x, y) in enumerate(zip(cx, cy, strict=True)):
            ax.annotate(str(k + 1), (x, y), textcoords="offset points", xytext=(5, 5), color="tab:red")
    ax.scatter([0.0], [0.0], s=30, c="k", marker="+", label="scene centre")
    ax.set_aspect("equal")
    ax.set_title(f"{title}\n(the cameras seen from {side}; the run's normalised units)", fontsize=9)
    ax.xaxis.set_major_locator(MaxNLocator(5))  # (tick labels ran into each other on a narrow capture)
    ax.yaxis.set_major_locator(MaxNLocator(5))
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.02, 1.0))  # beside the plot: it hid cameras inside
    import io

    buf = io.BytesIO()
    fig.savefig(buf, format="png", bbox_inches="tight")
    plt.close(fig)
    atomic_write_bytes(path, buf.getvalue())


FAR_CAPTURES = 2.0
"""``SelectConfig.plausible_only``: a candidate farther than this many capture sizes from every training camera is not
a next photo of this capture (the model there is a speck; the gap rule measured every other candidate against it)."""


WAY_CAMERAS = 3
"""``_walled_off``: the training cameras (the nearest) a candidate's way is tested from."""
WAY_POINTS = 24
"""``_walled_off``: points tested along each way."""


def _walled_off(looked, centres: torch.Tensor, used: torch.Tensor, device: torch.device) -> torch.Tensor:
    """[C] bool: the candidates at ``centres`` [C,3] whose straight way from every one of their ``WAY_CAMERAS`` nearest
    training cameras (``used`` [T,3]) passes a point ``seen_behind`` (inside an object, or behind a surface every photo
    that looked there saw in front of it). One clear way is enough: a pose behind a pillar seen from its nearest camera
    is reached from the next."""
    if not len(centres) or not len(used):
        return torch.zeros(len(centres), dtype=torch.bool)
    k = min(WAY_CAMERAS, len(used))
    nearest = torch.cdist(centres, used).topk(k, largest=False).indices  # [C,k]
    starts = used[nearest]  # [C,k,3]
    f = torch.arange(1, WAY_POINTS + 1, dtype=centres.dtype) / WAY_POINTS  # (0, 1]: not the camera itself
    points = starts[:, :, None] + f[None, None, :, None] * (centres[:, None, None] - starts[:, :, None])  # [C,k,S,3]
    behind = looked.seen_behind(points.reshape(-1, 3).float().to(device)).cpu().view(len(centres), k, WAY_POINTS)
    return behind.any(-1).all(-1)


def _held_out_twins(scene, cands, among: torch.Tensor) -> torch.Tensor:
    """[C] bool: of the candidates ``among`` ([C] bool), those at a held-out or set-aside view's pose
    (``sfm.scene.held_out_twins``, judged with the training views as a split is; the others are left out of the
    judging: a pose far out would widen the rig whose radius sets how near a twin is)."""
    from uncertsplat.sfm.scene import held_out_twins
    from uncertsplat.types import Cameras

    n, idx = len(scene.cameras), among.nonzero()[:, 0]
    twin = torch.zeros(len(cands), dtype=torch.bool)
    if not len(idx):
        return twin
    device = scene.cameras.device
    both = Cameras(torch.cat([scene.cameras.cam_from_world, cands.cameras.cam_from_world[idx].to(device)]),
                   torch.cat([scene.cameras.K, cands.cameras.K[idx].to(device)]), scene.cameras.width,
                   scene.cameras.height)
    for ts in held_out_twins(both, scene.split, range(n, n + len(idx))).values():
        twin[idx[[t - n for t in ts]]] = True
    return twin


def _plausible(loaded, scene, train: list[int], cands, cfg: SelectConfig, device: torch.device
               ) -> torch.Tensor | None:
    """[C] bool: the candidates that compete under ``SelectConfig.plausible_only`` (planned poses whose centre is not
    inside or behind what the training photos saw, nor ``FAR_CAPTURES`` capture sizes from them), with a note naming
    the others; None when every candidate competes (the setting off, the scene's unused photos, all plausible, or
    none: then every one competes, said so)."""
    from uncertsplat.config import EvalConfig
    from uncertsplat.eval.engine import view_consistency
    from uncertsplat.select.scores import nearest_used_distance

    if not cfg.plausible_only or cands.kind == "unused" or not train:
        return None
    # every training view up to the default 64, as Predictor.seen_free
    looked = view_consistency(loaded.sampler(scene.scene_scale, device), scene.cameras[train].to(device),
                              EvalConfig(finer_detail=False), device)
    centres, used = cands.cameras.centers.double(), scene.cameras[train].centers.double()
    inside = looked.seen_behind(centres.float().to(device)).cpu()  # [C]
    # or walled off: the way to it from each of its nearest training cameras crosses space every photo that looked
    # toward it saw a surface in front of (a floor, a wall): a pose under the floor lies where no photo's frame
    # reached, so only its way there tells (a helper's such poses were ranked first, 2.3x the best real one)
    inside |= _walled_off(looked, centres, used, device)
    spread = float(torch.cdist(used, used).max()) if len(train) > 1 else 0.0
    size = max(spread, looked.median_surface_depth())
    far = nearest_used_distance(centres, used) > FAR_CAPTURES * size if size > 0 else torch.zeros_like(inside)
    twin = _held_out_twins(scene, cands, ~(inside | far))
    ok = ~(inside | far | twin)
    if bool(ok.all()):
        return None
    names = cands.cameras.image_names
    if not bool(ok.any()):
        twins = [names[j] for j in range(len(cands)) if bool(twin[j])]
        if len(twins) == len(cands):  # the photo taken there would be refused: no choice to make
            raise UserError(f"every candidate lies at a held-out view's pose ({list_names(twins, 6)}): a photo taken "
                            "there is the held-out photo again, which `train --add-views` refuses",
                            hint="Give poses elsewhere (or --candidates around:N, or the scene's unused photos).")
        rest = int((~twin).sum())
        which = "the candidate lies" if rest == 1 else f"every one of the {rest} candidates lies"
        console.print(f"[yellow]note:[/] {which} inside or behind what the photos saw, or over {FAR_CAPTURES:g} capture "
                      f"sizes away: {'it competes' if rest == 1 else 'they compete'} all the same (nothing else does); "
                      "check the poses' convention (world-to-camera, the quaternion as w x y z, the scene's units and "
                      "frame)" + (f"; {count(len(twins), 'candidate')} at a held-out view's pose "
                                  f"({list_names(twins, 6)}) {'does' if len(twins) == 1 else 'do'} not compete"
                                  if twins else ""))
        return ~twin if twins else None
    for mask, where in ((inside, "inside or behind what every photo that looked toward them saw (an object, a wall), or "
                                 "beyond such a surface from every nearby training camera (under a floor, outside a "
                                 "wall)"),
                        (far & ~inside, f"over {FAR_CAPTURES:g} capture sizes from every training camera ({size:.3g} "
                                        "units a capture size, in the run's normalised world)"),
                        (twin & ~inside & ~far, "at a held-out view's pose (a photo taken there is the held-out photo "
                                                "again, which `train --add-views` refuses: it would score what the "
                                                "model memorised)")):
        out = [names[j] for j in range(len(cands)) if bool(mask[j])]
        if out:
            console.print(f"[yellow]note:[/] {count(len(out), 'candidate')} ({list_names(out, 6)}) "
                          f"{'lie' if len(out) > 1 else 'lies'} {where}: no score, ranked last (--set "
                          "plausible_only=false lets them compete)")
    return ok


def _refuse_output_among_photos(out: Path, scene, scene_path: Path | None) -> None:
    """Refuse an output folder that is, or lies inside, a folder of the scene's photos
    (``sfm.scene.photo_folder_holding``): ``selection.png`` landed among the photos, where the next ``reconstruct`` of
    them, the one that adds the chosen photo, takes it for a photo."""
    from uncertsplat.sfm.scene import photo_folder_holding

    folder = photo_folder_holding(out, scene_path, scene.image_paths)
    if folder is not None:
        raise UserError(f"the output folder is inside the folder of the scene's photos ({folder}): selection.png "
                        "would be taken for a photo there", path=out,
                        hint="Choose an output folder outside the photos (the default is RUN/select).")


def _kept_scene(loaded, run_dir: Path, cfg: SelectConfig, err: UserError):
    """The scene as the run's evaluation kept it (``RUN/eval/predictive.pt``: cameras, split, normalisation) where
    the scene folder cannot be loaded (``err``), for the scores that read the run alone; ``err``, with what else to do,
    where the score compares the model with the training photos (``fisher``) or the run holds no such file."""
    from uncertsplat.stages.predictive_cache import evaluation_predictive

    alone = "--score variance, unseen or coverage read the run alone (its eval/predictive.pt)"
    if cfg.score == "fisher":
        raise UserError(f"{err.message}; the fisher score (the default) compares the model with the training photos",
                        path=err.path, hint=f"{err.hint or 'Restore the scene folder.'} Or choose without the photos: "
                                            f"{alone}.") from err
    kept, problem = evaluation_predictive(loaded)
    if kept is None:
        raise UserError(f"{err.message}; and the cameras kept beside the run cannot stand in for it: {problem}",
                        path=err.path, hint=f"{err.hint or 'Restore the scene folder.'} Or run `uncertsplat evaluate "
                                            f"{q(run_dir)}` where the scene is and copy the run folder with its eval/ "
                                            f"folder: {alone}.") from err
    console.print(f"[yellow]note:[/] the scene cannot be loaded ({err.message}): the cameras, split and normalisation "
                  f"are those kept in {run_dir / 'eval' / 'predictive.pt'}")
    return kept.scene


def run(run_dir: Path, cfg: SelectConfig, device: torch.device, output: Path | None = None):
    """Choose ``cfg.num_views`` candidates for the run ``run_dir``; returns the written ``Selection``.

    Raises:
        UserError: a missing run, an ensemble (no single model), bad candidates (file and line named).
    """
    from uncertsplat import native

    with native.single_threaded_torch(device):  # torch's own ops on one thread, the kernels on all
        return _run(run_dir, cfg, device, output)


def _run(run_dir: Path, cfg: SelectConfig, device: torch.device, output: Path | None = None):
    from uncertsplat.baselines import load_run
    from uncertsplat.baselines.fisher import prior_stds
    from uncertsplat.data.dataset import load_images
    from uncertsplat.io.atomic import check_output_folder, run_lock
    from uncertsplat.io.images import resize_image, resize_mask
    from uncertsplat.schemas import PruneReport, RunScene, Selection
    from uncertsplat.schemas.select import CandidateScore, ChosenView
    from uncertsplat.select.candidates import blind_candidates_note, candidates_from_spec, pose_line
    from uncertsplat.select.scores import (
        coverage_choice,
        fisher_choice,
        gap_eligible,
        low_resolution,
        only_allowed,
        rank_order,
        relative_position_variance,
        unseen_scores,
        variance_scores,
    )

    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise run_folder_missing(run_dir)
    out = Path(output) if output is not None else run_dir / "select"
    check_output_folder(out)  # before the scoring's minutes (run_lock checks again at the end)
    with run_lock(out, "select-views"):  # a folder it cannot write (read-only run): said now, not after the scoring
        pass  # (a folder it made for this is removed again)
    loaded = load_run(run_dir, device)
    loaded.warn_if_unfinished()
    try:
        scene = loaded.load_scene()
    except UserError as err:  # a robot has the run, not the photos: the cameras and split its evaluation kept
        scene = _kept_scene(loaded, run_dir, cfg, err)
        loaded = loaded.with_scene(scene)  # (the empty-ray term's coverage reads the training cameras from it)
    if run_dir.resolve() not in out.resolve().parents:  # (RUN/select, the default: the run's own, wherever it lies)
        _refuse_output_among_photos(out, scene, loaded.scene_path)
    info = RunScene.read(run_dir / RunScene.FILE_NAME)
    gen = torch.Generator().manual_seed(cfg.seed)
    cands = candidates_from_spec(cfg.candidates, scene, torch.tensor(info.world_from_source, dtype=torch.float64),
                                 radius=cfg.around_radius, generator=gen)
    train = list(scene.split["train"])
    used_names = [scene.cameras.image_names[i] for i in train] if scene.cameras.image_names else []
    if cands.kind == "file":  # poses of one's own: a convention mixed up gives poses that look away, ranked as any
        blind = blind_candidates_note(cands.cameras, scene.cameras[train], loaded.model.params["means"].detach())
        if blind:
            console.print(f"[yellow]note:[/] {blind}")
        photos = set(scene.cameras.image_names)
        named = [n for n in cands.cameras.image_names if n in photos]
        if named:  # `--add-views NAME` adds the photo of that name, not the planned pose
            console.print(f"[yellow]note:[/] {len(named)} planned pose(s) carry the name of a photo of the scene "
                          f"({list_names(named, 5)}): `train --add-views` takes photos, so a chosen one adds that "
                          "photo (or is refused as trained or held out), not the pose; name planned poses apart")
    centres = cands.cameras.centers
    allowed = _plausible(loaded, scene, train, cands, cfg, device)  # [C] bool, or None: every one competes
    n = min(cfg.num_views, len(cands) if allowed is None else int(allowed.sum()))
    console.print(f"[bold]select-views[/] {run_dir}: {count(len(cands), 'candidate')} ({cands.kind}), score "
                  f"'{cfg.score}', choosing {n}, {device}")
    cannot_grow = None  # why `train --resume --add-views` refuses this run (the Next line then says what to do)
    if loaded.config.scene.calibration_holdout:  # found out only after choosing, at `train --add-views`
        cannot_grow = "it sets views aside for calibration"
        console.print(f"[yellow]note:[/] this run sets {loaded.config.scene.calibration_holdout} view(s) aside for "
                      "calibration, so `train --resume --add-views` refuses to add the chosen views (more training "
                      "views would change which ones are set aside): train a new run on its views and the chosen "
                      "ones (--set scene.train_names=[...]) to use them")
    if loaded.config.method in ("ensemble", "fisher"):  # found out only after choosing, at `train --add-views`
        article = "an" if loaded.config.method[0] in "aeiou" else "a"
        cannot_grow = f"it is {article} {loaded.config.method} run"
        console.print(f"[yellow]note:[/] `train --resume --add-views` does not grow {article} {loaded.config.method} run: "
                      "to use the chosen views, train a new run on its views and the chosen ones "
                      "(--set scene.train_names=[...])")
    settings: dict = cfg.model_dump(mode="json")  # the resolved settings (K, probes, gaps, ...), then what the score used
    if cands.kind == "file":  # (a relative pose file, given back by --config selection.json, was read from the folder
        settings["candidates"] = str(Path(cfg.candidates).resolve())  # the command ran in: looked for in no other)
    depth_std = None
    t0 = time.perf_counter()
    if cfg.score == "coverage":
        chosen, at, first = coverage_choice(centres, scene.cameras[train].centers, n, allowed)
    elif cfg.score == "random":
        first = only_allowed(torch.rand(len(cands), generator=torch.Generator().manual_seed(cfg.seed),
                                        dtype=torch.float64), allowed)
        chosen = rank_order(first)[:n]
        at = [float(first[j]) for j in chosen]
    elif cfg.score in ("unseen", "variance"):  # scores rendered from the posterior at the candidates
        if cfg.score == "unseen" and (loaded.model.num_carriers == 0
                                      or loaded.config.method in ("ensemble", "fisher", "deterministic")):
            raise UserError("the unseen score reads the Gaussians' posterior (offset tables), and this run has none",
                            path=run_dir, hint="Use --score variance, fisher or coverage for this run.")
        sampler = loaded.sampler(scene.scene_scale, device)
        low = low_resolution(cands.cameras, cfg.max_side).to(device)
        if cfg.score == "unseen":
            sample = sampler.det_sample if sampler.det_sample is not None else sampler.sample_fn(
                torch.Generator(device=device).manual_seed(cfg.seed))
            # (against the prior each carrier's posterior was fitted with: the informed posterior's is its own,
            # and against the config's single std nearly every Gaussian read as constrained by no view)
            u = relative_position_variance(loaded.model, loaded.prior, loaded.position_prior_std(scene))
            first = unseen_scores(sample, u, sampler.render_fn, low, empty_unknown=not loaded.transparent)
        else:
            if loaded.config.method == "deterministic" or (loaded.model.num_carriers == 0
                                                            and loaded.config.method not in ("ensemble", "fisher")):
                # every sample is the same model: the score is the unknown surface behind uncovered rays alone
                console.print("[yellow]note:[/] this run has no posterior (its samples are one model), so the variance "
                              "score holds only the empty-ray term: how much of each candidate's view the model "
                              "leaves uncovered; --score fisher or coverage rank by more")
            first, depth_std = variance_scores(sampler.sample_fn, sampler.render_fn, low, cfg.num_samples, cfg.seed,
                                               empty_std=sampler.empty_std, coverage=sampler.coverage)
        first = only_allowed(first, allowed)
        chosen = rank_order(first)[:n]
        at = [float(first[j]) for j in chosen]
        settings.update(width=low.width, height=low.height)
    else:  # fisher
        low_train = low_resolution(scene.cameras[train], cfg.max_side)
        photos = load_images(scene, train)
        exposure = loaded.photo_exposure()
        if exposure is not None:  # the photos at the model's exposure, as training compared them
            photos = exposure.unexposed_images(train, photos)
        images = torch.from_numpy(np.stack([resize_image(im.numpy(), low_train.width, low_train.height)
                                            for im in photos]))
        # the pixels training fitted (a low pixel counts only where every pixel under it does)
        full = loaded.training_masks(scene, train)
        masks = None if full is None else torch.from_numpy(np.stack(
            [resize_mask(m.numpy(), low_train.width, low_train.height) for m in full])).to(device)
        fcfg = loaded.config.fisher
        params = {k: v.detach() for k, v in loaded.model.params.items()}
        low = low_resolution(cands.cameras, cfg.max_side)
        with torch.enable_grad():
            chosen, at, first, noise = fisher_choice(
                params, low_train.to(device), images.to(device), low.to(device), loaded.render_fn(scene.scene_scale, device),
                names=fcfg.params, prior_std=prior_stds(fcfg, loaded.extent), sh_degree=loaded.sh_degree,
                probes=cfg.probes, seed=cfg.seed, n=n, information=cfg.information,
                # (gaps 0 with candidates left out: the gap rule at fraction 0 is the allowed ones not chosen yet)
                eligible=(gap_eligible(centres, scene.cameras[train].centers, cfg.gaps, allowed)
                          if cfg.gaps > 0 or allowed is not None else None), competing=allowed,
                train_masks=masks)
        settings.update(width=low.width, height=low.height, noise_std=noise, params=list(fcfg.params))
        if loaded.config.method == "ensemble":
            settings["note"] = "ensemble: the Fisher of member 0's Gaussians"
    seconds = time.perf_counter() - t0

    world_from_source = torch.tensor(info.world_from_source, dtype=torch.float64)

    def pose(c: int) -> dict:
        name, cam = cands.cameras.image_names[c], cands.cameras.cam_from_world[c]
        return {"name": name, "cam_from_world": cam.double().tolist(), "position": centres[c].double().tolist(),
                "pose_line": pose_line(name, cam, world_from_source),
                # in the scene's own units, as the schema says (the run's normalised units before: x the scale)
                "depth_std": float(depth_std[c]) * scene.depth_to_source if depth_std is not None else None}

    def num(x) -> float | None:
        x = float(x)
        return None if x != x or x in (float("inf"), float("-inf")) else x

    ranking = [CandidateScore(score=num(first[c]), **pose(c)) for c in rank_order(first)]
    picked = [ChosenView(rank=k + 1, score=num(first[c]), score_when_chosen=num(at[k]), **pose(c))
              for k, c in enumerate(chosen)]
    sel = Selection(run=str(run_dir), score=cfg.score, candidates=cfg.candidates, num_candidates=len(cands),
                    chosen=picked, ranking=ranking, used=used_names, seconds=seconds,
                    seconds_per_candidate=seconds / max(len(cands), 1), settings=settings)
    with run_lock(out, "select-views"):  # (it makes the folder, or says why it cannot)
        earlier = out / Selection.FILE_NAME
        if earlier.is_file():  # the last round's choice, which its photos may still be taken from: one generation kept
            kept = out / "selection.previous.json"
            os.replace(earlier, kept)
            console.print(f"[dim]the earlier {Selection.FILE_NAME} is kept as {kept.name}[/]")
        sel.write(out / Selection.FILE_NAME)
        up = -torch.linalg.inv(scene.cameras[train].cam_from_world.double())[:, :3, 1].mean(0)
        held = list(scene.split.get("test", ()))
        drawn = list(range(len(cands))) if allowed is None else [j for j in range(len(cands)) if bool(allowed[j])]
        # (a pose far outside the capture, ranked last, set the axes and squashed every other into a strip)
        _plot(out / "selection.png", scene.cameras[train].centers, centres[drawn], [drawn.index(c) for c in chosen], up,
              f"{run_dir.name}: {cfg.score} chose {', '.join(p.name for p in picked)}",
              held=scene.cameras[held].centers if held else None, not_drawn=len(cands) - len(drawn))
    gaps = cfg.score == "fisher" and cfg.gaps > 0
    for p in picked:
        when = f"{p.score_when_chosen:.6g}" if p.score_when_chosen is not None else "-"
        alone = f"{p.score:.6g}" if p.score is not None else "-"
        # greedy policies score later choices after the earlier ones (score_when_chosen); alone: before any choice
        if p.score is None and p.score_when_chosen is not None and gaps:
            why = " (outside the gaps before the earlier choices, which moved them: not scored alone)"
        else:
            why = f" (alone {alone})" if alone != when else ""
        console.print(f"  {p.rank}. {p.name}  score {when}{why}")
    if cfg.score == "fisher" and len(picked) > 1:
        console.print("[dim]score: the information a view adds to the model's Fisher information, each after the views "
                      "chosen before it" + (f"; only candidates in the capture's gaps compete (at least {cfg.gaps:g} x "
                                            "the largest distance to the views used and chosen so far; --set gaps=0 "
                                            "lets every candidate compete), so a later choice can score higher than "
                                            "an earlier one whose gap it was not yet in" if gaps else "") + "[/]")
    console.print(f"chose {len(picked)} of {len(cands)} in {seconds:.2f} s -> {out / Selection.FILE_NAME}, "
                  f"{out / 'selection.png'}")
    if len(picked) < cfg.num_views:
        competing = len(cands) if allowed is None else int(allowed.sum())
        there = "was there" if competing == 1 else "were there"
        console.print(f"[yellow]note:[/] {cfg.num_views} views were asked for and only {count(competing, 'candidate')} "
                      f"{'competed' if allowed is not None else there}: every one is chosen")
    folder = loaded.scene_path or "SCENE"
    source = PruneReport.training_run(run_dir)
    if source is not None and picked:  # no checkpoint to add views to: `train --resume` there is refused
        console.print(f"[yellow]note:[/] {run_dir} is a pruned model (prune.json): the views are added to the run it "
                      f"was pruned from, {source}, which is then pruned again")
        run_dir = source
    added = ",".join(p.name for p in picked) if cands.kind == "unused" else "NEW_PHOTOS"
    init_ply = getattr(loaded.config, "init_ply", None)
    if init_ply is not None:  # a model trained elsewhere: `train --resume` trains no step of it (and refuses views)
        train_next = (f"train the model on with them in the tool that trained it ({Path(init_ply).name}) and give "
                      f"its new file the posterior: [bold]uncertsplat train {qm(folder)} -o NEW_RUN --from-ply "
                      f"NEW_MODEL.ply[/] (with --set 'scene.train_names=[...]', the names in "
                      f"{run_dir / 'scene.json'}'s training list and {added}, where the run chose its views)")
    elif cannot_grow is None:
        train_next = f"[bold]uncertsplat train {qm(folder)} -o {qm(run_dir)} --resume --iterations N --add-views {esc(added)}[/]"
    else:  # the command the note above said is refused: a new run instead
        train_next = (f"(`--resume --add-views` refuses this run: {cannot_grow}) train a new run on its views and "
                      # (its config: a fisher or ensemble run's method, its settings; without it a variational run)
                      f"these, [bold]uncertsplat train {qm(folder)} -o NEW_RUN --config {qm(run_dir / 'config.json')} "
                      f"--set 'scene.train_names=[...]'[/] with the "
                      f"names in {run_dir / 'scene.json'}'s training and calibration lists and {added}")
    if picked and cands.kind == "unused":  # photos of the scene: the run trains on them as they are
        console.print(f"Next: {train_next}")
    elif picked:  # poses: a photo is taken at each first
        from uncertsplat.sfm.report import REPORT_NAME

        if (Path(folder) / REPORT_NAME).is_file():  # a workspace of `reconstruct`: a new photo joins it
            console.print(f"Next: take a photo at each chosen pose ({out / Selection.FILE_NAME}), put them into the "
                          f"photo folder, [bold]uncertsplat reconstruct PHOTOS -o {qm(folder)} --extend[/] (its cameras "
                          f"kept), then {train_next}")
        else:  # (--extend grows workspaces of reconstruct only)
            console.print(f"Next: take a photo at each chosen pose ({out / Selection.FILE_NAME}) and add it to the "
                          f"scene {folder} with its camera, as the scene's own tool writes them, then {train_next}")
    return sel


__all__ = ["run"]
