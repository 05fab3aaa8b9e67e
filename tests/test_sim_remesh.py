"""Adaptive remeshing: conforming, refines where curved, coarsens where flat, moves nothing."""

from __future__ import annotations

import numpy as np
import pytest

from sim import remesh as R


def _flat(mesh):
    uv = mesh.uv.astype(np.float64)
    return np.c_[uv[:, 0], np.zeros(len(uv)), uv[:, 1]]


def _folded(mesh, at=0.25, width=0.02, height=0.05):
    pos = _flat(mesh)
    pos[:, 1] = height * np.exp(-(((pos[:, 0] - at) / width) ** 2))
    return pos


def _check_conforming(mesh):
    t = mesh.uv[mesh.faces].astype(np.float64)
    area = 0.5 * ((t[:, 1, 0] - t[:, 0, 0]) * (t[:, 2, 1] - t[:, 0, 1]) - (t[:, 1, 1] - t[:, 0, 1]) * (t[:, 2, 0] - t[:, 0, 0]))
    assert (area > 0).all(), "every face counter-clockwise in uv"
    assert area.sum() == pytest.approx(mesh.size ** 2)
    f = mesh.faces
    edges, counts = np.unique(np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), 1), axis=0,
                              return_counts=True)
    assert counts.max() == 2, "no edge shared by three faces"
    lat = mesh.lattice[edges[counts == 1]]
    on_border = ((lat[:, 0, 0] == lat[:, 1, 0]) & np.isin(lat[:, 0, 0], [0, mesh.n_fine])) | \
                ((lat[:, 0, 1] == lat[:, 1, 1]) & np.isin(lat[:, 0, 1], [0, mesh.n_fine]))
    assert on_border.all(), "open edges only on the cloth's border: no T-junctions"


@pytest.mark.parametrize("level,side", [(1, 16), (2, 31), (3, 61)])
def test_uniform_levels(level, side):
    m = R.uniform(16, 0.5, level)
    assert m.num_vertices == side * side
    _check_conforming(m)


def test_refines_at_a_fold_and_coarsens_when_flat():
    m = R.uniform(16, 0.5, 1)
    m2, pos, vel = R.remesh(m, _folded(m), np.zeros((m.num_vertices, 3)))
    _check_conforming(m2)
    assert m2.num_vertices > m.num_vertices
    fine = m2.level == 3
    cols = np.nonzero(fine.any(axis=1))[0] * m2.size / m2.n_fine
    assert abs(cols.mean() - 0.25) < 0.05, "refinement sits on the fold"
    assert (m2.level[-10:] == 1).all(), "flat cloth far from the fold stays coarse"
    m3, _, _ = R.remesh(m2, _flat(m2), np.zeros((m2.num_vertices, 3)))
    assert m3.num_vertices == m.num_vertices, "a flattened cloth coarsens back to the base grid"


def test_transfer_keeps_vertices_and_interpolates_linearly():
    m = R.uniform(16, 0.5, 1)
    m2, _, _ = R.remesh(m, _folded(m), np.zeros((m.num_vertices, 3)))
    uv, uv2 = m.uv.astype(np.float64), m2.uv.astype(np.float64)
    field = np.c_[2 * uv[:, 0] + uv[:, 1], uv[:, 1] - uv[:, 0], np.ones(len(uv))]
    (moved,) = R.transfer(m, m2, [field])
    expect = np.c_[2 * uv2[:, 0] + uv2[:, 1], uv2[:, 1] - uv2[:, 0], np.ones(len(uv2))]
    np.testing.assert_allclose(moved, expect, atol=1e-6)  # uv are float32
    # a vertex in both meshes keeps its exact value, even for a non-linear field
    rnd = np.random.default_rng(0).random((m.num_vertices, 3))
    (kept,) = R.transfer(m, m2, [rnd])
    both = {tuple(p): k for k, p in enumerate(m.lattice.tolist())}
    for v, p in enumerate(m2.lattice.tolist()):
        if tuple(p) in both:
            assert (kept[v] == rnd[both[tuple(p)]]).all()


def test_balance_keeps_neighbours_within_one_level():
    n = 60
    target = np.ones((n, n), np.int64)
    target[30, 30] = 3
    level = R.build_levels(target, 3)
    assert level[30, 30] == 3
    assert np.abs(np.diff(level, axis=0)).max() <= 1 and np.abs(np.diff(level, axis=1)).max() <= 1


