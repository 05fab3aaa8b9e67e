"""The tabulated fabric BSDF: its importance sampling is consistent with its evaluation."""

from __future__ import annotations

import numpy as np
import pytest

from render import fabric_bsdf
from render.backend import find_libllvm, load_mitsuba


def test_table_layout_and_reciprocity():
    table = fabric_bsdf.make_charlie_table(n_h=8, n_d=8, n_phi=4)
    assert table.shape == (4, 8, 8, 2)
    assert np.all(table >= 0) and table[..., 1].max() > 0


@pytest.mark.skipif(find_libllvm() is None, reason="vectorised check needs llvm_ad_rgb")
def test_sampled_estimate_matches_uniform_estimate():
    mi = load_mitsuba("llvm_ad_rgb")
    import drjit as dr

    fabric_bsdf.register(mi)
    bsdf = mi.load_dict({"type": fabric_bsdf.PLUGIN, "base_color": {"type": "rgb", "value": [0.4, 0.5, 0.6]}})
    si = dr.zeros(mi.SurfaceInteraction3f)
    wi = np.array([0.5, 0.1, 0.6]) / np.linalg.norm([0.5, 0.1, 0.6])
    si.wi = mi.Vector3f(*[float(x) for x in wi])
    ctx = mi.BSDFContext()
    rng = np.random.default_rng(0)
    n = 400_000
    s1, s2 = mi.Float(rng.random(n)), mi.Point2f(rng.random(n), rng.random(n))
    bs, weight = bsdf.sample(ctx, si, s1, s2)
    sampled = np.array(dr.mean(weight, axis=1)).ravel()
    wo = mi.warp.square_to_uniform_hemisphere(s2)
    uniform = np.array(dr.mean(bsdf.eval(ctx, si, wo), axis=1)).ravel() * 2 * np.pi
    assert np.allclose(sampled, uniform, rtol=0.03)
    # pdf() agrees with the pdf that sample() reports
    assert np.allclose(np.array(bsdf.pdf(ctx, si, bs.wo)), np.array(bs.pdf), rtol=1e-4, atol=1e-6)
