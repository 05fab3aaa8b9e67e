"""Adaptive remeshing on a restricted quadtree (the "adaptive" rows of the paper's Table 3).

ArcSim, which the paper used, remeshes with edge splits, flips and collapses
driven by a sizing field. Here the same idea is kept on a structure that is
cheap to rebuild every frame and easy to batch: a quadtree over the square
cloth's material space whose leaves are refined where the cloth is curved and
coarsened where it is flat, between uniform level 1 (the base grid) and level
``max_level`` (the finest lattice, uniform level 3 by default).

* Every vertex lies on the finest lattice, so a vertex keeps its identity (and
  its exact position and velocity) across remeshes while it stays in the mesh.
* Neighbouring leaves differ by at most one level (2:1 balance). A leaf whose
  neighbour is finer has a hanging midpoint on that edge and is fanned around
  its centre; a leaf without one is split along a diagonal. The result is a
  conforming triangle mesh with no T-junctions.
* Vertices that appear are placed on the current deformed surface by
  barycentric interpolation in the old triangle that holds them (positions and
  velocities), so remeshing adds no motion of its own.

Lattice coordinates are integers (i along u, j along v), uv = (i, j) * size / N
with N = (n_base - 1) * 2**(max_level - 1) fine cells per side.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sim.mesh import ClothMesh, hinges_of, mesh_rest, sorted_pairs


@dataclass
class QuadMesh:
    """A conforming triangulation of a restricted quadtree over the cloth square."""

    n_fine: int               # fine cells per side (N)
    size: float               # side of the cloth, metres
    level: np.ndarray         # (N, N) int: level (1..max_level) of the leaf covering each fine cell
    max_level: int
    lattice: np.ndarray       # (V, 2) int: lattice coordinates of each vertex
    faces: np.ndarray         # (F, 3) int32, counter-clockwise in uv
    face_leaf: np.ndarray     # (F,) int: the leaf (index into ``leaves``) each face lies in
    leaves: np.ndarray        # (L, 3) int: (i0, j0, s) of each leaf, s its size in fine cells

    @property
    def uv(self) -> np.ndarray:
        return (self.lattice * (self.size / self.n_fine)).astype(np.float32)

    @property
    def num_vertices(self) -> int:
        return len(self.lattice)


def _block_reduce(a: np.ndarray, s: int, fn) -> np.ndarray:
    n = a.shape[0] // s
    return fn(fn(a.reshape(n, s, n, s), axis=3), axis=1)


def _expand(b: np.ndarray, s: int) -> np.ndarray:
    return np.repeat(np.repeat(b, s, axis=0), s, axis=1)


def _neighbour_max(level: np.ndarray) -> np.ndarray:
    """Largest level among each fine cell's four edge neighbours."""
    p = np.pad(level, 1, constant_values=0)
    return np.maximum.reduce([p[:-2, 1:-1], p[2:, 1:-1], p[1:-1, :-2], p[1:-1, 2:]])


def build_levels(target: np.ndarray, max_level: int) -> np.ndarray:
    """Leaf levels from a per-fine-cell target level: refine until every target
    is met, then restore 2:1 balance between edge neighbours."""
    n = target.shape[0]
    level = np.ones_like(target, dtype=np.int64)
    for lv in range(1, max_level):
        s = 2 ** (max_level - lv)
        at_lv = _block_reduce(level, s, np.min) == lv
        refine = at_lv & (_block_reduce(target, s, np.max) > lv)
        level = np.where(_expand(refine, s), lv + 1, level)
    while True:  # 2:1 balance; converges in at most max_level passes
        changed = False
        nbr = _neighbour_max(level)
        for lv in range(1, max_level - 1):
            s = 2 ** (max_level - lv)
            at_lv = (_block_reduce(level, s, np.min) == lv) & (_block_reduce(level, s, np.max) == lv)
            refine = at_lv & (_block_reduce(nbr, s, np.max) >= lv + 2)
            if refine.any():
                level = np.where(_expand(refine, s), lv + 1, level)
                changed = True
        if not changed:
            assert level.shape == (n, n)
            return level


