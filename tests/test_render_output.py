"""Rendered frames: HDR survives to EXR, seeds reproduce, alpha is kept, tone mapping is sane, the stage runs."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
from PIL import Image

from clothgap.config import ConfigError, preset, validate
from clothgap.runs import clip_id, is_done
from dataclasses import replace
from render.backend import BackendError, MIN_LLVM_VERSION, _LLVM_NAME, find_libllvm, load_mitsuba, resolve_backend
from render.exr import read_exr, write_exr
from render.scene import ClipRenderer
from render.synthetic import waving_sheet
from sim.clip import SimClip
from render.tonemap import OPERATORS, tonemap
from render.variants import USER_VARIANTS_ENV, get_variant
from tests.conftest import RENDER_BACKEND, synthetic_sim_run

BACKEND = RENDER_BACKEND


def render(variant="paper", clip_index=0, t=0, resolution=24, clip=None, **kw):
    clip = clip or waving_sheet(frames=3, n=8)
    renderer = ClipRenderer(clip, get_variant(variant), resolution=resolution, spp=2, run_seed=7,
                            clip_index=clip_index, backend=BACKEND, **kw)
    return renderer, renderer.render_frame(t)


@pytest.mark.parametrize("half", [False, True])
def test_hdr_above_one_survives_into_exr_exactly(tmp_path, half):
    _, frame = render("grid")  # a light cloth under the key light
    assert frame.hdr[..., :3].max() > 1.0, "the lighting must produce radiance above 1"
    path = tmp_path / "f.exr"
    write_exr(path, frame.hdr, half=half)
    back = read_exr(path)
    expected = frame.hdr.astype(np.float16 if half else np.float32)
    assert back.dtype == expected.dtype and back.shape == expected.shape
    assert np.array_equal(back, expected)
    assert back[..., :3].max() > 1.0


def test_same_seed_same_image_other_clip_other_image():
    _, a = render(clip_index=3)
    _, b = render(clip_index=3)
    _, c = render(clip_index=4)
    assert np.array_equal(a.hdr, b.hdr) and np.array_equal(a.ldr, b.ldr)
    assert not np.array_equal(a.ldr, c.ldr)


def test_turning_a_randomizer_on_does_not_change_the_others():
    plain, _ = render("paper", clip_index=5)
    noisy, _ = render("camera-noise", clip_index=5)
    assert plain.info["draws"]["texture"] == noisy.info["draws"]["texture"]
    assert np.array_equal(plain.texture.image, noisy.texture.image)
    assert np.array_equal(plain.background, noisy.background)


def test_alpha_is_cloth_coverage():
    _, frame = render("paper", resolution=32)
    alpha = frame.hdr[..., 3]
    assert alpha.min() == 0.0 and alpha.max() == pytest.approx(1.0)
    assert alpha[0, 0] == 0.0 and alpha[16, 16] == pytest.approx(1.0)  # a corner is background, the centre cloth
    assert ((alpha > 0.01) & (alpha < 0.99)).any()  # partly covered edge pixels keep fractional alpha
    assert np.all(frame.hdr[..., :3][alpha == 0] == 0)  # the background is not in the HDR frame


def test_remeshed_clip_rebuilds_only_when_counts_change():
    clip = waving_sheet(frames=6, n=8, remesh_every=2)
    renderer = ClipRenderer(clip, get_variant("paper"), resolution=16, spp=1, run_seed=0, clip_index=0,
                            backend=BACKEND, reuse_scenes=False)
    for t in range(clip.num_frames):
        renderer.render_frame(t)
    assert renderer.rebuilds == 3


def _jit_or_scalar() -> list[str]:
    return ["llvm_ad_rgb", "scalar_rgb"] if find_libllvm() else ["scalar_rgb"]


@pytest.mark.parametrize("backend", _jit_or_scalar())
def test_pooled_scenes_render_exactly_what_a_scene_per_clip_renders(backend):
    """Retargeting a pooled scene (camera, lights, room, texture, padded mesh) must not change a pixel."""
    from render.scene import scene_pool

    pool = scene_pool(load_mitsuba(backend))
    pool.clear()
    for variant in ("paper", "room", "daylight", "fabric-table"):
        for index, remesh in ((0, 0), (1, 0), (2, 2), (3, 3)):  # 0, 1 share a scene; so do the remeshed 2, 3
            clip = waving_sheet(frames=4, n=8, index=index, remesh_every=remesh)
            kw = dict(resolution=16, spp=2, run_seed=3, clip_index=index, backend=backend)
            alone = ClipRenderer(clip, get_variant(variant), reuse_scenes=False, **kw)
            pooled = ClipRenderer(clip, get_variant(variant), **kw)
            for t in range(clip.num_frames):
                a, b = pooled.render_hdr(t), alone.render_hdr(t)
                # Equal up to a rare single path: Mitsuba's parallel BVH builds may break ties between
                # coincident triangle edges differently from one build to the next (seen with a scene per
                # clip alone, twice in a row), which moves one sample of a pixel; nothing else may differ.
                off = np.abs(a - b).max(axis=-1) > 1e-5
                assert off.mean() <= 0.01, f"{variant} clip {index} frame {t}: {off.sum()} pixels differ"
    assert pool.retargets > 0, "clips of one structure must share a scene"
    assert pool.builds < pool.retargets + pool.builds


def test_a_scenes_shapes_keep_the_dicts_order():
    # Merged by load_dict's default optimisation, the shapes (and so the area lights) came in an order that
    # followed memory addresses, never the dict's (render.scene.load_scene).
    for index in (2, 3):
        clip = waving_sheet(frames=1, n=8, index=index)
        r = ClipRenderer(clip, get_variant("lighting-random"), resolution=16, spp=2, run_seed=3, clip_index=index,
                         backend=BACKEND, reuse_scenes=False)
        r.render_hdr(0)
        ids = [shape.id() for shape in r.scene.shapes()]
        assert len(ids) >= 2 and ids == [key for key in (*r.lights, *r.room, "cloth") if key in ids]


def test_random_lighting_builds_render_alike():
    # With the shapes in an address-dependent order these clips rendered other noise in about one build in twelve.
    for index in (2, 3, 5, 6):
        clip = waving_sheet(frames=1, n=8, index=index)
        kw = dict(resolution=16, spp=2, run_seed=3, clip_index=index, backend=BACKEND, reuse_scenes=False)
        frames = [ClipRenderer(clip, get_variant("lighting-random"), **kw).render_hdr(0) for _ in range(12)]
        assert all(np.array_equal(f, frames[0]) for f in frames), index


def test_a_second_clip_of_the_same_structure_retargets_the_first_ones_scene():
    from render.scene import scene_pool

    scene_pool(load_mitsuba(BACKEND)).clear()
    first, _ = render("grid", clip_index=0)
    second, _ = render("grid", clip_index=1)
    assert (first.rebuilds, first.retargets) == (1, 0)
    assert (second.rebuilds, second.retargets) == (0, 1) and second.scene is first.scene
    again, frame = render("grid", clip_index=0)  # the first clip again, after the second took its scene
    np.testing.assert_allclose(frame.hdr, render("grid", clip_index=0, reuse_scenes=False)[1].hdr, atol=1e-6)


@pytest.mark.parametrize("name", sorted(OPERATORS))
def test_tonemap_operators_are_monotone_and_map_zero_to_zero(name):
    ramp = np.concatenate([np.linspace(0, 2, 500), np.geomspace(2, 1e4, 500)])
    display = OPERATORS[name](ramp)
    assert display[0] == 0.0
    assert np.all(np.diff(display) >= 0)
    assert display.max() <= 1.0
    grey = tonemap(np.repeat(ramp[None, :, None], 3, axis=2), name)
    assert grey[0, 0].tolist() == [0, 0, 0]
    assert np.all(np.diff(grey[0, :, 0].astype(int)) >= 0)


def test_corrupt_background_is_reported_by_name_and_the_run_goes_on(tmp_path, monkeypatch):
    backgrounds = tmp_path / "bg"
    backgrounds.mkdir()
    Image.fromarray(np.full((40, 60, 3), 120, np.uint8)).save(backgrounds / "room.png")
    broken = {str(backgrounds / f"broken{i}.jpg") for i in range(5)}
    for name in broken:
        open(name, "wb").write(b"this is not a jpeg")
    variants = tmp_path / "variants"
    variants.mkdir()
    (variants / "photos.toml").write_text(f'description = "photo backgrounds"\nbackground = "folder"\n'
                                          f'background_dir = "{backgrounds}"\n')
    monkeypatch.setenv(USER_VARIANTS_ENV, str(variants))
    run = make_run(tmp_path / "run", variants=("photos",), clips=3)
    from render.stage import run_render

    with pytest.warns(UserWarning, match=r"background image .*broken\d\.jpg cannot be read") as record:
        summary = run_render(run, progress=False)
    assert summary["rendered"] == 3 and not summary["failed"]
    assert summary["skipped_backgrounds"] and set(summary["skipped_backgrounds"]) <= broken
    named = {m for w in record for m in re.findall(r"background image (\S+) cannot be read", str(w.message))}
    assert named == set(summary["skipped_backgrounds"])  # every skipped file was reported by name


def make_run(root, variants=("paper",), clips=2, frames=3, remeshing=("uniform1",), variant_settings=()):
    return synthetic_sim_run(root, variants, clips, frames, remeshing, variant_settings=variant_settings)


def test_stage_writes_frames_meta_and_done_and_skips_done_clips(tmp_path):
    from render.stage import run_render

    run = make_run(tmp_path / "run", variants=("paper", "grid"))
    summary = run_render(run, progress=False)
    assert summary["rendered"] == 4 and summary["failed"] == [] and summary["backend"] == BACKEND
    folder = run.render_dir("grid", run.config.sim.settings()[0]) / clip_id(1)
    assert is_done(folder)
    assert sorted(p.name for p in (folder / "ldr").iterdir()) == ["0000.png", "0001.png", "0002.png"]
    assert read_exr(folder / "hdr" / "0002.exr").shape == (16, 16, 4)
    with Image.open(folder / "ldr" / "0000.png") as im:
        assert (im.mode, im.size) == ("RGB", (16, 16))
    meta = json.loads((folder / "meta.json").read_text())
    assert meta["variant"] == "grid" and meta["num_frames"] == 3 and meta["index"] == 1
    assert meta["render"]["backend"] == BACKEND and meta["render"]["texture"] == "grid"
    assert meta["render"]["sampler_seed"] > 0 and meta["render"]["spp"] == 1
    again = run_render(run, progress=False)
    assert again["rendered"] == 0 and again["skipped"] == 4


@pytest.mark.parametrize("backend", _jit_or_scalar())
def test_a_finished_look_is_released_and_the_next_renders_the_same_frames(tmp_path, monkeypatch, backend):
    """A render worker frees each look's scenes and kernels once its last clip is done (render.stage.release_look),
    so its memory does not grow with a study's datasets; what it renders must not change."""
    import render.stage
    from render.scene import scene_pool

    pool = scene_pool(load_mitsuba(backend))
    import drjit as dr                                 # after load_mitsuba: it picks libLLVM first
    flushes, flush = [], dr.flush_kernel_cache
    monkeypatch.setattr(dr, "flush_kernel_cache", lambda: (flushes.append(len(pool)), flush()))
    frames = {}
    for release in (True, False):
        monkeypatch.setattr(render.stage, "RELEASE_LOOKS", release)
        run = synthetic_sim_run(tmp_path / str(release), ("paper", "grid"), backend=backend)
        pool.clear()
        assert render.stage.run_render(run, progress=False)["rendered"] == 4
        setting = run.config.sim.settings()[0]
        frames[release] = [np.load(run.render_dir(v, setting) / clip_id(i) / "frames.npy")
                           for v in ("paper", "grid") for i in range(2)]
        # released: Dr.Jit's kernels flushed after paper's last clip and when the call ends, every pool emptied
        # first; kept: no flush, both looks' scenes pooled
        assert (flushes, len(pool)) == (([0, 0], 0) if release else ([], 2))
        flushes.clear()
    assert all(np.array_equal(a, b) for a, b in zip(frames[True], frames[False]))
    # a call that renders nothing (every clip done) releases nothing
    monkeypatch.setattr(render.stage, "RELEASE_LOOKS", True)
    assert render.stage.run_render(run, progress=False)["skipped"] == 4 and flushes == []


