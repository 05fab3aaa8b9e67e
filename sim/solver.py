"""A batched implicit cloth solver in Warp: many cloths, one launch per kernel per step.

Model: Wang et al. 2011 stretching (per-face, k from the table at the current
strain, held constant when differentiating) and bending (dihedral-angle hinges
with ke from the 3x5 table), gravity, the aerodynamic wind force of ArcSim's
model, area-lumped mass. Cloth rest shapes are flat (rest dihedral angle 0).

Integrator: backward Euler with one linearised Newton step per time step,

    (M (1 + h a) + h^2 K) dv = h (f(x, v) - a M v) - h^2 K v,   v += dv,   x += h v,

where K is a positive semi-definite approximation of the stiffness: the
Gauss-Newton part of the stretching Hessian with its 2x2 (k0, k1; k1, k2)
block clamped to PSD, plus the geometric (stress) part with the stress
projected onto PSD matrices, and the Gauss-Newton part kb g g^T of the
bending Hessian. A PSD K keeps the step stable from the softest (p=0.5, k=0.5)
to the stiffest (p=20, k=20) class. ``a`` is a mild mass-proportional damping
(``SolverParams.damping``, 1/s); backward Euler adds its own numerical damping.
Wind is applied explicitly. An optional kinematic capsule arm (``ArmSpec``) is
handled in two places:

* inside the solve, as velocity constraints (Baraff & Witkin 1998's modified
  PCG): a vertex touching a capsule and not moving away from it gets the
  surface's normal velocity prescribed (plus what closes any penetration in one
  step); CG starts from that dv and filters the normal direction out of the
  residual, so the cloth's stiff forces react against the arm instead of moving
  the contact vertex. A contact persists while its normal impulse pushes: one
  whose constraint impulse comes out adhesive is released for the next step.
  The penetration-closing part of the prescribed velocity is taken back off
  after the step (it moves the vertex, it is not a velocity the cloth keeps).
  Friction is in the solve too, as regularised Coulomb friction: a tangential
  damping c P (P = I - n n^T) on the contact vertex's mass, c = mu J_n /
  max(|slip|, ``slip_velocity``) from the previous step's normal impulse J_n
  and the slip relative to the (rigidly turning) arm surface: mu J_n against a
  sliding vertex, and at rest a stiff damping that holds a draped cloth
  (creeping below ``slip_velocity``) while the pull stays inside the cone.
  Contact resolved only after the solve lets stiff cloths stretch round the
  forearm and every cloth slide off the arm (docs/simulation.md, "Arm contact");
* after the step, as a projection: vertices out of the capsules, edges whose
  inside comes closer than the contact thickness out of them too (vertex-only
  contact lets a capsule of the edge length's size slide between two vertices),
  both with non-penetrating velocity relative to the surface and Coulomb friction.

The system is solved per cloth with a preconditioned conjugate gradient of at
most ``cg_iterations`` iterations: block-Jacobi by default (each vertex's 3 x 3
block of A = M + h^2 K, inverted; ``cg_preconditioner="jacobi"`` keeps only its
diagonal, which the arm's contact-filtered solve always uses); per-cloth dot products are atomic adds
into per-cloth slots. Pinned vertices are filtered out of the system. Each
cloth stops on its own once its residual has fallen to ``cg_tolerance`` times
its initial residual (|r| <= tol |r0|, unpreconditioned), or before a division
by a p.A p or r.z so small that float32 has nothing left of it (past
convergence both underflow to subnormals, and iterating on makes NaN). A
stopped cloth is masked out of the remaining launches rather than the loop
broken on the host, so a step stays a fixed list of launches (CUDA-graph
captured on GPUs) with no device-to-host sync; on the CPU, whose device memory
is the host's, a step leaves the loop once no cloth runs. ``cg_stats()`` reports per cloth
the iterations taken per step (mean, max) and the largest final relative
residual.

Self-collision (``SolverParams.self_collision``, ``sim.collision``): after the step, point-triangle and
edge-edge velocity impulses keep non-adjacent parts of each cloth ``collision_thickness`` apart, before the
arm's projection (the arm, kinematic, has the last word).

Batching: ``BatchSolver(specs)`` concatenates the cloths; every face, hinge and
vertex knows its cloth id, so per-cloth materials, densities and winds are just
per-cloth arrays.
"""

from __future__ import annotations

import math
import sys
import time
from dataclasses import dataclass

import numpy as np
import warp as wp

