"""Deep-ensemble baseline: N independently seeded deterministic 3DGS models, uncertainty = their spread; or
(``TrainConfig.ensemble_members = "variational"``) N of our variational models, each sample a posterior sample of one.

Run folder::

    RUN/config.json            the TrainConfig with method = "ensemble", ensemble_size = N
    RUN/scene.json             copied from member 0 (all members share the scene and split)
    RUN/members/member_{i}/    a normal deterministic run (seed = seed + i), readable by every stage
    RUN/train_summary.json     summed training time, per-member summaries, mean held-out PSNR

``evaluate`` draws its K samples by cycling through the members in a random order per view (drawn from
the view's generator), so K = N renders each member exactly once and the MC mean/std are the ensemble
mean and spread. Members differ only through their seed (view order, split noise): 3DGS starts from
the same SfM points, so the spread is the optimisation's variability, as in the ensembles the paper
compares against.
"""

from __future__ import annotations

import json
import shutil
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import torch

from uncertsplat.baselines.runs import LoadedRun, load_single_model, mean_exposure, read_run_config
from uncertsplat.console import console, q
from uncertsplat.conventions import ensemble_member_dir
from uncertsplat.errors import UserError, out_of_memory
from uncertsplat.eval.engine import SAME_RENDER, Sampler
from uncertsplat.io.atomic import atomic_write_text, run_lock
from uncertsplat.schemas import TrainSummary
from uncertsplat.types import GaussianSample


def member_config(cfg, i: int):
    """The TrainConfig of member ``i`` (``cfg.ensemble_members``' method, seed ``cfg.seed + i``)."""
    from uncertsplat.config import TrainConfig, build_config

    data = json.loads(cfg.model_dump_json())
    data.update(method=cfg.ensemble_members, seed=cfg.seed + i)
    return build_config(TrainConfig, data, source=f"ensemble member {i}")


def _train_members(scene: Path, run_dir: Path, cfg, device: torch.device, resume: bool, on_trainer) -> list:
    """Train (or keep, or resume) each member of the ensemble ``cfg`` in ``run_dir/members``; their summaries."""
    from uncertsplat.train.session import train_model

    n = cfg.ensemble_size
    summaries = []
    for i in range(n):
        mdir = ensemble_member_dir(run_dir, i)
        done = mdir / "train_summary.json"
        if not done.is_file():
            console.print(f"[bold]ensemble[/] member {i + 1}/{n} (seed {cfg.seed + i})")
            started = mdir.exists() and (mdir / "config.json").is_file()
            train_model(scene, mdir, member_config(cfg, i), device=device, resume=started, on_trainer=on_trainer,
                        done_label=f"member {i + 1}/{n} trained", resume_dir=run_dir)
        elif resume:
            console.print(f"[bold]ensemble[/] member {i + 1}/{n} (seed {cfg.seed + i}): trained before")
        summaries.append(TrainSummary.read(done))
    return summaries


def _members_transients(summaries: list[TrainSummary], members: list[Path]) -> dict[str, float] | None:
    """{photo: the share of its pixels any member left out} of the members' regions (``members``: their run folders;
    what the ensemble's fits leave out), None with the detection off (``summaries``' ``transients``)."""
    import numpy as np

    from uncertsplat.data.dataset import transient_mask_files
    from uncertsplat.io.images import read_mask

    if all(s.transients is None for s in summaries):
        return None
    kept: dict[str, np.ndarray] = {}  # photo -> [H,W] bool, the pixels every member kept
    apart: set[str] = set()  # photos whose members' masks differ in shape (members trained at other resolutions)
    for run_dir in members:
        for name, path in transient_mask_files(run_dir).items():
            mask = read_mask(path)
            if name in kept and kept[name].shape != mask.shape:
                apart.add(name)
            kept[name] = mask if name not in kept or name in apart else kept[name] & mask
    shares = {name: round(1.0 - float(m.mean()), 4) for name, m in sorted(kept.items())}
    for name in apart:  # no union to take: the largest member's share
        shares[name] = max((s.transients or {}).get(name, 0.0) for s in summaries)
    return shares


