"""Self-intersections of a cloth surface: how many pairs of its triangles cut through each other.

An independent check of the solver's self-collision (``sim.collision``), in
float64 NumPy with nothing shared with the Warp kernels. Two triangles that
share a vertex (neighbours across an edge or a vertex) touch by construction
and are never counted, whatever their shape: counting them would make every
mesh "intersect". Any other two triangles intersect when an edge of one
crosses the other (the exact signed-volume test, so touching within float64
rounding is a matter of sign; coplanar overlaps, which a simulated cloth meets
with probability zero, are not counted).

Broad phase: triangles whose centroids are closer than twice the largest
bounding radius (a k-d tree on the centroids), then box overlap.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree


def _orient(a: np.ndarray, b: np.ndarray, c: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Signed volume (times 6) of the tetrahedra (a, b, c, d), row by row."""
    return np.einsum("ij,ij->i", np.cross(b - a, c - a), d - a)


def _segment_crosses(p: np.ndarray, q: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Whether segment p-q passes through triangle a-b-c (strictly: end points on opposite sides of its
    plane, and the segment's line inside all three of its edges)."""
    sp, sq = np.sign(_orient(a, b, c, p)), np.sign(_orient(a, b, c, q))
    s1, s2, s3 = np.sign(_orient(p, q, a, b)), np.sign(_orient(p, q, b, c)), np.sign(_orient(p, q, c, a))
    return (sp * sq < 0) & (s1 == s2) & (s2 == s3) & (s1 != 0)


def candidate_pairs(x: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(M, 2) pairs i < j of triangles whose bounding boxes overlap and that share no vertex."""
    tri = x[faces]                                            # (F, 3, 3)
    centre = tri.mean(axis=1)
    radius = np.linalg.norm(tri - centre[:, None], axis=2).max(axis=1)
    if len(faces) < 2:
        return np.zeros((0, 2), dtype=np.int64)
    pairs = cKDTree(centre).query_pairs(2.0 * float(radius.max()), output_type="ndarray")
    if len(pairs) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    lo, hi = tri.min(axis=1), tri.max(axis=1)
    i, j = pairs[:, 0], pairs[:, 1]
    keep = np.ones(len(pairs), dtype=bool)
    for a in range(3):                      # share no vertex (column by column: cheaper than a 3x3 broadcast)
        fa = faces[i, a]
        for b in range(3):
            keep &= fa != faces[j, b]
    i, j = i[keep], j[keep]
    keep = np.ones(len(i), dtype=bool)
    for a in range(3):                      # bounding boxes overlap
        keep &= (lo[i, a] <= hi[j, a]) & (lo[j, a] <= hi[i, a])
    return np.sort(np.stack([i[keep], j[keep]], axis=1), axis=1)


def intersecting_pairs(x: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(M, 2) pairs of triangles (sharing no vertex) that intersect, for positions ``x`` (V, 3)."""
    x = np.asarray(x, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    pairs = candidate_pairs(x, faces)
    if len(pairs) == 0:
        return pairs
    A, B = x[faces[pairs[:, 0]]], x[faces[pairs[:, 1]]]     # (M, 3, 3)
    hit = np.zeros(len(pairs), dtype=bool)
    for S, T in ((A, B), (B, A)):
        for e in range(3):
            hit |= _segment_crosses(S[:, e], S[:, (e + 1) % 3], T[:, 0], T[:, 1], T[:, 2])
    return pairs[hit]


def count_intersections(x: np.ndarray, faces: np.ndarray) -> int:
    """How many pairs of triangles (sharing no vertex) cut through each other."""
    return len(intersecting_pairs(x, faces))
