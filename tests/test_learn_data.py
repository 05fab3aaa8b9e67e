"""The frame cache, sub-sequences, bad frames and augmentation."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from clothgap.config import StudyConfig
from learn.config import TrainConfig
from learn.dataset import SubsequenceDataset, build_cache, cache_path, read_frames, subsequence_starts
from learn.synthetic import synthetic_run
from sim.config import SimConfig
from render.config import RenderConfig

SETTING, VARIANT = "wind-uniform1", "paper"


@pytest.fixture
def run(tmp_path):
    cfg = StudyConfig(sim=SimConfig(classes=(0, 53), sequences_per_class=2, frames=12),
                      render=RenderConfig(resolution=40), train=TrainConfig(image_size=32))
    return synthetic_run(tmp_path / "run", cfg)


def test_subsequence_starts():
    assert subsequence_starts(20, 10, 5) == [0, 5, 10]
    assert subsequence_starts(9, 10, 5) == []
    with pytest.raises(ValueError, match="clip_stride"):
        subsequence_starts(20, 10, 0)


def test_cache_holds_resized_frames_and_is_reused(run):
    cache = build_cache(run, VARIANT, SETTING, 32, progress=False)
    assert cache.frames.shape == (4 * 12, 32, 32, 3) and cache.frames.dtype == np.uint8
    clip = cache.clips["c00001"]
    expected = read_frames(run.render_dir(VARIANT, SETTING) / "c00001", 32)
    np.testing.assert_array_equal(cache.frames[clip.offset:clip.offset + clip.num_frames], expected)
    stamp = cache_path(run, VARIANT, SETTING, 32).stat().st_mtime_ns
    build_cache(run, VARIANT, SETTING, 32, progress=False)
    assert cache_path(run, VARIANT, SETTING, 32).stat().st_mtime_ns == stamp

    data = SubsequenceDataset(cache, ["c00000", "c00003", "c99999"], clip_len=5, clip_stride=3)
    assert len(data) == 2 * 3   # starts 0, 3, 6; an unknown clip id is skipped
    frames, label = data[0]
    assert frames.shape == (5, 3, 32, 32) and frames.dtype == torch.uint8 and label == 0
    assert data.labels == [0, 0, 0, 53, 53, 53]


def test_corrupt_and_missing_frames_are_reported_and_skipped(run):
    clips = run.render_dir(VARIANT, SETTING)
    (clips / "c00001" / "ldr" / "0004.png").write_bytes(b"not a png")
    (clips / "c00002" / "ldr" / "0007.png").unlink()
    with pytest.warns(UserWarning) as caught:
        cache = build_cache(run, VARIANT, SETTING, 32, progress=False)
    messages = " ".join(str(w.message) for w in caught)
    assert "c00001" in messages and "0004.png" in messages
    assert "c00002" in messages and "0007.png" in messages
    assert sorted(cache.clips) == ["c00000", "c00003"]
    with pytest.warns(UserWarning) as again:   # a reused cache still says what it left out
        build_cache(run, VARIANT, SETTING, 32, progress=False)
    assert {str(w.message).split(":")[0] for w in again} == {"clip c00001", "clip c00002"}


def test_augmentation_is_fixed_by_seed_epoch_and_item(run):
    cache = build_cache(run, VARIANT, SETTING, 32, progress=False)
    ids = sorted(cache.clips)
    data = SubsequenceDataset(cache, ids, clip_len=4, clip_stride=4, augment=True, seed=7)
    again = SubsequenceDataset(cache, ids, clip_len=4, clip_stride=4, augment=True, seed=7)
    plain = SubsequenceDataset(cache, ids, clip_len=4, clip_stride=4)
    assert torch.equal(data[1][0], again[1][0])
    assert not torch.equal(data[1][0], plain[1][0])
    before = data[1][0]
    data.set_epoch(1)
    assert not torch.equal(before, data[1][0])
    assert data[1][0].shape == plain[1][0].shape and data[1][0].dtype == torch.uint8


def test_config_fields_have_defaults():
    # TrainConfig may only grow with defaults: old run folders must still load.
    assert all(f.default is not dataclasses.MISSING for f in dataclasses.fields(TrainConfig))
