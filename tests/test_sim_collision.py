"""Cloth self-collision (sim.collision) and the intersection counter that checks it (sim.intersections).

CPU, small meshes: a soft cloth dropped from one corner folds onto itself within
a second; without self-collision its triangles cut through each other, with it
none do and every vertex stays the thickness away from every triangle not
incident to it.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from sim.config import SimConfig
from sim.intersections import count_intersections, intersecting_pairs
from sim.materials import load_material
from sim.mesh import square_cloth
from sim.solver import BatchSolver, ClothSpec, SolverParams

SOFT = load_material("camel-ponte-roma").scaled(0.5, 0.5)
THICKNESS = SolverParams.collision_thickness


def _corner_drop(n: int = 10, size: float = 0.3) -> ClothSpec:
    """A soft square cloth lying flat 1 m up, held at one corner: it swings down and folds onto itself."""
    mesh = square_cloth(size, n, 1)
    pos = np.stack([mesh.uv[:, 0], mesh.uv[:, 1], np.ones(len(mesh.uv))], axis=1)
    return ClothSpec(mesh, pos, SOFT.stretching, SOFT.bending, SOFT.density, pinned=[0])


def _vertex_triangle_distance(x: np.ndarray, faces: np.ndarray) -> float:
    """The smallest distance from a vertex to a triangle not incident to it (brute force, float64)."""
    x = x.astype(np.float64)
    p = x[:, None, :]
    a, b, c = (x[faces[:, k]][None] for k in range(3))

    def on_segment(s, e):
        d = e - s
        t = np.clip(((p - s) * d).sum(-1) / (d * d).sum(-1), 0.0, 1.0)
        return np.linalg.norm(p - (s + t[..., None] * d), axis=-1)

    n = np.cross(b - a, c - a)
    n = n / np.linalg.norm(n, axis=-1, keepdims=True)
    q = p - ((p - a) * n).sum(-1)[..., None] * n            # projection on the triangle's plane
    inside = np.ones(q.shape[:2], dtype=bool)
    for s, e in ((a, b), (b, c), (c, a)):
        inside &= (np.cross(e - s, q - s) * n).sum(-1) >= 0.0
    dist = np.minimum(np.minimum(on_segment(a, b), on_segment(b, c)), on_segment(c, a))
    dist = np.where(inside, np.linalg.norm(p - q, axis=-1), dist)
    dist[(faces[None] == np.arange(len(x))[:, None, None]).any(axis=2)] = np.inf
    return float(dist.min())


def test_counter_counts_crossing_triangles_only():
    faces = np.array([[0, 1, 2], [3, 4, 5]])
    flat = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], float)
    through = np.array([[0.2, 0.2, -0.5], [0.3, 0.2, 0.5], [0.2, 0.3, 0.5]])     # an edge pierces the first
    assert count_intersections(np.concatenate([flat, through]), faces) == 1
    assert count_intersections(np.concatenate([flat, through + [0, 0, 0.6]]), faces) == 0     # above it
    assert count_intersections(np.concatenate([flat, through + [2, 0, 0]]), faces) == 0       # beside it
    # Sharing a vertex, the same crossing is not counted (neighbours touch by construction).
    shared = np.array([[0, 1, 2], [0, 4, 5]])
    bent = np.concatenate([flat, [[0, 0, 0], [0.5, 0.5, 0.5], [0.5, 0.5, -0.5]]])
    assert count_intersections(bent, shared) == 0
    mesh = square_cloth(0.5, 16, 2)
    assert len(intersecting_pairs(np.c_[mesh.uv, np.zeros(len(mesh.uv))], mesh.faces)) == 0


@pytest.fixture(scope="module")
def corner_drops():
    """Positions every 0.1 s over 2 s, without and with self-collision."""
    out = {}
    for on in (False, True):
        solver = BatchSolver([_corner_drop()], SolverParams(self_collision=on), "cpu")
        frames = []
        for _ in range(20):
            solver.step(20)
            frames.append(solver.positions()[0])
        out[on] = (frames, solver.collision_dropped())
    return out


def test_corner_drop_folds_through_itself_without_collision_and_not_with_it(corner_drops):
    faces = _corner_drop().mesh.faces
    off = [count_intersections(x, faces) for x in corner_drops[False][0]]
    on = [count_intersections(x, faces) for x in corner_drops[True][0]]
    assert off[-1] >= 10 and max(off) >= 20, off
    assert on == [0] * len(on)
    assert corner_drops[True][1] == [0]        # no pair dropped for lack of a slot
    assert corner_drops[False][1] is None


def test_corner_drop_keeps_the_thickness(corner_drops):
    """Once folded (min distance well under an edge), every vertex stays ~the thickness from every triangle
    not incident to it: without collision they touch or pass."""
    faces = _corner_drop().mesh.faces
    on = [_vertex_triangle_distance(x, faces) for x in corner_drops[True][0]]
    off = [_vertex_triangle_distance(x, faces) for x in corner_drops[False][0]]
    assert min(off) < 0.2 * THICKNESS
    assert min(on[6:]) < 1.5 * THICKNESS       # in contact ...
    assert min(on) > 0.95 * THICKNESS, on      # ... at the thickness


def test_a_full_vertex_keeps_its_closest_pairs(corner_drops):
    """With too few slots, each vertex and edge keeps the pairs closest over the step: the same as the first
    ones of a solver with room for all, and the rest are counted as dropped."""
    import dataclasses

    frames, _ = corner_drops[True]
    spec = dataclasses.replace(_corner_drop(), positions=frames[9], velocities=(frames[9] - frames[8]) / 0.1)
    kept, dropped = {}, {}
    for slots in (3, 64):
        solver = BatchSolver([spec], SolverParams(self_collision=True, collision_slots=slots), "cpu")
        solver.step(1)
        c = solver.collision
        kept[slots] = [(c.pt_count.numpy(), c.pt_key.numpy()), (c.ee_count.numpy(), c.ee_key.numpy())]
        dropped[slots] = solver.collision_dropped()[0]
    assert dropped[64] == 0 and dropped[3] > 0
    for (few_n, few_key), (all_n, all_key) in zip(kept[3], kept[64]):
        assert all_n.max() > 3                  # some vertex or edge has more pairs than 3 slots hold
        for q in np.flatnonzero(all_n):
            want = np.sort(all_key[q, :all_n[q]])[:3]
            assert np.array_equal(np.sort(few_key[q, :few_n[q]]), want)


def test_pair_slots_are_read_only_where_the_step_wrote_them(corner_drops):
    """The pair slots start uninitialised (``wp.empty``: a rebuild does not zero ~0.6 KB per vertex and edge):
    every step reads only the slots it has filled, so slots holding garbage before each step change nothing."""
    import dataclasses

    import warp as wp

    frames, _ = corner_drops[True]
    spec = dataclasses.replace(_corner_drop(), positions=frames[9], velocities=(frames[9] - frames[8]) / 0.1)
    runs = []
    for poison in (False, True):
        solver = BatchSolver([spec], SolverParams(self_collision=True, collision_slots=4), "cpu")
        c = solver.collision
        for _ in range(10):
            if poison:
                for a in (c.pt_pair, c.ee_pair):
                    a.fill_(7)                                  # a real face or edge, not the one found
                for a in (c.pt_weight, c.pt_normal, c.ee_weight, c.ee_normal):
                    a.fill_(wp.vec3(float("nan")))
                for a in (c.pt_gap, c.pt_key, c.ee_gap, c.ee_key):
                    a.fill_(float("nan"))
            solver.step(1)
        runs.append((solver.positions()[0], solver.velocities()[0], solver.collision_dropped()))
        assert c.pt_count.numpy().max() == 4 and solver.collision_dropped()[0] > 0   # full slots, too
    assert runs[0][0].tobytes() == runs[1][0].tobytes() and runs[0][1].tobytes() == runs[1][1].tobytes()
    assert runs[0][2] == runs[1][2]


def test_self_collision_is_deterministic_and_batched_equals_alone():
    """Two runs give the same bytes; two cloths overlapping in space in one batch do not collide with each
    other: each moves exactly as it does alone."""
    params = SolverParams(self_collision=True)
    runs = []
    for specs in ([_corner_drop()], [_corner_drop()], [_corner_drop(), _corner_drop()]):
        solver = BatchSolver(specs, params, "cpu")
        solver.step(160)
        runs.append(solver.positions())
    assert runs[0][0].tobytes() == runs[1][0].tobytes()
    assert runs[2][0].tobytes() == runs[0][0].tobytes() == runs[2][1].tobytes()


def test_soft_wind_clip_ends_without_intersections():
    """The softest class's wind clip 2 (rod pose) at the stage's uniform1 defaults folds through itself
    without self-collision (30 pairs in its last frame), never with it."""
    from sim.stage import build_scene, parse_setting, simulate_scenes

    cfg = SimConfig(classes=(0,), frames=40, device="cpu")
    mesh = square_cloth(cfg.cloth_size_m, cfg.grid_vertices, 1)
    scene, _ = build_scene(cfg, 0, 2, parse_setting("wind-uniform1"), mesh)
    counts = {}
    for on in (False, True):
        (result,) = simulate_scenes([scene], fps=cfg.fps, frames=cfg.frames, substeps=cfg.substeps,
                                    settle_s=cfg.settle_s, self_collision=on)
        assert result.reason is None
        counts[on] = [count_intersections(x, mesh.faces) for x in result.positions]
    assert counts[False][-1] > 0 and max(counts[False]) >= 20, counts[False]
    assert counts[True] == [0] * cfg.frames


def test_stage_meta_records_self_collision_and_intersections(tmp_path):
    """Fixed and adaptive clips with self-collision on: meta says so and the health holds the last frame's
    intersecting pairs and the unresolved pairs."""
    from sim.stage import run_sim
    from tests.conftest import tiny_sim_run

    run = tiny_sim_run(tmp_path, classes=(0,), remeshing=("uniform1", "adaptive"), self_collision=True)
    summary = run_sim(run, progress=False)
    assert summary["simulated"] == 2 and summary["failed"] == 0
    for setting in ("wind-uniform1", "wind-adaptive"):
        meta = json.loads((run.sim_dir(setting) / "c00000" / "meta.json").read_text())
        assert meta["self_collision"] is True and meta["collision_thickness_m"] == SimConfig.collision_thickness
        assert meta["health"]["self_intersections"] == 0
        assert meta["health"]["collision_pairs_dropped"] == 0


def test_collision_thickness_is_checked_against_the_finest_edge():
    assert SimConfig(self_collision=True).problems() == []
    assert any("collision_thickness" in p for p in SimConfig(collision_thickness=0.0).problems())
    # uniform3 of a 16-vertex 0.5 m grid has 8.3 mm edges: 5 mm would push the flat cloth apart from itself
    bad = SimConfig(self_collision=True, collision_thickness=0.005, remeshing=("uniform1", "uniform3")).problems()
    assert len(bad) == 1 and "half the finest edge" in bad[0] and "level 3" in bad[0]
    assert SimConfig(self_collision=True, collision_thickness=0.005).problems() == []      # uniform1: 33 mm
    assert SimConfig(self_collision=False, collision_thickness=0.005, remeshing=("adaptive",)).problems() == []
