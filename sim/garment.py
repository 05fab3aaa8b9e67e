"""A skirt for material cloning (the paper's Fig. 9): an A-line frustum of cloth on a moving waist.

Pattern. An A-line skirt is one cone frustum, and a cone unrolls flat into an
annular sector: a waist of radius ``waist_radius_m``, a slant ``length_m`` and a
flare half-angle ``alpha`` (from vertical) unroll into a sector of inner radius
``rho_w = waist_radius / sin(alpha)``, outer radius ``rho_w + length`` and angle
``2 pi sin(alpha)`` (for the meshed, polygonal cone, sin(alpha) is corrected so
that every triangle of the sewn skirt is congruent to its pattern triangle).
That sector is the cloth's material (u, v) space (metres, the fabric's grain
along u), so the skirt starts exactly unstretched; its two straight edges meet
in a side seam.

Seam. The solver keeps one (u, v) per vertex, and a closed tube has none that
suits both sides of the seam. The skirt's simulation mesh therefore shares the
seam vertices and carries its material coordinates per face corner
(``Skirt.face_uv``); ``SkirtSolver`` builds a ``BatchSolver`` with a seamless
stand-in (u, v) (the skirt seen from above, an annulus) and then writes each
face's rest shape, area, the lumped masses and each hinge's rest length, area
and grain direction from the per-corner coordinates, with the formulas of
``BatchSolver._build``. For rendering, the seam vertices are duplicated
(``Skirt.render_index``), so the texture's uv map is continuous everywhere and
meets itself at the seam as a sewn seam does.

Motion. The waist ring is pinned and moved kinematically every solver step
(position and velocity written into the solver before the step, so the implicit
step sees the waist's velocity): ``twirl`` turns the waist back and forth about
the vertical axis with a small hip sway, ``walk`` sways the hips sideways at the
step rate, bobs them up and down at twice that, and turns the pelvis a little.
The motion fades in over ``ramp_s`` so the skirt is not jerked. The hem's swing,
its lag behind the waist and the folds it throws show the cloth's stiffness.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import warp as wp

from sim.materials import Material
from sim.mesh import ClothMesh, edge_directions, edge_sides, hinges_of
from sim.solver import BatchSolver, ClothSpec, SolverParams

MOTIONS = ("twirl", "walk")


@dataclass(frozen=True)
class SkirtShape:
    waist_radius_m: float = 0.14        # a 88 cm waist
    length_m: float = 0.45              # waist to hem along the cloth
    flare_deg: float = 25.0             # half-angle of the cone (0 would be a tube, 90 a flat circle skirt)
    around: int = 56                    # vertices around each ring
    down: int = 16                      # rings of faces from waist to hem
    waist_height_m: float = 1.0         # z of the waist at rest

    def __post_init__(self) -> None:
        if not 5.0 <= self.flare_deg <= 85.0:
            raise ValueError(f"flare_deg must be in [5, 85] degrees, got {self.flare_deg}")
        if self.around < 8 or self.down < 2:
            raise ValueError(f"a skirt needs at least 8 vertices around and 2 rings down, got "
                             f"{self.around} and {self.down}")
        if not (self.waist_radius_m > 0 and self.length_m > 0):
            raise ValueError("waist_radius_m and length_m must be positive")


@dataclass(frozen=True)
class WaistMotion:
    kind: str = "twirl"                 # "twirl" or "walk"
    frequency_hz: float = 0.8           # twirl: turns per second back and forth; walk: strides per second
    twirl_deg: float = 70.0             # twirl: amplitude of the waist's turn
    sway_m: float = 0.03                # hips' sideways sway amplitude
    bob_m: float = 0.015                # walk: vertical bob amplitude (at twice the frequency)
    pelvis_deg: float = 8.0             # walk: pelvic rotation amplitude
    ramp_s: float = 0.3                 # the motion fades in over this long

    def __post_init__(self) -> None:
        if self.kind not in MOTIONS:
            raise ValueError(f"unknown waist motion {self.kind!r}; known: {', '.join(MOTIONS)}")

    def transform(self, t: float) -> tuple[float, np.ndarray]:
        """(angle about z in radians, translation (3,)) of the waist ``t`` seconds after the motion starts."""
        if t <= 0:
            return 0.0, np.zeros(3)
        x = min(t / self.ramp_s, 1.0) if self.ramp_s > 0 else 1.0
        env = x * x * (3.0 - 2.0 * x)                       # smoothstep fade-in
        w = 2.0 * math.pi * self.frequency_hz * t
        if self.kind == "twirl":
            angle = math.radians(self.twirl_deg) * math.sin(w)
            shift = np.array([self.sway_m * math.sin(w), 0.0, 0.0])
        else:
            angle = math.radians(self.pelvis_deg) * math.sin(w)
            shift = np.array([self.sway_m * math.sin(w), 0.0, self.bob_m * math.sin(2.0 * w)])
        return env * angle, env * shift

    def params(self) -> dict:
        return {"kind": self.kind, "frequency_hz": self.frequency_hz, "twirl_deg": self.twirl_deg,
                "sway_m": self.sway_m, "bob_m": self.bob_m, "pelvis_deg": self.pelvis_deg, "ramp_s": self.ramp_s}


@dataclass
class Skirt:
    """The simulation mesh (seam shared) and what the renderer needs (seam split)."""

    shape: SkirtShape
    mesh: ClothMesh                     # faces and hinges; uv is the seamless stand-in (top view)
    face_uv: np.ndarray                 # (F, 3, 2) material coordinates per face corner, metres
    positions: np.ndarray               # (V, 3) the sewn skirt at rest, waist at the top
    waist: np.ndarray                   # indices of the waist ring (pinned)
    hem: np.ndarray                     # indices of the hem ring
    render_index: np.ndarray            # (R,) simulation vertex of each render vertex
    render_faces: np.ndarray            # (F, 3) faces into the render vertices
    render_uv: np.ndarray               # (R, 2) material coordinates, continuous (the unrolled sector)
    rest_lengths: np.ndarray = field(repr=False, default=None)   # per edge of ``edges``
    edges: np.ndarray = field(repr=False, default=None)          # (E, 2) unique edges of the sim mesh

    @property
    def num_vertices(self) -> int:
        return len(self.positions)

    def to_render(self, positions: np.ndarray) -> np.ndarray:
        """Simulated positions (..., V, 3) -> render-mesh positions (..., R, 3)."""
        return positions[..., self.render_index, :]


def skirt(shape: SkirtShape = SkirtShape()) -> Skirt:
    """The skirt's meshes: ``shape.down + 1`` rings of ``shape.around`` vertices, ring 0 the waist."""
    n, m = shape.around, shape.down
    sin_a = math.sin(math.radians(shape.flare_deg))
    # The sewn skirt is a polyhedral frustum of regular n-gons: its isosceles-trapezoid cells are congruent
    # to the pattern's when a ring of pattern radius rho has radius c * rho (equal chords), so the skirt
    # starts exactly unstretched. c ~ sin(alpha) for large n.
    c = math.sin(math.pi * sin_a / n) / math.sin(math.pi / n)
    cos_c = math.sqrt(1.0 - c * c)
    rho_w = shape.waist_radius_m / c                   # apex -> waist along the unrolled cone
    s = np.linspace(0.0, shape.length_m, m + 1)       # distance down the cloth from the waist

    def material(ring: np.ndarray, col: np.ndarray) -> np.ndarray:
        """Unrolled-sector coordinates of (ring, unwrapped column); column n is the seam's other side."""
        rho = rho_w + s[ring]
        phi = 2.0 * math.pi * sin_a * col / n
        return np.stack([rho * np.cos(phi), rho * np.sin(phi)], axis=-1)

    ring, col = np.divmod(np.arange((m + 1) * n), n)
    theta = 2.0 * math.pi * col / n
    radius = shape.waist_radius_m + s[ring] * c
    positions = np.stack([radius * np.cos(theta), radius * np.sin(theta),
                          shape.waist_height_m - s[ring] * cos_c], axis=1)
    stand_in = np.stack([(shape.waist_radius_m + s[ring]) * np.cos(theta),
                         (shape.waist_radius_m + s[ring]) * np.sin(theta)], axis=1)

    # Faces, counter-clockwise in (ring, column) order, diagonals alternating per cell; corners as
    # (ring, unwrapped column) so the seam's faces reach column n.
    corners = []
    for i in range(m):
        for j in range(n):
            a, b, c, d = (i, j), (i, j + 1), (i + 1, j), (i + 1, j + 1)
            corners += [(a, c, d), (a, d, b)] if (i + j) % 2 == 0 else [(a, c, b), (c, d, b)]
    corners = np.array(corners)                        # (F, 3, 2): ring, unwrapped column
    faces = (corners[..., 0] * n + corners[..., 1] % n).astype(np.int32)
    face_uv = material(corners[..., 0], corners[..., 1])
    mesh = ClothMesh(stand_in, faces, hinges_of(faces))

    # Render mesh: columns 0..n (column n duplicates column 0 with the other side's uv).
    rr, rc = np.divmod(np.arange((m + 1) * (n + 1)), n + 1)
    render_index = (rr * n + rc % n).astype(np.int64)
    render_faces = (corners[..., 0] * (n + 1) + corners[..., 1]).astype(np.int32)
    render_uv = material(rr, rc)

    edges, rest = _rest_edges(faces, face_uv)
    return Skirt(shape, mesh, face_uv, positions, np.arange(n), np.arange(m * n, (m + 1) * n),
                 render_index, render_faces, render_uv, rest, edges)


