"""A clip's frames as one uint8 array: the same bytes as its PNGs, in the cache either way, never half-written."""

from __future__ import annotations

import json
import shutil
from dataclasses import replace

import numpy as np
import pytest
from PIL import Image

from clothgap.runs import DONE, Run, clip_id
from learn.dataset import build_cache
from render.frames import FRAMES_FILE, FrameError, export_png, main as frames_main, read_clip_frames
from render.tonemap import LUT_BINS, OPERATORS, encode_srgb8, srgb8_reference, srgb8_steps, tonemap
from tests.test_render_output import make_run

SETTING, VARIANT = "wind-uniform1", "paper"


def with_render(run: Run, **settings) -> Run:
    return replace(run, config=replace(run.config, render=replace(run.config.render, **settings)))


def cache_bytes(run: Run, size: int) -> tuple[np.ndarray, dict]:
    cache = build_cache(run, VARIANT, SETTING, size, progress=False)
    return np.array(cache.frames), {c.clip_id: (c.offset, c.num_frames) for c in cache.clips.values()}


def test_frames_npy_holds_the_png_bytes_and_packs_into_the_same_cache_as_pngs(tmp_path):
    from render.stage import run_render

    run = make_run(tmp_path / "run", clips=3, frames=3)
    assert run_render(run, progress=False)["rendered"] == 3
    folder = run.render_dir(VARIANT, SETTING)
    for cid in run.done_clips(folder):
        frames = np.load(folder / cid / FRAMES_FILE)
        assert frames.shape == (3, 16, 16, 3) and frames.dtype == np.uint8
        for t in range(3):
            with Image.open(folder / cid / "ldr" / f"{t:04d}.png") as im:
                assert np.array_equal(np.asarray(im), frames[t])
    from_arrays = {size: cache_bytes(run, size) for size in (16, 8)}   # as rendered, and resized
    # The same clips as an older run has them: PNGs only.
    shutil.rmtree(run.root / "cache")
    for cid in run.done_clips(folder):
        (folder / cid / FRAMES_FILE).unlink()
    for size, (frames, index) in from_arrays.items():
        png_frames, png_index = cache_bytes(run, size)
        assert png_index == index and np.array_equal(png_frames, frames), size


def test_without_png_or_exr_only_the_array_is_written_and_it_trains(tmp_path):
    from render.stage import run_render

    run = with_render(make_run(tmp_path / "run", clips=2, frames=3), write_png=False, write_hdr=False)
    assert run_render(run, progress=False)["rendered"] == 2
    folder = run.render_dir(VARIANT, SETTING) / clip_id(1)
    assert sorted(p.name for p in folder.iterdir()) == [DONE, FRAMES_FILE, "meta.json"]
    frames, index = cache_bytes(run, 16)
    assert np.array_equal(frames[index[clip_id(1)][0]:][:3], np.load(folder / FRAMES_FILE))
    paths = export_png(folder, tmp_path / "look")                      # a run is still inspectable frame by frame
    with Image.open(paths[2]) as im:
        assert np.array_equal(np.asarray(im), np.load(folder / FRAMES_FILE)[2])


def test_unfinished_and_damaged_clips_stay_out_of_the_cache_and_a_resumed_render_redoes_them(tmp_path):
    from render.stage import run_render

    run = with_render(make_run(tmp_path / "run", clips=3, frames=3), write_png=False, write_hdr=False)
    run_render(run, progress=False)
    folder = run.render_dir(VARIANT, SETTING)
    before = np.load(folder / clip_id(0) / FRAMES_FILE)
    # Killed after frames.npy but before DONE, with a temporary array of another kill beside it.
    (folder / clip_id(0) / DONE).unlink()
    (folder / clip_id(0) / "frames.tmp999.npy").write_bytes(b"\x93NUMPY half")
    # Finished, then damaged on disk.
    path = folder / clip_id(2) / FRAMES_FILE
    path.write_bytes(path.read_bytes()[:200])
    with pytest.warns(UserWarning) as caught:
        _, index = cache_bytes(run, 16)
    assert set(index) == {clip_id(1)}
    (message,) = [str(w.message) for w in caught if clip_id(2) in str(w.message)]
    assert str(path) in message and "left out" in message
    with pytest.raises(FrameError, match=f"clip {clip_id(2)}: frames .*{FRAMES_FILE}"):
        read_clip_frames(folder / clip_id(2), 3)

    summary = run_render(run, progress=False)
    assert summary["rendered"] == 1 and summary["skipped"] == 2            # the unfinished clip, redone
    assert np.array_equal(np.load(folder / clip_id(0) / FRAMES_FILE), before)
    assert not list(folder.rglob("*.tmp*"))
    (folder / clip_id(2) / FRAMES_FILE).write_bytes(np.load(folder / clip_id(0) / FRAMES_FILE)[:2].tobytes())
    with pytest.raises(FrameError, match="unreadable"):
        read_clip_frames(folder / clip_id(2), 3)
    np.save(folder / clip_id(2) / FRAMES_FILE, before[:2])                 # a well-formed array, one frame short
    with pytest.raises(FrameError, match=r"not 3 frames"):
        read_clip_frames(folder / clip_id(2), 3)


