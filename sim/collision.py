"""Cloth self-collision: point-triangle and edge-edge repulsion with a thickness, batched.

Where it acts. After the implicit step has produced the new velocities v and
the predicted positions x1 = x0 + h v, and before anything else reads them, in
the style of Bridson, Fedkiw and Anderson 2002 (velocity impulses after the
dynamics, positions updated from the corrected velocities), not as a penalty
force inside the solve: a penalty needs a stiffness far above the cloth's to
stop a fold in one 5 ms step, which the solve's linearisation then has to
carry (and the CG to converge on); an impulse stops exactly what must be
stopped and leaves the solve as it is.

What it enforces. Every pair of a vertex and a triangle not incident to it,
and of two edges with no common vertex, whose swept boxes over the step come
within ``REACH`` x thickness of each other, is linearised at the start of
the step: the closest points at x0 (barycentric weights w, distance d0 and the
unit normal n from the second element to the first). Its relative velocity
along n must then satisfy

    n . (sum_i w_i v_i) >= (thickness - d0) / h,

i.e. the pair may close the gap beyond the thickness in this step but no more
(a "speculative" contact: it holds for a vertex that would have passed right
through a triangle within one step, which a proximity-only repulsion misses),
and a pair already closer than the thickness is pushed back to it. A violated
constraint gets the mass-weighted impulse that meets it exactly, plus Coulomb
friction (``friction`` x the normal velocity change, at most stopping the
tangential slip). Constraints are solved in ``passes`` Jacobi passes, each
vertex taking the mean of the changes of the pairs it belongs to (a vertex
between several layers would overshoot with the sum), over-relaxed by
``RELAXATION``; each pass changes v and moves x by h times the change.

Batching. All cloths of a ``BatchSolver`` share two BVHs (``wp.Bvh``), one over
the triangles' and one over the edges' swept boxes, grouped by cloth: a query
starts at its cloth's group root, so cloths that overlap in space (every wind
clip hangs at the origin) never see each other. Both are refitted every step
(the same topology, boxes from the moving cloth: a recorded launch, so a step
is still one CUDA graph). Found pairs go to fixed slots per querying vertex
or edge, in the BVH's traversal order: no global counter, so the pair lists are
the same on every run of a device (the CPU's tree is built by SAH, a GPU's by
LBVH, so their orders differ). A vertex or edge with more pairs than
``slots`` (deep in a fold pressed into several layers) keeps the closest ones
and drops the farthest, counted per cloth (meta health
``collision_pairs_dropped``); a dropped pair is one that was farther than
every kept one.

Determinism. On the CPU, Warp runs a kernel's threads one after another, so
the atomic sums of the impulses are added in thread order and a rerun is
byte-identical, as for the solver's force assembly. On a GPU the order of
float atomic adds varies, as it does for the rest of the solver.

Not handled: contact with other cloths of the batch (they are separate
simulations) and pairs that come within reach only through another pair's
correction in the same step (the next step finds them).
"""

from __future__ import annotations

import numpy as np
import warp as wp

# Pairs are kept while they are within REACH x thickness at the start or the predicted end of the step: the
# active ones (closer than the thickness at the end) and those that another pair's correction may push in.
# 1.5 keeps the in-sheet neighbours of a flat uniform3 mesh (0.71 x 8.3 mm from a vertex) out of the lists.
REACH = 1.5
# Jacobi over-relaxation: each vertex moves by 1.5 x the mean of its pairs' changes. With the plain mean (1.0)
# a vertex in several pairs meets each only partly per pass; a fold pressed together by the solve every step
# then closed by ~0.3 mm a step through 4 passes and crossed; 1.5 with 8 passes holds it at the thickness.
RELAXATION = 1.5

# ---------------------------------------------------------------- geometry


