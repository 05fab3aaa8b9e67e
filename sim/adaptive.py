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
import warnings
from concurrent.futures.process import BrokenProcessPool

import numpy as np

from clothgap.parallel import chunk_size, pool_size, spawn_pool
from sim import remesh
from sim.motions import ClipScene
from sim.phases import timed
from sim.solver import BatchSolver, CGStats, ClothSpec, SolverParams

# A batch this large on a machine with this many cores remeshes its cloths in a process pool: a cloth's
# remeshing, solver mesh and rest state are ~12 ms of numpy a frame (45 minutes a frame-serial paper-size
# setting), and each cloth's step is a pure function of its mesh, positions and velocities.
REMESH_POOL_MIN_CLOTHS = 64
REMESH_POOL_MIN_CPUS = 4


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
    state: remesh.MeshState        # of ``quad``: the solver's mesh and rest state, the edges and their rest lengths
    spec: ClothSpec
    pin_edge: bool                 # pinned along the whole top edge
    pin_points: np.ndarray         # (P, 2) lattice points pinned


def _pins(c: _Cloth) -> np.ndarray:
    lat = c.quad.lattice
    if c.pin_edge:
        return np.flatnonzero(lat[:, 1] == c.quad.n_fine)
    # lattice points as integers, matched in one pass (a Python loop over the vertices was ~1 ms a cloth a rebuild)
    n = c.quad.n_fine + 1
    return np.flatnonzero(np.isin(lat[:, 0] * n + lat[:, 1], c.pin_points[:, 0] * n + c.pin_points[:, 1]))


def _start(scene: ClipScene, base: remesh.QuadMesh, state: remesh.MeshState) -> _Cloth:
    spec = scene.spec
    pinned = np.asarray(spec.pinned if spec.pinned is not None else [], dtype=np.int64)
    top = np.flatnonzero(base.lattice[:, 1] == base.n_fine)
    return _Cloth(base, state, spec, pin_edge=len(pinned) > 0 and set(top.tolist()) <= set(pinned.tolist()),
                  pin_points=base.lattice[pinned])


def _solver(cloths: list[_Cloth], params: SolverParams, device: str, elapsed: float,
            winds: np.ndarray | None) -> BatchSolver:
    specs = []
    for c in cloths:
        arm = c.spec.arm
        if arm is not None:  # the solver's clock starts at zero with every rebuild
            arm = dataclasses.replace(arm, t0=arm.t0 - elapsed)
        specs.append(dataclasses.replace(c.spec, arm=arm, pinned=_pins(c)))
    solver = BatchSolver(specs, params, device, mesh_rests=[c.state.rest for c in cloths])
    if winds is not None:
        solver.set_wind(winds)
    return solver


class _Remesher:
    """Every cloth's remeshing step of a frame: in this process, or in a spawned process pool (the parent
    holds a CUDA context) when ``workers`` > 1. Results come back in the cloths' order."""

    def __init__(self, workers: int):
        self.workers = workers
        self.pool = spawn_pool(workers) if workers > 1 else None

    def __call__(self, cloths: list[int], quads: list, positions: list, velocities: list,
                 refine_angle: float) -> list[remesh.Remeshed | None]:
        if self.pool is None or len(cloths) < 2:
            return [remesh.remesh_cloth(q, p, v, refine_angle, c)
                    for c, q, p, v in zip(cloths, quads, positions, velocities)]
        try:
            return list(self.pool.map(remesh.remesh_cloth, quads, positions, velocities,
                                      [refine_angle] * len(cloths), cloths,
                                      chunksize=chunk_size(len(cloths), self.workers)))
        except BrokenProcessPool:
            # a worker died (killed, out of memory): the same steps in this process give the same bytes
            warnings.warn("a remeshing worker died; remeshing the rest of this batch in this process",
                          stacklevel=2)
            self.close()
            self.pool = None
            return self(cloths, quads, positions, velocities, refine_angle)

    def close(self) -> None:
        if self.pool is not None:
            self.pool.shutdown(cancel_futures=True)




