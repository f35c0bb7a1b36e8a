"""Stage ``evaluate``: Monte-Carlo uncertainty maps of held-out views, scored against the images.

Writes into ``RUN/eval/``:
- ``maps/{image}.exr``: float channels ``rgb_mean.R/G/B``, ``rgb_std.R/G/B``, ``depth_mean.Z``,
  ``depth_std.Z`` (depth in the run's normalised world units), and PNG previews
  ``{image}_{gt,mean,error,std,error_rank,std_rank,depth,depth_std}.png``. Colour scales: ``error`` and
  ``std`` use the turbo map over the 1st-99th percentile of that map (``--set preview=fixed`` maps [0, 1]);
  the ``*_rank`` previews colour each pixel by its rank, so error and std compare without any scale.
- ``metrics.json``: the ``EvalReport`` (per view by image name, mean, curves, calibration).

The prediction is the Monte-Carlo mean (as in the paper); the per-pixel uncertainty is the unbiased
std over the K samples.
"""

from __future__ import annotations

import functools
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from uncertsplat.config import EvalConfig
from uncertsplat.console import console, progress
from uncertsplat.errors import UserError
from uncertsplat.types import SceneData

EXR_CHANNELS = ("rgb_mean.R", "rgb_mean.G", "rgb_mean.B", "rgb_std.R", "rgb_std.G", "rgb_std.B",
                "depth_mean.Z", "depth_std.Z")
KDE_MAX_SAMPLES = 64
"""The KDE NLL keeps every sample of a view in memory; above this K it is skipped (and noted)."""


def map_stem(image_name: str) -> str:
    """File stem for an image's maps: extension dropped, sub-folders flattened with '__'."""
    p = Path(image_name)
    return str(p.with_suffix("")).replace("/", "__").replace("\\", "__")


@dataclass
class _ViewResult:
    name: str
    metrics: dict
    curves: dict
    calibration: object
    depth_mean: torch.Tensor  # [H,W,1] on CPU
    depth_std: torch.Tensor
    alpha: torch.Tensor


def _gt_depth_from_folder(folder: Path, scene: SceneData, indices: list[int]) -> torch.Tensor:
    """GT depth [C,H,W,1] from ``folder/{stem}.npy|.exr`` (in GT units, resized to the cameras)."""
    from uncertsplat.data.dataset import load_depth_map

    folder = Path(folder)
    if not folder.is_dir():
        raise UserError("GT depth folder not found", path=folder, hint="Give --depth-gt a folder of .npy/.exr maps.")
    W, H = scene.cameras.width, scene.cameras.height
    out = []
    for i in indices:
        stem = Path(scene.cameras.image_names[i]).stem
        cands = [folder / f"{stem}{ext}" for ext in (".npy", ".exr", ".NPY", ".EXR")]
        path = next((c for c in cands if c.is_file()), None)
        if path is None:
            raise UserError(f"no GT depth map for image '{scene.cameras.image_names[i]}'", path=folder,
                            hint=f"Expected {stem}.npy or {stem}.exr.")
        out.append(load_depth_map(path, W, H))
    return torch.from_numpy(np.stack(out)[..., None])


def _samplers(loaded, scene: SceneData, device: torch.device):
    """(sample_fn, render_fn, det_sample) of a run: one posterior sample per generator call (a baseline's own
    sampler for ensemble / Fisher runs), the renderer with the run's settings, and the one deterministic
    render that ``train`` reports (the expected render; None for the baselines)."""
    from uncertsplat.baselines import make_sample_fn
    from uncertsplat.gaussians import variational
    from uncertsplat.render import near_plane, render

    tcfg, prior, model = loaded.config, loaded.prior, loaded.model
    bg = torch.tensor(tcfg.scene.background, dtype=torch.float32, device=device)
    render_fn = functools.partial(render, background=bg, tile_size=tcfg.tile_size, near=near_plane(scene.scene_scale))
    kw = {"variant": prior.variant, "extent": loaded.extent, "temperature": prior.temperature,
          "sh_degree": loaded.sh_degree}
    baseline_fn = make_sample_fn(loaded, device)  # ensemble / fisher runs bring their own sampler
    if baseline_fn is not None:
        return baseline_fn, render_fn, None
    with torch.no_grad():
        det_sample = variational.expected_render_sample(model, **kw)
    if tcfg.method == "deterministic" or model.num_carriers == 0:
        mean_sample = variational.posterior_mean(model, **kw)

        def sample_fn(g):
            return mean_sample
    else:
        def sample_fn(g):
            return variational.sample(model, g, subset_size=tcfg.variational.subset_size, **kw)
    return sample_fn, render_fn, det_sample


