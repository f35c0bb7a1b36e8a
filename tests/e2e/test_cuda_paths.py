"""The commands end to end on a CUDA device: the smoke pipeline (synth, train, evaluate, prune with its sweep, the
pruned model's evaluation, report), `select-views` by every score, the other methods' training, and the Python API.

They run with ``--device cuda`` on a GPU (``benchmarks/device_check.sh``) and with ``--device fake-cuda`` on the CPU
(``make test-fake-cuda``: ``tests/fake_cuda.py`` fails the session on any op that mixes the devices); with the
default ``--device cpu`` they are skipped, the same code being tested on the CPU elsewhere. Most unit tests of the
selection, the Predictor and the posterior build their tensors on the CPU, so without this file the emulator saw no
CUDA tensor in their code (a review planted CPU tensors there that it did not catch).
"""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from uncertsplat.config import SelectConfig, shipped_file


@pytest.fixture(scope="module")
def cuda_run(request, tmp_path_factory) -> Path:
    """The smoke pipeline's output folder, run on the test session's CUDA device."""
    name = request.config.getoption("--device")
    if name == "cpu":
        pytest.skip("a CUDA path: run with --device cuda on a GPU or --device fake-cuda (make test-fake-cuda)")
    from uncertsplat.stages import pipeline

    out = tmp_path_factory.mktemp("cuda") / "smoke"
    pipeline.run(shipped_file("smoke", "pipeline"), out, device="cuda",
                 overrides=["train.iterations=120", "evaluate.num_samples=2", "evaluate_pruned.num_samples=2"])
    return out


def test_the_smoke_pipeline_writes_every_stage(cuda_run):
    from uncertsplat.schemas.metrics import EvalReport

    report = EvalReport.read(cuda_run / "train" / "eval" / "metrics.json")
    assert report.device.startswith("cuda") and report.mean.psnr > 10
    assert (cuda_run / "prune" / "prune.json").is_file() and (cuda_run / "report" / "index.html").is_file()


@pytest.mark.parametrize("score", ["fisher", "variance", "unseen", "coverage"])
def test_select_views_scores_candidates_on_cuda(cuda_run, tmp_path, score):
    from uncertsplat.stages import select

    sel = select.run(cuda_run / "train", SelectConfig(score=score, candidates="around:6", num_views=2),
                     torch.device("cuda"), output=tmp_path / score)
    assert len(sel.chosen) == 2


def test_the_predictor_on_cuda(cuda_run, monkeypatch):
    """The maps come back on the CPU, and no view's maps stay on the device while the next view renders (a batch of
    poses held them all there, then joined them there: twice the batch's maps)."""
    import gc
    import weakref

    from uncertsplat.predict import Predictor
    from uncertsplat.uncertainty import mc

    real, kept = mc.mc_render, []

    def mc_render(*args, **kwargs):
        gc.collect()
        assert all(ref() is None for ref in kept), "an earlier view's maps are still on the device"
        maps, rest = real(*args, **kwargs)
        kept.append(weakref.ref(maps.rgb_std))
        return maps, rest

    monkeypatch.setattr(mc, "mc_render", mc_render)
    pred = Predictor.load(cuda_run / "train", "cuda")
    cams = pred.scene.cameras[[0, 1, 2]]
    out = pred.predict(cams.to(torch.device("cuda")), num_samples=2)
    assert len(kept) == 3 and out.rgb_std.device.type == "cpu"
    assert bool(torch.isfinite(out.depth_std).all()) and out.depth_std.shape[0] == 3
    points = pred.scene.cameras.centers[:3].to(torch.device("cuda"))
    assert pred.seen_free(points).shape == (3,)


@pytest.mark.parametrize("method", ["deterministic", "ensemble", "fisher"])
def test_the_other_methods_train_and_evaluate_on_cuda(cuda_run, tmp_path, method):
    from uncertsplat.baselines import train_run
    from uncertsplat.config import EvalConfig, train_config_from
    from uncertsplat.stages import evaluate

    cfg = train_config_from("tiny").model_copy(update={"iterations": 60, "method": method})
    if method == "ensemble":
        cfg = cfg.model_copy(update={"ensemble_size": 2})
    train_run(cuda_run / "synth", tmp_path / method, cfg, torch.device("cuda"))
    report = evaluate.run(tmp_path / method, EvalConfig(num_samples=2), torch.device("cuda"), quiet=True)
    assert report.mean.psnr > 5


def test_transients_found_and_left_out_on_cuda(cuda_run, tmp_path):
    """`transients.detect` on the device: the step's test and the kept masks, the written folder, then evaluate's fits
    and the Fisher baseline's curvature without them."""
    import shutil

    from uncertsplat.baselines import train_run
    from uncertsplat.config import EvalConfig, train_config_from
    from uncertsplat.data.dataset import TRANSIENTS_FOLDER
    from uncertsplat.io.images import read_image, write_png
    from uncertsplat.sfm.scene import load_scene
    from uncertsplat.stages import evaluate

    ws = tmp_path / "ws"
    shutil.copytree(cuda_run / "synth", ws)
    scene = load_scene(ws)
    for i in scene.split["train"][:3]:
        path = ws / "images" / scene.cameras.image_names[i]
        im = read_image(path)
        h, w = im.shape[:2]
        im[h // 4:h // 2, w // 4:w // 2] = (1.0, 0.0, 1.0)
        write_png(path, im)
    for method in ("variational", "fisher"):
        cfg = train_config_from("tiny", {"iterations": 150, "method": method,
                                         "transients": {"detect": True, "start": 0.3, "window": 0.1, "core": 0.5}})
        train_run(ws, tmp_path / method, cfg, torch.device("cuda"))
        assert any((tmp_path / method / TRANSIENTS_FOLDER).iterdir())
        report = evaluate.run(tmp_path / method, EvalConfig(num_samples=2), torch.device("cuda"), quiet=True)
        assert report.mean.psnr > 5 and any("transient objects training found" in n for n in report.notes)