def test_frames_command_names_a_clip_without_frames(tmp_path, capsys):
    with pytest.raises(SystemExit, match=f"error: clip empty: no frames in .*and no {FRAMES_FILE}"):
        frames_main([str(tmp_path / "empty"), "--out", str(tmp_path / "out")])


def test_srgb_lookup_gives_the_reference_codes_at_every_step_and_between():
    steps = srgb8_steps()
    assert len(steps) == 255 and np.all(np.diff(steps) > 1.0 / LUT_BINS)
    edges = np.arange(LUT_BINS + 1) / LUT_BINS
    values = np.concatenate([steps, np.nextafter(steps, 0), np.nextafter(steps, 2), edges,
                             np.random.default_rng(0).uniform(0, 1, 200_000)])
    assert np.array_equal(encode_srgb8(values), srgb8_reference(values))
    assert encode_srgb8(np.array([-1.0, 2.0, np.inf, np.nan])).tolist() == [0, 255, 255, 0]
    linear = np.random.default_rng(1).uniform(-0.1, 6.0, (4, 16, 16, 3)).astype(np.float32)
    for name, op in OPERATORS.items():   # float32 frames, as the renderer hands them over
        assert np.array_equal(tonemap(linear, name), srgb8_reference(op(linear.astype(np.float64)))), name


def test_srgb_to_linear_is_colour_sciences_curve():
    import colour

    from render.textures import srgb_to_linear

    for dtype in (np.float32, np.float64):
        values = np.random.default_rng(2).uniform(-0.2, 1.2, 100_000).astype(dtype)
        values[:4] = [0.0, 1.0, 0.04045, float(colour.models.eotf_inverse_sRGB(0.0031308))]
        expected = np.asarray(colour.models.eotf_sRGB(np.clip(values, 0.0, 1.0)), np.float32)
        assert np.array_equal(srgb_to_linear(values), expected), dtype


