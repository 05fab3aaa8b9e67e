"""Many frames per launch (render.batch): same images in expectation, remeshed clips, variants, stage and resume."""

from __future__ import annotations

import json

import numpy as np
import pytest
from PIL import Image

from clothgap.runs import clip_id, is_done
from render.batch import BatchRenderer, batchable, enclosure_mesh, grid_offsets
from render.config import RenderConfig, frames_per_launch
from render.exr import read_exr
from render.scene import ClipRenderer
from render.synthetic import waving_sheet
from render.variants import get_variant, list_variants
from tests.conftest import synthetic_sim_run
from tests.test_render_output import BACKEND


def make_run(root, variants=("paper",), clips=2, frames=3, **render):
    """A run with finished synthetic sim clips and render overrides."""
    return synthetic_sim_run(root, variants, clips, frames, **render)


def renderer(variant="paper", spp=4, resolution=16, clip=None, clip_index=2, seed_shift=0):
    clip = clip or waving_sheet(frames=4, n=10)
    r = ClipRenderer(clip, get_variant(variant), resolution=resolution, spp=spp, run_seed=7, clip_index=clip_index,
                     backend=BACKEND)
    r.sampler_seed += seed_shift
    return r


def blocks(image, n=4):
    """Low-frequency content: the image averaged over n x n blocks (RGBA)."""
    h = image.shape[0] // n
    return image[: h * n, : h * n].reshape(n, h, n, h, 4).mean((1, 3))


@pytest.mark.parametrize("variant,remesh", [("paper", 0), ("room", 0), ("paper", 2)])
def test_batched_frames_equal_unbatched_in_expectation(variant, remesh):
    clip = waving_sheet(frames=4, n=10, remesh_every=remesh)
    spp = 96
    one = [renderer(variant, spp, 24, clip).render_hdr(t) for t in (1, 3)]
    other_seed = [renderer(variant, spp, 24, clip, seed_shift=1).render_hdr(t) for t in (1, 3)]
    batch = BatchRenderer(renderer(variant, spp, 24, clip), 4)
    frames = batch.render_hdr([0, 1, 2, 3])
    assert batch.launches == 1 and len(frames) == 4
    for a, a2, b in zip(one, other_seed, (frames[1], frames[3])):
        assert b.shape == a.shape == (24, 24, 4) and np.isfinite(b).all()
        # Alpha is cloth coverage either way (camera rays that miss leave through the shell's tunnel).
        assert abs(b[..., 3].mean() - a[..., 3].mean()) < 0.01
        assert np.all(b[..., :3][b[..., 3] == 0] == 0)
        # Same scene: the image means and the low-frequency content agree to within Monte Carlo noise
        # (batched frames are noisier: next-event estimation is spread over every slot's lights).
        assert np.allclose(b[..., :3].mean((0, 1)), a[..., :3].mean((0, 1)), rtol=0.04, atol=2e-3)
        noise = np.abs(blocks(a2) - blocks(a)).max()
        assert np.abs(blocks(b) - blocks(a)).max() < 4 * noise + 2e-3


def test_other_frames_and_clips_differ_and_same_seed_repeats():
    batch = BatchRenderer(renderer(), 4)
    a = batch.render_hdr([0, 1, 2, 3])
    again = BatchRenderer(renderer(), 4).render_hdr([0, 1, 2, 3])
    assert all(np.array_equal(x, y) for x, y in zip(a, again))
    assert not np.array_equal(a[0][..., 3], a[3][..., 3])  # the cloth moved between frames 0 and 3
    one = [renderer().render_hdr(t)[..., 3] for t in range(4)]
    for t, frame in enumerate(a):  # sub-image t is frame t: its coverage is nearest frame t's one-by-one coverage
        assert int(np.argmin([np.abs(frame[..., 3] - o).sum() for o in one])) == t
    other = BatchRenderer(renderer(clip_index=3), 4).render_hdr([0, 1, 2, 3])
    assert not np.array_equal(a[0], other[0])


def test_partial_last_launch_and_remeshed_clip_need_one_scene():
    clip = waving_sheet(frames=5, n=8, remesh_every=2)  # vertex and face counts change every 2 frames
    r = renderer(clip=clip)
    batch = BatchRenderer(r, 2)
    frames = list(batch.frames())
    assert [t for t, _ in frames] == [0, 1, 2, 3, 4]
    assert batch.launches == 3 and r.rebuilds == 1
    assert all(np.isfinite(f.hdr).all() and f.ldr.shape == (16, 16, 3) for _, f in frames)