@wp.func
def triangle_barycentric(p: wp.vec3, a: wp.vec3, b: wp.vec3, c: wp.vec3):
    """Barycentric weights of the point of triangle a-b-c closest to p (Ericson, 5.1.5)."""
    ab = b - a
    ac = c - a
    ap = p - a
    d1 = wp.dot(ab, ap)
    d2 = wp.dot(ac, ap)
    bp = p - b
    d3 = wp.dot(ab, bp)
    d4 = wp.dot(ac, bp)
    cp = p - c
    d5 = wp.dot(ab, cp)
    d6 = wp.dot(ac, cp)
    vc = d1 * d4 - d3 * d2
    vb = d5 * d2 - d1 * d6
    va = d3 * d6 - d5 * d4
    w = wp.vec3(0.0)
    if d1 <= 0.0 and d2 <= 0.0:
        w = wp.vec3(1.0, 0.0, 0.0)
    elif d3 >= 0.0 and d4 <= d3:
        w = wp.vec3(0.0, 1.0, 0.0)
    elif vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
        t = d1 / (d1 - d3)
        w = wp.vec3(1.0 - t, t, 0.0)
    elif d6 >= 0.0 and d5 <= d6:
        w = wp.vec3(0.0, 0.0, 1.0)
    elif vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
        t = d2 / (d2 - d6)
        w = wp.vec3(1.0 - t, 0.0, t)
    elif va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:
        t = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        w = wp.vec3(0.0, 1.0 - t, t)
    else:
        s = 1.0 / (va + vb + vc)
        w = wp.vec3(1.0 - (vb + vc) * s, vb * s, vc * s)
    return w


@wp.func
def box_min(a: wp.vec3, b: wp.vec3):
    return wp.vec3(wp.min(a[0], b[0]), wp.min(a[1], b[1]), wp.min(a[2], b[2]))


@wp.func
def box_max(a: wp.vec3, b: wp.vec3):
    return wp.vec3(wp.max(a[0], b[0]), wp.max(a[1], b[1]), wp.max(a[2], b[2]))


# ---------------------------------------------------------------- broad phase: swept boxes


@wp.kernel
def face_boxes(x0: wp.array(dtype=wp.vec3), x1: wp.array(dtype=wp.vec3), tri: wp.array2d(dtype=int), pad: float,
               lowers: wp.array(dtype=wp.vec3), uppers: wp.array(dtype=wp.vec3)):
    """Each triangle's box over the step (start and predicted positions), grown by ``pad``."""
    f = wp.tid()
    lo = box_min(x0[tri[f, 0]], x1[tri[f, 0]])
    hi = box_max(x0[tri[f, 0]], x1[tri[f, 0]])
    for q in range(1, 3):
        i = tri[f, q]
        lo = box_min(lo, box_min(x0[i], x1[i]))
        hi = box_max(hi, box_max(x0[i], x1[i]))
    lowers[f] = lo - wp.vec3(pad)
    uppers[f] = hi + wp.vec3(pad)


@wp.kernel
def edge_boxes(x0: wp.array(dtype=wp.vec3), x1: wp.array(dtype=wp.vec3), edge: wp.array2d(dtype=int), pad: float,
               lowers: wp.array(dtype=wp.vec3), uppers: wp.array(dtype=wp.vec3)):
    """Each edge's box over the step, grown by ``pad``."""
    e = wp.tid()
    i = edge[e, 0]
    j = edge[e, 1]
    lowers[e] = box_min(box_min(x0[i], x1[i]), box_min(x0[j], x1[j])) - wp.vec3(pad)
    uppers[e] = box_max(box_max(x0[i], x1[i]), box_max(x0[j], x1[j])) + wp.vec3(pad)


# ---------------------------------------------------------------- narrow phase: pairs into per-query slots