def _rest_edges(faces: np.ndarray, face_uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unique edges and their rest lengths in material space (from the faces' own corners)."""
    lengths: dict[tuple[int, int], float] = {}
    for f, uv in zip(faces, face_uv):
        for e in range(3):
            a, b = int(f[e]), int(f[(e + 1) % 3])
            lengths[(min(a, b), max(a, b))] = float(np.linalg.norm(uv[(e + 1) % 3] - uv[e]))
    keys = sorted(lengths)
    return np.array(keys, dtype=np.int64).reshape(-1, 2), np.array([lengths[k] for k in keys])


def skirt_spec(garment: Skirt, material: Material) -> ClothSpec:
    """The skirt as one cloth of a batch: its material, waist pinned."""
    return ClothSpec(garment.mesh, garment.positions.copy(), material.stretching, material.bending,
                     material.density, pinned=garment.waist)


# ------------------------------------------------------------------ solver

@wp.kernel
def _drive(index: wp.array(dtype=int), rest: wp.array(dtype=wp.vec3), c: float, s: float, shift: wp.vec3,
           vel_c: float, vel_s: float, vel_shift: wp.vec3, x: wp.array(dtype=wp.vec3), v: wp.array(dtype=wp.vec3)):
    """Pinned vertex i: x = R(angle) rest + shift, v = dR/dt rest + dshift/dt (R about z)."""
    i = wp.tid()
    p = rest[i]
    k = index[i]
    x[k] = wp.vec3(c * p[0] - s * p[1], s * p[0] + c * p[1], p[2]) + shift
    v[k] = wp.vec3(vel_c * p[0] - vel_s * p[1], vel_s * p[0] + vel_c * p[1], 0.0) + vel_shift


class SkirtSolver:
    """Skirts of different materials, simulated together on one moving waist (paired: same motion)."""

    def __init__(self, garment: Skirt, materials: list[Material], params: SolverParams, device: str = "cpu"):
        if not materials:
            raise ValueError("simulate at least one material")
        self.garment = garment
        self.solver = BatchSolver([skirt_spec(garment, mat) for mat in materials], params, device)
        self._patch_rest_state(materials)
        nv = garment.num_vertices
        offsets = self.solver.vertex_offsets
        index = np.concatenate([offsets[c] + garment.waist for c in range(len(materials))])
        rest = np.tile(garment.positions[garment.waist], (len(materials), 1))
        dev = self.solver.device
        self._index = wp.array(index.astype(np.int32), dtype=int, device=dev)
        self._rest = wp.array(rest.astype(np.float32), dtype=wp.vec3, device=dev)
        self.time = 0.0
        assert offsets[-1] == nv * len(materials)

    def _patch_rest_state(self, materials: list[Material]) -> None:
        """Rest shape from the per-corner material coordinates (``BatchSolver._build``'s formulas)."""
        g, S = self.garment, self.solver
        uv, faces = g.face_uv, g.mesh.faces
        d1, d2 = uv[:, 1] - uv[:, 0], uv[:, 2] - uv[:, 0]
        dm = np.stack([np.stack([d1[:, 0], d2[:, 0]], 1), np.stack([d1[:, 1], d2[:, 1]], 1)], 1)
        area = 0.5 * (d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0])
        if np.any(area <= 0):
            raise ValueError("skirt faces must be counter-clockwise in material space")
        h = g.mesh.hinges
        # each hinge's two faces; its edge's own (u, v) comes from the corners of the first (a seam's two sides
        # have different material coordinates)
        side_a, side_b = edge_sides(faces, h[:, 0], h[:, 1])
        face_a, corner = side_a // 3, side_a % 3
        e_uv = uv[face_a, (corner + 1) % 3] - uv[face_a, corner]
        hlen = np.linalg.norm(e_uv, axis=1)
        harea = area[face_a] + area[side_b // 3]
        hdir = edge_directions(e_uv)
        nc = len(materials)
        masses = []
        for mat in materials:
            mass = np.zeros(g.num_vertices)
            np.add.at(mass, faces.ravel(), np.repeat(area * mat.density / 3.0, 3))
            masses.append(mass)
        f32 = np.float32
        S.dm_inv.assign(np.tile(np.linalg.inv(dm), (nc, 1, 1)).astype(f32))
        S.area.assign(np.tile(area, nc).astype(f32))
        S.mass.assign(np.concatenate(masses).astype(f32))
        S.hinge_length.assign(np.tile(hlen, nc).astype(f32))
        S.hinge_area.assign(np.tile(harea, nc).astype(f32))
        S.hinge_dir.assign(np.tile(hdir, nc).astype(f32))

    def _set_waist(self, motion: WaistMotion | None, t: float) -> None:
        if motion is None:
            angle, shift, dangle, dshift = 0.0, np.zeros(3), 0.0, np.zeros(3)
        else:
            eps = 1e-4
            angle, shift = motion.transform(t)
            a1, s1 = motion.transform(t + eps)
            a0, s0 = motion.transform(t - eps)
            dangle, dshift = (a1 - a0) / (2 * eps), (s1 - s0) / (2 * eps)
        c, s = math.cos(angle), math.sin(angle)
        wp.launch(_drive, dim=len(self._index), device=self.solver.device,
                  inputs=[self._index, self._rest, c, s, wp.vec3(*shift), -s * dangle, c * dangle,
                          wp.vec3(*dshift), self.solver.x, self.solver.v])

    def advance(self, steps: int, motion: WaistMotion | None = None, motion_start: float = 0.0) -> None:
        """``steps`` solver steps; the waist follows ``motion`` (started at ``motion_start`` seconds)."""
        dt = self.solver.params.dt
        for _ in range(steps):
            self._set_waist(motion, self.time - motion_start)
            self.solver.step(1)
            self.time += dt
        self._set_waist(motion, self.time - motion_start)     # positions read back show the waist at `time`

    def positions(self) -> list[np.ndarray]:
        return self.solver.positions()


@dataclass
class SkirtResult:
    positions: np.ndarray | None        # (T, V, 3) float32, simulation mesh
    reason: str | None                  # why it failed the health check, else None


def simulate_skirts(garment: Skirt, materials: list[Material], motion: WaistMotion, *, fps: float, frames: int,
                    substeps: int, settle_s: float, cg_iterations: int = 30,
                    device: str = "cpu") -> list[SkirtResult]:
    """Let the skirts settle on a still waist for ``settle_s``, then record ``frames`` frames of the motion.

    Every recorded frame passes the sim stage's health check (finite, not too fast, not over-stretched).
    """
    from sim.stage import health

    dt = 1.0 / (fps * substeps)
    sim = SkirtSolver(garment, materials, SolverParams(dt=dt, cg_iterations=cg_iterations), device)
    sim.advance(int(round(settle_s / dt)))
    start = sim.time
    prev = sim.positions()
    reasons: list[str | None] = [None] * len(materials)
    recorded = []
    for t in range(frames):
        sim.advance(substeps, motion, start)
        cur = sim.positions()
        for c, (x, xp) in enumerate(zip(cur, prev)):
            if reasons[c] is None:
                why = health(x, xp, 1.0 / fps, garment.edges, garment.rest_lengths)
                reasons[c] = None if why is None else f"frame {t}: {why}"
        recorded.append(cur)
        prev = cur
    return [SkirtResult(None, r) if r else SkirtResult(np.stack([f[c] for f in recorded]), None)
            for c, r in enumerate(reasons)]


def waist_path(garment: Skirt, motion: WaistMotion, fps: float, frames: int) -> np.ndarray:
    """(T, W, 3) where the waist ring should be at each recorded frame (frame t is (t + 1) / fps in)."""
    rest = garment.positions[garment.waist]
    out = []
    for t in range(frames):
        angle, shift = motion.transform((t + 1) / fps)
        c, s = math.cos(angle), math.sin(angle)
        out.append(np.stack([c * rest[:, 0] - s * rest[:, 1], s * rest[:, 0] + c * rest[:, 1], rest[:, 2]], 1) + shift)
    return np.stack(out)
