"""The cantilever bending test (ASTM D1388, option A; Peirce 1930) run on the project's solver.

A strip lies on a horizontal platform and is pushed over its edge; the overhang
of length l bends down under its own weight. ASTM D1388 reads the overhang O at
which the chord from the platform edge to the strip's tip lies 41.5 deg below
the horizontal, and reports the bending length c = O / 2 and the flexural
rigidity G = w g c^3 (w: mass per area; G per unit width, N m). 41.5 deg is the
chord angle of the heavy elastica (an inextensible strip clamped horizontally,
loaded by its own weight) at l = 2c, where c^3 = B / (w g).

Here the strip is the project's mesh (right-triangle grid of edge length h, two
vertex columns pinned: the platform holds the strip flat up to its edge), with
the fabric's own tables and density, settled quasi-statically (long time steps,
heavy damping, CG converged tightly) at one or more overhangs in one batch. For
each overhang the tip's chord angle gives c from the heavy elastica, solved here
by shooting (``elastica_chord_angle``; exact for any angle, where Peirce's
formula c = l (cos(t/2) / (8 tan t))^(1/3), also printed, is 2-4 % high at
40-57 deg). When the overhangs bracket 41.5 deg, the ASTM reading itself
(O interpolated, c = O / 2) is given too.

The model's own value. A hinge with dihedral angle t stores
ke l^2 t^2 / (8 (A0 + A1)) (``sim.materials.bending_energy``). Bent about an
axis along a grid direction, only the edges along the axis carry an angle,
kappa h each, with A0 + A1 = h^2, one per h^2 of cloth: the energy per area is
ke kappa^2 / 8, so B = ke / 4, ke from the table row of edges along the axis
(90 deg for a strip whose length runs along u, 0 deg along v). The table is
nonlinear in curvature (columns 0..40 1/m): ``model_value`` gives B at zero
curvature and its range over the table, and a fabric whose ke changes with
curvature has no single bending length to match.

What the solver gives (constant table, c = 0.96 cm, strip along u): the bending
length converges at first order in the edge length, 0.74 / 0.84 / 0.88 / 0.90 /
0.92 of (ke / 4 / (w g))^(1/3) at h = 8 / 4 / 2 / 1 / 0.5 mm, towards about
0.93, not 1: a discrete chain with the same lumped masses and springs B / h
reaches 0.99 at 0.25 mm. The exact cylinder does store ke kappa^2 / 8 per area
on these meshes, but the settled strip is not one: its diagonal and
along-the-strip hinges take angles too (up to a third of the along-axis
hinges'), a softer mode of the alternating right-triangle grid, so the discrete
shell's effective rigidity there is about 0.8 ke / 4 at any resolution. The
force is the exact gradient of the energy and the settled state is an
equilibrium (net force under 3 % of one vertex's weight); the gap is the
discretisation's, and the command shows it beside the model's value.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from sim.analysis import _grid
from sim.materials import Material, load_material
from sim.mesh import ClothMesh, hinges_of, vertices_per_side
from sim.solver import BatchSolver, ClothSpec, SolverParams

GRAVITY = 9.81
ASTM_ANGLE = math.radians(41.5)
WIDTH_EDGES = 2                 # the test is one-dimensional: the width only scales the strip's weight and stiffness


def material_of(fabric: str) -> tuple[Material, str]:
    """A measured fabric by name, or a class index 0..53 (the basis fabric scaled by the class's p, k)."""
    if fabric.isdigit():
        from sim import classes
        from sim.config import SimConfig

        p, k = classes.class_values(int(fabric))
        basis = SimConfig().basis
        return load_material(basis).scaled(p, k), f"class {int(fabric)} ({basis} x p={p:g}, k={k:g})"
    return load_material(fabric), fabric


def level_edge(level: int) -> float:
    """Edge length (m) of the stage's uniform mesh at ``level`` (default cloth size and grid)."""
    from sim.config import SimConfig

    cfg = SimConfig()
    return cfg.cloth_size_m / (vertices_per_side(cfg.grid_vertices, level) - 1)


@dataclass(frozen=True)
class ModelValue:
    """The model's flexural rigidity per unit width (N m) and bending length (m) along one axis."""

    rigidity: float             # B = ke / 4 at zero curvature
    bending_length: float       # (B / (w g))^(1/3)
    rigidity_range: tuple[float, float]   # B over the table's curvatures 0..40 1/m


def model_value(material: Material, axis: str = "u") -> ModelValue:
    """B = ke / 4 of the row of hinges along the bending axis (module docstring)."""
    row = material.bending[2 if axis == "u" else 0]
    b = float(row[0]) / 4.0
    return ModelValue(b, (b / (material.density * GRAVITY)) ** (1.0 / 3.0),
                      (float(row.min()) / 4.0, float(row.max()) / 4.0))


# ---------------------------------------------------------------- the heavy elastica (c = 1)

def _shoot(lam: np.ndarray, k0: np.ndarray, steps: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Integrate phi'' = -(lam - s) cos(phi), phi(0) = 0, phi'(0) = k0 over s in [0, lam] (RK4,
    vectorised over strips): returns phi'(lam) and the tip (x, z)."""
    h = lam / steps
    phi, k = np.zeros_like(lam), k0.copy()
    x, z = np.zeros_like(lam), np.zeros_like(lam)
    for i in range(steps):
        s = i * h

        def f(si, ph, kk):
            return kk, -(lam - si) * np.cos(ph)
        a1, b1 = f(s, phi, k)
        a2, b2 = f(s + h / 2, phi + h / 2 * a1, k + h / 2 * b1)
        a3, b3 = f(s + h / 2, phi + h / 2 * a2, k + h / 2 * b2)
        a4, b4 = f(s + h, phi + h * a3, k + h * b3)
        mid = phi + h / 2 * a1                       # midpoint angle for the position (second order)
        x += h * np.cos(mid)
        z += h * np.sin(mid)
        phi = phi + h / 6 * (a1 + 2 * a2 + 2 * a3 + a4)
        k = k + h / 6 * (b1 + 2 * b2 + 2 * b3 + b4)
    return k, x, z


def elastica_chord_angle(lam: np.ndarray | float, steps: int = 400) -> np.ndarray:
    """Chord angle below the horizontal (rad) of a heavy elastica of length lam = l / c, clamped flat.

    Bending moment M(s) = w int_s^l (x(t) - x(s)) dt gives B phi'' = -w (l - s) cos(phi) with phi(0) = 0
    and a free tip, phi'(l) = 0; with c^3 = B / (w g) = 1 the root curvature phi'(0) in [0, lam^2]
    is found by bisection."""
    lam = np.atleast_1d(np.asarray(lam, dtype=np.float64))
    lo, hi = np.zeros_like(lam), lam ** 2
    for _ in range(50):
        mid = 0.5 * (lo + hi)
        k_tip = _shoot(lam, mid, steps)[0]
        hi = np.where(k_tip > 0, mid, hi)
        lo = np.where(k_tip > 0, lo, mid)
    _, x, z = _shoot(lam, 0.5 * (lo + hi), steps)
    return np.arctan2(z, x)


_TABLE: tuple[np.ndarray, np.ndarray] | None = None


def bending_length(overhang: float, angle: float) -> float:
    """c from an overhang l (m) and its chord angle (rad), inverting the heavy elastica (NaN beyond
    80 deg, where the chord angle no longer tells c)."""
    global _TABLE
    if _TABLE is None:
        # up to l = 4.5 c (80 deg): beyond, the tip hangs nearly vertical and phi'(l) is no longer
        # monotone in the root curvature, so bisection could pick another branch
        lam = np.geomspace(0.05, 4.5, 300)
        _TABLE = (lam, elastica_chord_angle(lam))
    lam, theta = _TABLE
    if not 0.0 < angle < theta[-1]:
        return float("nan")
    if angle < theta[0]:                              # small deflection: tan(t) = lam^3 / 8
        return overhang / (8.0 * math.tan(angle)) ** (1.0 / 3.0)
    return overhang / float(np.interp(angle, theta, lam))


def peirce_length(overhang: float, angle: float) -> float:
    """Peirce's formula c = l (cos(t/2) / (8 tan t))^(1/3), what ASTM D1388 tabulates."""
    return overhang * (math.cos(angle / 2.0) / (8.0 * math.tan(angle))) ** (1.0 / 3.0)


# ---------------------------------------------------------------- the simulated test

def strip_spec(material: Material, edge: float, overhang_edges: int, axis: str = "u") -> ClothSpec:
    """A strip of ``overhang_edges`` free edges beyond the platform edge (column 1; columns 0, 1 pinned),
    ``WIDTH_EDGES`` wide, its length along material axis ``axis``, lying flat at z = 0."""
    nu, nv = overhang_edges + 2, WIDTH_EDGES + 1
    uv, faces = _grid(nu, nv, (nu - 1) * edge, WIDTH_EDGES * edge)
    pos = np.stack([uv[:, 0], uv[:, 1], np.zeros(len(uv))], 1)
    pinned = np.flatnonzero(uv[:, 0] <= edge * 1.000001)
    if axis == "v":       # the same strip in space, its length along v: swap (u, v), keep faces CCW
        uv, faces = uv[:, ::-1].copy(), faces[:, ::-1].copy()
    return ClothSpec(ClothMesh(uv, faces, hinges_of(faces)), pos, material.stretching, material.bending,
                     material.density, pinned=pinned)


@dataclass(frozen=True)
class Reading:
    overhang: float             # m
    angle: float                # chord angle below horizontal, rad
    bending_length: float       # m, heavy elastica
    peirce_length: float        # m, Peirce's formula
    rigidity: float             # N m, w g c^3 from the elastica c
    settled: float              # m, largest vertex move over the last check interval
    cg_residual_max: float      # the solver's largest final relative residual of a step


@dataclass(frozen=True)
class Setup:
    dt: float = 0.02            # s: quasi-static, each step close to a Newton step on the energy
    damping: float = 10.0       # 1/s
    cg_iterations: int = 1000
    cg_tolerance: float = 1e-5
    check_s: float = 0.5        # settle in intervals of this long ...
    max_s: float = 8.0          # ... until nothing moves more than ``still`` in one, or this long
    still: float = 1e-6         # m


def measure(material: Material, edge: float, overhang_edges: list[int], axis: str = "u",
            device: str = "cpu", setup: Setup = Setup()) -> list[Reading]:
    """The strips of ``overhang_edges`` (each a whole number of edges) settled in one batch."""
    specs = [strip_spec(material, edge, n, axis) for n in overhang_edges]
    params = SolverParams(dt=setup.dt, cg_iterations=setup.cg_iterations, cg_tolerance=setup.cg_tolerance,
                          damping=setup.damping, air_density=0.0, air_drag=0.0)
    solver = BatchSolver(specs, params, device)
    steps = max(1, int(round(setup.check_s / setup.dt)))
    prev = solver.positions()
    moved = np.full(len(specs), np.inf)
    t = 0.0
    while t < setup.max_s and moved.max() > setup.still:
        solver.step(steps)
        t += steps * setup.dt
        cur = solver.positions()
        moved = np.array([np.abs(a - b).max() for a, b in zip(cur, prev)])
        prev = cur
    residual = [s.max_residual for s in solver.cg_stats()]   # over the whole run: the worst step
    out = []
    for spec, n, x, still, res in zip(specs, overhang_edges, prev, moved, residual):
        along = spec.positions[:, 0]
        tip = x[np.isclose(along, along.max())].astype(np.float64).mean(axis=0)
        root = x[np.isclose(along, edge)].astype(np.float64).mean(axis=0)
        angle = math.atan2(root[2] - tip[2], tip[0] - root[0])
        length = n * edge
        c = bending_length(length, angle)
        out.append(Reading(length, angle, c, peirce_length(length, angle) if angle > 0 else float("nan"),
                           material.density * GRAVITY * c ** 3, float(still), float(res)))
    return out


def default_overhangs(model: ModelValue, edge: float) -> list[int]:
    """Whole numbers of edges around the ASTM overhang 2c, for c over the table's range of rigidities
    (a curvature-dependent table bends with a ke between its extremes), at most 9 of them."""
    c_lo, c_hi = (model.bending_length * (b / model.rigidity) ** (1.0 / 3.0) for b in model.rigidity_range)
    lo = max(1, int(math.floor(0.8 * 2.0 * min(c_lo, c_hi) / edge)))
    hi = max(lo + 1, int(math.ceil(1.25 * 2.0 * max(c_hi, c_lo, model.bending_length) / edge)))
    return list(range(lo, hi + 1)) if hi - lo <= 8 else sorted({int(round(v)) for v in np.linspace(lo, hi, 9)})


def astm_reading(readings: list[Reading]) -> float | None:
    """The ASTM overhang O where the chord angle crosses 41.5 deg (linear in angle between the two
    bracketing overhangs), or None when the overhangs do not bracket it."""
    pts = sorted((r.angle, r.overhang) for r in readings if math.isfinite(r.angle))
    for (a0, o0), (a1, o1) in zip(pts, pts[1:]):
        if a0 <= ASTM_ANGLE <= a1 and a1 > a0:
            return o0 + (ASTM_ANGLE - a0) / (a1 - a0) * (o1 - o0)
    return None


def run_test(fabric: str, level: int = 1, overhangs_cm: tuple[float, ...] = (), axis: str = "u",
             device: str = "cpu", setup: Setup = Setup()) -> str:
    """The ``clothgap sim cantilever`` report: every overhang's reading beside the model's own value."""
    from clothgap.errors import ConfigError

    try:
        material, name = material_of(fabric)
    except (KeyError, ValueError) as e:
        raise ConfigError(f"fabric {fabric!r}: {e.args[0]}") from None
    if axis not in ("u", "v"):
        raise ConfigError(f"axis {axis!r}: must be u or v")
    edge = level_edge(level)
    model = model_value(material, axis)
    if overhangs_cm:
        edges = sorted({max(1, int(round(o / 100.0 / edge))) for o in overhangs_cm})
    else:
        edges = default_overhangs(model, edge)
    readings = measure(material, edge, edges, axis, device, setup)
    w = material.density * GRAVITY
    lines = [f"cantilever test (ASTM D1388 / Peirce): {name}, strip length along {axis}, "
             f"level {level} mesh (edge {edge * 1000:.1f} mm)",
             f"model: flexural rigidity B = ke/4 = {model.rigidity:.3e} N m at zero curvature "
             f"({model.rigidity_range[0]:.3e}..{model.rigidity_range[1]:.3e} over the table), "
             f"bending length (B / w g)^(1/3) = {model.bending_length * 100:.3f} cm "
             f"({(model.rigidity_range[0] / w) ** (1 / 3) * 100:.3f}..{(model.rigidity_range[1] / w) ** (1 / 3) * 100:.3f}"
             f" over the table), w g = {w:.3f} N/m^2",
             f"{'overhang cm':>11} {'chord deg':>9} {'c cm':>8} {'c Peirce':>8} {'G N m':>10} "
             f"{'c/model':>7} {'settled um':>10}"]
    for r in readings:
        lines.append(f"{r.overhang * 100:11.2f} {math.degrees(r.angle):9.2f} {r.bending_length * 100:8.3f} "
                     f"{r.peirce_length * 100:8.3f} {r.rigidity:10.3e} "
                     f"{r.bending_length / model.bending_length:7.3f} {r.settled * 1e6:10.3f}")
    o = astm_reading(readings)
    if o is None:
        lines.append("ASTM reading: the overhangs do not bracket a 41.5 deg chord (give more --overhang)")
    else:
        c = o / 2.0
        lines.append(f"ASTM reading: overhang {o * 100:.2f} cm at 41.5 deg -> bending length {c * 100:.3f} cm, "
                     f"flexural rigidity {w * c ** 3:.3e} N m ({c / model.bending_length:.3f} x the model's "
                     f"bending length, {c ** 3 / model.bending_length ** 3:.3f} x its rigidity)")
    lines.append("c: heavy-elastica inversion of each overhang's chord angle; c Peirce: Peirce's formula "
                 f"(the ASTM tables); largest CG residual {max(r.cg_residual_max for r in readings):.1e}")
    return "\n".join(lines)