def test_variant_settings_render_and_train_only_the_listed_pairs(tmp_path):
    # The paper's Table 3 puts the grid texture on adaptive meshes only.
    from clothgap.config import pairs
    from learn.stage import training_grid
    from render.stage import run_render

    run = make_run(tmp_path / "run", variants=("paper", "grid"), clips=1, frames=2,
                   remeshing=("uniform1", "adaptive"), variant_settings=("grid:wind-adaptive",))
    assert pairs(run.config) == [("wind-uniform1", "paper"), ("wind-adaptive", "paper"), ("wind-adaptive", "grid")]
    summary = run_render(run, progress=False)
    assert summary["rendered"] == 3 and summary["failed"] == []
    assert not run.render_dir("grid", "wind-uniform1").exists()
    assert is_done(run.render_dir("grid", "wind-adaptive") / clip_id(0))
    assert {(s, v) for s, v, _m, _seed in training_grid(run)} == set(pairs(run.config))
    with pytest.raises(ConfigError, match="not simulate"):
        validate(replace(run.config, render=replace(run.config.render, variant_settings=("grid:arm-adaptive",))))
    with pytest.raises(ConfigError, match="VARIANT:SETTING"):
        validate(replace(run.config, render=replace(run.config.render, variant_settings=("grid",))))
    study = preset("study")
    assert len(pairs(study)) == 12 and ("arm-adaptive", "color") in pairs(study)
    assert ("arm-uniform3", "grid") not in pairs(study)


