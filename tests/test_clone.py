"""Material cloning (the paper's Fig. 9): the skirt garment, and `clothgap clone` end to end on a video
written here with PyAV against a tiny run with a model in the checkpoint contract format."""

from __future__ import annotations

import json
import subprocess
import sys

import av
import numpy as np
import pytest

from sim import classes
from sim.garment import SkirtShape, SkirtSolver, WaistMotion, simulate_skirts, skirt, skirt_spec, waist_path
from sim.materials import load_material
from sim.solver import BatchSolver, SolverParams
from tests.test_eval_real import fresh_model, write_video

SHAPE = SkirtShape(around=16, down=5)
FPS = 25.0


def material(class_index: int):
    return load_material("camel-ponte-roma").scaled(*classes.class_values(class_index))


def clothgap(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "clothgap", *args], capture_output=True, text=True)


def test_skirt_mesh_is_one_unrolled_cone_with_a_seam_split_for_rendering():
    g = skirt(SHAPE)
    n, m = SHAPE.around, SHAPE.down
    assert g.num_vertices == (m + 1) * n and len(g.waist) == len(g.hem) == n
    assert np.allclose(np.linalg.norm(g.positions[g.waist, :2], axis=1), SHAPE.waist_radius_m)
    # the sewn skirt is the pattern without stretch: every edge as long in 3D as in material space
    e = g.edges
    assert np.allclose(np.linalg.norm(g.positions[e[:, 1]] - g.positions[e[:, 0]], axis=1), g.rest_lengths,
                       rtol=1e-9)
    # render mesh: seam vertices duplicated, uv continuous (every face counter-clockwise, none spans the pattern)
    uv, f = g.render_uv, g.render_faces
    d1, d2 = uv[f[:, 1]] - uv[f[:, 0]], uv[f[:, 2]] - uv[f[:, 0]]
    assert np.all(d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0] > 0)
    assert len(uv) == (m + 1) * (n + 1) and np.array_equal(g.to_render(g.positions)[:, :], g.positions[g.render_index])


def test_rest_state_comes_from_the_pattern_across_the_seam():
    """Without gravity or bending, the sewn skirt must stay put; the solver's own per-vertex (u, v)
    (the top view) would pull it out of shape."""
    g = skirt(SHAPE)
    flat = load_material("camel-ponte-roma").scaled(1.0, 1e-6)
    params = SolverParams(dt=1 / 200, gravity=(0.0, 0.0, 0.0))
    sim = SkirtSolver(g, [flat], params)
    sim.advance(60)
    assert np.abs(sim.positions()[0] - g.positions).max() < 0.01
    plain = BatchSolver([skirt_spec(g, flat)], params)
    plain.step(60)
    assert np.abs(plain.positions()[0] - g.positions).max() > 0.05


@pytest.mark.parametrize("kind", ["twirl", "walk"])
def test_skirt_simulates_stably_with_the_waist_on_its_path_and_the_hem_swinging(kind):
    g, motion = skirt(SHAPE), WaistMotion(kind=kind)
    frames = 12
    (result,) = simulate_skirts(g, [material(22)], motion, fps=FPS, frames=frames, substeps=8, settle_s=0.3)
    assert result.reason is None
    x = result.positions
    assert x.shape == (frames, g.num_vertices, 3) and np.all(np.isfinite(x))
    assert np.abs(x[:, g.waist] - waist_path(g, motion, FPS, frames)).max() < 1e-5      # pinned, and moving
    assert np.ptp(x[:, g.waist], axis=0).max() > 0.01
    hem = x[:, g.hem]
    assert np.linalg.norm(hem[-1] - hem[0], axis=1).mean() > 0.01                   # the hem swings
    assert hem[..., 2].max() < SHAPE.waist_height_m                                  # and hangs below the waist