@wp.func
def keep_pair(q: int, found: int, key: float, other: int, w: wp.vec3, n: wp.vec3, dist: float,
              pair: wp.array2d(dtype=int), weight: wp.array2d(dtype=wp.vec3), normal: wp.array2d(dtype=wp.vec3),
              gap: wp.array2d(dtype=float), closeness: wp.array2d(dtype=float), dropped: wp.array(dtype=int),
              cloth: int):
    """Store a pair of query ``q`` (its closest predicted distance ``key``) in the next free slot, or when all
    are taken in the slot of the farthest kept pair if this one is closer; a full query counts one dropped pair
    for its cloth. Returns the number of slots in use."""
    slots = pair.shape[1]
    slot = found
    if found == slots:
        wp.atomic_add(dropped, cloth, 1)
        slot = int(0)
        for s in range(1, slots):
            if closeness[q, s] > closeness[q, slot]:
                slot = s
        if key >= closeness[q, slot]:
            return found
    pair[q, slot] = other
    weight[q, slot] = w
    normal[q, slot] = n
    gap[q, slot] = dist
    closeness[q, slot] = key
    return wp.min(found + 1, slots)


@wp.kernel
def find_point_triangle(bvh: wp.uint64, x0: wp.array(dtype=wp.vec3), x1: wp.array(dtype=wp.vec3),
                        vertex_cloth: wp.array(dtype=int), tri: wp.array2d(dtype=int), reach: float,
                        count: wp.array(dtype=int), pair: wp.array2d(dtype=int), weight: wp.array2d(dtype=wp.vec3),
                        normal: wp.array2d(dtype=wp.vec3), gap: wp.array2d(dtype=float),
                        closeness: wp.array2d(dtype=float), dropped: wp.array(dtype=int)):
    """Vertex i's triangles (not incident to it) within ``reach`` at the start or the predicted end of the
    step, along the start's normal: triangle, barycentric weights, normal (triangle -> vertex), distance."""
    i = wp.tid()
    c = vertex_cloth[i]
    p0 = x0[i]
    p1 = x1[i]
    query = wp.bvh_query_aabb(bvh, box_min(p0, p1), box_max(p0, p1), wp.bvh_get_group_root(bvh, c))
    f = int(0)
    found = int(0)
    while wp.bvh_query_next(query, f):
        a = tri[f, 0]
        b = tri[f, 1]
        d = tri[f, 2]
        if a == i or b == i or d == i:
            continue
        w = triangle_barycentric(p0, x0[a], x0[b], x0[d])
        diff = p0 - (w[0] * x0[a] + w[1] * x0[b] + w[2] * x0[d])
        dist = wp.length(diff)
        n = wp.vec3(0.0)
        if dist > 1.0e-9:
            n = diff / dist
        else:                          # on the triangle: its own normal
            m = wp.cross(x0[b] - x0[a], x0[d] - x0[a])
            if wp.length(m) == 0.0:
                continue
            n = wp.normalize(m)
        key = wp.min(dist, wp.dot(n, p1 - (w[0] * x1[a] + w[1] * x1[b] + w[2] * x1[d])))
        if key < reach:
            found = keep_pair(i, found, key, f, w, n, dist, pair, weight, normal, gap, closeness, dropped, c)
    count[i] = found


@wp.kernel
def find_edge_edge(bvh: wp.uint64, x0: wp.array(dtype=wp.vec3), x1: wp.array(dtype=wp.vec3),
                   edge_cloth: wp.array(dtype=int), edge: wp.array2d(dtype=int), reach: float,
                   count: wp.array(dtype=int), pair: wp.array2d(dtype=int), weight: wp.array2d(dtype=wp.vec3),
                   normal: wp.array2d(dtype=wp.vec3), gap: wp.array2d(dtype=float),
                   closeness: wp.array2d(dtype=float), dropped: wp.array(dtype=int)):
    """Edge e's edges of higher index (each pair once) sharing no vertex with it, within ``reach`` as in
    ``find_point_triangle``: other edge, closest-point parameters (s on e, t on the other, 0), normal, distance."""
    e = wp.tid()
    c = edge_cloth[e]
    i = edge[e, 0]
    j = edge[e, 1]
    half = wp.vec3(0.5 * reach)        # the other edge's box is grown by the other half
    lo = box_min(box_min(x0[i], x1[i]), box_min(x0[j], x1[j])) - half
    hi = box_max(box_max(x0[i], x1[i]), box_max(x0[j], x1[j])) + half
    query = wp.bvh_query_aabb(bvh, lo, hi, wp.bvh_get_group_root(bvh, c))
    g = int(0)
    found = int(0)
    while wp.bvh_query_next(query, g):
        if g <= e:
            continue
        k = edge[g, 0]
        l = edge[g, 1]
        if k == i or k == j or l == i or l == j:
            continue
        st = wp.closest_point_edge_edge(x0[i], x0[j], x0[k], x0[l], 1.0e-18)
        s = st[0]
        t = st[1]
        diff = (x0[i] + s * (x0[j] - x0[i])) - (x0[k] + t * (x0[l] - x0[k]))
        dist = wp.length(diff)
        n = wp.vec3(0.0)
        if dist > 1.0e-9:
            n = diff / dist
        else:                          # crossing: the edges' common normal
            m = wp.cross(x0[j] - x0[i], x0[l] - x0[k])
            if wp.length(m) == 0.0:
                continue
            n = wp.normalize(m)
        key = wp.min(dist, wp.dot(n, (x1[i] + s * (x1[j] - x1[i])) - (x1[k] + t * (x1[l] - x1[k]))))
        if key < reach:
            found = keep_pair(e, found, key, g, wp.vec3(s, t, 0.0), n, dist, pair, weight, normal, gap, closeness,
                              dropped, c)
    count[e] = found


