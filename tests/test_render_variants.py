"""Render variants: the registry, and every registered variant rendering a tiny clip."""

from __future__ import annotations

import numpy as np
import pytest

from render.scene import ClipRenderer
from render.synthetic import waving_sheet
from render.variants import (USER_VARIANTS_ENV, VariantError, describe_variants, get_variant, list_variants)
from sim.clip import SimClip


def test_paper_grid_color_registered_and_paper_is_the_defaults():
    names = list_variants()
    assert names[0] == "paper"
    assert {"paper", "grid", "color"} <= set(names)
    assert get_variant("paper").changes_from(get_variant("paper")) == {}
    assert get_variant("grid").changes_from(get_variant("paper")) == {"texture": "grid"}


def test_unknown_variant_lists_the_known_ones():
    with pytest.raises(VariantError, match="known variants: .*paper"):
        get_variant("no-such-variant")


def test_describe_lists_every_variant_with_its_changes():
    text = describe_variants()
    for name in list_variants():
        assert f"{name}: " in text
    assert "changes: texture=grid" in text


def test_user_folder_adds_a_variant(tmp_path, monkeypatch):
    (tmp_path / "mine.toml").write_text('description = "reinhard over the grid"\nbase = "grid"\ntonemap = "reinhard"\n')
    monkeypatch.setenv(USER_VARIANTS_ENV, str(tmp_path))
    variant = get_variant("mine")
    assert (variant.texture, variant.tonemap) == ("grid", "reinhard")
    assert "mine" in list_variants()


@pytest.mark.parametrize("text, message", [
    ('description = "x"\ntonemap = "aces"\n', "tonemap='aces' is not one of"),
    ('description = "x"\ncolour = "red"\n', "unknown setting"),
    ('tonemap = "reinhard"\n', "needs a description"),
    ('description = "x"\nroughness = "high"\n', "roughness must be float"),
])
def test_bad_variant_files_name_the_problem(tmp_path, monkeypatch, text, message):
    (tmp_path / "bad.toml").write_text(text)
    monkeypatch.setenv(USER_VARIANTS_ENV, str(tmp_path))
    with pytest.raises(VariantError, match=message):
        get_variant("bad")


def test_a_user_file_may_not_redefine_a_builtin(tmp_path, monkeypatch):
    (tmp_path / "paper.toml").write_text('description = "mine"\n')
    monkeypatch.setenv(USER_VARIANTS_ENV, str(tmp_path))
    with pytest.raises(VariantError, match="defined twice"):
        list_variants()


@pytest.mark.parametrize("name", list_variants())
def test_every_registered_variant_renders(name):
    clip = waving_sheet(frames=2, n=8)
    renderer = ClipRenderer(clip, get_variant(name), resolution=16, spp=2, run_seed=0, clip_index=1,
                            backend="scalar_rgb")
    for t in range(clip.num_frames):
        frame = renderer.render_frame(t)
        assert frame.hdr.shape == (16, 16, 4) and frame.hdr.dtype == np.float32
        assert np.isfinite(frame.hdr).all()
        assert frame.ldr.shape == (16, 16, 3) and frame.ldr.dtype == np.uint8
        assert frame.hdr[..., 3].max() > 0.5, "the cloth must be in view"
    assert renderer.rebuilds + renderer.retargets == 1, "a fixed-topology clip sets up its scene once"


def test_zoom_narrows_the_view_and_the_cloth_fills_more_of_the_frame():
    clip = waving_sheet(frames=1, n=8)

    def coverage(variant):
        renderer = ClipRenderer(clip, variant, resolution=32, spp=2, run_seed=0, clip_index=1, backend="scalar_rgb")
        return renderer, float((renderer.render_frame(0).hdr[..., 3] > 0.5).mean())

    paper, near = get_variant("paper"), get_variant("close")
    assert near.changes_from(paper) == {"zoom": 1.3}
    (wide, wide_cover), (close, close_cover) = coverage(paper), coverage(near)
    np.testing.assert_array_equal(close.framing.origin, wide.framing.origin)     # the camera stays where it was
    assert np.tan(np.radians(wide.framing.fov_deg) / 2) == pytest.approx(1.3 * np.tan(np.radians(close.framing.fov_deg) / 2))
    assert close_cover > 1.4 * wide_cover       # 1.3 x 1.3 = 1.69 times the pixels where the cloth stays in view
    with pytest.raises(VariantError, match="zoom must be positive"):
        type(paper)(name="bad", zoom=0.0)


def test_a_motions_view_zoom_frames_its_clips_as_a_zoomed_look_would_and_the_two_multiply():
    from clothgap.config import preset
    from sim.config import SimConfig
    from sim.motions import view_zoom

    paper = preset("paper").sim
    assert view_zoom("arm", paper) == paper.arm_view_zoom == 1.3 and view_zoom("wind", paper) == 1.0
    assert view_zoom("arm", SimConfig()) == 1.0        # the setting's default: runs made before it, framed by the box
    sheet = waving_sheet(frames=1, n=8)
    box = [[-0.4, -0.2, -0.2], [0.4, 0.6, 1.1]]     # a setting's camera box, as the sim writes it

    def framed(variant, view_zoom=None):
        meta = {**sheet.meta, "view_box": box, **({"view_zoom": view_zoom} if view_zoom else {})}
        clip = SimClip.from_fixed(meta, sheet.frame(0)[0][None], sheet.faces, sheet.uv)
        renderer = ClipRenderer(clip, get_variant(variant), resolution=32, spp=2, run_seed=0, clip_index=1,
                                backend="scalar_rgb")
        cover = float((renderer.render_frame(0).hdr[..., 3] > 0.5).mean())
        return renderer.framing, cover, renderer.rebuilds

    (box_only, cover, _), (by_motion, motion_cover, rebuilds) = framed("paper"), framed("paper", 1.3)
    assert rebuilds == 1    # not the first clip's pooled scene: a frozen render may have its field of view baked in
    assert framed("paper")[2] == 0                                       # the same framing takes it again
    by_look, look_cover, _ = framed("close")
    assert by_motion.fov_deg == pytest.approx(by_look.fov_deg) and motion_cover == pytest.approx(look_cover)
    np.testing.assert_array_equal(by_motion.origin, box_only.origin)       # the camera stays where it was
    assert motion_cover > 1.4 * cover
    both, _, _ = framed("close", 1.3)
    half_width = np.tan(np.radians(box_only.fov_deg) / 2), np.tan(np.radians(both.fov_deg) / 2)
    assert half_width[0] == pytest.approx(1.3 * 1.3 * half_width[1])