@torch.no_grad()
def fit_std_scale(loaded, scene: SceneData, cfg: EvalConfig, device: torch.device) -> tuple[float | None, list[str]]:
    """One factor for the predicted std, fitted on ``cfg.calibration_views`` evenly spaced *training* views.

    The maximum-likelihood scale of a Gaussian predictive, s^2 = mean((error / max(std, std_floor))^2) over
    every valid pixel and channel of those views (K samples each, as in evaluation). Fitted on training
    views, never on the views it is scored on (so not at all when ``cfg.split`` is "train"); training views
    fit better than held-out ones, so it errs low. Returns (scale, image names), or (None, []) when disabled,
    when scoring the training split, or when there is no training view.
    """
    from uncertsplat.data.dataset import load_images, load_masks
    from uncertsplat.uncertainty.mc import mc_render

    train = list(scene.split.get("train", ()))
    n = min(cfg.calibration_views, len(train))
    if n == 0 or cfg.split != "test":
        return None, []
    chosen = [train[round(j * (len(train) - 1) / max(n - 1, 1))] for j in range(n)]  # both ends included
    sample_fn, render_fn, _ = _samplers(loaded, scene, device)
    images, masks = load_images(scene, chosen), load_masks(scene, chosen)
    gen = torch.Generator(device=device)
    total, count = 0.0, 0
    for j, i in enumerate(chosen):
        gen.manual_seed(cfg.seed * 1_000_003 + i)
        maps, _ = mc_render(sample_fn, render_fn, scene.cameras[[i]].to(device), cfg.num_samples, gen)
        z2 = ((maps.rgb_mean[0].cpu().clamp(0, 1) - images[j]) / maps.rgb_std[0].cpu().clamp_min(cfg.std_floor)) ** 2
        if masks is not None:
            z2 = z2[masks[j][..., 0]]
        total += float(z2.double().sum())
        count += z2.numel()
    if count == 0:
        return None, []
    return (total / count) ** 0.5, [scene.cameras.image_names[i] for i in chosen]