# ---------------------------------------------------------------- response: Jacobi passes of velocity impulses


@wp.func
def pair_change(rel: wp.vec3, n: wp.vec3, target: float, friction: float):
    """The change of a pair's relative velocity that brings its normal part up to ``target`` (zero if it is
    already there), with Coulomb friction on the tangential part."""
    vn = wp.dot(rel, n)
    out = wp.vec3(0.0)
    if vn < target:
        dn = target - vn
        vt = rel - vn * n
        vtl = wp.length(vt)
        out = dn * n
        if vtl > 0.0:
            out = out - wp.min(1.0, friction * dn / vtl) * vt
    return out


@wp.kernel
def resolve_point_triangle(v: wp.array(dtype=wp.vec3), inv_mass: wp.array(dtype=float),
                           tri: wp.array2d(dtype=int), count: wp.array(dtype=int), pair: wp.array2d(dtype=int),
                           weight: wp.array2d(dtype=wp.vec3), normal: wp.array2d(dtype=wp.vec3),
                           gap: wp.array2d(dtype=float), thickness: float, dt: float, friction: float,
                           change: wp.array(dtype=wp.vec3), hits: wp.array(dtype=float)):
    i = wp.tid()
    for s in range(count[i]):
        f = pair[i, s]
        a = tri[f, 0]
        b = tri[f, 1]
        d = tri[f, 2]
        w = weight[i, s]
        rel = v[i] - (w[0] * v[a] + w[1] * v[b] + w[2] * v[d])
        drel = pair_change(rel, normal[i, s], (thickness - gap[i, s]) / dt, friction)
        k = inv_mass[i] + w[0] * w[0] * inv_mass[a] + w[1] * w[1] * inv_mass[b] + w[2] * w[2] * inv_mass[d]
        if wp.length_sq(drel) > 0.0 and k > 0.0:
            drel = drel / k
            wp.atomic_add(change, i, inv_mass[i] * drel)
            wp.atomic_add(change, a, -w[0] * inv_mass[a] * drel)
            wp.atomic_add(change, b, -w[1] * inv_mass[b] * drel)
            wp.atomic_add(change, d, -w[2] * inv_mass[d] * drel)
            wp.atomic_add(hits, i, 1.0)
            wp.atomic_add(hits, a, 1.0)
            wp.atomic_add(hits, b, 1.0)
            wp.atomic_add(hits, d, 1.0)


