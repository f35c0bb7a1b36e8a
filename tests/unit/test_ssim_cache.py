"""The training photos' SSIM statistics kept between steps (``TrainConfig.ssim_cache_mb``, ``SsimTargetCache``): the
same training to the bit with and without them, the budget, the low-resolution phase's own entries, and the cases
where nothing is kept."""

from __future__ import annotations

import pydantic
import pytest
import torch

from tests.e2e.test_train_resume import toy_config, toy_scene
from uncertsplat.config import TrainConfig
from uncertsplat.train.losses import SsimTargetCache
from uncertsplat.train.trainer import Trainer


@pytest.fixture
def native_kernels(monkeypatch):
    from uncertsplat import native

    if native.library() is None:  # (no compiler, or no writable cache for the build)
        pytest.skip("the native CPU kernels are not available on this machine")
    monkeypatch.setenv("UNCERTSPLAT_RASTERIZER", "native")


def _train(cfg: TrainConfig, steps: int) -> Trainer:
    scene, tr, te = toy_scene(width=48, height=36)
    t = Trainer(scene, cfg, tr, te)
    for _ in range(steps):
        t.train_step()
    return t


class TestSsimTargetCache:
    def test_keeps_each_photo_once_within_the_budget(self, native_kernels):
        photos = torch.rand(3, 1, 20, 30, 3, generator=torch.Generator().manual_seed(0))
        per_photo = 8 * 20 * 30 * 3
        cache = SsimTargetCache(2 * per_photo + 10)
        first = cache.get(0, photos[0])
        assert first is not None and cache.get(0, photos[0]) is first  # the same tensor, not blurred again
        assert cache.get(1, photos[1]) is not None
        assert cache.used_bytes == 2 * per_photo <= cache.budget_bytes
        assert cache.get(2, photos[2]) is None and len(cache) == 2  # past the budget: blurred in the loss
        assert cache.get(1, photos[1]) is not None  # the photos kept stay

    def test_a_budget_of_exactly_the_photos_keeps_them(self, native_kernels):
        photos = torch.rand(2, 1, 20, 30, 3, generator=torch.Generator().manual_seed(0))
        cache = SsimTargetCache(2 * 8 * 20 * 30 * 3)
        assert cache.get(0, photos[0]) is not None and cache.get(1, photos[1]) is not None
        assert cache.used_bytes == cache.budget_bytes

    def test_pending_bytes_are_the_photos_statistics_not_kept_yet_within_the_budget(self, native_kernels):
        """What the trainer's memory room reserves for the cache (``Trainer._memory_room``): the statistics of the
        training photos still to be kept, at most what the budget leaves, 0 once the budget is spent."""
        photos = torch.rand(3, 20, 30, 3, generator=torch.Generator().manual_seed(0))
        per_photo = 8 * 20 * 30 * 3
        cache = SsimTargetCache(10**9)  # a budget far above the photos: only they are reserved
        assert cache.pending_bytes(photos.shape) == 3 * per_photo
        cache.get(0, photos[:1])
        assert cache.pending_bytes(photos.shape) == 2 * per_photo
        small = SsimTargetCache(per_photo + 10)  # a budget under the photos: what it leaves
        assert small.pending_bytes(photos.shape) == per_photo + 10
        small.get(0, photos[:1])
        assert small.pending_bytes(photos.shape) == 10
        assert small.get(1, photos[1:2]) is None and small.pending_bytes(photos.shape) == 0  # spent
        assert SsimTargetCache(0).pending_bytes(photos.shape) == 0

    def test_nothing_is_kept_with_no_budget_or_without_the_fused_kernel(self, native_kernels, monkeypatch):
        photo = torch.rand(1, 20, 30, 3, generator=torch.Generator().manual_seed(0))
        assert SsimTargetCache(0).get(0, photo) is None
        assert SsimTargetCache(10**9).get(0, photo.double()) is None
        monkeypatch.setenv("UNCERTSPLAT_RASTERIZER", "torch")
        cache = SsimTargetCache(10**9)
        assert cache.get(0, photo) is None and len(cache) == 0


class TestTrainingWithTheStatistics:
    def test_the_same_parameters_to_the_bit_as_without(self, native_kernels):
        """20 steps with the photos' statistics kept (the default) and with ``ssim_cache_mb = 0``: every parameter
        the same bits; the cache holds an entry for each photo a step used and nothing of the other runs."""
        runs = {mb: _train(toy_config(iterations=20, ssim_cache_mb=mb), 20) for mb in (1024.0, 0.0)}
        kept, off = runs[1024.0], runs[0.0]
        assert len(kept.ssim_cache) > 0 and len(off.ssim_cache) == 0
        for name, value in kept.model.params.items():
            assert torch.equal(value, off.model.params[name]), name

    def test_the_low_resolution_steps_keep_their_own_entries(self, native_kernels):
        t = _train(toy_config(iterations=12, low_res_fraction=0.5, densify={"start": 1000}, method="deterministic"),
                   12)
        sizes = {tuple(v.shape[-2:]) for v in t.ssim_cache._stats.values()}
        assert sizes == {(18, 24), (36, 48)}
        assert {low for _, low in t.ssim_cache._stats} == {True, False}

    def test_negative_budgets_are_refused(self):
        with pytest.raises(pydantic.ValidationError):
            TrainConfig(ssim_cache_mb=-1)