def triangulate(level: np.ndarray, max_level: int, size: float) -> QuadMesh:
    """The conforming triangulation of the quadtree whose leaf levels are ``level``.

    Leaves are taken coarsest level first, row-major within a level. A leaf with no finer neighbour is split
    along a diagonal that alternates like a checkerboard (no directional bias); one with a finer neighbour is
    fanned around its centre through its corners and the hanging midpoints. Vertices are numbered in the order
    the leaves first use them (corners counter-clockwise from (i, j), each hanging midpoint after the corner
    before it, then the centre), so that the numbering is the same however the arrays are computed."""
    n = level.shape[0]
    leaves = []
    for lv in range(1, max_level + 1):
        s = 2 ** (max_level - lv)
        is_leaf = (_block_reduce(level, s, np.min) == lv) & (_block_reduce(level, s, np.max) == lv)
        bi, bj = np.nonzero(is_leaf)
        leaves.append(np.stack([bi * s, bj * s, np.full_like(bi, s)], axis=1))
    leaves = np.concatenate(leaves).astype(np.int64)
    i, j, s = leaves[:, 0], leaves[:, 1], leaves[:, 2]
    h = s // 2
    own = level[i, j]
    padded = np.pad(level, 1, constant_values=0)

    def finer(rows, cols) -> np.ndarray:      # either of two padded cells finer than the leaf (leaves above 1 cell)
        return (s > 1) & (np.maximum(padded[rows[0], cols[0]], padded[rows[1], cols[1]]) > own)

    hanging = np.stack([finer((i + h, i + h + 1), (j, j)),                      # bottom, v = j
                        finer((1 + i + s, 1 + i + s), (j + h, j + h + 1)),      # right, u = i + s
                        finer((i + h, i + h + 1), (1 + j + s, 1 + j + s)),      # top, v = j + s
                        finer((i, i), (j + h, j + h + 1))], axis=1)             # left, u = i
    fan = hanging.any(axis=1)
    # the points each leaf uses, in order: c00, mid bottom, c10, mid right, c11, mid top, c01, mid left, centre
    points = np.stack([np.stack(p, axis=1) for p in
                       ((i, j), (i + h, j), (i + s, j), (i + s, j + h), (i + s, j + s), (i + h, j + s), (i, j + s),
                        (i, j + h), (i + h, j + h))], axis=1)                   # (L, 9, 2)
    used = np.zeros((len(leaves), 9), dtype=bool)
    used[:, 0:8:2] = True
    used[:, 1:8:2] = hanging
    used[:, 8] = fan
    key = points[..., 0] * (n + 1) + points[..., 1]
    unique, first, inverse = np.unique(key[used], return_index=True, return_inverse=True)
    rank = np.empty(len(unique), dtype=np.int64)
    rank[np.argsort(first, kind="stable")] = np.arange(len(unique))
    ids = np.full(used.shape, -1, dtype=np.int64)
    ids[used] = rank[inverse]
    lattice = np.stack([unique // (n + 1), unique % (n + 1)], axis=1)[np.argsort(rank)]

    # each leaf's triangles, up to 8, in order
    ring_slots = np.argsort(~used[:, :8], axis=1, kind="stable")               # the used ring points first
    ring = np.take_along_axis(ids[:, :8], ring_slots, axis=1)
    count = np.where(fan, used[:, :8].sum(axis=1), 2)
    k = np.arange(8)[None, :]
    following = np.take_along_axis(ring, (k + 1) % count[:, None], axis=1)
    tris = np.stack([ring, following, np.repeat(ids[:, 8:9], 8, axis=1)], axis=2)   # (L, 8, 3) fans
    a, b, c, d = ids[:, 0], ids[:, 2], ids[:, 4], ids[:, 6]
    even = ((i // s) + (j // s)) % 2 == 0
    split = np.where(even[:, None, None], np.stack([np.stack([a, b, c], 1), np.stack([a, c, d], 1)], 1),
                     np.stack([np.stack([a, b, d], 1), np.stack([b, c, d], 1)], 1))
    tris[~fan, :2] = split[~fan]
    keep = k < count[:, None]
    return QuadMesh(n, size, level, max_level, lattice, tris[keep].astype(np.int32),
                    np.repeat(np.arange(len(leaves)), count).astype(np.int64), leaves)


def uniform(n_base: int, size: float, level: int, max_level: int = 3) -> QuadMesh:
    """The quadtree with every leaf at ``level`` (uniform remeshing at that level)."""
    n = (n_base - 1) * 2 ** (max_level - 1)
    return triangulate(np.full((n, n), level, np.int64), max_level, size)


def edge_curvature(mesh: QuadMesh, positions: np.ndarray) -> np.ndarray:
    """Per-face max curvature theta * l / (A0 + A1) of its interior edges (paper eq. 3 per edge)."""
    f = mesh.faces
    x = positions[f]
    n = np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True) + 1e-20
    uv = mesh.uv.astype(np.float64)
    t = uv[f]
    a, b = t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]
    area = 0.5 * np.abs(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0])
    e = np.stack([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]], axis=1).reshape(-1, 2)
    key = sorted_pairs(e)
    face_of = np.repeat(np.arange(len(f)), 3)
    # (lexsort's order by first, then second vertex, as one stable argsort of an integer key: twice as fast)
    order = np.argsort(key[:, 0].astype(np.int64) * (int(key.max(initial=0)) + 1) + key[:, 1], kind="stable")
    key, face_of = key[order], face_of[order]
    same = np.all(key[1:] == key[:-1], axis=1)
    f0, f1, k = face_of[:-1][same], face_of[1:][same], key[:-1][same]
    theta = np.arccos(np.clip(np.einsum("ij,ij->i", n[f0], n[f1]), -1.0, 1.0))
    length = np.linalg.norm(uv[k[:, 0]] - uv[k[:, 1]], axis=1)
    c = theta * length / (area[f0] + area[f1])
    out = np.zeros(len(f))
    np.maximum.at(out, f0, c)
    np.maximum.at(out, f1, c)
    return out