def train_ensemble(scene: Path, run_dir: Path, cfg, device: torch.device, resume: bool = False,
                   on_trainer=None) -> Path:
    """Train ``cfg.ensemble_size`` members (``cfg.ensemble_members``) into ``run_dir/members`` one after the other.

    A finished member (``train_summary.json`` present) is kept on ``resume``; an unfinished one resumes
    from its last checkpoint. Returns ``run_dir``.

    Raises:
        UserError: an existing run folder without ``resume``, a stored config of another method.
    """
    scene, run_dir = Path(scene), Path(run_dir)
    exists = run_dir.exists() and (not run_dir.is_dir() or any(p.name != ".lock" for p in run_dir.iterdir()))
    if exists and not resume:
        raise UserError("the run folder already exists", path=run_dir,
                        hint="Add --resume to continue it, or choose another output folder (-o).")
    if resume and (run_dir / "config.json").is_file():
        stored = read_run_config(run_dir)
        if stored.method != "ensemble":
            raise UserError(f"the run folder holds a '{stored.method}' run, not an ensemble", path=run_dir,
                            hint="Choose another output folder (-o).")
        if stored != cfg:
            console.print("[yellow]note:[/] resuming with the run's stored configuration")
        cfg = stored
    n = cfg.ensemble_size
    t0 = time.perf_counter()
    with run_lock(run_dir, "train"):
        atomic_write_text(run_dir / "config.json", cfg.model_dump_json(indent=2) + "\n")
        try:
            summaries = _train_members(scene, run_dir, cfg, device, resume, on_trainer)
        except (UserError, MemoryError, RuntimeError) as err:
            # (and memory that ran out before any member's checkpoint: its advice is the same command again)
            if not isinstance(err, UserError) and out_of_memory(err, "train") is None:
                raise
            if not exists and not any(run_dir.glob("members/*/ckpts/*")):
                # nothing trained (a scene the first member refused): the folder this call made goes, as a single
                # run's does, so the same command can run again (it was refused as an existing run, and --resume
                # went on with the failed settings)
                shutil.rmtree(run_dir / "members", ignore_errors=True)
                (run_dir / "config.json").unlink(missing_ok=True)
            raise
        first_scene = ensemble_member_dir(run_dir, 0) / "scene.json"
        atomic_write_text(run_dir / "scene.json", first_scene.read_text(encoding="utf-8"))
        psnrs = [s.test_psnr for s in summaries if s.test_psnr is not None]
        seconds = sum(s.seconds for s in summaries)
        summary = TrainSummary(
            method="ensemble", ensemble_size=n, steps=cfg.iterations, seconds=seconds,
            sec_per_step=seconds / max(cfg.iterations, 1), wall_seconds_this_call=time.perf_counter() - t0,
            num_gaussians=sum(s.num_gaussians for s in summaries), num_carriers=sum(s.num_carriers for s in summaries),
            peak_memory_mb=max(s.peak_memory_mb for s in summaries),
            test_psnr_members_mean=sum(psnrs) / len(psnrs) if psnrs else None,
            test_psnr=None,  # the ensemble's own PSNR (of the mean render) comes from `evaluate`
            variant=cfg.variant, device=str(device), scene=str(scene.resolve()), members=summaries,
            # what training warned about in any member, where the report and `evaluate` look for it
            warnings=list(dict.fromkeys(f"member {i + 1}: {w}" for i, s in enumerate(summaries) for w in s.warnings)),
            transients=_members_transients(summaries, [ensemble_member_dir(run_dir, i) for i in range(n)]))
        summary.write(run_dir / "train_summary.json")
    psnr_txt = (f", the members' held-out PSNR {summary.test_psnr_members_mean:.2f} dB on average (the ensemble's own "
                "comes from `evaluate`)" if summary.test_psnr_members_mean is not None else "")
    console.print(f"done: ensemble of {n} member{'s' if n != 1 else ''}, {summary.seconds:.1f} s of training in all"
                  f"{psnr_txt} -> {run_dir}")
    return run_dir