@wp.kernel
def resolve_edge_edge(v: wp.array(dtype=wp.vec3), inv_mass: wp.array(dtype=float), edge: wp.array2d(dtype=int),
                      count: wp.array(dtype=int), pair: wp.array2d(dtype=int), weight: wp.array2d(dtype=wp.vec3),
                      normal: wp.array2d(dtype=wp.vec3), gap: wp.array2d(dtype=float), thickness: float, dt: float,
                      friction: float, change: wp.array(dtype=wp.vec3), hits: wp.array(dtype=float)):
    e = wp.tid()
    i = edge[e, 0]
    j = edge[e, 1]
    for s in range(count[e]):
        g = pair[e, s]
        k = edge[g, 0]
        l = edge[g, 1]
        st = weight[e, s]
        wi = 1.0 - st[0]
        wj = st[0]
        wk = 1.0 - st[1]
        wl = st[1]
        rel = (wi * v[i] + wj * v[j]) - (wk * v[k] + wl * v[l])
        drel = pair_change(rel, normal[e, s], (thickness - gap[e, s]) / dt, friction)
        m = wi * wi * inv_mass[i] + wj * wj * inv_mass[j] + wk * wk * inv_mass[k] + wl * wl * inv_mass[l]
        if wp.length_sq(drel) > 0.0 and m > 0.0:
            drel = drel / m
            wp.atomic_add(change, i, wi * inv_mass[i] * drel)
            wp.atomic_add(change, j, wj * inv_mass[j] * drel)
            wp.atomic_add(change, k, -wk * inv_mass[k] * drel)
            wp.atomic_add(change, l, -wl * inv_mass[l] * drel)
            wp.atomic_add(hits, i, 1.0)
            wp.atomic_add(hits, j, 1.0)
            wp.atomic_add(hits, k, 1.0)
            wp.atomic_add(hits, l, 1.0)


@wp.kernel
def apply_changes(dt: float, relaxation: float, change: wp.array(dtype=wp.vec3), hits: wp.array(dtype=float),
                  x: wp.array(dtype=wp.vec3), v: wp.array(dtype=wp.vec3)):
    """Each vertex takes ``relaxation`` times the mean of its pairs' velocity changes and moves by h times it;
    accumulators reset."""
    i = wp.tid()
    n = hits[i]
    if n > 0.0:
        dv = change[i] * (relaxation / n)
        v[i] = v[i] + dv
        x[i] = x[i] + dt * dv
    change[i] = wp.vec3(0.0)
    hits[i] = 0.0


# ---------------------------------------------------------------- host side