def evaluate_views(loaded, scene: SceneData, indices: list[int], cfg: EvalConfig, device: torch.device, *,
                   write_maps_to: Path | None = None, gt_depth: torch.Tensor | None = None,
                   depth_known_scale: bool = False, show_progress: bool = True, std_scale: float | None = None,
                   calibration_views: list[str] | None = None):
    """Render K posterior samples of each view in ``indices`` and compute every metric.

    Args:
        loaded: a ``io.checkpoints.LoadedRun`` (model, config, extent, sh_degree, prior).
        scene: the scene the run was trained on (cameras, images, optional GT depth).
        indices: camera indices to evaluate.
        cfg: the evaluation config (K, seed, std floor, depth alignment, ...).
        device: where to render.
        write_maps_to: a folder for EXR maps and PNG previews (nothing is written when None).
        gt_depth: [C,H,W,1] GT depth for these views; None uses the scene's own GT depth if any.
        depth_known_scale: the GT depth is in the run's world units (no scale to estimate).
        std_scale: a factor for the RGB std (``fit_std_scale``): adds ``nll_calibrated`` and
            ``calibration_error_calibrated`` (the maps and the other metrics keep the raw std).
        calibration_views: the image names ``std_scale`` was fitted on (recorded in the report).

    Returns:
        ``eval.report_schema.EvalReport`` (not written to disk).
    """
    from uncertsplat.data.dataset import load_depths, load_images, load_masks
    from uncertsplat.eval.calibration import calibration, mean_calibration, spearman
    from uncertsplat.eval.depth import align_depth_scale, depth_metrics, valid_depth_mask
    from uncertsplat.eval.image import lpips, lpips_available, psnr, ssim
    from uncertsplat.eval.nll import gaussian_nll, kde_nll, paper_nll
    from uncertsplat.eval.report_schema import (
        CalibrationTable,
        CurveSet,
        DepthScaleInfo,
        EvalReport,
        LpipsStatus,
        SparsificationCurve,
        ViewMetrics,
    )
    from uncertsplat.eval.sparsification import mean_curves, sparsification_all
    from uncertsplat.stages.manifest import hash_config, versions
    from uncertsplat.uncertainty.mc import mc_render

    if not indices:
        raise UserError("no view to evaluate in this split",
                        hint="Use --split train, or a scene with held-out views.")
    from uncertsplat.baselines import eval_notes

    sample_fn, render_fn, det_sample = _samplers(loaded, scene, device)
    images = load_images(scene, indices)  # [C,H,W,3] CPU
    masks = load_masks(scene, indices)
    if gt_depth is None:
        gt_depth = load_depths(scene, indices)
        depth_known_scale = gt_depth is not None
    lp_ok, lp_reason = lpips_available()
    K = cfg.num_samples
    keep = K <= KDE_MAX_SAMPLES
    notes = eval_notes(loaded, cfg.num_samples)
    if not keep:
        notes.append(f"KDE NLL skipped: K={K} > {KDE_MAX_SAMPLES} would keep every sample in memory")
    if K == 1:
        notes.append("K=1: the std is 0 everywhere; AUSE and NLL then measure no uncertainty")

    results: list[_ViewResult] = []
    gen = torch.Generator(device=device)
    prog = progress() if show_progress else None
    task = prog.add_task("evaluate", total=len(indices), info="") if prog else None
    if prog:
        prog.start()
    try:
        for j, i in enumerate(indices):
            name = scene.cameras.image_names[i]
            cams = scene.cameras[[i]].to(device)
            gen.manual_seed(cfg.seed * 1_000_003 + i)  # per view: the same seed gives the same maps
            if device.type == "cuda":
                torch.cuda.synchronize(device)
            t0 = time.perf_counter()
            maps, samples = mc_render(sample_fn, render_fn, cams, K, gen, keep_samples=keep)
            if device.type == "cuda":
                torch.cuda.synchronize(device)
            seconds = time.perf_counter() - t0
            pred = maps.rgb_mean[0].cpu().clamp(0, 1)
            std = maps.rgb_std[0].cpu()
            gt = images[j]
            mask = masks[j] if masks is not None else None
            err = pred - gt
            sp = sparsification_all(err, std, mask=mask, steps=cfg.ause_steps)
            cal = calibration(err, std, mask=mask)
            sm = spearman(std, err.abs(), mask=mask)
            m = dict(
                psnr=float(psnr(pred, gt, mask)), ssim=float(ssim(pred, gt)),
                ause_mae=sp["mae"].ause, ause_mse=sp["mse"].ause, ause_rmse=sp["rmse"].ause,
                nll=float(gaussian_nll(gt, pred, std, std_floor=cfg.std_floor, mask=mask)),
                calibration_error=cal.calibration_error, spearman=sm.value, spearman_note=sm.reason,
                seconds=seconds,
            )
            if std_scale is not None:
                m.update(nll_calibrated=float(gaussian_nll(gt, pred, std * std_scale, std_floor=cfg.std_floor,
                                                           mask=mask)),
                         calibration_error_calibrated=calibration(err, std * std_scale, mask=mask).calibration_error)
            if lp_ok:
                m["lpips"] = float(lpips(pred, gt))
            if det_sample is not None:
                with torch.no_grad():
                    det = render_fn(det_sample, cams).rgb[0].cpu().clamp(0, 1)
                m["psnr_render"] = float(psnr(det, gt, mask))
            if samples is not None:
                s_rgb = samples.rgb[:, 0].cpu()
                m["nll_kde"] = float(kde_nll(s_rgb, gt, mask=mask))
                if cfg.paper_nll:
                    m["nll_paper"] = float(paper_nll(s_rgb, gt, mask=mask))
            curves = {k: SparsificationCurve.from_result(v) for k, v in sp.items()}
            results.append(_ViewResult(name, m, {"rgb": sp, "rgb_curves": curves}, cal,
                                       maps.depth_mean[0].cpu(), maps.depth_std[0].cpu(), maps.alpha_mean[0].cpu()))
            if write_maps_to is not None:
                _write_view_maps(write_maps_to, name, gt, pred, std, maps.depth_mean[0].cpu(),
                                 maps.depth_std[0].cpu(), cfg.preview)
            if prog:
                prog.update(task, advance=1, info=f"{name}: PSNR {m['psnr']:.2f} AUSE {m['ause_mae']:.3f} "
                                                  f"{seconds:.2f}s")
    finally:
        if prog:
            prog.stop()

    # ---- depth: one scale for the whole split (estimated over all views' valid pixels, or known)
    depth_info = None
    depth_cal = []
    depth_sp_all = []
    if gt_depth is not None:
        dm = torch.stack([r.depth_mean for r in results])  # [C,H,W,1]
        ds = torch.stack([r.depth_std for r in results])
        alpha = torch.stack([r.alpha for r in results])
        base_mask = alpha > 0.5
        if masks is not None:
            base_mask = base_mask & masks
        if isinstance(cfg.depth_scale, float):
            scale = align_depth_scale(dm, gt_depth, mask=base_mask, method=cfg.depth_scale)
        elif depth_known_scale:
            scale = align_depth_scale(dm, gt_depth, mask=base_mask, method=1.0)
            scale = type(scale)(1.0, "scene", scale.num_pixels)
        else:
            try:
                scale = align_depth_scale(dm, gt_depth, mask=base_mask, method=cfg.depth_align)
            except ValueError as err:
                raise UserError(f"cannot align depth with the GT: {err}") from None
        depth_info = DepthScaleInfo(scale=scale.scale, method=scale.method, num_pixels=scale.num_pixels)
        for j, r in enumerate(results):
            valid = valid_depth_mask(dm[j], gt_depth[j], base_mask[j])
            d_err = dm[j] * scale.scale - gt_depth[j]
            d_std = ds[j] * scale.scale
            dsp = sparsification_all(d_err, d_std, mask=valid, steps=cfg.ause_steps)
            dmet = depth_metrics(dm[j], gt_depth[j], scale=scale.scale, mask=valid)
            dcal = calibration(d_err, d_std, mask=valid)
            r.metrics.update(
                depth_ause_mae=dsp["mae"].ause if dsp["mae"].num_elements else None,
                depth_ause_rmse=dsp["rmse"].ause if dsp["rmse"].num_elements else None,
                depth_abs_rel=dmet.abs_rel, depth_rmse=dmet.rmse, depth_mae=dmet.mae,
                depth_nll=float(gaussian_nll(gt_depth[j], dm[j] * scale.scale, d_std, std_floor=cfg.std_floor,
                                             mask=valid)) if dmet.num_pixels else None,
                depth_spearman=spearman(d_std, d_err.abs(), mask=valid).value,
            )
            r.curves["depth"] = dsp
            depth_sp_all.append(dsp)
            if dcal.num_elements:
                depth_cal.append(dcal)

    per_view = {r.name: ViewMetrics(**r.metrics) for r in results}
    curves = {}
    for r in results:
        cs = CurveSet(rgb={k: v for k, v in r.curves["rgb_curves"].items() if v is not None})
        if "depth" in r.curves:
            cs.depth = {k: c for k, v in r.curves["depth"].items() if (c := SparsificationCurve.from_result(v))}
        curves[r.name] = cs
    mean_set = CurveSet()
    for metric in ("mae", "mse", "rmse"):
        mean_set.rgb[metric] = SparsificationCurve.from_result(mean_curves([r.curves["rgb"][metric] for r in results]))
        ok = [d[metric] for d in depth_sp_all if d[metric].num_elements > 0]
        if ok:
            mean_set.depth[metric] = SparsificationCurve.from_result(mean_curves(ok))
    curves["mean"] = mean_set
    cal_tables = {"rgb": CalibrationTable.from_result(mean_calibration([r.calibration for r in results]))}
    if depth_cal:
        cal_tables["depth"] = CalibrationTable.from_result(mean_calibration(depth_cal))
    seconds = [r.metrics["seconds"] for r in results]
    return EvalReport(
        split=cfg.split,
        image_names=[r.name for r in results],
        per_view=per_view,
        mean=ViewMetrics.mean_of(list(per_view.values())),
        curves=curves,
        calibration=cal_tables,
        config_hash=hash_config(cfg.model_dump(mode="json")),
        versions=versions(),
        num_samples=K,
        seed=cfg.seed,
        seconds_per_view=sum(seconds) / len(seconds),
        ause_steps=cfg.ause_steps,
        std_floor=cfg.std_floor,
        depth_scale=depth_info,
        std_scale=std_scale,
        calibration_views=calibration_views or [],
        lpips=LpipsStatus(available=lp_ok, reason=lp_reason),
        device=str(device),
        notes=notes,
    )