def simulate_adaptive(scenes: list[ClipScene], base: remesh.QuadMesh, *, fps: float, frames: int,
                      substeps: int, settle_s: float, cg_iterations: int = 30,
                      cg_tolerance: float = SolverParams.cg_tolerance, self_collision: bool = False,
                      collision_thickness: float = SolverParams.collision_thickness, device: str = "cpu",
                      refine_angle: float = 0.3, health=None, on_frame=None,
                      host_workers: int | None = None, phases: dict[str, float] | None = None) -> list[AdaptiveResult]:
    """Settle without wind on the base mesh, then record ``frames`` frames with the wind on,
    remeshing every cloth after each frame. ``scenes`` must be built on ``remesh.cloth_mesh(base)``.
    ``health(cloth, x, x_prev, frame_dt)`` may read ``cloth.state`` (the mesh the solver ran this frame
    on). ``host_workers``: processes that remesh the cloths (None: one per CPU for a large batch; 0 or 1:
    this process); the clips are the same bytes either way. ``phases`` (optional) gets the seconds
    of building the first solver and settling (``settle``), the recorded frames' steps and read-backs
    (``steps``), the health checks (``health``), remeshing (``remesh``, the pool's wall time) and the
    solvers rebuilt after it (``rebuild``)."""
    dt = 1.0 / (fps * substeps)
    params = SolverParams(dt=dt, cg_iterations=cg_iterations, cg_tolerance=cg_tolerance,
                          self_collision=self_collision, collision_thickness=collision_thickness)
    remesher = _Remesher(pool_size(len(scenes), REMESH_POOL_MIN_CLOTHS, REMESH_POOL_MIN_CPUS)
                         if host_workers is None else host_workers)
    try:
        return _simulate(scenes, base, params, fps, frames, substeps, settle_s, refine_angle, health, on_frame,
                         remesher, device, phases)
    finally:
        remesher.close()


def _simulate(scenes, base, params, fps, frames, substeps, settle_s, refine_angle, health, on_frame, remesher,
              device, phases) -> list[AdaptiveResult]:
    dt = params.dt
    cg = [CGStats() for _ in scenes]        # summed over the solvers a remeshing run rebuilds
    dropped = [0] * len(scenes)
    with timed(phases, "settle"):
        base_state = remesh.mesh_state(base)
        cloths = [_start(s, base, base_state) for s in scenes]
        winds = np.stack([s.wind for s in scenes])
        solver = _solver(cloths, params, device, 0.0, None)
        settle_steps = int(round(settle_s / dt))
        solver.step(settle_steps)
        elapsed = settle_steps * dt
        solver.set_wind(winds)
        prev = solver.positions()
    reasons: list[str | None] = [None] * len(scenes)
    recorded: list[list] = [[] for _ in scenes]
    for t in range(frames):
        with timed(phases, "steps"):
            solver.step(substeps)
            elapsed += substeps * dt
            pos, vel = solver.positions(), solver.velocities()
        with timed(phases, "health"):
            for c, cloth in enumerate(cloths):
                if reasons[c] is None and health is not None:
                    why = health(cloth, pos[c], prev[c], 1.0 / fps)
                    reasons[c] = None if why is None else f"frame {t}: {why}"
                recorded[c].append((pos[c], cloth.quad.faces, cloth.quad.uv))
        alive = [c for c in range(len(cloths)) if reasons[c] is None] if t + 1 < frames else []
        with timed(phases, "remesh"):
            steps = dict(zip(alive, remesher(alive, [cloths[c].quad for c in alive], [pos[c] for c in alive],
                                             [vel[c] for c in alive], refine_angle)))
        changed = False
        for c, cloth in enumerate(cloths):
            new = steps.get(c)
            if new is not None:
                cloth.quad, cloth.state = new.quad, new.state
                cloth.spec = dataclasses.replace(cloth.spec, mesh=new.state.mesh, positions=new.positions,
                                                 velocities=new.velocities)
                pos[c] = new.positions
                changed = True
            else:
                cloth.spec = dataclasses.replace(cloth.spec, positions=pos[c], velocities=vel[c])
        if changed:                         # (never after the last frame: nothing is remeshed then)
            with timed(phases, "rebuild"):
                cg = [a.merged(b) for a, b in zip(cg, solver.cg_stats())]
                dropped = [a + b for a, b in zip(dropped, solver.collision_dropped() or [0] * len(scenes))]
                solver = None               # freed before the next one allocates: one solver's memory at a time
                solver = _solver(cloths, params, device, elapsed, winds)
        prev = pos
        if on_frame is not None:
            on_frame()
    cg = [a.merged(b) for a, b in zip(cg, solver.cg_stats())]
    dropped = [a + b for a, b in zip(dropped, solver.collision_dropped() or [0] * len(scenes))]
    return [AdaptiveResult(None if r else rec, r, [len(f[0]) for f in rec], c, d if params.self_collision else None)
            for r, rec, c, d in zip(reasons, recorded, cg, dropped)]