from sim import collision, kernels
from sim.collision import SelfCollision
from sim.mesh import mesh_rest
from sim.specs import ArmSpec, ClothSpec   # plain data, kept apart so that sim.motions needs no Warp


class _StderrLogger:
    """Warp's logger with its info lines (the start-up banner, module loads) on stderr, where they do not
    mix with a command's output; warnings and errors go to Warp's own logger."""

    def __init__(self, default):
        self.default = default

    def debug(self, message: str) -> None:
        print(message, file=sys.stderr)

    info = debug

    def warning(self, message: str, category=None, stacklevel: int = 1) -> None:
        self.default.warning(message, category, stacklevel + 1)

    def error(self, message: str) -> None:
        self.default.error(message)


if hasattr(wp, "set_logger"):
    wp.set_logger(_StderrLogger(wp.get_logger()))
else:                                           # an older Warp: no logger to replace, only a switch
    wp.config.quiet = True


@dataclass(frozen=True)
class SolverParams:
    dt: float = 1.0 / 200.0               # seconds per step
    cg_iterations: int = 30               # the most CG iterations per step (the launches are fixed: graph capture)
    cg_tolerance: float = 1.0e-3          # a cloth's CG stops at |r| <= tol |r0|; 0: only at float32's limit
    cg_preconditioner: str = "block"      # "block" (each vertex's 3 x 3 block of A) or "jacobi" (its diagonal)
    gravity: tuple[float, float, float] = (0.0, 0.0, -9.81)
    air_density: float = 1.225            # kg/m^3, the wind pressure coefficient
    air_drag: float = 0.1                 # kg/(m^2 s), tangential drag coefficient
    damping: float = 0.1                  # 1/s, mass-proportional
    contact_thickness: float = 0.005      # m, kept between the cloth and an arm's surface
    friction: float = 0.6                 # Coulomb coefficient between cloth and arm (fabric on skin)
    slip_velocity: float = 1.0e-3         # m/s, below it friction is a stiff damping (static friction's creep)
    contact_tolerance: float = 0.005      # m, beyond the contact surface a vertex still counts as touching
    contact_iterations: int = 1           # Jacobi passes of the edge-capsule contact after each step
    self_collision: bool = False          # point-triangle and edge-edge repulsion within a cloth (sim.collision)
    collision_thickness: float = 0.003    # m, kept between non-adjacent parts of one cloth
    self_friction: float = 0.3            # Coulomb coefficient of cloth on itself
    collision_passes: int = 8             # Jacobi passes of the self-collision impulses per step
    collision_slots: int = 16             # pairs kept per vertex and per edge each step


@dataclass(frozen=True)
class CGStats:
    """One cloth's conjugate-gradient work over ``steps`` solver steps (``BatchSolver.cg_stats``)."""

    steps: int = 0
    iterations: float = 0.0               # summed over the steps
    max_iterations: int = 0               # the most one step took
    max_residual: float = 0.0             # the largest final |r| / |r0| of a step

    def merged(self, other: "CGStats") -> "CGStats":
        """The statistics of both runs together (a cloth simulated by successive solvers)."""
        a, b = self.max_residual, other.max_residual
        worst = b if (math.isnan(b) or b > a) else a          # a NaN residual is kept
        return CGStats(self.steps + other.steps, self.iterations + other.iterations,
                       max(self.max_iterations, other.max_iterations), worst)

    def health(self) -> dict:
        """The clip's health entries: mean and max iterations per step, max final relative residual."""
        return {"cg_steps": self.steps,
                "cg_iterations_mean": round(self.iterations / self.steps, 3) if self.steps else 0.0,
                "cg_iterations_max": self.max_iterations,
                "cg_residual_max": float(f"{self.max_residual:.4g}")}


def load_kernels(device: str) -> None:
    """Compiles the solver's Warp modules (a machine's first run; up to four at once) or loads them from Warp's
    kernel cache, so that the time goes here rather than into the first step."""
    wp.init()
    wp.force_load(device=resolve_device(device), modules=[wp.get_module(m.__name__) for m in (kernels, collision)])


def resolve_device(device: str) -> str:
    """'auto' -> 'cuda' when a CUDA device exists, else 'cpu'."""
    if device == "auto":
        return "cuda" if wp.get_cuda_device_count() > 0 else "cpu"
    return device


