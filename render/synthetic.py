"""A synthetic waving sheet in the SimClip format: for tests and benchmarks that must not depend on sim.

The sheet hangs in the x-z plane from its top edge (z up, like the simulator's
world) and waves along y with a travelling sine whose amplitude grows away
from the pinned edge. ``remesh_every`` > 0 changes the grid resolution every
that many frames, imitating adaptive remeshing (the renderer must rebuild).
"""

from __future__ import annotations

import numpy as np

from sim.clip import SimClip


def grid_sheet(n: int, size_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A flat n x n vertex sheet: rest positions (V, 3) in the x-z plane, faces (F, 3), uv (V, 2) in metres."""
    s = np.linspace(0.0, size_m, n)
    u, v = np.meshgrid(s, s, indexing="xy")
    uv = np.stack([u.ravel(), v.ravel()], -1).astype(np.float32)
    rest = np.stack([u.ravel() - size_m / 2, np.zeros(n * n), 1.0 - v.ravel()], -1).astype(np.float32)
    i, j = np.meshgrid(np.arange(n - 1), np.arange(n - 1), indexing="ij")
    a = (i * n + j).ravel()
    faces = np.concatenate([np.stack([a, a + 1, a + n + 1], -1), np.stack([a, a + n + 1, a + n], -1)])
    return rest, faces.astype(np.int32), uv


def wave(rest: np.ndarray, t: float, size_m: float, amplitude: float = 0.06) -> np.ndarray:
    hang = (1.0 - rest[:, 2]) / size_m  # 0 at the pinned top edge, 1 at the bottom
    phase = 2 * np.pi * (rest[:, 0] / size_m - 0.15 * t)
    positions = rest.copy()
    positions[:, 1] = amplitude * hang * np.sin(phase)
    positions[:, 2] += 0.3 * amplitude * hang * np.cos(phase)
    return positions


def waving_sheet(frames: int = 8, n: int = 16, size_m: float = 0.5, index: int = 0, setting: str = "wind-uniform1",
                 remesh_every: int = 0) -> SimClip:
    """A clip of a sheet waving for ``frames`` frames, with a sim-like meta (class 0)."""
    meta = {"clip_id": f"c{index:05d}", "index": index, "setting": setting, "motion": "wind", "remeshing": "synthetic",
            "class_index": 0, "seed": 0, "fps": 25.0, "frames": frames, "status": "ok", "synthetic": True}
    if remesh_every <= 0:
        rest, faces, uv = grid_sheet(n, size_m)
        return SimClip.from_fixed(meta, np.stack([wave(rest, t, size_m) for t in range(frames)]), faces, uv)
    out = []
    for t in range(frames):
        level = n + (t // remesh_every) % 2 * (n // 2)  # alternate between two resolutions
        rest, faces, uv = grid_sheet(level, size_m)
        out.append((wave(rest, t, size_m), faces, uv))
    return SimClip.from_frames(meta, out)