@pytest.mark.parametrize("name", list_variants())
def test_every_variant_renders_batched_or_says_why_not(name):
    r = renderer(name, spp=1)
    reason = batchable(r)
    if get_variant(name).lighting == "fixed":
        assert reason is None
        frames = list(BatchRenderer(r, 3).frames())
        assert len(frames) == 4 and all(f.ldr.dtype == np.uint8 for _, f in frames)
    else:  # environment maps and a sun do not survive rotating the slots: one frame per launch
        assert reason and get_variant(name).lighting in reason
        with pytest.raises(ValueError, match="cannot be batched"):
            BatchRenderer(r, 3)


def test_shell_is_closed_except_the_window():
    verts, faces = enclosure_mesh(1.0, 30.0)
    assert faces.max() < len(verts)
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    assert set(counts) <= {1, 2} and (counts == 1).sum() == 48  # only the tunnel's mouth is a boundary
    normal = np.cross(verts[faces[:, 1]] - verts[faces[:, 0]], verts[faces[:, 2]] - verts[faces[:, 0]])
    radial = verts[faces].mean(1) * [1, 1, 0]
    assert (np.einsum("ij,ij->i", normal, radial) < 0).all()  # every face looks inward, toward the axis
    sphere = verts[faces].mean(1)[:, 2] > -0.8
    assert (np.einsum("ij,ij->i", normal, verts[faces].mean(1))[sphere] < 0).all()
    offsets = grid_offsets(10, 3.0)
    assert len(offsets) == 10 and np.allclose(offsets.mean(0)[2], 0)
    gaps = np.linalg.norm(offsets[:, None] - offsets[None], axis=-1) + np.eye(10) * 99
    assert gaps.min() >= 3.0 - 1e-9


def test_frames_per_launch_auto_and_explicit():
    assert frames_per_launch(RenderConfig(), "scalar_rgb") == 1
    assert frames_per_launch(RenderConfig(), "llvm_ad_rgb") == 1
    assert frames_per_launch(RenderConfig(), "cuda_ad_rgb") >= 1
    assert frames_per_launch(RenderConfig(frames_per_launch=5), "scalar_rgb") == 5
    with pytest.raises(ValueError):
        frames_per_launch(RenderConfig(frames_per_launch=-1), "scalar_rgb")


def test_stage_batched_writes_everything_records_it_and_resumes(tmp_path):
    from render.stage import run_render

    run = make_run(tmp_path / "run", variants=("paper", "lighting-random"), clips=2, frames=5,
                   frames_per_launch=2, writer_threads=2)
    summary = run_render(run, progress=False)
    assert summary["rendered"] == 4 and not summary["failed"]
    setting = run.config.sim.settings()[0]
    folder = run.render_dir("paper", setting) / clip_id(1)
    assert sorted(p.name for p in (folder / "ldr").iterdir()) == [f"{t:04d}.png" for t in range(5)]
    assert sorted(p.name for p in (folder / "hdr").iterdir()) == [f"{t:04d}.exr" for t in range(5)]
    meta = json.loads((folder / "meta.json").read_text())
    assert meta["render"]["frames_per_launch"] == 2 and "unbatched_because" not in meta["render"]
    fallback = json.loads((run.render_dir("lighting-random", setting) / clip_id(0) / "meta.json").read_text())
    assert fallback["render"]["frames_per_launch"] == 1 and "envmap" in fallback["render"]["unbatched_because"]
    before = [np.asarray(Image.open(folder / "ldr" / f"{t:04d}.png")) for t in range(5)]
    hdr_before = read_exr(folder / "hdr" / "0004.exr")
    # Resume: a clip whose DONE is missing (killed mid-way) is rendered again, the same way; the rest are skipped.
    (folder / "DONE").unlink()
    (folder / "ldr" / "0003.png").unlink()
    again = run_render(run, progress=False)
    assert again["rendered"] == 1 and again["skipped"] == 3 and is_done(folder)
    assert all(np.array_equal(b, np.asarray(Image.open(folder / "ldr" / f"{t:04d}.png"))) for t, b in enumerate(before))
    assert np.array_equal(hdr_before, read_exr(folder / "hdr" / "0004.exr"))


def test_a_failing_write_fails_the_clip_not_the_run(tmp_path, monkeypatch):
    from render import stage

    run = make_run(tmp_path / "run", clips=2, frames=3, frames_per_launch=3)
    calls = {"n": 0}
    real = stage.write_exr

    def flaky(path, rgba, half=False):
        calls["n"] += 1
        if "c00000" in str(path) and path.name == "0001.exr":
            raise OSError("disk full")
        real(path, rgba, half)

    monkeypatch.setattr(stage, "write_exr", flaky)
    with pytest.warns(UserWarning, match="disk full"):
        summary = stage.run_render(run, progress=False)
    assert summary["rendered"] == 1 and len(summary["failed"]) == 1 and "disk full" in summary["failed"][0]["error"]
