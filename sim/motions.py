"""The paper's motion sub-space (Section 4.3): what drives each simulated clip.

``wind``: the cloth hangs from its pinned top edge under gravity; after a short
settling period a constant-velocity wind, mostly horizontal and into the cloth,
switches on and the recorded frames start. Speed and direction are drawn per
clip from the clip's ``motion`` random stream.

A motion builds a ``ClipScene``: the cloth at rest (``ClothSpec`` without wind)
plus what changes when recording starts, and the parameters written to the
clip's ``meta.json``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from sim.materials import Material
from sim.mesh import ClothMesh
from sim.solver import ClothSpec

MOTIONS = ("wind",)

# Wind speed range, m/s. The basis fabric weighs 0.28 kg/m^2 (2.8 Pa under gravity);
# 1 to 2.5 m/s gives 0.6 to 3.8 Pa of dynamic pressure: from a sway to a billow.
WIND_SPEED_MPS = (1.0, 2.5)
WIND_AZIMUTH_DEG = 35.0        # max deviation from the cloth's normal, in the horizontal plane
WIND_ELEVATION_DEG = 10.0      # max deviation from horizontal


@dataclass
class ClipScene:
    spec: ClothSpec                    # the cloth at rest, no wind
    wind: np.ndarray                   # (3,) m/s, switched on when recording starts
    motion_params: dict = field(default_factory=dict)


def hanging_positions(mesh: ClothMesh, size_m: float) -> tuple[np.ndarray, np.ndarray]:
    """A cloth hanging flat in the x-z plane (u along x, v up), its top edge at z = size_m, centred on x = 0.
    Returns the positions and the pinned top-edge vertex indices."""
    uv = mesh.uv
    pos = np.stack([uv[:, 0] - 0.5 * size_m, np.zeros(len(uv)), uv[:, 1]], axis=1)
    top = np.flatnonzero(np.isclose(uv[:, 1], uv[:, 1].max()))
    return pos, top


def wind_scene(mesh: ClothMesh, size_m: float, material: Material, rng: np.random.Generator) -> ClipScene:
    """A hanging cloth and a constant wind drawn from ``rng`` (the clip's motion stream)."""
    speed = rng.uniform(*WIND_SPEED_MPS)
    azimuth = math.radians(rng.uniform(-WIND_AZIMUTH_DEG, WIND_AZIMUTH_DEG))
    elevation = math.radians(rng.uniform(-WIND_ELEVATION_DEG, WIND_ELEVATION_DEG))
    wind = speed * np.array([math.sin(azimuth) * math.cos(elevation), math.cos(azimuth) * math.cos(elevation),
                             math.sin(elevation)])
    pos, top = hanging_positions(mesh, size_m)
    spec = ClothSpec(mesh, pos, material.stretching, material.bending, material.density, pinned=top)
    params = {"wind_speed_mps": speed, "wind_azimuth_deg": math.degrees(azimuth),
              "wind_elevation_deg": math.degrees(elevation), "wind_velocity_mps": wind.tolist(),
              "pinned": "top edge"}
    return ClipScene(spec, wind, params)
