"""The frame cache, sub-sequences, bad frames and augmentation."""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import pytest
import torch

from clothgap.config import StudyConfig
from learn.config import TrainConfig
from learn.dataset import build_cache, read_frames, subsequence_starts
from learn.windows import WindowSet, gather_rows
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
    stamp = run.frame_cache_path(VARIANT, SETTING, 32).stat().st_mtime_ns
    build_cache(run, VARIANT, SETTING, 32, progress=False)
    assert run.frame_cache_path(VARIANT, SETTING, 32).stat().st_mtime_ns == stamp

    data = WindowSet(cache, ["c00000", "c00003", "c99999"], clip_len=5, clip_stride=3)
    assert len(data) == 2 * 3   # starts 0, 3, 6; an unknown clip id is skipped
    assert data.labels.tolist() == [0, 0, 0, 53, 53, 53] and data.starts.tolist() == [0, 3, 6] * 2
    (x, labels, target), = list(data.batches(6))
    assert x.shape == (6, 5, 3, 32, 32) and x.dtype == torch.float32 and target is None
    assert labels.tolist() == [0, 0, 0, 53, 53, 53]
    # Each window is its clip's frames start..start+4, scaled to [0, 1].
    c3 = cache.clips["c00003"]
    expected = torch.from_numpy(np.array(cache.frames[c3.offset + 3:c3.offset + 8])).permute(0, 3, 1, 2) / 255
    assert torch.equal(x[4], expected)


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


def test_augmentation_is_fixed_by_seed_and_epoch_whatever_the_batching(run):
    cache = build_cache(run, VARIANT, SETTING, 32, progress=False)
    data = WindowSet(cache, sorted(cache.clips), clip_len=4, clip_stride=4)

    def epoch(seed, number, batch_size, ranks=1):
        order = [data.order(seed, number, r, ranks) for r in range(ranks)]
        table = data.augment_table(seed, number)
        out = {}
        for rank_order in order:
            for lo in range(0, len(rank_order), batch_size):
                idx = rank_order[lo:lo + batch_size]
                (x, _, _), = list(data.batches(batch_size, order=idx, augment=table))
                out.update({int(i): xi for i, xi in zip(idx, x)})
        return out

    whole = epoch(7, 0, batch_size=16)
    assert sorted(whole) == list(range(len(data)))
    split = epoch(7, 0, batch_size=3, ranks=2)          # other batches, two DDP ranks: same windows
    assert all(torch.equal(whole[i], split[i]) for i in whole)
    plain = {i: x for i, x in enumerate(next(data.batches(len(data)))[0])}
    assert not torch.equal(whole[1], plain[1])
    later = epoch(7, 1, batch_size=16)
    assert not torch.equal(whole[1], later[1])
    assert whole[1].shape == plain[1].shape and 0 <= float(whole[1].min()) and float(whole[1].max()) <= 1
    assert torch.equal(data.order(7, 0), data.order(7, 0)) and not torch.equal(data.order(7, 0), data.order(7, 1))


def test_identity_augmentation_leaves_frames_unchanged(run):
    from learn.windows import augment_batch

    cache = build_cache(run, VARIANT, SETTING, 32, progress=False)
    x, _, _ = next(WindowSet(cache, sorted(cache.clips), clip_len=4, clip_stride=4).batches(4))
    # side 1 (params[1] = 1), centred, no flip (params[4] >= 0.5), colour factors 1 (params 5-7 = 0.5).
    params = torch.tensor([[0.0, 1.0, 0.5, 0.5, 0.9, 0.5, 0.5, 0.5]]).repeat(len(x), 1)
    assert torch.allclose(augment_batch(x.clone(), params), x, atol=1e-5)
    params[:, 4] = 0.1                                   # a flip mirrors every frame of the clip
    assert torch.allclose(augment_batch(x.clone(), params), x.flip(-1), atol=1e-5)
    # Without the crop a flip and a small crop leave every pixel where it was; only colours change.
    params[:, 1], params[:, 2], params[:, 5] = 0.0, 0.0, 0.0
    assert torch.allclose(augment_batch(x.clone(), params, crop=False), (0.8 * x).clamp(0, 1), atol=1e-5)
    moved = augment_batch(x.clone(), params)
    assert not torch.allclose(moved, (0.8 * x).clamp(0, 1), atol=1e-3)


def test_config_fields_have_defaults():
    # TrainConfig may only grow with defaults: old run folders must still load.
    assert all(f.default is not dataclasses.MISSING for f in dataclasses.fields(TrainConfig))


def test_a_cache_that_would_not_fit_on_disk_is_refused_by_name(run, monkeypatch):
    import shutil

    from clothgap.errors import StorageError

    real = shutil.disk_usage
    monkeypatch.setattr(shutil, "disk_usage", lambda p: real(p)._replace(free=1000))
    with pytest.raises(StorageError, match=r"32\.npy needs .* GiB free"):
        build_cache(run, VARIANT, SETTING, 32, progress=False)
    folder = run.frame_cache_path(VARIANT, SETTING, 32).parent
    assert not list(folder.iterdir())                      # no temporary array, no index
    monkeypatch.setattr(shutil, "disk_usage", real)
    assert build_cache(run, VARIANT, SETTING, 32, progress=False).frames.shape[0] == 4 * 12