def test_backend_choice():
    with pytest.raises(BackendError, match="unknown render backend"):
        resolve_backend("opengl")
    assert resolve_backend("scalar_rgb") == "scalar_rgb"
    found = find_libllvm()
    if found is not None:
        assert int(_LLVM_NAME.match(found.name).group(1)) >= MIN_LLVM_VERSION
    assert resolve_backend("auto") in ("cuda_ad_rgb", "llvm_ad_rgb", "scalar_rgb")


@pytest.mark.skipif(find_libllvm() is None, reason="no libLLVM 16+ on this machine")
def test_llvm_backend_matches_scalar_roughly():
    clip = waving_sheet(frames=1, n=8)
    images = {}
    for backend in ("llvm_ad_rgb", "scalar_rgb"):
        renderer = ClipRenderer(clip, get_variant("grid"), resolution=16, spp=64, run_seed=0, clip_index=0,
                                backend=backend)
        images[backend] = renderer.render_frame(0).hdr
    assert np.abs(images["llvm_ad_rgb"][..., 3] - images["scalar_rgb"][..., 3]).mean() < 0.02
    assert abs(images["llvm_ad_rgb"][..., :3].mean() - images["scalar_rgb"][..., :3].mean()) < 0.05


def test_clips_of_a_setting_share_one_camera_and_a_sagging_cloth_looks_longer():
    """The camera frames the setting's view box, not each clip: a cloth that hangs lower covers more rows."""
    rest = waving_sheet(frames=1, n=8, index=0)
    box = [[-0.4, -0.2, -0.2], [0.4, 0.6, 1.1]]
    p = rest.frame(0)[0][None]
    long = SimClip.from_fixed({**rest.meta, "view_box": box}, p * np.array([1.0, 1.0, 1.3]) - np.array([0, 0, 0.3]),
                              rest.faces, rest.uv)
    short = SimClip.from_fixed({**rest.meta, "view_box": box}, p, rest.faces, rest.uv)
    a, fa = render("grid", clip=short, resolution=32)
    b, fb = render("grid", clip=long, resolution=32, clip_index=1)
    assert np.allclose(a.framing.origin, b.framing.origin) and np.allclose(a.framing.target, b.framing.target)
    rows = [int((f.hdr[..., 3].max(axis=1) > 0.5).sum()) for f in (fa, fb)]
    assert rows[1] > rows[0] + 2, rows
