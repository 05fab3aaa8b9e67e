"""A fixed n x n lattice of cloth points, frame by frame: a mesh-independent summary of a clip's shape.

Each lattice point is the vertex nearest to it in uv space (inset by half a
cell), so uniform and adaptive meshes give comparable points. The learnability
probe (``eval.learnability``) reads it as features and training can use it as
a privileged auxiliary target (``learn.geometry``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from sim.clip import SimClip

LATTICE = 8                    # points per side


def lattice_vertices(uv: np.ndarray, n: int = LATTICE) -> np.ndarray:
    """Index of the vertex nearest to each point of an n x n lattice in uv space (inset by half a cell)."""
    grid = (np.arange(n) + 0.5) / n
    lo, hi = uv.min(axis=0), uv.max(axis=0)
    pts = lo + np.stack(np.meshgrid(grid, grid, indexing="ij"), -1).reshape(-1, 2) * (hi - lo)
    # Squared distances axis by axis in two buffers: the same sums as ((uv - pts) ** 2).sum(-1), bit for bit,
    # without its (points, vertices, 2) temporaries (an adaptive clip needs an index every frame: its lattice
    # takes 12 ms instead of 82 on the 2-core CPU, benchmarks/train_inputs.py).
    d = np.subtract.outer(pts[:, 0], uv[:, 0])
    d *= d
    e = np.subtract.outer(pts[:, 1], uv[:, 1])
    e *= e
    d += e
    return np.argmin(d, axis=1)


def clip_lattice(folder: Path, n: int = LATTICE) -> np.ndarray:
    """(T, n*n, 3) lattice positions of a simulated clip, frame by frame."""
    clip = SimClip.load(folder)
    out = []
    index = lattice_vertices(clip.uv, n) if clip.fixed_topology else None
    for pos, _faces, uv in clip.frames():
        out.append(pos[index if index is not None else lattice_vertices(uv, n)])
    return np.stack(out).astype(np.float32)