@dataclass
class EnsembleRun(LoadedRun):
    """A loaded ensemble: ``model`` etc. are member 0's (for printing), ``config`` is the ensemble's."""

    members: list[LoadedRun] = field(default_factory=list)

    def member_samples(self) -> list[GaussianSample]:
        """The render-ready Gaussians of every member (a variational member's posterior mean)."""
        from uncertsplat.gaussians.variational import posterior_mean

        out = []
        with torch.no_grad():  # renders to score, nothing to differentiate
            for m in self.members:
                out.append(posterior_mean(m.model, **m.sample_kwargs))
        return out

    @property
    def variational_members(self) -> bool:
        """Whether the members are variational models with a posterior to sample."""
        return any(m.config.method == "variational" and m.model.num_carriers > 0 for m in self.members)

    def sampler(self, scene_scale: float, device: torch.device) -> Sampler:
        """Samples cycle through the members (``ensemble_sample_fn``): each member's render, or with variational
        members a posterior sample of it; no deterministic render of its own."""
        members = self.member_samples()
        draws = [m.sample_fn() for m in self.members] if self.variational_members else members
        return Sampler(ensemble_sample_fn(draws), self.render_fn(scene_scale, device), empty_std=self.empty_std(),
                       coverage=self.coverage(scene_scale, device, members[0]), mean_sample=members[0],
                       exposure=self.photo_exposure())

    def transient_runs(self) -> list:
        """Each member's run folder (or its checkpoint's regions): a region any member's training left out is left
        out of the fits."""
        return [r for m in self.members for r in m.transient_runs()]

    def size_text(self) -> str:
        """All members' Gaussians (``model`` is member 0's alone)."""
        what = "each with its posterior" if self.variational_members else "no posterior"
        return f"{sum(len(m.model) for m in self.members)} Gaussians in {len(self.members)} members ({what})"

    def _method_notes(self, num_samples: int) -> list[str]:
        n = len(self.members)
        if n == 1 and not self.variational_members:
            return [f"ensemble of 1 member: {SAME_RENDER}, so the samples' spread is 0 everywhere; "
                    "the std holds the predictive's other terms (the 'std² =' note lists them)"]
        if num_samples % n:
            return [f"K={num_samples} is not a multiple of the {n} ensemble members: members are weighted "
                    f"unequally (K = {n} uses each member once)"]
        return []


def load_ensemble(run_dir: Path, cfg, device: torch.device | str = "cpu") -> EnsembleRun:
    """Load every member of the ensemble run ``run_dir`` whose config is ``cfg`` (``runs.load_run`` calls it).

    Raises:
        UserError: a member folder missing or unfinished (the message names it and how to finish it).
    """
    run_dir = Path(run_dir)
    members = []
    for i in range(cfg.ensemble_size):
        mdir = ensemble_member_dir(run_dir, i)
        if not (mdir / "train_summary.json").is_file():
            raise UserError(f"ensemble member {i} is missing or unfinished", path=mdir,
                            hint=f"Finish it with: uncertsplat train SCENE -o {q(run_dir)} --method ensemble --resume")
        members.append(load_single_model(mdir, device))
    first = members[0]
    return EnsembleRun(first.model, cfg, first.scene_path, first.extent, first.step, first.sh_degree, run_dir,
                       run_dir, first.transparent, mean_exposure([m.exposure for m in members]), first.near,
                       members=members)


def ensemble_sample_fn(samples: list):
    """A ``sample_fn(generator)`` that cycles through ``samples`` in a random order per sequence; a member given as a
    function ``generator -> GaussianSample`` (a variational member's posterior) is drawn from with the generator.

    A sequence starts whenever the generator is not in the state this function left it in (a fresh
    seed per view, or another generator); it then draws a permutation of the members from the
    generator and returns them in that order, drawing a new permutation after every full cycle. So K
    samples of one view use each member once when K = N, the same seed gives the same members, and
    no state leaks between views. The sequence is kept per thread, so threads that draw at once (each with its own
    generator, as ``Predictor.predict`` from a thread pool) each get the members a serial draw gives them.
    """
    if not samples:
        raise ValueError("an ensemble needs at least one member")
    n = len(samples)
    # per thread: one shared sequence let a second thread's draw restart the first's cycle (the same member drawn
    # twice in one view, a wrong std without a word)
    local = threading.local()

    def sample_fn(generator: torch.Generator) -> GaussianSample:
        state = local.__dict__
        if not state:
            state.update(expect=None, order=[], pos=0)
        current = generator.get_state()
        fresh = state["expect"] is None or not torch.equal(current, state["expect"])
        if fresh or state["pos"] >= len(state["order"]):
            state["order"] = torch.randperm(n, generator=generator, device=generator.device).tolist()
            state["pos"] = 0
            current = generator.get_state()
        member = samples[state["order"][state["pos"]]]
        state["pos"] += 1
        if callable(member):
            member = member(generator)
            current = generator.get_state()  # the draw moved it: the sequence goes on from here
        state["expect"] = current
        return member

    return sample_fn