def test_a_killed_cache_build_leaves_no_temporary_after_the_next_build(run):
    import subprocess
    import sys

    folder = run.frame_cache_path(VARIANT, SETTING, 32).parent
    folder.mkdir(parents=True, exist_ok=True)
    gone = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True,
                          text=True).stdout.strip()          # a pid whose process has exited
    stem = run.frame_cache_path(VARIANT, SETTING, 32).stem
    (folder / f"{stem}.tmp{gone}.npy").write_bytes(b"half a cache")     # what kill -9 mid-build leaves
    alive = folder / f"{stem}.tmp1.npy"                                  # pid 1 exists: another build, kept
    alive.write_bytes(b"in progress")
    build_cache(run, VARIANT, SETTING, 32, progress=False)
    assert sorted(p.name for p in folder.iterdir() if ".tmp" in p.name) == [alive.name]


def test_a_cache_built_in_a_process_pool_is_the_one_built_here(tmp_path):
    """Two runs of the same synthetic clips, one clip corrupt in each: the pool's cache holds every clip's frames
    at the rows the in-process build gives them and leaves the same clip out, naming it."""
    cfg = StudyConfig(sim=SimConfig(classes=(0, 53), sequences_per_class=3, frames=12),
                      render=RenderConfig(resolution=40), train=TrainConfig(image_size=32))
    caches = {}
    for processes in (0, 2):
        run = synthetic_run(tmp_path / f"run{processes}", cfg)
        (run.render_dir(VARIANT, SETTING) / "c00002" / "ldr" / "0005.png").write_bytes(b"not a png")
        with pytest.warns(UserWarning, match="c00002.*0005.png"):
            caches[processes] = build_cache(run, VARIANT, SETTING, 32, progress=False, processes=processes)
    here, pooled = caches[0], caches[2]
    assert pooled.clips == here.clips and "c00002" not in pooled.clips and len(pooled.clips) == 5
    for clip in here.clips.values():
        rows = slice(clip.offset, clip.offset + clip.num_frames)
        assert np.array_equal(pooled.frames[rows], here.frames[rows])
        assert pooled.frames[rows].std() > 0                     # the clip's frames, not an empty stretch


def test_rows_gathered_in_chunks_are_the_rows_and_bad_rows_are_named(tmp_path):
    frames = np.lib.format.open_memmap(tmp_path / "frames.npy", mode="w+", dtype=np.uint8, shape=(50, 4, 3, 3))
    frames[:] = np.random.default_rng(0).integers(0, 256, frames.shape, dtype=np.uint8)
    rows = np.array([3, 4, 5, 17, 18, 40, 41, 42, 43, 49, 0])
    for chunk_bytes in (None, 1, 36 * 2, 36 * 3, 36 * 100):    # a row is 36 bytes: chunks of 1, 2, 3 rows, all
        got = gather_rows(frames, rows, "cpu", chunk_bytes=chunk_bytes)
        assert got.dtype == torch.uint8 and np.array_equal(got.numpy(), frames[rows]), chunk_bytes
    assert gather_rows(frames, np.zeros(0, np.int64), "cpu", chunk_bytes=36).shape == (0, 4, 3, 3)
    frames.flush()
    read_only = np.load(tmp_path / "frames.npy", mmap_mode="r")         # as the frame cache opens it
    with warnings.catch_warnings():
        warnings.simplefilter("error")              # (torch warns of a tensor made from a read-only array)
        assert np.array_equal(gather_rows(read_only, rows, "cpu", chunk_bytes=72).numpy(), frames[rows])
    with pytest.raises(IndexError, match="50 frames"):
        gather_rows(frames, np.array([2, 50]), "cpu", chunk_bytes=72)


def test_frames_stay_on_the_gpu_while_a_quarter_of_its_free_memory_and_8_gib_stay_free(monkeypatch):
    from learn import windows

    gib = 1 << 30
    cuda = torch.device("cuda", 0)
    for free, nbytes, fits in ((79 * gib, 46 * gib, True),       # 768 a class's training frames, one model a GPU
                               (79 * gib, 60 * gib, False),
                               (52 * gib, 23 * gib, True),       # a second 384 model beside one
                               (30 * gib, 23 * gib, False),      # a third: 8 GiB would not be left
                               (10 * gib, 3 * gib, False)):
        monkeypatch.setattr(torch.cuda, "mem_get_info", lambda device, free=free: (free, 80 * gib))
        assert windows._fits_on_device(nbytes, cuda) is fits, (free / gib, nbytes / gib)
    assert windows._fits_on_device(10**15, torch.device("cpu"))
