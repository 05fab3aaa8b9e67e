"""What the solver is given for one cloth: its mesh, placement, material tables and loads.

Plain data (numpy only), kept apart from the Warp solver (``sim.solver``) so
that the motions that build it (``sim.motions``) and the config checks that
list them import no Warp.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sim.mesh import ClothMesh


@dataclass(frozen=True)
class ArmSpec:
    """Two capsules: the upper arm (shoulder -> elbow) stays put; the forearm (elbow -> elbow + forearm)
    turns about ``axis`` through the elbow at ``omega`` rad/s, starting at simulated time ``t0``
    (seconds since the solver started), until it has turned ``max_angle`` radians."""

    shoulder: tuple[float, float, float]
    elbow: tuple[float, float, float]
    forearm: tuple[float, float, float]
    axis: tuple[float, float, float]
    radius: float
    omega: float
    max_angle: float
    t0: float


@dataclass
class ClothSpec:
    """One cloth of a batch: mesh, initial placement, material tables (already scaled), loads."""

    mesh: ClothMesh
    positions: np.ndarray                 # (V, 3) initial world positions, metres
    stretching: np.ndarray                # (6, 4) Wang stretching table, N/m (scaled by p)
    bending: np.ndarray                   # (3, 5) Wang bending table, N*m (scaled by k)
    density: float                        # kg/m^2
    pinned: np.ndarray | None = None      # indices of vertices held fixed
    wind: tuple[float, float, float] = (0.0, 0.0, 0.0)   # m/s
    velocities: np.ndarray | None = None  # (V, 3) initial velocities, default zero
    arm: ArmSpec | None = None            # a kinematic arm the cloth collides with