def _batch_rest(specs: list[ClothSpec], offsets: np.ndarray,
                shared: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """The batch's host-side rest state, cloths concatenated (cloth c from vertex ``offsets[c]`` on), in the
    dtypes the solver uploads (float32, int32): positions, velocities, free flags, each vertex's, face's, hinge's
    and edge's cloth, each cloth's mesh rest state ``shared[c]`` (``sim.mesh.mesh_rest``) with its vertex
    indices offset into the batch, and the lumped masses in float64 (self-collision inverts them).

    Built with one concatenation per array, straight into its dtype: cloth-by-cloth assembly (``np.add.at`` of
    each cloth's masses above all, then concatenating and converting) was most of the host time of an adaptive
    rebuild, ~1 ms a cloth every frame. A vertex's mass is still its faces' area * density / 3 added in face
    order, and every value is converted once as before, so the solver gets the same bytes."""
    for c, s in enumerate(specs):
        nv = len(s.mesh.uv)
        if s.positions.shape != (nv, 3):
            raise ValueError(f"cloth {c}: positions must be ({nv}, 3), got {s.positions.shape}")
        if s.stretching.shape != (6, 4) or s.bending.shape != (3, 5):
            raise ValueError(f"cloth {c}: stretching must be 6x4 and bending 3x5")
        if not s.density > 0:
            raise ValueError(f"cloth {c}: density must be positive, got {s.density}")
    f32, i32 = np.float32, np.int32
    nv = int(offsets[-1])
    start = offsets[:-1].astype(i32)
    cloth = np.arange(len(specs), dtype=i32)
    per_vertex = np.diff(offsets)
    per_face = np.array([len(s.mesh.faces) for s in specs])
    per_hinge = np.array([len(s.mesh.hinges) for s in specs])
    per_edge = np.array([len(r["edges"]) for r in shared])

    def cat(arrays, dtype):
        return np.concatenate(arrays, dtype=dtype, casting="same_kind")

    def indices(arrays, count, width):      # the cloths' vertex indices, offset into the batch
        out = cat([np.reshape(a, (-1, width)) for a in arrays], i32)
        out += np.repeat(start, count)[:, None]
        return out

    tri = indices([s.mesh.faces for s in specs], per_face, 3)
    area = np.concatenate([r["area"] for r in shared])
    weight = area * np.repeat(np.array([s.density for s in specs], dtype=np.float64), per_face)
    weight /= 3.0
    # bincount adds each vertex's weights in input order, as np.add.at does: the same float64 sums
    mass = np.bincount(tri.ravel(), weights=np.repeat(weight, 3), minlength=nv)
    free = np.ones(nv, dtype=f32)
    pinned = []
    for c, s in enumerate(specs):
        if s.pinned is not None and len(s.pinned):
            p = np.asarray(s.pinned, dtype=np.int64)
            if p.min() < 0 or p.max() >= per_vertex[c]:
                raise ValueError(f"cloth {c}: pinned vertices must be in [0, {per_vertex[c]})")
            pinned.append(p + offsets[c])
    if pinned:
        free[np.concatenate(pinned)] = 0.0
    return {"x": cat([s.positions for s in specs], f32),
            "v": cat([np.zeros((n, 3), f32) if s.velocities is None else s.velocities
                      for n, s in zip(per_vertex, specs)], f32),
            "mass": mass, "free": free, "vertex_cloth": np.repeat(cloth, per_vertex),
            "tri": tri, "dm_inv": cat([r["dm_inv"] for r in shared], f32), "area": area.astype(f32),
            "face_cloth": np.repeat(cloth, per_face),
            "hinge": indices([s.mesh.hinges for s in specs], per_hinge, 4),
            "hinge_length": cat([r["hinge_length"] for r in shared], f32),
            "hinge_area": cat([r["hinge_area"] for r in shared], f32),
            "hinge_dir": cat([r["hinge_dir"] for r in shared], f32), "hinge_cloth": np.repeat(cloth, per_hinge),
            "edges": indices([r["edges"] for r in shared], per_edge, 2), "edge_cloth": np.repeat(cloth, per_edge)}


def _launch_name(cmd) -> str:
    """A recorded command's name: its kernel's key, or the function's name (memsets)."""
    kernel = getattr(getattr(cmd, "__self__", None), "kernel", None)
    return kernel.key if kernel is not None else getattr(cmd, "__qualname__", repr(cmd))


def cloth_chunks(owner: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(start, end, cloth)`` of chunks of at most ``size`` consecutive elements of one cloth each, covering a
    batch's elements in order; ``owner`` (each element's cloth) must be sorted, as a batch concatenates its cloths."""
    owner = np.asarray(owner)
    if len(owner) == 0:
        empty = np.zeros(0, np.int32)
        return empty, empty, empty
    if np.any(np.diff(owner) < 0):
        raise ValueError("a batch's elements must be grouped by cloth in order")
    cuts = np.flatnonzero(np.diff(owner)) + 1
    first, last = np.r_[0, cuts], np.r_[cuts, len(owner)]
    count = -(-(last - first) // size)
    segment = np.repeat(np.arange(len(first)), count)
    within = np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)
    start = first[segment] + size * within
    end = np.minimum(start + size, last[segment])
    return start.astype(np.int32), end.astype(np.int32), owner[first[segment]].astype(np.int32)


class BatchSolver:
    """Advances a batch of cloths together. ``step(n)`` runs n time steps; positions are read back
    per cloth with ``positions()``."""

    def __init__(self, specs: list[ClothSpec], params: SolverParams = SolverParams(), device: str = "cpu",
                 mesh_rests: list[dict[str, np.ndarray]] | None = None):
        """``mesh_rests`` (optional): each cloth's ``sim.mesh.mesh_rest`` of its mesh, computed elsewhere
        (adaptive remeshing computes it in its host workers); by default computed here, once per mesh."""
        if not specs:
            raise ValueError("a batch needs at least one cloth")
        wp.init()
        self.params = params
        self.device = resolve_device(device)
        self.num_cloths = len(specs)
        vcount = [s.mesh.num_vertices for s in specs]
        self.vertex_offsets = np.concatenate([[0], np.cumsum(vcount)]).astype(np.int64)
        self._build(specs, mesh_rests)
        self._graph = None
        self._steps = 0
        self._program = self._record_step()     # (before, [one list per CG iteration], after)

    # ---------------------------------------------------------------- set-up
    def _build(self, specs: list[ClothSpec], mesh_rests: list[dict] | None) -> None:
        # What depends on the mesh alone is computed once per mesh: a batch of thousands of cloths shares one.
        by_mesh: dict[int, dict] = {}
        shared = []
        for c, s in enumerate(specs):
            if mesh_rests is None and id(s.mesh) not in by_mesh:
                by_mesh[id(s.mesh)] = mesh_rest(s.mesh, c)
            shared.append(mesh_rests[c] if mesh_rests is not None else by_mesh[id(s.mesh)])
        rest = _batch_rest(specs, self.vertex_offsets, shared)
        self._upload_cloths(specs, rest)
        if self.has_arm:
            self._allocate_contact(rest["edges"])
        self._allocate_step()
        self.collision = None
        if self.params.self_collision:
            self.x_start = wp.zeros_like(self.x)
            self.collision = SelfCollision(
                x0=self.x_start, x=self.x, v=self.v, mass=rest["mass"], free=rest["free"],
                vertex_cloth=self.vertex_cloth, tri=self.tri, face_cloth=self.face_cloth, edges=rest["edges"],
                edge_cloth=rest["edge_cloth"],
                num_cloths=self.num_cloths, thickness=self.params.collision_thickness,
                friction=self.params.self_friction, passes=self.params.collision_passes,
                slots=self.params.collision_slots, device=self.device)

    def _upload_cloths(self, specs: list[ClothSpec], rest: dict[str, np.ndarray]) -> None:
        """Every cloth's rest state (``_batch_rest``), materials, loads and arm as device arrays."""
        dev = self.device
        f32 = np.float32

        def arr(a, dtype):
            return wp.array(np.asarray(a), dtype=dtype, device=dev)

        self.x = arr(rest["x"], wp.vec3)
        self.v = arr(rest["v"], wp.vec3)
        self.mass = arr(rest["mass"].astype(f32), float)
        self.free = arr(rest["free"], float)
        self.vertex_cloth = arr(rest["vertex_cloth"], int)
        self.tri = arr(rest["tri"], int)
        self.dm_inv = arr(rest["dm_inv"], wp.mat22)
        self.area = arr(rest["area"], float)
        self.face_cloth = arr(rest["face_cloth"], int)
        self.hinge = arr(rest["hinge"], int)
        self.hinge_length = arr(rest["hinge_length"], float)
        self.hinge_area = arr(rest["hinge_area"], float)
        self.hinge_dir = arr(rest["hinge_dir"], float)
        self.hinge_cloth = arr(rest["hinge_cloth"], int)
        self.vertex_chunks = tuple(arr(a, int) for a in cloth_chunks(rest["vertex_cloth"], kernels.CLOTH_CHUNK))
        self.face_chunks = tuple(arr(a, int) for a in cloth_chunks(rest["face_cloth"], kernels.CLOTH_CHUNK))
        self.hinge_chunks = tuple(arr(a, int) for a in cloth_chunks(rest["hinge_cloth"], kernels.CLOTH_CHUNK))
        self.stretch = arr(np.stack([np.asarray(s.stretching).ravel() for s in specs]).astype(f32), float)
        self.bend = arr(np.stack([np.asarray(s.bending).ravel() for s in specs]).astype(f32), float)
        self.wind = arr(np.array([s.wind for s in specs], dtype=f32).reshape(-1, 3), wp.vec3)
        self.has_arm = any(s.arm is not None for s in specs)
        self.arms = wp.array(self._arm_table([s.arm for s in specs]), dtype=kernels.Arm, device=dev)
        self.clock = wp.zeros(1, dtype=float, device=dev)
        self.faces_per_cloth = [len(s.mesh.faces) for s in specs]

    def _allocate_contact(self, edges: np.ndarray) -> None:
        """The arm contact's per-vertex state, and the unique edges ((E, 2) int32, batch indices) for edge-capsule
        contact."""
        dev, nv = self.device, self.x.shape[0]
        self.edge = wp.array(edges, dtype=int, device=dev)
        self.contact_dx = wp.zeros(nv, dtype=wp.vec3, device=dev)
        self.contact_dv = wp.zeros(nv, dtype=wp.vec3, device=dev)
        self.contact_count = wp.zeros(nv, dtype=float, device=dev)
        self.contact_n = wp.zeros(nv, dtype=wp.vec3, device=dev)
        self.contact_y = wp.zeros(nv, dtype=wp.vec3, device=dev)
        self.vy = wp.zeros(nv, dtype=wp.vec3, device=dev)
        self.contact_rn = wp.zeros(nv, dtype=float, device=dev)
        self.released = wp.zeros(nv, dtype=int, device=dev)
        self.contact_jn = wp.zeros(nv, dtype=float, device=dev)
        self.friction_c = wp.zeros(nv, dtype=float, device=dev)
        self.friction_b = wp.zeros(nv, dtype=wp.vec3, device=dev)
        self.contact_recover = wp.zeros(nv, dtype=wp.vec3, device=dev)

    def _allocate_step(self) -> None:
        """The per-step work arrays: forces, the CG's vectors and per-cloth dot products, its statistics."""
        dev = self.device
        nv, nf, nh = self.x.shape[0], self.tri.shape[0], self.hinge.shape[0]
        self.num_vertices, self.num_faces, self.num_hinges = nv, nf, nh

        def vec3s(n):
            return wp.zeros(n, dtype=wp.vec3, device=dev)

        self.force, self.diag, self.kv = vec3s(nv), vec3s(nv), vec3s(nv)
        # the vertices' 3 x 3 stiffness blocks, then the block-Jacobi preconditioner (cloths without an arm;
        # the arm's contact-filtered solve keeps Jacobi)
        self.block = wp.zeros(nv, dtype=wp.mat33, device=dev)
        self._block = self.params.cg_preconditioner == "block" and not self.has_arm
        self.dv, self.r, self.z, self.p, self.ap = vec3s(nv), vec3s(nv), vec3s(nv), vec3s(nv), vec3s(nv)
        self.f0, self.f1 = vec3s(nf), vec3s(nf)
        self.kmat = wp.zeros(nf, dtype=wp.vec4, device=dev)
        self.smat = wp.zeros(nf, dtype=wp.vec3, device=dev)
        self.hinge_k = wp.zeros(nh, dtype=float, device=dev)
        self.hinge_grad = wp.zeros((nh, 4), dtype=wp.vec3, device=dev)
        slots = self.params.cg_iterations + 1
        self.rz = wp.zeros((slots, self.num_cloths), dtype=float, device=dev)
        self.pap = wp.zeros((slots, self.num_cloths), dtype=float, device=dev)
        self.rr = wp.zeros((slots, self.num_cloths), dtype=float, device=dev)
        self.face_dot = wp.zeros(nf, dtype=float, device=dev)    # each element's share of a product's p.K p
        self.hinge_dot = wp.zeros(nh, dtype=float, device=dev)
        self.vertex_dot = (wp.zeros(nv, dtype=float, device=dev), wp.zeros(nv, dtype=float, device=dev))
        nc = self.num_cloths
        self.cg_active = wp.zeros(nc, dtype=int, device=dev)
        self.cg_taken = wp.zeros(nc, dtype=int, device=dev)          # this step's iterations
        self.cg_residual = wp.zeros(nc, dtype=float, device=dev)       # the current r.r per cloth
        self.cg_iteration_sum = wp.zeros(nc, dtype=float, device=dev)  # statistics over all steps so far
        self.cg_iteration_max = wp.zeros(nc, dtype=int, device=dev)
        self.cg_residual_max = wp.zeros(nc, dtype=float, device=dev)

    @staticmethod
    def _arm_table(arms: list[ArmSpec | None]) -> np.ndarray:
        """The cloths' ``kernels.Arm`` structs as one NumPy structured array, a row per cloth (all zero, inactive,
        for a cloth without an arm). Rows rather than Warp struct instances: setting a struct's fields one by one
        costs ~25 us a cloth, and every adaptive rebuild builds them all again (the arm's clock restarts)."""
        table = np.zeros(len(arms), dtype=kernels.Arm.numpy_dtype())
        for c, arm in enumerate(arms):
            if arm is not None:
                axis = np.asarray(arm.axis, dtype=np.float64)
                table[c] = (1, arm.shoulder, arm.elbow, arm.forearm, axis / np.linalg.norm(axis), arm.radius,
                            arm.omega, arm.max_angle, arm.t0)
        return table

    def _launcher(self, cmds: list):
        """``launch(kernel, dim, inputs)``: records a launch on the solver's device into ``cmds`` (none when
        ``dim`` is 0)."""
        def launch(kernel, dim, inputs):
            if dim > 0:
                cmds.append(wp.launch(kernel, dim=dim, inputs=inputs, device=self.device, record_cmd=True).launch)
        return launch

    def _record_step(self) -> tuple[list, list[list], list]:
        """One time step as fixed lists of recorded launches (and memsets): before the CG iterations,
        one list per iteration, after them."""
        before: list = [self.rz.zero_, self.pap.zero_, self.rr.zero_]
        self._record_cg_start(self._launcher(before))
        iterations: list[list] = []
        for it in range(self.params.cg_iterations):
            iterations.append([])
            self._record_cg_iteration(self._launcher(iterations[-1]), it)
        after: list = []
        self._record_step_end(self._launcher(after), after)
        return before, iterations, after

    def _record_hessian_product(self, launch, vec, out, scale, acc=None, slot: int = 0) -> None:
        """out += scale * K vec; with ``acc``, acc[slot, cloth] += scale * vec.K vec, summed a chunk of a cloth's
        elements at a time (``kernels.cloth_chunk_sum``)."""
        nf, nh = self.num_faces, self.num_hinges
        launch(kernels.face_hessian_product, nf, [vec, self.tri, self.dm_inv, self.face_cloth, self.f0, self.f1,
                                                  self.kmat, self.smat, scale, self.cg_active, out, self.face_dot])
        launch(kernels.hinge_hessian_product, nh, [vec, self.hinge, self.hinge_cloth, self.hinge_k,
                                                   self.hinge_grad, scale, self.cg_active, out, self.hinge_dot])
        if acc is not None:
            self._record_cloth_sums(launch, [(self.face_dot, self.face_chunks, acc),
                                             (self.hinge_dot, self.hinge_chunks, acc)], slot)

    def _record_cloth_sums(self, launch, sums: list, slot: int) -> None:
        """acc[slot, cloth] += the cloth's share of ``values`` for each (values, chunks, acc) of ``sums``
        (``chunks``: the vertex, face or hinge chunks the values are laid out by), a chunk a thread
        (``kernels.cloth_chunk_sum``)."""
        for values, (start, end, cloth), acc in sums:
            launch(kernels.cloth_chunk_sum, start.shape[0], [values, start, end, cloth, slot, self.cg_active, acc])

    def _record_cg_check(self, launch, slot: int) -> None:
        tol2 = float(self.params.cg_tolerance) ** 2
        launch(kernels.cg_check, self.num_cloths, [slot, tol2, self.rz, self.pap, self.rr, self.cg_active,
                                                   self.cg_taken, self.cg_residual])

    def _record_cg_start(self, launch) -> None:
        """The forces, their Jacobians and the arm contacts at the step's start, and the CG's first residual."""
        P = self.params
        dt = float(P.dt)
        nv, nf, nh, nc = self.num_vertices, self.num_faces, self.num_hinges, self.num_cloths
        launch(kernels.cg_reset, nc, [self.cg_active, self.cg_taken, self.cg_residual])

        launch(kernels.begin_step, nv, [self.mass, wp.vec3(*P.gravity), self.force, self.diag, self.kv, self.block])
        launch(kernels.face_prepare, nf, [self.x, self.v, self.tri, self.dm_inv, self.area, self.face_cloth,
                                          self.stretch, self.wind, float(P.air_density), float(P.air_drag),
                                          self.force, self.diag, self.f0, self.f1, self.kmat, self.smat,
                                          self.block])
        launch(kernels.hinge_prepare, nh, [self.x, self.hinge, self.hinge_length, self.hinge_area, self.hinge_dir,
                                           self.hinge_cloth, self.bend, self.force, self.diag, self.hinge_k,
                                           self.hinge_grad, self.block])
        if self.has_arm:
            launch(kernels.contact_prepare, nv, [self.arms, self.vertex_cloth, self.free, self.clock,
                                                 float(P.contact_thickness), float(P.contact_tolerance), dt,
                                                 float(P.friction), float(P.slip_velocity), self.x, self.v,
                                                 self.released, self.contact_jn, self.contact_n, self.contact_y,
                                                 self.vy, self.friction_c, self.friction_b, self.contact_recover])
            self._record_hessian_product(launch, self.vy, self.kv, 1.0)
            launch(kernels.cg_start_contact, nv, [self.force, self.v, self.kv, self.mass, self.free, self.vertex_cloth,
                                                  dt, float(P.damping), self.diag, self.contact_n, self.contact_y,
                                                  self.friction_c, self.friction_b, self.contact_rn, self.dv, self.r,
                                                  self.z, self.p, self.ap, self.rz, self.pap, self.rr])
        else:
            self._record_hessian_product(launch, self.v, self.kv, 1.0)
            launch(kernels.cg_start, nv, [self.force, self.v, self.kv, self.mass, self.free, self.vertex_cloth, dt,
                                          float(P.damping), self.diag, self.dv, self.r, self.z, self.p, self.ap,
                                          self.rz, self.pap, self.rr, int(self._block), self.block])
        self._record_cg_check(launch, 0)

    def _record_cg_iteration(self, launch, it: int) -> None:
        """CG iteration ``it``: the step along the search direction, the convergence check, the next direction."""
        P = self.params
        dt, h2 = float(P.dt), float(P.dt) ** 2
        nv = self.num_vertices
        self._record_hessian_product(launch, self.p, self.ap, h2, self.pap, it)
        vrz, vrr = self.vertex_dot
        if self.has_arm:
            launch(kernels.cg_update_contact, nv, [self.mass, self.free, self.vertex_cloth, self.diag, self.p,
                                                   self.ap, self.contact_n, self.contact_rn, it, self.cg_active,
                                                   self.dv, self.r, self.z, self.rz, self.pap, vrz, vrr])
        else:
            launch(kernels.cg_update, nv, [self.mass, self.free, self.vertex_cloth, self.diag, self.p, self.ap,
                                           it, self.cg_active, self.dv, self.r, self.z, self.rz, self.pap,
                                           vrz, vrr, int(self._block), self.block])
        self._record_cloth_sums(launch, [(vrz, self.vertex_chunks, self.rz), (vrr, self.vertex_chunks, self.rr)],
                                it + 1)
        self._record_cg_check(launch, it + 1)
        if it + 1 < P.cg_iterations and self.has_arm:
            launch(kernels.cg_direction_contact, nv, [self.mass, self.vertex_cloth, dt, float(P.damping),
                                                      self.friction_c, self.z, it, self.cg_active, self.p,
                                                      self.ap, self.rz, self.vertex_dot[0]])
        elif it + 1 < P.cg_iterations:
            launch(kernels.cg_direction, nv, [self.mass, self.vertex_cloth, dt, float(P.damping), self.z, it,
                                              self.cg_active, self.p, self.ap, self.rz, self.vertex_dot[0]])
        if it + 1 < P.cg_iterations:
            self._record_cloth_sums(launch, [(self.vertex_dot[0], self.vertex_chunks, self.pap)], it + 1)

    def _record_step_end(self, launch, cmds: list) -> None:
        """After the CG: its statistics, the integration, self-collision and the arm's contacts, into ``cmds``
        (``launch`` records into it too)."""
        P = self.params
        dt = float(P.dt)
        nv, nc = self.num_vertices, self.num_cloths
        launch(kernels.cg_finish, nc, [self.rr, self.cg_taken, self.cg_residual, self.cg_iteration_sum,
                                       self.cg_iteration_max, self.cg_residual_max])
        if self.has_arm:
            launch(kernels.contact_release, nv, [self.contact_n, self.contact_rn, self.released, self.contact_jn])
        if self.collision is not None:
            # closes over the arrays, not ``self``: a recorded step that refers to its solver makes a reference
            # cycle, and a replaced solver (adaptive remeshing rebuilds one a frame) would keep its device memory
            # until Python's cyclic collector came round, ~20 solvers' worth at once
            x_start, x = self.x_start, self.x
            cmds.append(lambda: wp.copy(x_start, x))
        launch(kernels.integrate, nv, [self.dv, self.free, dt, self.x, self.v])
        if self.collision is not None:
            self.collision.record(launch, cmds, dt)
        if self.has_arm:
            launch(kernels.contact_recovered, nv, [self.contact_recover, self.v])
            launch(kernels.advance_clock, 1, [self.clock, dt])
            launch(kernels.collide_arm, nv, [self.arms, self.vertex_cloth, self.free, self.clock,
                                             float(P.contact_thickness), float(P.friction), self.x, self.v])
            for _ in range(P.contact_iterations):
                launch(kernels.collide_arm_edges, self.edge.shape[0],
                       [self.arms, self.edge, self.vertex_cloth, self.free, self.clock, float(P.contact_thickness),
                        float(P.friction), self.x, self.v, self.contact_dx, self.contact_dv, self.contact_count])
                launch(kernels.apply_corrections, nv, [self.contact_dx, self.contact_dv, self.contact_count,
                                                       self.x, self.v])

    # ---------------------------------------------------------------- stepping and state
    def step(self, n: int = 1) -> None:
        """Advance every cloth by ``n`` time steps."""
        before, iterations, after = self._program
        if wp.get_device(self.device).is_cuda:
            if self._graph is None:
                with wp.ScopedCapture(device=self.device) as capture:
                    for cmd in self._all_launches():
                        cmd()
                self._graph = capture.graph
            for _ in range(n):
                wp.capture_launch(self._graph)
        else:
            # On the CPU the device memory is the host's: once no cloth's CG runs, the remaining
            # (all masked) iterations are skipped, the same result without their launch overhead.
            running = self.cg_active.numpy()
            for _ in range(n):
                for cmd in before:
                    cmd()
                for it in iterations:
                    if not running.any():
                        break
                    for cmd in it:
                        cmd()
                for cmd in after:
                    cmd()
        self._steps += n

    def _all_launches(self) -> list:
        """A step's launches in order: before the CG, every CG iteration, after it."""
        before, iterations, after = self._program
        return before + [c for it in iterations for c in it] + after

    def step_uncaptured(self, n: int = 1, host_times: dict[str, list[float]] | None = None) -> None:
        """``step`` with every launch issued from the host, no CUDA graph and no early exit: the same
        result, slower; for timing each kernel (``benchmarks/sim_profile.py``). With ``host_times`` each
        launch's wall time is appended under its kernel's name (a kernel's own time on the CPU, where
        launches run to completion; only the launch's cost on a GPU)."""
        launches = self._all_launches()
        for _ in range(n):
            for cmd in launches:
                if host_times is None:
                    cmd()
                    continue
                start = time.perf_counter()
                cmd()
                host_times.setdefault(_launch_name(cmd), []).append(time.perf_counter() - start)
        self._steps += n

    def cg_stats(self) -> list[CGStats]:
        """Per cloth: the CG iterations and final relative residuals of every step so far."""
        sums, maxes = self.cg_iteration_sum.numpy(), self.cg_iteration_max.numpy()
        res = self.cg_residual_max.numpy()
        return [CGStats(self._steps, float(sums[c]), int(maxes[c]), float(res[c])) for c in range(self.num_cloths)]

    def collision_dropped(self) -> list[int] | None:
        """Per cloth: the self-collision pairs dropped over every step so far (the farthest pairs of a vertex or
        edge with more than ``collision_slots``; left unresolved); None when self-collision is off."""
        if self.collision is None:
            return None
        return [int(n) for n in self.collision.dropped_pairs()]

    def set_wind(self, winds: np.ndarray) -> None:
        """Per-cloth wind velocities, (num_cloths, 3) m/s."""
        winds = np.asarray(winds, dtype=np.float32).reshape(self.num_cloths, 3)
        self.wind.assign(winds)

    def _split(self, a: wp.array) -> list[np.ndarray]:
        # .numpy() of a CPU array is a view of the live buffer: copy before the next step changes it
        a = a.numpy().copy()
        o = self.vertex_offsets
        return [a[o[c]:o[c + 1]] for c in range(self.num_cloths)]

    def positions(self) -> list[np.ndarray]:
        """Current positions, one (V, 3) float32 array per cloth."""
        return self._split(self.x)

    def velocities(self) -> list[np.ndarray]:
        return self._split(self.v)
