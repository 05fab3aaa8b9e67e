"""Flat square cloth meshes in material space, their uniform refinements, and hinge lists.

Material coordinates (u, v) are metres in the cloth's rest space. Faces are
counter-clockwise in (u, v). A uniform refinement splits every triangle into
four at its edge midpoints, so level L of a base grid with n vertices per side
has (n - 1) * 2^(L - 1) + 1 vertices per side and keeps every coarser edge.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class ClothMesh:
    uv: np.ndarray        # (V, 2) float64, metres
    faces: np.ndarray     # (F, 3) int32, counter-clockwise in (u, v)
    hinges: np.ndarray    # (H, 4) int32: edge (x0, x1), opposite vertex in face x0-x1-x2, in face x1-x0-x3

    @property
    def num_vertices(self) -> int:
        return len(self.uv)


def grid_faces(n: int) -> np.ndarray:
    """Triangles of an n x n vertex grid (row-major, u fastest), diagonals alternating per cell
    so the mesh has no preferred shear direction."""
    faces = []
    for j in range(n - 1):
        for i in range(n - 1):
            a, b, c, d = j * n + i, j * n + i + 1, (j + 1) * n + i, (j + 1) * n + i + 1
            if (i + j) % 2 == 0:
                faces += [(a, b, d), (a, d, c)]
            else:
                faces += [(a, b, c), (b, d, c)]
    return np.array(faces, dtype=np.int32)


def subdivide(uv: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One uniform 1-to-4 midpoint refinement."""
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    unique, inverse = np.unique(edges, axis=0, return_inverse=True)
    inverse = inverse.reshape(3, len(faces)).T + len(uv)   # midpoint index of edges 01, 12, 20
    new_uv = np.concatenate([uv, 0.5 * (uv[unique[:, 0]] + uv[unique[:, 1]])])
    a, b, c = faces[:, 0], faces[:, 1], faces[:, 2]
    ab, bc, ca = inverse[:, 0], inverse[:, 1], inverse[:, 2]
    new_faces = np.concatenate([np.stack(t, axis=1) for t in
                                ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))])
    return new_uv, new_faces.astype(np.int32)


def hinges_of(faces: np.ndarray) -> np.ndarray:
    """Interior edges with their two opposite vertices, oriented as the solver expects:
    (x0, x1, x2, x3) where face A = (x0, x1, x2) and face B = (x1, x0, x3) in the faces' own order."""
    opposite: dict[tuple[int, int], int] = {}
    for f in faces:
        for e in range(3):
            opposite[(int(f[e]), int(f[(e + 1) % 3]))] = int(f[(e + 2) % 3])
    hinges = [(a, b, c, opposite[(b, a)]) for (a, b), c in opposite.items() if a < b and (b, a) in opposite]
    return np.array(hinges, dtype=np.int32).reshape(-1, 4)


def square_cloth(size_m: float, vertices_per_side: int, level: int = 1) -> ClothMesh:
    """A square cloth of side ``size_m``: a base grid refined uniformly ``level - 1`` times."""
    if vertices_per_side < 2:
        raise ValueError(f"a cloth needs at least 2 vertices per side, got {vertices_per_side}")
    if level < 1:
        raise ValueError(f"refinement level must be >= 1, got {level}")
    n = vertices_per_side
    g = np.linspace(0.0, size_m, n)
    uu, vv = np.meshgrid(g, g)
    uv = np.stack([uu.ravel(), vv.ravel()], axis=1)
    faces = grid_faces(n)
    for _ in range(level - 1):
        uv, faces = subdivide(uv, faces)
    return ClothMesh(uv, faces, hinges_of(faces))


def vertices_per_side(base: int, level: int) -> int:
    return (base - 1) * 2 ** (level - 1) + 1