def test_packed_frames_go_into_one_array_that_the_cache_indexes_in_place(tmp_path):
    """render.pack_frames: the frames of a (variant, setting) go into one array at render time, each clip at its
    index's rows; they read back as the per-clip array's bytes, the frame cache at the render resolution is that
    array (nothing copied), a resized cache is the same bytes either way, and a clip rendered again after a kill
    rewrites its rows."""
    from clothgap.executor import ExecutorOptions, run_stage
    from render.frames import STORE_KEY, store_path
    from render.stage import run_render
    from tests.conftest import synthetic_sim_run

    plain = synthetic_sim_run(tmp_path / "plain", clips=3, frames=3)
    packed = synthetic_sim_run(tmp_path / "packed", clips=3, frames=3, pack_frames=True)
    assert run_render(plain, progress=False)["rendered"] == 3
    assert run_stage(packed, "render", ExecutorOptions("process", workers=2, shard_size=2, progress=False)) \
        ["rendered"] == 3                                     # two processes write one array
    folder = packed.render_dir(VARIANT, SETTING)
    store = store_path(folder, 16)
    assert np.load(store, mmap_mode="r").shape == (packed.config.sim.num_clips() * 3, 16, 16, 3)
    for cid in packed.done_clips(folder):
        assert not (folder / cid / FRAMES_FILE).exists()
        pointer = json.loads((folder / cid / "meta.json").read_text())[STORE_KEY]
        assert pointer == {"file": store.name, "row": 3 * int(cid.lstrip("c")), "frames": 3}
        expected = np.load(plain.render_dir(VARIANT, SETTING) / cid / FRAMES_FILE)
        np.testing.assert_array_equal(read_clip_frames(folder / cid), expected)

    cache = build_cache(packed, VARIANT, SETTING, 16, progress=False)
    assert cache.array_path == store and not packed.frame_cache_path(VARIANT, SETTING, 16).exists()
    reference = build_cache(plain, VARIANT, SETTING, 16, progress=False)
    for size in (16, 12):
        ours, theirs = build_cache(packed, VARIANT, SETTING, size, progress=False), \
            build_cache(plain, VARIANT, SETTING, size, progress=False)
        for cid, clip in theirs.clips.items():
            mine = ours.clips[cid]
            np.testing.assert_array_equal(ours.frames[mine.offset:mine.offset + mine.num_frames],
                                          theirs.frames[clip.offset:clip.offset + clip.num_frames])
    index = packed.frame_cache_path(VARIANT, SETTING, 16).with_suffix(".json")
    stamp = index.stat().st_mtime_ns
    assert build_cache(packed, VARIANT, SETTING, 16, progress=False).array_path == store
    assert index.stat().st_mtime_ns == stamp                                        # the index reused

    # A clip killed after its rows were half written has no DONE: the next render writes its rows again.
    rows = np.load(store, mmap_mode="r+")
    rows[3:6] = 0
    del rows
    (folder / "c00001" / DONE).unlink()
    again = run_render(packed, progress=False)
    assert again["rendered"] == 1 and again["skipped"] == 2
    clip = reference.clips["c00001"]
    np.testing.assert_array_equal(read_clip_frames(folder / "c00001"),
                                  reference.frames[clip.offset:clip.offset + clip.num_frames])
    assert len(export_png(folder / "c00001", tmp_path / "look")) == 3     # still inspected frame by frame

    # A clip rendered again without packing (its own frames.npy) beside packed ones: the cache copies them all.
    (folder / "c00002" / DONE).unlink()
    assert run_render(with_render(packed, pack_frames=False), progress=False)["rendered"] == 1
    assert (folder / "c00002" / FRAMES_FILE).is_file()
    mixed = build_cache(packed, VARIANT, SETTING, 16, progress=False)
    assert mixed.array_path == packed.frame_cache_path(VARIANT, SETTING, 16)
    for cid, clip in reference.clips.items():
        mine = mixed.clips[cid]
        np.testing.assert_array_equal(mixed.frames[mine.offset:mine.offset + mine.num_frames],
                                      reference.frames[clip.offset:clip.offset + clip.num_frames])


def test_a_packed_array_of_other_settings_or_too_little_disk_stops_the_render_by_name(tmp_path, monkeypatch):
    import shutil as shutil_module

    from clothgap.errors import StorageError
    from render.frames import store_path
    from render.stage import run_render
    from tests.conftest import synthetic_sim_run

    run = synthetic_sim_run(tmp_path / "run", clips=2, frames=3, pack_frames=True)
    store = store_path(run.render_dir(VARIANT, SETTING), 16)
    real = shutil_module.disk_usage
    clip_bytes = 3 * 16 * 16 * 3
    monkeypatch.setattr(shutil_module, "disk_usage", lambda p: real(p)._replace(free=2 * clip_bytes - 1))
    with pytest.raises(StorageError, match="free some space"):
        run_render(run, progress=False)
    assert not store.exists() and not run.done_clips(run.render_dir(VARIANT, SETTING))
    # Room for the clips to render is enough, not for every clip index's rows (the array is sparse): a test-only
    # look renders a sixth of them.
    assert run.config.sim.num_clips() > 2
    monkeypatch.setattr(shutil_module, "disk_usage", lambda p: real(p)._replace(free=2 * clip_bytes))
    assert run_render(run, progress=False)["rendered"] == 2
    monkeypatch.setattr(shutil_module, "disk_usage", real)
    shutil.rmtree(run.render_dir(VARIANT, SETTING))
    store.parent.mkdir(parents=True, exist_ok=True)
    np.save(store, np.zeros((5, 16, 16, 3), np.uint8))          # made for another number of clips
    with pytest.raises(FrameError, match="made for other settings"):
        run_render(run, progress=False)
    assert not run.done_clips(run.render_dir(VARIANT, SETTING))