def _write_view_maps(folder: Path, name: str, gt, pred, std, depth_mean, depth_std, preview: str) -> None:
    """EXR float maps and PNG previews of one view (see the module docstring for the colour scales)."""
    from uncertsplat.io.images import write_exr, write_png
    from uncertsplat.report.colormaps import colorize, rank_colorize

    folder = Path(folder)
    stem = map_stem(name)
    arrays = [pred[..., c] for c in range(3)] + [std[..., c] for c in range(3)] + [depth_mean[..., 0], depth_std[..., 0]]
    write_exr(folder / f"{stem}.exr", {n: a.numpy() for n, a in zip(EXR_CHANNELS, arrays, strict=True)})
    err = (pred - gt).abs().mean(-1).numpy()
    s = std.mean(-1).numpy()
    write_png(folder / f"{stem}_gt.png", gt.numpy())
    write_png(folder / f"{stem}_mean.png", pred.numpy())
    write_png(folder / f"{stem}_error.png", colorize(err, mode=preview))
    write_png(folder / f"{stem}_std.png", colorize(s, mode=preview))
    write_png(folder / f"{stem}_error_rank.png", rank_colorize(err))
    write_png(folder / f"{stem}_std_rank.png", rank_colorize(s))
    write_png(folder / f"{stem}_depth.png", colorize(depth_mean[..., 0].numpy(), mode="percentile"))
    write_png(folder / f"{stem}_depth_std.png", colorize(depth_std[..., 0].numpy(), mode="percentile"))