class SelfCollision:
    """The self-collision of one ``BatchSolver``'s cloths: BVHs, pair slots and the launches of a step.

    ``x0`` is the positions at the start of the step (the solver copies them there before integrating);
    ``x``, ``v`` the integrated positions and velocities, corrected in place.
    """

    def __init__(self, *, x0: wp.array, x: wp.array, v: wp.array, mass: np.ndarray, free: np.ndarray,
                 vertex_cloth: wp.array, tri: wp.array, face_cloth: wp.array, edges: np.ndarray,
                 edge_cloth: np.ndarray, num_cloths: int, thickness: float, friction: float, passes: int,
                 slots: int, device: str):
        self.x0, self.x, self.v = x0, x, v
        self.vertex_cloth, self.tri = vertex_cloth, tri
        self.thickness, self.friction, self.passes = float(thickness), float(friction), int(passes)
        self.reach = REACH * self.thickness
        dev = device
        nv, nf, ne = x.shape[0], tri.shape[0], len(edges)
        with np.errstate(divide="ignore"):
            inv = np.where(free > 0, 1.0 / mass, 0.0)
        self.inv_mass = wp.array(inv.astype(np.float32), dtype=float, device=dev)
        self.edge = wp.array(np.asarray(edges, dtype=np.int32).reshape(-1, 2), dtype=int, device=dev)   # int32: no copy
        self.edge_cloth = wp.array(np.asarray(edge_cloth, dtype=np.int32), dtype=int, device=dev)
        self.face_lo, self.face_hi = wp.zeros(nf, dtype=wp.vec3, device=dev), wp.zeros(nf, dtype=wp.vec3, device=dev)
        self.edge_lo, self.edge_hi = wp.zeros(ne, dtype=wp.vec3, device=dev), wp.zeros(ne, dtype=wp.vec3, device=dev)
        # The trees are built once on the initial boxes (the cloths' rest layout) and refitted every step.
        wp.launch(face_boxes, nf, [x, x, tri, self.reach], [self.face_lo, self.face_hi], device=dev)
        wp.launch(edge_boxes, ne, [x, x, self.edge, 0.5 * self.reach], [self.edge_lo, self.edge_hi], device=dev)
        self.face_bvh = wp.Bvh(self.face_lo, self.face_hi, groups=face_cloth)
        self.edge_bvh = wp.Bvh(self.edge_lo, self.edge_hi, groups=self.edge_cloth)
        # The pair slots are left uninitialised: a step reads only the slots its find kernels filled (a query's
        # first ``count``, all of them once full), and zeroing ~0.6 KB per vertex and edge was a quarter of an
        # adaptive rebuild on the CPU.
        self.pt_count = wp.zeros(nv, dtype=int, device=dev)
        self.pt_pair = wp.empty((nv, slots), dtype=int, device=dev)
        self.pt_weight = wp.empty((nv, slots), dtype=wp.vec3, device=dev)
        self.pt_normal = wp.empty((nv, slots), dtype=wp.vec3, device=dev)
        self.pt_gap = wp.empty((nv, slots), dtype=float, device=dev)
        self.pt_key = wp.empty((nv, slots), dtype=float, device=dev)
        self.ee_count = wp.zeros(ne, dtype=int, device=dev)
        self.ee_pair = wp.empty((ne, slots), dtype=int, device=dev)
        self.ee_weight = wp.empty((ne, slots), dtype=wp.vec3, device=dev)      # (s, t, 0)
        self.ee_normal = wp.empty((ne, slots), dtype=wp.vec3, device=dev)
        self.ee_gap = wp.empty((ne, slots), dtype=float, device=dev)
        self.ee_key = wp.empty((ne, slots), dtype=float, device=dev)
        self.dropped = wp.zeros(num_cloths, dtype=int, device=dev)
        self.change = wp.zeros(nv, dtype=wp.vec3, device=dev)
        self.hits = wp.zeros(nv, dtype=float, device=dev)

    def record(self, launch, cmds: list, dt: float) -> None:
        """Append one step's self-collision to ``cmds`` (``launch(kernel, dim, inputs)`` records a launch)."""
        x0, x, v = self.x0, self.x, self.v
        nv, ne = x.shape[0], self.edge.shape[0]
        launch(face_boxes, self.tri.shape[0], [x0, x, self.tri, self.reach, self.face_lo, self.face_hi])
        launch(edge_boxes, ne, [x0, x, self.edge, 0.5 * self.reach, self.edge_lo, self.edge_hi])
        cmds.append(self.face_bvh.refit)
        cmds.append(self.edge_bvh.refit)
        launch(find_point_triangle, nv, [self.face_bvh.id, x0, x, self.vertex_cloth, self.tri, self.reach,
                                         self.pt_count, self.pt_pair, self.pt_weight, self.pt_normal, self.pt_gap,
                                         self.pt_key, self.dropped])
        launch(find_edge_edge, ne, [self.edge_bvh.id, x0, x, self.edge_cloth, self.edge, self.reach, self.ee_count,
                                    self.ee_pair, self.ee_weight, self.ee_normal, self.ee_gap, self.ee_key,
                                    self.dropped])
        for _ in range(self.passes):
            launch(resolve_point_triangle, nv, [v, self.inv_mass, self.tri, self.pt_count, self.pt_pair,
                                                self.pt_weight, self.pt_normal, self.pt_gap, self.thickness, dt,
                                                self.friction, self.change, self.hits])
            launch(resolve_edge_edge, ne, [v, self.inv_mass, self.edge, self.ee_count, self.ee_pair,
                                           self.ee_weight, self.ee_normal, self.ee_gap, self.thickness, dt,
                                           self.friction, self.change, self.hits])
            launch(apply_changes, nv, [dt, RELAXATION, self.change, self.hits, x, v])

    def dropped_pairs(self) -> np.ndarray:
        """Per cloth: the pairs found so far beyond a full vertex's or edge's slots (the farthest; not resolved)."""
        return self.dropped.numpy().copy()
