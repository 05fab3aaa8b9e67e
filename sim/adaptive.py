"""Simulation with adaptive remeshing: the batch is remeshed between frames.

Each cloth lives on a ``sim.remesh.QuadMesh``. After every recorded frame the
cloths are remeshed by curvature (refined where folded, coarsened where flat);
when any cloth's mesh changed, the batch solver is rebuilt from the carried-over
positions and velocities (``sim.remesh.transfer``). Kernels are compiled once,
so a rebuild costs array uploads (and a new CUDA graph), not a compile.

Pinned vertices follow their rule across remeshes: a cloth pinned along its
whole top edge (the ``rod`` pose) pins every top-edge vertex the remesher
creates, at the position interpolated on the pinned edge; a cloth pinned at
points pins the same lattice points.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from sim import remesh
from sim.mesh import ClothMesh, hinges_of
from sim.motions import ClipScene
from sim.solver import BatchSolver, CGStats, ClothSpec, SolverParams


def cloth_mesh(q: remesh.QuadMesh) -> ClothMesh:
    """The solver's mesh of a quadtree mesh."""
    return ClothMesh(q.uv.astype(np.float64), q.faces, hinges_of(q.faces))


@dataclasses.dataclass
class AdaptiveResult:
    frames: list[tuple[np.ndarray, np.ndarray, np.ndarray]] | None   # (positions, faces, uv) per frame
    reason: str | None
    vertex_counts: list[int] = dataclasses.field(default_factory=list)
    cg: CGStats | None = None
    collision_dropped: int | None = None


@dataclasses.dataclass
class _Cloth:
    quad: remesh.QuadMesh
    spec: ClothSpec
    pin_edge: bool                 # pinned along the whole top edge
    pin_points: set[tuple[int, int]]


def _pins(c: _Cloth) -> np.ndarray:
    lat = c.quad.lattice
    if c.pin_edge:
        return np.flatnonzero(lat[:, 1] == c.quad.n_fine)
    return np.array([k for k, p in enumerate(map(tuple, lat.tolist())) if p in c.pin_points], dtype=np.int64)


def _start(scene: ClipScene, base: remesh.QuadMesh) -> _Cloth:
    spec = scene.spec
    pinned = np.asarray(spec.pinned if spec.pinned is not None else [], dtype=np.int64)
    top = np.flatnonzero(base.lattice[:, 1] == base.n_fine)
    return _Cloth(base, spec, pin_edge=len(pinned) > 0 and set(top.tolist()) <= set(pinned.tolist()),
                  pin_points={tuple(p) for p in base.lattice[pinned].tolist()})


def _solver(cloths: list[_Cloth], params: SolverParams, device: str, elapsed: float,
            winds: np.ndarray | None) -> BatchSolver:
    specs = []
    for c in cloths:
        arm = c.spec.arm
        if arm is not None:  # the solver's clock starts at zero with every rebuild
            arm = dataclasses.replace(arm, t0=arm.t0 - elapsed)
        specs.append(dataclasses.replace(c.spec, arm=arm, pinned=_pins(c)))
    solver = BatchSolver(specs, params, device)
    if winds is not None:
        solver.set_wind(winds)
    return solver


def simulate_adaptive(scenes: list[ClipScene], base: remesh.QuadMesh, *, fps: float, frames: int,
                      substeps: int, settle_s: float, cg_iterations: int = 30,
                      cg_tolerance: float = SolverParams.cg_tolerance, self_collision: bool = False,
                      collision_thickness: float = SolverParams.collision_thickness, device: str = "cpu",
                      refine_angle: float = 0.3, health=None, on_frame=None) -> list[AdaptiveResult]:
    """Settle without wind on the base mesh, then record ``frames`` frames with the wind on,
    remeshing every cloth after each frame. ``scenes`` must be built on ``cloth_mesh(base)``."""
    dt = 1.0 / (fps * substeps)
    params = SolverParams(dt=dt, cg_iterations=cg_iterations, cg_tolerance=cg_tolerance,
                          self_collision=self_collision, collision_thickness=collision_thickness)
    cg = [CGStats() for _ in scenes]        # summed over the solvers a remeshing run rebuilds
    dropped = [0] * len(scenes)
    cloths = [_start(s, base) for s in scenes]
    winds = np.stack([s.wind for s in scenes])
    solver = _solver(cloths, params, device, 0.0, None)
    settle_steps = int(round(settle_s / dt))
    solver.step(settle_steps)
    elapsed = settle_steps * dt
    solver.set_wind(winds)
    reasons: list[str | None] = [None] * len(scenes)
    recorded: list[list] = [[] for _ in scenes]
    prev = solver.positions()
    for t in range(frames):
        solver.step(substeps)
        elapsed += substeps * dt
        pos, vel = solver.positions(), solver.velocities()
        changed = False
        for c, cloth in enumerate(cloths):
            if reasons[c] is None and health is not None:
                why = health(cloth, pos[c], prev[c], 1.0 / fps)
                reasons[c] = None if why is None else f"frame {t}: {why}"
            recorded[c].append((pos[c], cloth.quad.faces, cloth.quad.uv))
            if reasons[c] is None and t + 1 < frames:
                quad, p, v = remesh.remesh(cloth.quad, pos[c].astype(np.float64), vel[c].astype(np.float64),
                                           refine_angle)
                if quad is not cloth.quad:
                    cloth.quad = quad
                    cloth.spec = dataclasses.replace(cloth.spec, mesh=cloth_mesh(quad), positions=p.astype(np.float32),
                                                     velocities=v.astype(np.float32))
                    pos[c] = p.astype(np.float32)
                    changed = True
                else:
                    cloth.spec = dataclasses.replace(cloth.spec, positions=pos[c], velocities=vel[c])
            else:
                cloth.spec = dataclasses.replace(cloth.spec, positions=pos[c], velocities=vel[c])
        if changed and t + 1 < frames:
            cg = [a.merged(b) for a, b in zip(cg, solver.cg_stats())]
            dropped = [a + b for a, b in zip(dropped, solver.collision_dropped() or [0] * len(scenes))]
            solver = _solver(cloths, params, device, elapsed, winds)
        prev = pos
        if on_frame is not None:
            on_frame()
    cg = [a.merged(b) for a, b in zip(cg, solver.cg_stats())]
    dropped = [a + b for a, b in zip(dropped, solver.collision_dropped() or [0] * len(scenes))]
    return [AdaptiveResult(None if r else rec, r, [len(f[0]) for f in rec], c, d if self_collision else None)
            for r, rec, c, d in zip(reasons, recorded, cg, dropped)]