def _triangulate_leaf_by_leaf(level: np.ndarray, max_level: int, size: float) -> R.QuadMesh:
    """The triangulation's definition, one leaf at a time (vertices numbered on first use)."""
    n = level.shape[0]
    leaves = []
    for lv in range(1, max_level + 1):
        s = 2 ** (max_level - lv)
        is_leaf = (R._block_reduce(level, s, np.min) == lv) & (R._block_reduce(level, s, np.max) == lv)
        bi, bj = np.nonzero(is_leaf)
        leaves.append(np.stack([bi * s, bj * s, np.full_like(bi, s)], axis=1))
    leaves = np.concatenate(leaves).astype(np.int64)
    padded = np.pad(level, 1, constant_values=0)

    def finer_across(i, j, s, side):
        h = s // 2
        cells = (padded[i + h: i + h + 2, j], padded[1 + i + s, j + h: j + h + 2],
                 padded[i + h: i + h + 2, 1 + j + s], padded[i, j + h: j + h + 2])[side]
        return s > 1 and cells.max() > level[i, j]

    points: dict[tuple[int, int], int] = {}

    def vid(p):
        return points.setdefault(p, len(points))

    faces, face_leaf = [], []
    for li, (i, j, s) in enumerate(leaves):
        h = s // 2
        corners = ((i, j), (i + s, j), (i + s, j + s), (i, j + s))
        mids = ((i + h, j), (i + s, j + h), (i + h, j + s), (i, j + h))
        hanging = [finer_across(i, j, s, side) for side in range(4)]
        if not any(hanging):
            a, b, c, d = (vid(p) for p in corners)
            tris = [(a, b, c), (a, c, d)] if ((i // s) + (j // s)) % 2 == 0 else [(a, b, d), (b, c, d)]
        else:
            ring = []
            for corner, mid, hang in zip(corners, mids, hanging):
                ring.append(vid(corner))
                if hang:
                    ring.append(vid(mid))
            centre = vid((i + h, j + h))
            tris = [(ring[k], ring[(k + 1) % len(ring)], centre) for k in range(len(ring))]
        faces += tris
        face_leaf += [li] * len(tris)
    lattice = np.array(sorted(points, key=points.get), dtype=np.int64)
    return R.QuadMesh(n, size, level, max_level, lattice, np.array(faces, np.int32), np.array(face_leaf), leaves)


def test_triangulation_is_its_leaf_by_leaf_definition():
    rng = np.random.default_rng(5)
    cases = [np.full((8, 8), lv) for lv in (1, 2, 3)]
    for _ in range(12):                       # balanced quadtrees from random refinement targets
        cases.append(R.build_levels(rng.integers(1, 4, (16, 16)), 3))
    fans = 0
    for level in cases:
        got, want = R.triangulate(level, 3, 0.5), _triangulate_leaf_by_leaf(level, 3, 0.5)
        fans += int(np.bincount(want.face_leaf).max() > 2)       # leaves fanned around hanging midpoints
        for name in ("lattice", "faces", "face_leaf", "leaves"):
            np.testing.assert_array_equal(getattr(got, name), getattr(want, name), err_msg=name)
        assert got.faces.dtype == np.int32 and got.lattice.shape[1] == 2
    assert fans >= 10


def test_pinned_lattice_points_are_found_on_every_later_mesh():
    """An adaptive cloth pinned at points (not its whole top edge) pins, on each remeshed mesh, exactly the
    vertices at those lattice points (``sim.adaptive._pins`` matches them as integer keys); one pinned along its
    top edge pins every top-edge vertex the remesher makes."""
    from sim.adaptive import _pins, _start
    from sim.materials import load_material
    from sim.motions import ClipScene
    from sim.solver import ClothSpec

    m = load_material("camel-ponte-roma")
    base = R.uniform(16, 0.5, 1)
    refined, _, _ = R.remesh(base, _folded(base, at=0.1), np.zeros((base.num_vertices, 3)))
    top = np.flatnonzero(base.lattice[:, 1] == base.n_fine)
    moved = False
    for pinned in ([top[0], top[-1]], [top[0], top[7], 40], [], top):
        spec = ClothSpec(R.cloth_mesh(base), _flat(base), m.stretching, m.bending, m.density, pinned=np.array(pinned))
        cloth = _start(ClipScene(spec, np.zeros(3)), base, R.mesh_state(base))
        np.testing.assert_array_equal(_pins(cloth), np.sort(np.asarray(pinned, dtype=np.int64)))
        cloth.quad = refined
        points = {tuple(p) for p in base.lattice[np.asarray(pinned, dtype=np.int64)].tolist()}
        if cloth.pin_edge:
            points = {tuple(p) for p in refined.lattice.tolist() if p[1] == refined.n_fine}
        want = [k for k, p in enumerate(map(tuple, refined.lattice.tolist())) if p in points]
        got = _pins(cloth)
        assert got.dtype == np.int64 and len(got) == len(points)
        np.testing.assert_array_equal(got, want)
        moved |= len(pinned) < len(top) and want != sorted(pinned)
    assert moved, "the remesher renumbered pinned points"
    assert len(want) > len(top), "the remesher refined the top edge"


def test_leaf_cells_cover_every_fine_cell_once_with_its_leaf():
    """The vectorised painting of per-leaf values onto the fine grid (target levels, the transfer's cell -> leaf
    map) gives each cell the leaf whose square holds it."""
    rng = np.random.default_rng(3)
    target = rng.integers(1, 4, size=(60, 60))
    mesh = R.triangulate(R.build_levels(target, 3), 3, 0.5)
    leaf, row, col = R.leaf_cells(mesh.leaves)
    assert len(leaf) == 60 * 60 and len(set(zip(row.tolist(), col.tolist()))) == 60 * 60
    painted = np.full((60, 60), -1)
    for li, (i, j, s) in enumerate(mesh.leaves):
        painted[i:i + s, j:j + s] = li
    assert np.array_equal(painted[row, col], leaf)


def test_sorted_pairs_is_a_row_sort():
    from sim.mesh import sorted_pairs

    pairs = np.random.default_rng(0).integers(0, 50, size=(200, 2)).astype(np.int32)
    out = sorted_pairs(pairs)
    assert out.dtype == pairs.dtype and np.array_equal(out, np.sort(pairs, axis=1))
    assert sorted_pairs(np.zeros((0, 2), np.int64)).shape == (0, 2)
