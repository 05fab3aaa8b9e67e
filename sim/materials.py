"""The Wang et al. 2011 data-driven cloth materials: tables on disk and a numpy reference model.

Tables live in ``assets/materials/<name>.json`` (schema ``clothgap.material/1``:
named fields with units). ``stretching_stiffness`` and ``bending_stiffness`` are
the reference evaluation of the model exactly as ArcSim uses it (see
``shared/reference/wang2011-model.md`` in the project workspace); the Warp kernels in
``sim.solver`` evaluate the same formulas and the tests compare the two.

Source: Wang, Ramamoorthi, O'Brien, Data-Driven Elastic Models for Cloth,
SIGGRAPH 2011, http://graphics.berkeley.edu/papers/Wang-DDE-2011-08/
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

MATERIALS_DIR = Path(__file__).resolve().parent.parent / "assets" / "materials"
SCHEMA = "clothgap.material/1"


@dataclass(frozen=True)
class Material:
    """One fabric: area density and the raw (unscaled, un-doubled) Wang tables."""

    name: str
    garment: str
    fibre: str
    density: float              # kg/m^2
    stretching: np.ndarray      # (6, 4) N/m: row 0 low strain, rows 1..5 high strain at 0..90 deg
    bending: np.ndarray         # (3, 5) N*m: edge direction 0/45/90 deg x curvature 0..40 1/m

    def scaled(self, p: float, k: float) -> "Material":
        """The paper's sub-space: every stretching entry times p, every bending entry times k."""
        return Material(f"{self.name}*(p={p:g},k={k:g})", self.garment, self.fibre, self.density,
                        self.stretching * p, self.bending * k)

    def reshaped(self, stretching_factors: np.ndarray, bending_factors: np.ndarray) -> "Material":
        """Each table entry times its (positive) factor, then each table rescaled so that its summary
        (``stretching_summary``, ``bending_summary``) is what it was: the same stiffness by the figures a class and
        a measured fabric are labelled with, another anisotropy and another curve over strain and curvature."""
        st = self.stretching * np.asarray(stretching_factors, np.float64)
        be = self.bending * np.asarray(bending_factors, np.float64)
        st *= stretching_summary(self.stretching) / stretching_summary(st)
        be *= bending_summary(self.bending) / bending_summary(be)
        return Material(f"{self.name}~reshaped", self.garment, self.fibre, self.density, st, be)


def stretching_summary(stretching: np.ndarray) -> float:
    """A stretching table in one figure, N/m: the mean of the low-strain row's direct entries k0 (warp), k2 (weft)
    and k3 (shear); the coupling k1 is left out (it can be negative)."""
    return float(np.asarray(stretching)[0, [0, 2, 3]].mean())


def bending_summary(bending: np.ndarray) -> float:
    """A bending table in one figure, N*m: the mean of all 15 entries (3 directions x 5 curvatures)."""
    return float(np.asarray(bending).mean())


