"""Meshes out: a simulated clip's frames written with trimesh read back to the clip's own vertices."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh

from clothgap.config import apply_overrides, preset
from clothgap.runs import Run
from sim.clip import SimClip
from sim.export import Z_UP_TO_Y_UP, export_clip, parse_frames

ROOT = Path(__file__).resolve().parent.parent


def read_back(path: Path) -> trimesh.Trimesh:
    return trimesh.load(path, process=False, force="mesh")


@pytest.fixture(scope="module")
def simulated(tmp_path_factory) -> Run:
    from sim.stage import run_sim

    cfg = apply_overrides(preset("smoke"), ["sim.classes=8", "sim.sequences_per_class=1", "sim.frames=10"])
    run = Run.create_or_resume(tmp_path_factory.mktemp("export") / "r", cfg)
    run_sim(run, progress=False)
    return run


def export(run: Run, fmt: str, out: Path) -> list[Path]:
    """Frames 0, 4, 5 and 9 of clip 0 through the command (ply) or the function (obj, glb)."""
    if fmt != "ply":
        return export_clip(run.sim_dir("wind-uniform1") / "c00000", out, fmt, "0,4-5,9")
    r = subprocess.run([sys.executable, "-m", "clothgap", "sim", "export", str(run.root), "0", "--frames",
                        "0,4-5,9", "--format", fmt, "--out", str(out)], capture_output=True, text=True,
                       env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert r.returncode == 0, r.stderr
    return sorted(out.iterdir())


@pytest.mark.parametrize("fmt", ["ply", "obj", "glb"])
def test_exported_frames_hold_the_simulated_vertices(simulated, tmp_path, fmt):
    clip = SimClip.load(simulated.sim_dir("wind-uniform1") / "c00000")
    files = export(simulated, fmt, tmp_path / "m")
    assert [f.name for f in files] == [f"c00000_{t:04d}.{fmt}" for t in (0, 4, 5, 9)]
    for t, path in zip((0, 4, 5, 9), files):
        positions, faces, uv = clip.frame(t)
        mesh = read_back(path)
        vertices = mesh.vertices @ Z_UP_TO_Y_UP if fmt == "glb" else mesh.vertices   # back to z up
        np.testing.assert_allclose(vertices, positions, atol=1e-6)
        np.testing.assert_array_equal(mesh.faces, faces)
        np.testing.assert_allclose(mesh.visual.uv, uv, atol=1e-6)
    # the cloth moved between the frames written: each file is its own frame
    assert not np.allclose(read_back(files[0]).vertices, read_back(files[-1]).vertices)
    if fmt == "glb":        # glTF is +Y up: the cloth hangs along -y there (gravity along -z in the sim)
        top, bottom = clip.frame(0)[0][:, 2].argmax(), clip.frame(0)[0][:, 2].argmin()
        assert read_back(files[0]).vertices[top, 1] > read_back(files[0]).vertices[bottom, 1]


def test_frames_whose_topology_changes_export_each_its_own_mesh(tmp_path):
    # An adaptive clip stores faces and uv per frame: each frame's file has its own vertex and face counts.
    rng = np.random.default_rng(0)
    small = (rng.random((4, 3), np.float32), np.array([[0, 1, 2], [0, 2, 3]]), rng.random((4, 2), np.float32))
    large = (rng.random((5, 3), np.float32), np.array([[0, 1, 4], [1, 2, 4], [2, 3, 4]]),
             rng.random((5, 2), np.float32))
    SimClip.from_frames({"clip_id": "c00000"}, [small, large]).save(tmp_path / "c00000")
    files = export_clip(tmp_path / "c00000", tmp_path / "out", "ply")
    for path, (positions, faces, _) in zip(files, (small, large)):
        mesh = read_back(path)
        np.testing.assert_allclose(mesh.vertices, positions, atol=1e-7)
        np.testing.assert_array_equal(mesh.faces, faces)
    assert not list((tmp_path / "out").glob("*.tmp*"))


def test_frame_lists_and_bad_requests_are_named(tmp_path):
    assert parse_frames("0,5,10-12,5", 20) == [0, 5, 10, 11, 12]
    assert parse_frames(None, 3) == [0, 1, 2] == parse_frames("all", 3)
    with pytest.raises(ValueError, match="outside the clip's frames 0..19"):
        parse_frames("18-21", 20)
    with pytest.raises(ValueError, match="'x' is not a frame number"):
        parse_frames("1,x", 20)
    with pytest.raises(ValueError, match="unknown mesh format 'stl'"):
        export_clip(tmp_path, tmp_path / "out", "stl")
    with pytest.raises(ValueError, match="does not hold a readable sim clip"):
        export_clip(tmp_path, tmp_path / "out", "ply")
