"""Frames finished on the device (render.device_finish) give the host's bytes, in the stage too, and resume."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
from PIL import Image

from clothgap.runs import clip_id
from render.backend import find_libllvm, load_mitsuba
from render.config import RenderConfig
from render.exr import read_exr
from render.frames import FRAMES_FILE
from render.scene import ClipRenderer
from render.synthetic import waving_sheet
from render.tonemap import encode_srgb8, encode_srgb8_device, srgb8_steps, srgb8_table
from render.variants import get_variant

BACKEND = "llvm_ad_rgb"   # the device path needs Dr.Jit arrays; on CPU that is the LLVM backend
pytestmark = pytest.mark.skipif(find_libllvm() is None, reason="llvm_ad_rgb needs libLLVM 16+")


def photos(folder):
    """A folder of small background photographs (random colours, odd sizes) for background='folder'."""
    folder.mkdir()
    rng = np.random.default_rng(3)
    for i, (w, h) in enumerate([(40, 30), (25, 50), (33, 33)]):
        Image.fromarray(rng.integers(0, 256, (h, w, 3), np.uint8)).save(folder / f"room{i}.png")
    return folder


def variant_named(name, tmp_path):
    if name == "photos":
        return replace(get_variant("paper"), name="photos", background="folder",
                       background_dir=str(photos(tmp_path / "photos")))
    if name == "camera":  # exposure, white balance and vignetting without the noise, under a curved operator
        return replace(get_variant("camera-noise"), name="camera", shot_noise=0.0, read_noise=0.0, tonemap="filmic")
    return get_variant(name)


def test_device_encoding_gives_the_host_codes_at_every_step_for_float32_and_float64():
    mi = load_mitsuba(BACKEND)
    import drjit as dr

    steps = srgb8_steps()
    for dtype, array in ((np.float32, mi.Float), (np.float64, dr.float64_array_t(mi.Float))):
        s = steps.astype(dtype)
        values = np.concatenate([s, np.nextafter(s, dtype(0)), np.nextafter(s, dtype(2)),
                                 np.random.default_rng(0).uniform(0, 1, 20_000).astype(dtype),
                                 np.array([-1.0, 0.0, -0.0, 1.0, 2.0, np.inf, -np.inf, np.nan], dtype)])
        base, inside = srgb8_table(dtype)
        codes = encode_srgb8_device(array(values), dr.uint32_array_t(mi.Float)(base.astype(np.uint32)), array(inside))
        assert np.array_equal(np.asarray(codes), encode_srgb8(values)), dtype


@pytest.mark.parametrize("name", ["paper", "reinhard", "filmic", "camera", "photos", "motion-blur"])
def test_device_frames_are_the_host_frames(name, tmp_path):
    variant = variant_named(name, tmp_path)
    r = ClipRenderer(waving_sheet(frames=2, n=8), variant, resolution=32, spp=2, run_seed=7, clip_index=3,
                     backend=BACKEND)
    assert r.device_finish_unsupported is None
    for t in range(2):
        hdr = r.render_hdr(t)
        device, linear = r.render_finished(t, hdr=True)     # the same scene, frame and seed: the same render,
        # up to the order of the film's atomic adds, which LLVM's threads change on a busy CPU
        np.testing.assert_allclose(linear, hdr, rtol=1e-5, atol=1e-7)
        host = r.finish(linear, t)                           # the host's finish of the image the device finished
        assert device.shape == host.shape and device.dtype == np.uint8
        diff = np.abs(device.astype(int) - host)
        # Byte-identical on llvm_ad_rgb; the contract (and CUDA's fused multiply-adds) allow 1 code, rarely.
        assert diff.max() <= 1 and np.mean(diff > 0) < 1e-3, (name, t, diff.max(), np.mean(diff > 0))
    assert 20 < host.mean() < 235   # a real image: neither black nor white


def test_stage_frames_and_exrs_are_unchanged_by_the_switch_and_noise_stays_on_the_host(tmp_path):
    from render.stage import render_clip

    clip = waving_sheet(frames=3, n=8)
    # A scene per clip: a pooled scene retargeted from another clip renders a first frame that differs in the
    # last bits from a fresh one, and here the two paths must see the same scene.
    config = RenderConfig(resolution=24, spp=2, backend=BACKEND, writer_threads=2, reuse_scenes=False)
    for name, where in (("reinhard", "device"), ("camera-noise", "host")):
        out = {}
        for device in (True, False):
            folder = tmp_path / f"{name}-{device}"
            meta = render_clip(clip, get_variant(name), folder, config=config, run_seed=1, clip_index=4,
                               device_finish=device)
            out[device] = folder
            assert meta["render"]["finished_on"] == (where if device else "host")
            if device and where == "host":
                assert "noise" in meta["render"]["host_finish_because"]
        frames = np.load(out[True] / FRAMES_FILE)
        assert np.array_equal(frames, np.load(out[False] / FRAMES_FILE)), name
        for t in range(3):
            assert np.array_equal(read_exr(out[True] / "hdr" / f"{t:04d}.exr"),
                                  read_exr(out[False] / "hdr" / f"{t:04d}.exr"))
            with Image.open(out[True] / "ldr" / f"{t:04d}.png") as im:
                assert np.array_equal(np.asarray(im), frames[t])


def test_frames_in_flight_give_the_same_frames_in_order(tmp_path):
    from render.stage import render_clip

    clip = waving_sheet(frames=5, n=8)
    frames = {}
    for depth in (1, 3):
        config = RenderConfig(resolution=24, spp=2, backend=BACKEND, writer_threads=2, reuse_scenes=False,
                              write_png=False, frames_in_flight=depth)
        folder = tmp_path / f"depth{depth}"
        meta = render_clip(clip, get_variant("paper"), folder, config=config, run_seed=1, clip_index=4)
        assert meta["render"]["finished_on"] == "device"
        frames[depth] = np.load(folder / FRAMES_FILE)
        frames[f"hdr{depth}"] = np.stack([read_exr(folder / "hdr" / f"{t:04d}.exr") for t in range(5)])
    assert len({frames[1][t].tobytes() for t in range(5)}) == 5       # the cloth moves: every frame differs
    assert np.array_equal(frames[1], frames[3]) and np.array_equal(frames["hdr1"], frames["hdr3"])
    assert RenderConfig(frames_in_flight=0).problems()


def test_a_device_finished_run_resumes_to_the_same_frames(tmp_path):
    from render.stage import run_render
    from tests.test_render_frames import with_render
    from tests.test_render_output import make_run

    run = with_render(make_run(tmp_path / "run", clips=2, frames=3), backend=BACKEND, write_png=False,
                      write_hdr=False)
    assert run_render(run, progress=False)["rendered"] == 2
    folder = run.render_dir("paper", run.config.sim.settings()[0]) / clip_id(1)
    meta = json.loads((folder / "meta.json").read_text())
    assert meta["render"]["finished_on"] == "device" and meta["render"]["backend"] == BACKEND
    before = np.load(folder / FRAMES_FILE)
    (folder / "DONE").unlink()          # killed before its DONE: redone, the same way; the other clip is kept
    (folder / FRAMES_FILE).unlink()
    again = run_render(run, progress=False)
    assert again["rendered"] == 1 and again["skipped"] == 1
    assert np.array_equal(np.load(folder / FRAMES_FILE), before)