def test_softer_class_droops_and_swings_more_than_a_stiffer_one():
    from eval.clone import hem_statistics

    g = skirt(SHAPE)
    soft, stiff = simulate_skirts(g, [material(0), material(53)], WaistMotion(kind="walk"), fps=FPS, frames=10,
                                  substeps=8, settle_s=0.5)
    assert soft.reason is None and stiff.reason is None
    s, t = hem_statistics(g, soft.positions), hem_statistics(g, stiff.positions)
    assert s["hem_drop_m"] > t["hem_drop_m"] + 0.005            # hangs lower
    assert s["hem_radius_m"] < t["hem_radius_m"] - 0.05         # flares out less: the stiff skirt keeps its cone
    assert s["hem_swing_m_per_frame"] > 1.2 * t["hem_swing_m_per_frame"]   # swings more about the moving waist


def test_comparison_classes_stay_on_the_grid():
    from eval.clone import comparison_classes

    assert comparison_classes(22) == [("clone", 22), ("softer", classes.class_index(0, 0)),
                                      ("stiffer", classes.class_index(4, 8))]
    assert [n for n, _ in comparison_classes(0)] == ["clone", "stiffer"]
    assert [n for n, _ in comparison_classes(53)] == ["clone", "softer"]
    assert comparison_classes(22, compare=False) == [("clone", 22)]


def test_clone_command_end_to_end(tmp_path):
    video = tmp_path / "fabric.mp4"
    write_video(video, frames=12)
    train_dir = fresh_model(tmp_path / "run")
    out = tmp_path / "clone"
    frames, res = 4, 16
    r = clothgap("clone", str(video), "--run", str(tmp_path / "run"), "--frames", str(frames), "--resolution",
                 str(res), "--spp", "1", "--backend", "scalar_rgb", "--out", str(out))
    assert r.returncode == 0, r.stderr
    doc = json.loads((out / "clone.json").read_text())
    c = doc["class_index"]
    assert 0 <= c < 54 and (doc["p"], doc["k"]) == classes.class_values(c)
    assert 0 < doc["confidence"] <= 1 and doc["predicted"]["subsequences"] == 1
    assert doc["model"]["checkpoint"] == str(train_dir / "checkpoint.pt")
    assert {"run_seed", "render_clip_index", "sampler_seed"} <= set(doc["seeds"])
    panels = [p["panel"] for p in doc["panels"]]
    assert panels[0] == "clone" and set(panels) <= {"clone", "softer", "stiffer"} and len(panels) >= 2
    assert len(list((out / "frames").glob("*.png"))) == frames
    with av.open(str(out / "clone.mp4")) as container:
        decoded = [f.to_ndarray(format="rgb24") for f in container.decode(video=0)]
    assert len(decoded) == frames and decoded[0].shape[1] == (1 + len(panels)) * res
    assert len(list((out / "render" / "clone" / "ldr").glob("*.png"))) == frames
    assert (out / "sim" / "clone" / "clip.npz").is_file()


def test_clone_bad_inputs_are_named_without_a_traceback(tmp_path, monkeypatch, capsys):
    from clothgap.cli import main
    from clothgap.config import preset, save_config

    video = tmp_path / "v.mp4"
    write_video(video, frames=12)
    save_config(preset("smoke"), tmp_path / "untrained" / "config.json")
    garbage = tmp_path / "garbage.mp4"
    garbage.write_bytes(b"\x00 not a video " * 40)
    fresh_model(tmp_path / "run")
    cases = [
        (("clone", str(tmp_path / "missing.mp4"), "--run", str(tmp_path / "run")), "does not exist"),
        (("clone", str(video), "--run", str(tmp_path / "nowhere")), "run folder"),
        (("clone", str(video), "--run", str(tmp_path / "untrained")), "no trained model"),
        (("clone", str(video), "--run", str(tmp_path / "run"), "--model", "base1"), "no trained model matching"),
        (("clone", str(garbage), "--run", str(tmp_path / "run")), "cannot read the input video"),
    ]
    for args, message in cases:   # in process (fast): an uncaught exception would fail the test here
        monkeypatch.setattr(sys, "argv", ["clothgap", *args])
        with pytest.raises(SystemExit) as exit_:
            main()
        err = capsys.readouterr().err
        assert exit_.value.code != 0 and message in err, (args, err)
    r = clothgap("clone", "--help")
    assert r.returncode == 0 and "Figure 9" in r.stdout