def load_run_scene(loaded, run_dir: Path) -> SceneData:
    """The scene a run was trained on, with the run's scene config (same split and downscale)."""
    from uncertsplat.sfm.scene import load_scene

    if loaded.scene_path is None:
        raise UserError("the run does not record its scene (scene.json is missing)", path=run_dir,
                        hint="Evaluate a run written by `uncertsplat train`.")
    if not Path(loaded.scene_path).exists():
        raise UserError(f"the scene this run was trained on is gone: {loaded.scene_path}", path=run_dir,
                        hint="Restore the scene folder at that path, then run evaluate again.")
    return load_scene(loaded.scene_path, loaded.config.scene)


def run(run_dir: Path, cfg: EvalConfig, device: torch.device):
    """Evaluate ``run_dir`` and write ``run_dir/eval`` (maps + metrics.json); returns the EvalReport."""
    from rich.table import Table

    from uncertsplat.baselines import load_run
    from uncertsplat.io.atomic import atomic_write_text, run_lock

    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise UserError("run folder not found", path=run_dir, hint="Give a folder written by `uncertsplat train`.")
    loaded = load_run(run_dir, device)  # any method: variational, deterministic, ensemble, fisher
    scene = load_run_scene(loaded, run_dir)
    indices = list(scene.split[cfg.split])
    if cfg.max_views is not None:
        indices = indices[: cfg.max_views]
    gt_depth = None
    if cfg.depth_gt is not None:
        gt_depth = _gt_depth_from_folder(cfg.depth_gt, scene, indices)
    out = run_dir / "eval"
    with run_lock(run_dir, "evaluate"):
        console.print(f"[bold]evaluate[/] {run_dir}: {len(indices)} {cfg.split} views, K={cfg.num_samples}, "
                      f"{len(loaded.model)} Gaussians ({loaded.model.num_carriers} with a posterior), {device}")
        std_scale, cal_views = fit_std_scale(loaded, scene, cfg, device)
        report = evaluate_views(loaded, scene, indices, cfg, device, write_maps_to=out / "maps", gt_depth=gt_depth,
                                std_scale=std_scale, calibration_views=cal_views)
        atomic_write_text(out / "metrics.json", report.to_json() + "\n")
        atomic_write_text(out / "config.json", cfg.model_dump_json(indent=2) + "\n")

    table = Table(title=f"{run_dir.name}: {cfg.split} views (K={cfg.num_samples})")
    for col in ("view", "PSNR", "SSIM", "AUSE-MAE", "AUSE-RMSE", "NLL", "cal.err", "Spearman", "depth AUSE", "s/view"):
        table.add_column(col, justify="right")

    def f(x, p=3):
        return "-" if x is None else f"{x:.{p}f}"

    rows = list(report.per_view.items()) + [("mean", report.mean)]
    for name, v in rows:
        table.add_row(name, f(v.psnr, 2), f(v.ssim), f(v.ause_mae), f(v.ause_rmse), f(v.nll), f(v.calibration_error),
                      f(v.spearman), f(v.depth_ause_mae), f(v.seconds, 2))
    console.print(table)
    if report.std_scale is not None:
        m = report.mean
        console.print(f"std x {report.std_scale:.3g} (fitted on {len(report.calibration_views)} training views): "
                      f"NLL {m.nll_calibrated:.3f} (raw {m.nll:.3f}), calibration error "
                      f"{m.calibration_error_calibrated:.3f} (raw {m.calibration_error:.3f}); AUSE is unchanged")
    if report.mean.psnr_render is not None:
        console.print(f"PSNR is that of the mean of the {cfg.num_samples} samples; one deterministic render (the "
                      f"expected render, what train reports): {report.mean.psnr_render:.2f} dB")
    if report.depth_scale is not None:
        console.print(f"depth scale {report.depth_scale.scale:.4g} ({report.depth_scale.method})")
    console.print(f"wrote {out / 'metrics.json'} and maps in {out / 'maps'}")
    return report

