"""The solver's conjugate gradient: per-cloth residual stopping test, float32 floors, statistics.

CPU, small meshes; shares the compiled ``sim.kernels`` module with tests/test_sim.py.
"""

from __future__ import annotations

import numpy as np

from sim.config import SimConfig
from sim.materials import load_material
from sim.mesh import square_cloth
from sim.motions import hanging_positions
from sim.solver import BatchSolver, CGStats, ClothSpec, SolverParams

BASIS = load_material("camel-ponte-roma")


def _hanging(p: float, k: float, wind=(0.0, 0.0, 0.0), n: int = 6, size: float = 0.2) -> ClothSpec:
    mesh = square_cloth(size, n, 1)
    pos, top = hanging_positions(mesh, size)
    m = BASIS.scaled(p, k)
    return ClothSpec(mesh, pos, m.stretching, m.bending, m.density, pinned=top, wind=wind)


def test_many_iterations_stay_finite_where_the_fixed_count_cg_went_nan():
    """400 iterations at dt 1/200 on a small stiff cloth in wind: the fixed-count float32 CG ran past
    convergence into subnormal r.z and p.A p (1e-37..1e-44) and this cloth's positions were NaN within
    0.5 s. Now each cloth stops at its tolerance, or, with tolerance 0, at float32's floor."""
    specs = [_hanging(1.0, 1.0), _hanging(20.0, 20.0, wind=(0.0, 2.0, 0.0))]
    for tol in (SolverParams.cg_tolerance, 0.0):
        solver = BatchSolver(specs, SolverParams(dt=1.0 / 200.0, cg_iterations=400, cg_tolerance=tol), "cpu")
        solver.step(100)
        for x, v in zip(solver.positions(), solver.velocities()):
            assert np.isfinite(x).all() and np.isfinite(v).all() and np.abs(x).max() < 1.0
        for s in solver.cg_stats():
            assert s.steps == 100
            # every step stopped well before 400: the old loop would have iterated on in the subnormals
            assert 0 < s.max_iterations < 200, s
            assert s.max_residual <= max(tol, 1e-5), s


def test_small_time_step_stays_finite_and_converges_in_few_iterations():
    """dt 1/1600 at the default 30 iterations: the system is nearly the mass matrix, CG converges in a few
    iterations (the fixed loop then spent the rest of its 30 on underflowing scalars)."""
    specs = [_hanging(0.5, 0.5, wind=(0.0, 1.0, 0.0)), _hanging(20.0, 20.0, wind=(0.0, 2.0, 0.0))]
    solver = BatchSolver(specs, SolverParams(dt=1.0 / 1600.0, cg_iterations=30, cg_tolerance=0.0), "cpu")
    solver.step(320)
    assert all(np.isfinite(x).all() for x in solver.positions())
    stats = solver.cg_stats()
    assert stats[0].iterations / stats[0].steps < 25, stats      # stopped at float32's floor, not at 30


def test_each_cloth_of_a_batch_stops_on_its_own():
    """A soft and a stiff cloth in one launch: the soft one needs fewer iterations; batched equals alone."""
    specs = [_hanging(0.5, 0.5, wind=(0.0, 1.0, 0.0)), _hanging(20.0, 20.0, wind=(0.0, 2.0, 0.0))]
    params = SolverParams(dt=1.0 / 200.0, cg_iterations=200, cg_tolerance=1e-3)
    together = BatchSolver(specs, params, "cpu")
    together.step(40)
    soft, stiff = together.cg_stats()
    assert soft.iterations < stiff.iterations and soft.max_iterations < stiff.max_iterations
    assert max(soft.max_residual, stiff.max_residual) <= 1e-3
    for c, spec in enumerate(specs):
        alone = BatchSolver([spec], params, "cpu")
        alone.step(40)
        np.testing.assert_allclose(alone.positions()[0], together.positions()[c], atol=1e-5)
        assert alone.cg_stats()[0].max_iterations == together.cg_stats()[c].max_iterations


def test_tolerance_changes_a_default_wind_clip_by_at_most_a_few_mm():
    """The stage's defaults (16x16 cloth, dt 1/200, 30 iterations, block-Jacobi), the softest class and a mid
    one, 6 frames after the settle: the default tolerance against tolerance 0 (which runs the 30 iterations
    unless float32 has nothing left to reduce). Measured: at most 2.7 mm / 0.07 mm, 0.09 mm / 0.007 mm on
    average (Jacobi: 3.5 / 0.02, 0.15 / 0.002); for scale, one more iteration of the fixed-count CG moved a
    soft clip by 26 mm over 10 frames (a flapping cloth amplifies any small change)."""
    from sim.stage import build_scene, parse_setting, simulate_scenes

    cfg = SimConfig(classes=(0, 26), sequences_per_class=1)
    setting = parse_setting("wind-uniform1")
    mesh = square_cloth(cfg.cloth_size_m, cfg.grid_vertices, 1)
    scenes = [build_scene(cfg, 0, i, setting, mesh)[0] for i in range(2)]
    run = {tol: simulate_scenes(scenes, fps=cfg.fps, frames=6, substeps=cfg.substeps, settle_s=cfg.settle_s,
                                cg_iterations=cfg.cg_iterations, cg_tolerance=tol, device="cpu")
           for tol in (cfg.cg_tolerance, 0.0)}
    for with_tol, full in zip(run[cfg.cg_tolerance], run[0.0]):
        assert with_tol.reason is None and full.reason is None
        diff = np.linalg.norm(with_tol.positions - full.positions, axis=-1)
        assert diff.max() < 0.006 and diff.mean() < 0.001, (diff.max(), diff.mean())
        assert full.cg.max_iterations == 30 and full.cg.iterations >= 29 * full.cg.steps
        assert full.cg.iterations >= with_tol.cg.iterations
    soft = run[cfg.cg_tolerance][0].cg
    assert soft.iterations < 30 * soft.steps          # the tolerance did stop some steps early
    health = soft.health()
    assert set(health) == {"cg_steps", "cg_iterations_mean", "cg_iterations_max", "cg_residual_max"}
    assert health["cg_iterations_mean"] < 30 and health["cg_iterations_max"] <= 30


def test_stats_merge_across_solvers_and_keep_nan():
    a = CGStats(10, 100.0, 12, 1e-3)
    b = CGStats(5, 20.0, 4, 2e-3)
    m = a.merged(b)
    assert (m.steps, m.iterations, m.max_iterations, m.max_residual) == (15, 120.0, 12, 2e-3)
    assert m.health()["cg_iterations_mean"] == 8.0
    assert np.isnan(a.merged(CGStats(1, 1.0, 1, float("nan"))).max_residual)
    assert np.isnan(CGStats(1, 1.0, 1, float("nan")).merged(a).max_residual)


def test_cg_tolerance_is_validated():
    assert SimConfig().problems() == []
    assert SimConfig(cg_tolerance=0.0).problems() == []
    for bad in (-1e-3, 1.0):
        assert any("sim.cg_tolerance" in p for p in SimConfig(cg_tolerance=bad).problems())