def leaf_cells(leaves: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(leaf, row, column) of every fine cell each leaf covers, leaf by leaf: where a per-leaf value is painted
    onto the (N, N) grid in one assignment (a Python loop over a cloth's leaves was ~1.5 ms of its remeshing)."""
    side = leaves[:, 2]
    count = side * side
    leaf = np.repeat(np.arange(len(leaves)), count)
    k = np.arange(int(count.sum())) - np.repeat(np.cumsum(count) - count, count)
    s = side[leaf]
    return leaf, leaves[leaf, 0] + k // s, leaves[leaf, 1] + k % s


def target_levels(mesh: QuadMesh, positions: np.ndarray, refine_angle: float = 0.3) -> np.ndarray:
    """Per-fine-cell target level: fine enough that an edge turns by at most
    ``refine_angle`` radians at the local curvature (ArcSim's curvature sizing)."""
    curv = edge_curvature(mesh, positions)
    leaf_curv = np.zeros(len(mesh.leaves))
    np.maximum.at(leaf_curv, mesh.face_leaf, curv)
    h1 = mesh.size / (mesh.n_fine / 2 ** (mesh.max_level - 1))  # edge length at level 1
    need = np.log2(np.maximum(h1 * leaf_curv / refine_angle, 1.0))
    leaf_target = np.clip(1 + np.ceil(need).astype(np.int64), 1, mesh.max_level)
    target = np.ones_like(mesh.level)
    leaf, row, col = leaf_cells(mesh.leaves)
    target[row, col] = leaf_target[leaf]
    return target


def transfer(old: QuadMesh, new: QuadMesh, fields: list[np.ndarray]) -> list[np.ndarray]:
    """Carry per-vertex fields (positions, velocities) from ``old`` to ``new``:
    kept vertices exactly, new ones barycentrically in the old triangle holding them."""
    n = old.n_fine
    key = lambda lat: lat[:, 0] * (n + 1) + lat[:, 1]  # noqa: E731 - lattice point -> integer
    old_keys, new_keys = key(old.lattice), key(new.lattice)
    order = np.argsort(old_keys)
    pos = np.searchsorted(old_keys[order], new_keys).clip(0, len(old_keys) - 1)
    kept = old_keys[order][pos] == new_keys
    src = order[pos]
    out = [np.empty((new.num_vertices,) + f.shape[1:], f.dtype) for f in fields]
    for o, f in zip(out, fields):
        o[kept] = f[src[kept]]
    added = np.nonzero(~kept)[0]
    if len(added) == 0:
        return out
    # the old leaf under each added vertex, and that leaf's (at most 8) faces
    cell_leaf = np.empty((n, n), np.int64)
    leaf, row, col = leaf_cells(old.leaves)
    cell_leaf[row, col] = leaf
    counts = np.bincount(old.face_leaf, minlength=len(old.leaves))
    first = np.concatenate([[0], np.cumsum(counts)[:-1]])
    by_leaf = np.argsort(old.face_leaf, kind="stable")
    p = new.lattice[added].astype(np.float64)
    leaf = cell_leaf[np.minimum(new.lattice[added, 0], n - 1), np.minimum(new.lattice[added, 1], n - 1)]
    slot = np.arange(8)
    valid = slot[None, :] < counts[leaf][:, None]
    cand = by_leaf[np.minimum(first[leaf][:, None] + slot[None, :], len(by_leaf) - 1)]   # (A, 8) faces
    tri = old.lattice[old.faces[cand]].astype(np.float64)                                 # (A, 8, 3, 2)
    a, b, c = tri[..., 0, :], tri[..., 1, :], tri[..., 2, :]
    d = p[:, None, :] - a
    e1, e2 = b - a, c - a
    det = e1[..., 0] * e2[..., 1] - e1[..., 1] * e2[..., 0]
    l1 = (d[..., 0] * e2[..., 1] - d[..., 1] * e2[..., 0]) / det
    l2 = (e1[..., 0] * d[..., 1] - e1[..., 1] * d[..., 0]) / det
    w = np.stack([1 - l1 - l2, l1, l2], axis=-1)                                          # (A, 8, 3)
    score = np.where(valid, w.min(axis=-1), -np.inf)
    best = score.argmax(axis=1)
    rows = np.arange(len(added))
    wb, fb = w[rows, best], old.faces[cand[rows, best]]                                     # (A, 3), (A, 3)
    for o, f in zip(out, fields):
        o[added] = np.einsum("ak,ak...->a...", wb, f[fb])
    return out


def remesh(mesh: QuadMesh, positions: np.ndarray, velocities: np.ndarray,
           refine_angle: float = 0.3) -> tuple[QuadMesh, np.ndarray, np.ndarray]:
    """One adaptive remeshing step: refine where curved, coarsen where flat."""
    level = build_levels(target_levels(mesh, positions, refine_angle), mesh.max_level)
    if np.array_equal(level, mesh.level):
        return mesh, positions, velocities
    new = triangulate(level, mesh.max_level, mesh.size)
    pos, vel = transfer(mesh, new, [positions, velocities])
    return new, pos, vel


# ---------------------------------------------------------------- a cloth's step, as a host worker runs it

def cloth_mesh(q: QuadMesh) -> ClothMesh:
    """The solver's mesh of a quadtree mesh."""
    return ClothMesh(q.uv.astype(np.float64), q.faces, hinges_of(q.faces))


@dataclass
class MeshState:
    """What the solver and the health check need of a quadtree mesh, computed once per remesh: the solver's
    mesh, its rest state (``sim.mesh.mesh_rest``; ``rest["edges"]`` are its edges) and the edges' rest lengths."""

    mesh: ClothMesh
    rest: dict[str, np.ndarray]
    edge_rest: np.ndarray

    @property
    def edges(self) -> np.ndarray:
        return self.rest["edges"]


# Rest arrays that only the solver reads, and uploads as float32: cast where they are made, so that a remeshing
# worker sends a sixth less to the parent (which unpickles every cloth of every frame: at tens of workers, the
# pool's serial part). Casting before or after the batch's concatenation gives the same float32 values.
SOLVER_FLOAT32_REST = ("dm_inv", "hinge_length", "hinge_area", "hinge_dir")


def mesh_state(q: QuadMesh, c: int = 0) -> MeshState:
    mesh = cloth_mesh(q)
    rest = mesh_rest(mesh, c)
    rest.update({k: rest[k].astype(np.float32) for k in SOLVER_FLOAT32_REST})
    e, uv = rest["edges"], q.uv
    return MeshState(mesh, rest, np.linalg.norm(uv[e[:, 1]] - uv[e[:, 0]], axis=1))


@dataclass
class Remeshed:
    """A cloth whose mesh changed: the new quadtree mesh, its ``MeshState``, and the positions and velocities
    carried onto it (float32, as the solver takes them)."""

    quad: QuadMesh
    state: MeshState
    positions: np.ndarray
    velocities: np.ndarray


def remesh_cloth(quad: QuadMesh, positions: np.ndarray, velocities: np.ndarray, refine_angle: float,
                 c: int = 0) -> Remeshed | None:
    """Cloth ``c``'s remeshing step from its float32 positions and velocities; None when its mesh stays.
    A pure function of its arguments, so host workers can run it for many cloths at once."""
    new, p, v = remesh(quad, positions.astype(np.float64), velocities.astype(np.float64), refine_angle)
    if new is quad:
        return None
    return Remeshed(new, mesh_state(new, c), p.astype(np.float32), v.astype(np.float32))
