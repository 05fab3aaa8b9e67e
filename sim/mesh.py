"""Flat square cloth meshes in material space, their uniform refinements, and hinge lists.

Material coordinates (u, v) are metres in the cloth's rest space. Faces are
counter-clockwise in (u, v). A uniform refinement splits every triangle into
four at its edge midpoints, so level L of a base grid with n vertices per side
has (n - 1) * 2^(L - 1) + 1 vertices per side and keeps every coarser edge.
"""

from __future__ import annotations

import math
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


def directed_edges(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every face's three directed edges a -> b with the opposite corner c, face by face (edge e of face f at
    row 3 f + e: (f[e], f[e+1], f[e+2]))."""
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    return f.ravel(), f[:, [1, 2, 0]].ravel(), f[:, [2, 0, 1]].ravel()


def sorted_pairs(pairs: np.ndarray) -> np.ndarray:
    """Each (E, 2) row in increasing order: ``np.sort(pairs, axis=1)``, which sorts rows of two 100x slower."""
    return np.stack([np.minimum(pairs[:, 0], pairs[:, 1]), np.maximum(pairs[:, 0], pairs[:, 1])], axis=1)


def unique_edges(faces: np.ndarray) -> np.ndarray:
    """(E, 2) sorted vertex pairs of a triangle mesh's edges, in lexicographic order (the rows of
    ``np.unique(pairs, axis=0)``, found through one integer key per pair, which sorts far faster)."""
    f = np.asarray(faces)
    e = sorted_pairs(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]))
    if len(e) == 0:
        return e
    n = int(e.max()) + 1
    key = np.unique(e[:, 0].astype(np.int64) * n + e[:, 1])
    return np.stack([key // n, key % n], axis=1).astype(e.dtype)


def edge_sides(faces: np.ndarray, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``edge_rows`` of a -> b and of b -> a, with one sort: the two faces of each edge (a, b)."""
    rows = edge_rows(faces, np.concatenate([a, b]), np.concatenate([b, a]))
    return rows[:len(a)], rows[len(a):]


def edge_rows(faces: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """For each vertex pair (a, b): the row (3 face + edge, as ``directed_edges``) of the directed edge a -> b,
    the last one if several faces hold it, -1 if none does."""
    ea, eb, _ = directed_edges(faces)
    a, b = np.asarray(a, dtype=np.int64), np.asarray(b, dtype=np.int64)
    n = int(max(ea.max(initial=-1), a.max(initial=-1), b.max(initial=-1))) + 1
    key = ea * n + eb
    order = np.argsort(key, kind="stable")
    wanted = a * n + b
    pos = np.searchsorted(key[order], wanted, side="right") - 1
    found = (pos >= 0) & (key[order[np.maximum(pos, 0)]] == wanted)
    return np.where(found, order[np.maximum(pos, 0)], -1)


def hinges_of(faces: np.ndarray) -> np.ndarray:
    """Interior edges with their two opposite vertices, oriented as the solver expects:
    (x0, x1, x2, x3) where face A = (x0, x1, x2) and face B = (x1, x0, x3) in the faces' own order.
    One hinge per edge, in the order its a < b side first appears among the faces' edges."""
    a, b, c = directed_edges(faces)
    if len(a) == 0:
        return np.zeros((0, 4), dtype=np.int32)
    last, reverse = edge_sides(faces, a, b)
    # an edge's first appearance, as a dict keyed by (a, b) keeps it; the last face's corner, as it overwrites
    first = np.zeros(len(a), dtype=bool)
    first[np.unique(a * (int(a.max()) + 1) + b, return_index=True)[1]] = True
    keep = first & (a < b) & (reverse >= 0)
    return np.stack([a[keep], b[keep], c[last[keep]], c[reverse[keep]]], axis=1).astype(np.int32)


def edge_directions(e_uv: np.ndarray) -> np.ndarray:
    """Each edge's direction coordinate y in [0, 2] of the bending table (0, 45, 90 degrees) from its (du, dv)
    row. The angle comes from libm's atan2, as ``math.atan2`` (NumPy's differs in the last bit)."""
    angle = np.fromiter(map(math.atan2, e_uv[:, 1].tolist(), e_uv[:, 0].tolist()), dtype=np.float64,
                        count=len(e_uv))
    y = np.abs(angle) * 4.0 / math.pi
    y = np.where(y > 4.0, 8.0 - y, y)
    return np.where(y > 2.0, 4.0 - y, y)


def mesh_rest(mesh: ClothMesh, c: int = 0) -> dict[str, np.ndarray]:
    """The rest state every cloth on ``mesh`` shares (``c`` names the first in messages): faces' inverse rest
    matrices and areas, hinges' rest length, the two faces' area and the edge's direction in (u, v)."""
    uv, faces = mesh.uv, mesh.faces
    d1 = uv[faces[:, 1]] - uv[faces[:, 0]]
    d2 = uv[faces[:, 2]] - uv[faces[:, 0]]
    dm = np.stack([np.stack([d1[:, 0], d2[:, 0]], 1), np.stack([d1[:, 1], d2[:, 1]], 1)], 1)  # (F,2,2)
    area = 0.5 * (d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0])
    if np.any(area <= 0):
        raise ValueError(f"cloth {c}: faces must be counter-clockwise with positive area in (u, v)")
    h = np.asarray(mesh.hinges).reshape(-1, 4)
    e_uv = uv[h[:, 1]] - uv[h[:, 0]]
    # the two faces of each hinge: those holding its edge in either direction
    face_a, face_b = (rows // 3 for rows in edge_sides(faces, h[:, 0], h[:, 1]))
    return {"dm_inv": np.linalg.inv(dm), "area": area, "hinge_length": np.linalg.norm(e_uv, axis=1),
            "hinge_area": area[face_a] + area[face_b], "hinge_dir": edge_directions(e_uv),
            "edges": unique_edges(faces)}


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