def _entry_factors(spread: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Each entry exp(spread z), z standard normal, one draw an entry (stretching 6 x 4, then bending 3 x 5)."""
    return np.exp(spread * rng.standard_normal((6, 4))), np.exp(spread * rng.standard_normal((3, 5)))


def _smooth_factors(spread: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Factors with the structure the measured fabrics' tables differ from the basis's by: stretching, one factor a
    direction (warp, weft, shear columns) for every row and one more for the high-strain rows (how fast the cloth
    stiffens); bending, one factor a direction and a log-linear trend over the five curvatures. Eight draws, each
    exp(spread z) (the trend's end points)."""
    columns, high, directions, trend = (np.exp(spread * rng.standard_normal(n)) for n in (3, 1, 3, 1))
    st = np.ones((6, 4))
    st[:, [0, 2, 3]] = columns
    st[1:] *= high
    be = directions[:, None] * trend ** np.linspace(-1.0, 1.0, 5)[None, :]
    return st, be


# How a class clip's tables are reshaped under sim.table_spread (sim.config.SimConfig.table_shape names one).
TABLE_SHAPES = {"entries": _entry_factors, "smooth": _smooth_factors}


def table_factors(spread: float, rng: np.random.Generator, shape: str = "entries") -> tuple[np.ndarray, np.ndarray]:
    """Factors for ``Material.reshaped`` (stretching 6 x 4, bending 3 x 5), drawn as ``TABLE_SHAPES[shape]`` does.
    A coupling entry k1 gets the geometric mean of its row's k0 and k2 factors, so that k1 / sqrt(k0 k2), which
    keeps the stretching energy positive, is the table's own."""
    st, be = TABLE_SHAPES[shape](spread, rng)
    st[:, 1] = np.sqrt(st[:, 0] * st[:, 2])
    return st, be


def list_materials() -> list[str]:
    """Names of the fabrics in ``assets/materials``."""
    return sorted(p.stem for p in MATERIALS_DIR.glob("*.json"))


@lru_cache(maxsize=None)
def load_material(name: str) -> Material:
    """A fabric by name; an unknown name raises ``KeyError`` listing the known ones."""
    path = MATERIALS_DIR / f"{name}.json"
    if not path.is_file():
        raise KeyError(f"unknown material {name!r}; known materials: {', '.join(list_materials())}")
    doc = json.loads(path.read_text())
    if doc.get("schema") != SCHEMA:
        raise ValueError(f"{path}: expected schema {SCHEMA!r}, got {doc.get('schema')!r}")
    st = doc["stretching"]
    stretching = np.array([st["low_strain"], *st["high_strain"]], dtype=np.float64)
    bending = np.array(doc["bending"]["ke"], dtype=np.float64)
    if stretching.shape != (6, 4) or bending.shape != (3, 5):
        raise ValueError(f"{path}: stretching must be 6x4 and bending 3x5, got "
                         f"{stretching.shape} and {bending.shape}")
    return Material(doc["name"], doc["garment"], doc["fibre"], float(doc["density"]["value"]),
                    stretching, bending)


# ---------------------------------------------------------------- reference model (numpy)

def green_strain(F: np.ndarray) -> np.ndarray:
    """G = (F^T F - I) / 2 for a 3x2 deformation gradient."""
    F = np.asarray(F, dtype=np.float64)
    return 0.5 * (F.T @ F - np.eye(2))


def stretching_stiffness(stretching: np.ndarray, G: np.ndarray) -> np.ndarray:
    """k = (k0, k1, k2, k3) in N/m at Green strain ``G`` (2x2), already doubled and clamped >= 0."""
    st = np.asarray(stretching, dtype=np.float64)
    C = 2.0 * np.asarray(G, dtype=np.float64) + np.eye(2)
    c00, c01, c11 = C[0, 0], C[0, 1], C[1, 1]
    lmax = 0.5 * (c00 + c11) + math.sqrt(0.25 * (c00 - c11) ** 2 + c01 * c01)
    if c01 == 0.0:
        vec = (1.0, 0.0) if c00 >= c11 else (0.0, 1.0)
    else:
        vec = (lmax - c11, c01)       # normalisation does not change the angle
    theta = abs(math.atan2(vec[1], vec[0]))
    x = min(max(theta / (math.pi / 8.0), 0.0), 4.0 - 1e-6)
    ai = int(math.floor(x))
    ta = x - ai
    s = min(max(6.0 * (math.sqrt(max(lmax, 0.0)) - 1.0), 0.0), 1.0 - 1e-6)
    high = (1.0 - ta) * st[1 + ai] + ta * st[2 + ai]
    k = (1.0 - s) * st[0] + s * high
    return 2.0 * np.maximum(k, 0.0)


def stretching_energy(stretching: np.ndarray, F: np.ndarray, area: float) -> float:
    """W = A (k0 G00^2 + 2 k1 G00 G11 + k2 G11^2 + k3 G01^2) / 2, k at the current strain."""
    G = green_strain(F)
    k = stretching_stiffness(stretching, G)
    return 0.5 * area * (k[0] * G[0, 0] ** 2 + 2 * k[1] * G[0, 0] * G[1, 1] + k[2] * G[1, 1] ** 2
                         + k[3] * G[0, 1] ** 2)


def bending_stiffness(bending: np.ndarray, curvature: float, edge_angle: float) -> float:
    """ke in N*m at ``curvature`` (1/m, theta l / (A0 + A1)) for an edge at ``edge_angle`` (rad) in (u, v)."""
    b = np.asarray(bending, dtype=np.float64)
    v = min(max(0.1 * curvature, 0.0), 4.0)
    vi = min(int(math.floor(v)), 3)
    tv = v - vi
    y = abs(edge_angle) * 4.0 / math.pi
    if y > 4.0:
        y = 8.0 - y
    if y > 2.0:
        y = 4.0 - y
    bi = min(int(math.floor(y)), 1)
    tb = y - bi
    ke = ((1 - tb) * (1 - tv) * b[bi, vi] + (1 - tb) * tv * b[bi, vi + 1]
          + tb * (1 - tv) * b[bi + 1, vi] + tb * tv * b[bi + 1, vi + 1])
    return max(ke, 0.0)


def bending_energy(bending: np.ndarray, theta: float, theta0: float, edge_length: float,
                   area0: float, area1: float, edge_angle: float) -> float:
    """E = ke l^2 / (2 (A0 + A1)) (theta - theta0)^2 / 4 for one hinge."""
    curvature = abs(theta) * edge_length / (area0 + area1)
    ke = bending_stiffness(bending, curvature, edge_angle)
    return ke * edge_length ** 2 / (2.0 * (area0 + area1)) * (theta - theta0) ** 2 / 4.0
