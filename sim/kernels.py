"""Warp kernels of the batched implicit cloth solver (one module, compiled once, shared by all callers).

Everything is batched: particles, faces and hinges of many cloths live in one
array set, each element carrying its cloth id, and per-cloth quantities
(material tables, wind, CG dot products) are indexed by that id. See
``sim.solver`` for the algorithm these kernels implement.

Conventions: ``free`` is 1 for a simulated vertex and 0 for a pinned one (pinned
rows of the linear system are filtered out); dot products of the conjugate
gradient are accumulated per cloth with atomic adds into ``acc[iteration, cloth]``.
A cloth whose CG has stopped (``active[cloth] == 0``: converged, or a step would
divide by a vanishing number) is skipped by every CG kernel, so the step stays a
fixed list of launches (CUDA-graph capture) while each cloth stops on its own.
"""

from __future__ import annotations

import warp as wp

PI = 3.14159265358979


# ---------------------------------------------------------------- material model (Wang et al. 2011)

@wp.func
def wang_stretch_k(table: wp.array2d(dtype=float), c: int, c00: float, c01: float, c11: float):
    """(k0, k1, k2, k3) at right Cauchy-Green tensor C = [[c00, c01], [c01, c11]], doubled, clamped >= 0."""
    lmax = 0.5 * (c00 + c11) + wp.sqrt(0.25 * (c00 - c11) * (c00 - c11) + c01 * c01)
    vx = lmax - c11
    vy = c01
    if c01 == 0.0:
        if c00 >= c11:
            vx = 1.0
            vy = 0.0
        else:
            vx = 0.0
            vy = 1.0
    theta = wp.abs(wp.atan2(vy, vx))
    x = wp.clamp(theta / (PI / 8.0), 0.0, 4.0 - 1.0e-6)
    ai = int(wp.floor(x))
    ta = x - float(ai)
    s = wp.clamp(6.0 * (wp.sqrt(wp.max(lmax, 0.0)) - 1.0), 0.0, 1.0 - 1.0e-6)
    k = wp.vec4()
    for l in range(4):
        high = (1.0 - ta) * table[c, (1 + ai) * 4 + l] + ta * table[c, (2 + ai) * 4 + l]
        k[l] = 2.0 * wp.max((1.0 - s) * table[c, l] + s * high, 0.0)
    return k


@wp.func
def wang_bend_ke(table: wp.array2d(dtype=float), c: int, curvature: float, y: float):
    """ke at curvature (1/m) for an edge whose direction coordinate is y in [0, 2] (0, 45, 90 deg rows)."""
    v = wp.clamp(0.1 * curvature, 0.0, 4.0)
    vi = wp.min(int(wp.floor(v)), 3)
    tv = v - float(vi)
    bi = wp.min(int(wp.floor(y)), 1)
    tb = y - float(bi)
    ke = ((1.0 - tb) * (1.0 - tv) * table[c, bi * 5 + vi] + (1.0 - tb) * tv * table[c, bi * 5 + vi + 1]
          + tb * (1.0 - tv) * table[c, (bi + 1) * 5 + vi] + tb * tv * table[c, (bi + 1) * 5 + vi + 1])
    return wp.max(ke, 0.0)


# ---------------------------------------------------------------- per-step preparation

@wp.func
def add_vertex_block(block: wp.array(dtype=wp.mat33), diag: wp.array(dtype=wp.vec3), i: int, b: wp.mat33):
    """Adds an element's 3 x 3 stiffness block to vertex i's block and its diagonal to the Jacobi diagonal."""
    wp.atomic_add(block, i, b)
    wp.atomic_add(diag, i, wp.vec3(b[0, 0], b[1, 1], b[2, 2]))


@wp.kernel
def begin_step(mass: wp.array(dtype=float), gravity: wp.vec3,
               force: wp.array(dtype=wp.vec3), diag: wp.array(dtype=wp.vec3), kv: wp.array(dtype=wp.vec3),
               block: wp.array(dtype=wp.mat33)):
    i = wp.tid()
    force[i] = mass[i] * gravity
    diag[i] = wp.vec3(0.0)
    kv[i] = wp.vec3(0.0)
    block[i] = wp.mat33(0.0)


@wp.kernel
def face_prepare(x: wp.array(dtype=wp.vec3), v: wp.array(dtype=wp.vec3), tri: wp.array2d(dtype=int),
                 dm_inv: wp.array(dtype=wp.mat22), area: wp.array(dtype=float), cloth: wp.array(dtype=int),
                 stretch: wp.array2d(dtype=float), wind: wp.array(dtype=wp.vec3),
                 air_density: float, air_drag: float,
                 force: wp.array(dtype=wp.vec3), diag: wp.array(dtype=wp.vec3),
                 f0_out: wp.array(dtype=wp.vec3), f1_out: wp.array(dtype=wp.vec3),
                 kmat_out: wp.array(dtype=wp.vec4), smat_out: wp.array(dtype=wp.vec3),
                 block: wp.array(dtype=wp.mat33)):
    """Stretching force (Wang), wind force, the Jacobi diagonal and the 3 x 3 vertex blocks of the stiffness
    (the block-Jacobi preconditioner), and the per-face data the Hessian-vector product reuses: F's columns,
    the PSD-projected stiffness and stress."""
    f = wp.tid()
    c = cloth[f]
    i = tri[f, 0]
    j = tri[f, 1]
    k = tri[f, 2]
    a = area[f]
    d = dm_inv[f]
    e1 = x[j] - x[i]
    e2 = x[k] - x[i]
    f0 = e1 * d[0, 0] + e2 * d[1, 0]
    f1 = e1 * d[0, 1] + e2 * d[1, 1]
    c00 = wp.dot(f0, f0)
    c11 = wp.dot(f1, f1)
    c01 = wp.dot(f0, f1)
    g00 = 0.5 * (c00 - 1.0)
    g11 = 0.5 * (c11 - 1.0)
    g01 = 0.5 * c01
    kk = wang_stretch_k(stretch, c, c00, c01, c11)
    # second Piola-Kirchhoff stress (times area): dW/dG with k held constant
    s00 = a * (kk[0] * g00 + kk[1] * g11)
    s11 = a * (kk[1] * g00 + kk[2] * g11)
    s01 = a * kk[3] * g01 * 0.5
    dw0 = s00 * f0 + s01 * f1
    dw1 = s01 * f0 + s11 * f1
    # coefficients of vertex i, j, k in F's columns
    cj0 = d[0, 0]
    cj1 = d[0, 1]
    ck0 = d[1, 0]
    ck1 = d[1, 1]
    ci0 = -(cj0 + ck0)
    ci1 = -(cj1 + ck1)

    # wind: pressure on the normal component of the relative air velocity, drag on the tangential one
    nrm = wp.cross(e1, e2)
    nl = wp.length(nrm)
    fw = wp.vec3(0.0)
    if nl > 0.0:
        n = nrm / nl
        w = wind[c] - (v[i] + v[j] + v[k]) / 3.0
        wn = wp.dot(w, n)
        fw = (air_density * a * wp.abs(wn) * wn * n + air_drag * a * (w - wn * n)) / 3.0

    wp.atomic_add(force, i, fw - (ci0 * dw0 + ci1 * dw1))
    wp.atomic_add(force, j, fw - (cj0 * dw0 + cj1 * dw1))
    wp.atomic_add(force, k, fw - (ck0 * dw0 + ck1 * dw1))

    # Gauss-Newton stiffness with the 2x2 (k0, k1; k1, k2) block made PSD ...
    kb = wp.sqrt(kk[0] * kk[2])
    k1 = wp.clamp(kk[1], -kb, kb)
    km = wp.vec4(a * kk[0], a * k1, a * kk[2], a * kk[3])
    # ... plus the geometric stiffness S (x) I with S projected onto PSD matrices
    mid = 0.5 * (s00 + s11)
    rad = wp.sqrt(0.25 * (s00 - s11) * (s00 - s11) + s01 * s01)
    lmin = mid - rad
    lmax = mid + rad
    p00 = s00
    p01 = s01
    p11 = s11
    if lmax <= 0.0:
        p00 = 0.0
        p01 = 0.0
        p11 = 0.0
    elif lmin < 0.0:
        ex = lmax - s11
        ey = s01
        el = wp.sqrt(ex * ex + ey * ey)
        if el > 0.0:
            ex = ex / el
            ey = ey / el
        else:
            ex = 1.0
            ey = 0.0
            if s11 > s00:
                ex = 0.0
                ey = 1.0
        p00 = lmax * ex * ex
        p01 = lmax * ex * ey
        p11 = lmax * ey * ey
    f0_out[f] = f0
    f1_out[f] = f1
    kmat_out[f] = km
    smat_out[f] = wp.vec3(p00, p01, p11)

    # each vertex's 3 x 3 block of the (projected) stiffness, and its diagonal (the Jacobi preconditioner's)
    o00 = wp.outer(f0, f0)
    o11 = wp.outer(f1, f1)
    o01 = 0.5 * (wp.outer(f0, f1) + wp.outer(f1, f0))
    eye = wp.identity(n=3, dtype=float)
    b00 = km[0] * o00 + 0.25 * km[3] * o11 + p00 * eye
    b01 = (km[1] + 0.25 * km[3]) * o01 + p01 * eye
    b11 = km[2] * o11 + 0.25 * km[3] * o00 + p11 * eye
    add_vertex_block(block, diag, i, ci0 * ci0 * b00 + 2.0 * ci0 * ci1 * b01 + ci1 * ci1 * b11)
    add_vertex_block(block, diag, j, cj0 * cj0 * b00 + 2.0 * cj0 * cj1 * b01 + cj1 * cj1 * b11)
    add_vertex_block(block, diag, k, ck0 * ck0 * b00 + 2.0 * ck0 * ck1 * b01 + ck1 * ck1 * b11)


@wp.kernel
def hinge_prepare(x: wp.array(dtype=wp.vec3), hinge: wp.array2d(dtype=int), rest_length: wp.array(dtype=float),
                  rest_area: wp.array(dtype=float), direction: wp.array(dtype=float), cloth: wp.array(dtype=int),
                  bend: wp.array2d(dtype=float),
                  force: wp.array(dtype=wp.vec3), diag: wp.array(dtype=wp.vec3),
                  stiffness_out: wp.array(dtype=float), grad_out: wp.array2d(dtype=wp.vec3),
                  block: wp.array(dtype=wp.mat33)):
    """Bending force (Wang) of one hinge, E = kb/2 theta^2 with kb = ke l^2 / (4 (A0 + A1)),
    and its Gauss-Newton data (kb and the dihedral-angle gradient) for the Hessian-vector product."""
    h = wp.tid()
    x0 = x[hinge[h, 0]]
    x1 = x[hinge[h, 1]]
    x2 = x[hinge[h, 2]]
    x3 = x[hinge[h, 3]]
    e = x1 - x0
    le = wp.length(e)
    na = wp.cross(e, x2 - x0)
    nb = wp.cross(x3 - x0, e)
    la = wp.length(na)
    lb = wp.length(nb)
    zero = wp.vec3(0.0)
    stiffness_out[h] = 0.0
    for q in range(4):
        grad_out[h, q] = zero
    if le > 1.0e-9 and la > 1.0e-12 and lb > 1.0e-12:
        na = na / la
        nb = nb / lb
        theta = wp.atan2(wp.dot(wp.cross(na, nb), e) / le, wp.dot(na, nb))
        # gradient of the signed dihedral angle (opposite vertices along -n / height)
        g2 = -na * (le / la)
        g3 = -nb * (le / lb)
        a2 = wp.dot(x2 - x0, e) / (le * le)
        a3 = wp.dot(x3 - x0, e) / (le * le)
        g0 = -(1.0 - a2) * g2 - (1.0 - a3) * g3
        g1 = -a2 * g2 - a3 * g3
        l0 = rest_length[h]
        asum = rest_area[h]
        ke = wang_bend_ke(bend, cloth[h], wp.abs(theta) * l0 / asum, direction[h])
        kb = ke * l0 * l0 / (4.0 * asum)
        s = -kb * theta
        wp.atomic_add(force, hinge[h, 0], s * g0)
        wp.atomic_add(force, hinge[h, 1], s * g1)
        wp.atomic_add(force, hinge[h, 2], s * g2)
        wp.atomic_add(force, hinge[h, 3], s * g3)
        add_vertex_block(block, diag, hinge[h, 0], kb * wp.outer(g0, g0))
        add_vertex_block(block, diag, hinge[h, 1], kb * wp.outer(g1, g1))
        add_vertex_block(block, diag, hinge[h, 2], kb * wp.outer(g2, g2))
        add_vertex_block(block, diag, hinge[h, 3], kb * wp.outer(g3, g3))
        stiffness_out[h] = kb
        grad_out[h, 0] = g0
        grad_out[h, 1] = g1
        grad_out[h, 2] = g2
        grad_out[h, 3] = g3


# ---------------------------------------------------------------- Hessian-vector products

@wp.func
def face_product(f: int, p: wp.array(dtype=wp.vec3), tri: wp.array2d(dtype=int), dm_inv: wp.array(dtype=wp.mat22),
                 f0_in: wp.array(dtype=wp.vec3), f1_in: wp.array(dtype=wp.vec3), kmat: wp.array(dtype=wp.vec4),
                 smat: wp.array(dtype=wp.vec3), scale: float, out: wp.array(dtype=wp.vec3)):
    """out += scale * K_stretch p over face ``f``'s vertices; returns the face's share of scale * p.K p."""
    i = tri[f, 0]
    j = tri[f, 1]
    k = tri[f, 2]
    d = dm_inv[f]
    cj0 = d[0, 0]
    cj1 = d[0, 1]
    ck0 = d[1, 0]
    ck1 = d[1, 1]
    ci0 = -(cj0 + ck0)
    ci1 = -(cj1 + ck1)
    pi = p[i]
    pj = p[j]
    pk = p[k]
    df0 = ci0 * pi + cj0 * pj + ck0 * pk
    df1 = ci1 * pi + cj1 * pj + ck1 * pk
    f0 = f0_in[f]
    f1 = f1_in[f]
    km = kmat[f]
    sm = smat[f]
    dg00 = wp.dot(f0, df0)
    dg11 = wp.dot(f1, df1)
    dg01 = 0.5 * (wp.dot(f0, df1) + wp.dot(f1, df0))
    ds00 = km[0] * dg00 + km[1] * dg11
    ds11 = km[1] * dg00 + km[2] * dg11
    ds01 = 0.5 * km[3] * dg01
    g0 = ds00 * f0 + ds01 * f1 + sm[0] * df0 + sm[1] * df1
    g1 = ds01 * f0 + ds11 * f1 + sm[1] * df0 + sm[2] * df1
    ki = scale * (ci0 * g0 + ci1 * g1)
    kj = scale * (cj0 * g0 + cj1 * g1)
    kk = scale * (ck0 * g0 + ck1 * g1)
    wp.atomic_add(out, i, ki)
    wp.atomic_add(out, j, kj)
    wp.atomic_add(out, k, kk)
    return wp.dot(pi, ki) + wp.dot(pj, kj) + wp.dot(pk, kk)


@wp.func
def hinge_product(h: int, p: wp.array(dtype=wp.vec3), hinge: wp.array2d(dtype=int), stiffness: wp.array(dtype=float),
                  grad: wp.array2d(dtype=wp.vec3), scale: float, out: wp.array(dtype=wp.vec3)):
    """out += scale * kb g g^T p over hinge ``h``'s vertices (Gauss-Newton bending stiffness); returns the hinge's
    share of scale * p.K p."""
    kb = stiffness[h]
    if kb <= 0.0:
        return 0.0
    s = float(0.0)
    for q in range(4):
        s += wp.dot(grad[h, q], p[hinge[h, q]])
    w = scale * kb * s
    for q in range(4):
        wp.atomic_add(out, hinge[h, q], w * grad[h, q])
    return w * s


@wp.kernel
def face_hessian_product(p: wp.array(dtype=wp.vec3), tri: wp.array2d(dtype=int), dm_inv: wp.array(dtype=wp.mat22),
                         cloth: wp.array(dtype=int), f0_in: wp.array(dtype=wp.vec3), f1_in: wp.array(dtype=wp.vec3),
                         kmat: wp.array(dtype=wp.vec4), smat: wp.array(dtype=wp.vec3), scale: float,
                         active: wp.array(dtype=int), out: wp.array(dtype=wp.vec3), dots: wp.array(dtype=float)):
    """out += scale * K_stretch p, and dots[f] = this face's share of scale * p.K p (``cloth_chunk_sum`` adds
    those up a cloth); stopped cloths skipped."""
    f = wp.tid()
    if active[cloth[f]] == 0:
        return
    dots[f] = face_product(f, p, tri, dm_inv, f0_in, f1_in, kmat, smat, scale, out)


@wp.kernel
def hinge_hessian_product(p: wp.array(dtype=wp.vec3), hinge: wp.array2d(dtype=int), cloth: wp.array(dtype=int),
                          stiffness: wp.array(dtype=float), grad: wp.array2d(dtype=wp.vec3), scale: float,
                          active: wp.array(dtype=int), out: wp.array(dtype=wp.vec3), dots: wp.array(dtype=float)):
    """out += scale * kb g g^T p (Gauss-Newton bending stiffness), dots[h] = this hinge's share of scale * p.K p."""
    h = wp.tid()
    if active[cloth[h]] == 0:
        return
    dots[h] = hinge_product(h, p, hinge, stiffness, grad, scale, out)


# A cloth's vertices and elements are contiguous in a batch, so a per-cloth sum (the CG's dot products) is a
# segmented sum. One thread adds up a chunk of CLOTH_CHUNK consecutive values of one cloth and adds that into the
# cloth's slot: where every element added
# into the slot itself, the thousands of adds to one address a cloth made the Hessian products of an adaptive
# batch 7.6-10x dearer than the products alone (benchmarks/results/sim_adaptive_steps-cuda-wind-n432-atomics.json).
CLOTH_CHUNK = 64


@wp.kernel
def cloth_chunk_sum(values: wp.array(dtype=float), start: wp.array(dtype=int), end: wp.array(dtype=int),
                    cloth: wp.array(dtype=int), slot: int, active: wp.array(dtype=int), acc: wp.array2d(dtype=float)):
    """acc[slot, cloth[t]] += values[start[t]:end[t]].sum(), one chunk a thread; stopped cloths skipped (their
    elements' values were not written this time)."""
    t = wp.tid()
    c = cloth[t]
    if active[c] == 0:
        return
    s = float(0.0)
    for e in range(start[t], end[t]):
        s += values[e]
    wp.atomic_add(acc, slot, c, s)


# ---------------------------------------------------------------- conjugate gradient on (M (1 + h a) + h^2 K) dv = b

# Float32 floors of the CG scalars. Past convergence r.z and p.A p shrink into the subnormal range
# (below 1.2e-38), where their quotients alpha and beta are noise and the positions go to NaN; a cloth
# stops before a division by anything under CG_FLOOR, or once r.z has fallen by CG_ROUNDOFF (a relative
# residual of about 1e-7, float32's resolution: further iterations only add rounding noise).
CG_FLOOR = wp.constant(1.0e-30)
CG_ROUNDOFF = wp.constant(1.0e-14)


@wp.func
def cg_step_ok(pap: float):
    """Whether alpha = r.z / p.A p may be taken (False for NaN too)."""
    return pap > CG_FLOOR


@wp.kernel
def cg_start(force: wp.array(dtype=wp.vec3), v: wp.array(dtype=wp.vec3), kv: wp.array(dtype=wp.vec3),
             mass: wp.array(dtype=float), free: wp.array(dtype=float), cloth: wp.array(dtype=int),
             dt: float, damping: float, diag: wp.array(dtype=wp.vec3),
             dv: wp.array(dtype=wp.vec3), r: wp.array(dtype=wp.vec3), z: wp.array(dtype=wp.vec3),
             p: wp.array(dtype=wp.vec3), ap: wp.array(dtype=wp.vec3),
             rz: wp.array2d(dtype=float), pap: wp.array2d(dtype=float), rr: wp.array2d(dtype=float),
             use_block: int, block: wp.array(dtype=wp.mat33)):
    """Right-hand side b = h (f - a M v) - h^2 K v, the preconditioner (Jacobi: diag becomes its inverse;
    ``use_block``: block becomes the inverse of the vertex's 3 x 3 block of A = M + h^2 K), first search
    direction, and the first dot products (r.z, p.M p, r.r)."""
    i = wp.tid()
    c = cloth[i]
    m_eff = mass[i] * (1.0 + dt * damping)
    b = dt * (force[i] - damping * mass[i] * v[i]) - dt * dt * kv[i]
    ri = free[i] * b
    dinv = wp.cw_div(wp.vec3(1.0), wp.vec3(m_eff) + dt * dt * diag[i])
    zi = wp.cw_mul(ri, dinv)
    if use_block != 0:
        # SPD: the element blocks are PSD (Gauss-Newton, projected stress) and m_eff > 0
        pinv = wp.inverse(m_eff * wp.identity(n=3, dtype=float) + dt * dt * block[i])
        block[i] = pinv
        zi = pinv * ri
    diag[i] = dinv
    dv[i] = wp.vec3(0.0)
    r[i] = ri
    z[i] = zi
    p[i] = zi
    ap[i] = m_eff * zi
    wp.atomic_add(rz, 0, c, wp.dot(ri, zi))
    wp.atomic_add(pap, 0, c, m_eff * wp.dot(zi, zi))
    wp.atomic_add(rr, 0, c, wp.dot(ri, ri))


@wp.kernel
def cg_update(mass: wp.array(dtype=float), free: wp.array(dtype=float), cloth: wp.array(dtype=int),
              dinv: wp.array(dtype=wp.vec3), p: wp.array(dtype=wp.vec3), ap: wp.array(dtype=wp.vec3),
              slot: int, active: wp.array(dtype=int), dv: wp.array(dtype=wp.vec3), r: wp.array(dtype=wp.vec3),
              z: wp.array(dtype=wp.vec3), rz: wp.array2d(dtype=float), pap: wp.array2d(dtype=float),
              vrz: wp.array(dtype=float), vrr: wp.array(dtype=float), use_block: int,
              pinv: wp.array(dtype=wp.mat33)):
    """dv += alpha p, r -= alpha A p, z = P r, and each vertex's share of the next r.z and r.r in vrz, vrr
    (``cloth_chunk_sum`` adds them up a cloth; running cloths only)."""
    i = wp.tid()
    c = cloth[i]
    if active[c] == 0:
        return
    den = pap[slot, c]
    if not cg_step_ok(den):
        vrz[i] = 0.0
        vrr[i] = 0.0
        return
    alpha = rz[slot, c] / den
    dv[i] = dv[i] + alpha * p[i]
    ri = r[i] - alpha * free[i] * ap[i]
    zi = wp.vec3(0.0)
    if use_block != 0:
        zi = pinv[i] * ri
    else:
        zi = wp.cw_mul(ri, dinv[i])
    r[i] = ri
    z[i] = zi
    vrz[i] = wp.dot(ri, zi)
    vrr[i] = wp.dot(ri, ri)


@wp.kernel
def cg_direction(mass: wp.array(dtype=float), cloth: wp.array(dtype=int), dt: float, damping: float,
                 z: wp.array(dtype=wp.vec3), slot: int, active: wp.array(dtype=int), p: wp.array(dtype=wp.vec3),
                 ap: wp.array(dtype=wp.vec3), rz: wp.array2d(dtype=float), vpap: wp.array(dtype=float)):
    """p = z + beta p; starts A p with its mass part, and each vertex's share of that part of p.A p in vpap
    (running cloths: ``cg_check`` has made sure their r.z is well above underflow)."""
    i = wp.tid()
    c = cloth[i]
    if active[c] == 0:
        return
    beta = rz[slot + 1, c] / rz[slot, c]
    m_eff = mass[i] * (1.0 + dt * damping)
    pi = z[i] + beta * p[i]
    p[i] = pi
    ap[i] = m_eff * pi
    vpap[i] = m_eff * wp.dot(pi, pi)


@wp.kernel
def cg_reset(active: wp.array(dtype=int), iterations: wp.array(dtype=int), residual: wp.array(dtype=float)):
    """Per cloth, at the start of a step: every cloth's CG runs."""
    c = wp.tid()
    active[c] = 1
    iterations[c] = 0
    residual[c] = 0.0


@wp.kernel
def cg_check(slot: int, tol2: float, rz: wp.array2d(dtype=float), pap: wp.array2d(dtype=float),
             rr: wp.array2d(dtype=float), active: wp.array(dtype=int), iterations: wp.array(dtype=int),
             residual: wp.array(dtype=float)):
    """Per cloth, after ``slot`` CG updates: count the update if it was taken, keep r.r as the cloth's
    residual, and stop the cloth once r.r <= tol2 * r0.r0 or r.z is too small to divide by."""
    c = wp.tid()
    if active[c] == 0:
        return
    if slot > 0:
        if not cg_step_ok(pap[slot - 1, c]):       # cg_update skipped it: p.A p vanished
            active[c] = 0
            return
        iterations[c] = slot
    r2 = rr[slot, c]
    residual[c] = r2
    rzc = rz[slot, c]
    if not (r2 > tol2 * rr[0, c] and rzc > CG_FLOOR and rzc > CG_ROUNDOFF * rz[0, c]):
        active[c] = 0


@wp.kernel
def cg_finish(rr: wp.array2d(dtype=float), iterations: wp.array(dtype=int), residual: wp.array(dtype=float),
              iteration_sum: wp.array(dtype=float), iteration_max: wp.array(dtype=int),
              residual_max: wp.array(dtype=float)):
    """Per cloth, after the solve: accumulate the step's iteration count and its final relative residual
    |r| / |r0| into the cloth's running statistics (a NaN residual is kept, not hidden by max)."""
    c = wp.tid()
    n = iterations[c]
    iteration_sum[c] = iteration_sum[c] + float(n)
    iteration_max[c] = wp.max(iteration_max[c], n)
    r0 = rr[0, c]
    rel = float(0.0)
    if r0 > 0.0:
        rel = wp.sqrt(residual[c] / r0)
    if not (rel <= residual_max[c]):
        residual_max[c] = rel


@wp.kernel
def integrate(dv: wp.array(dtype=wp.vec3), free: wp.array(dtype=float), dt: float,
              x: wp.array(dtype=wp.vec3), v: wp.array(dtype=wp.vec3)):
    i = wp.tid()
    vi = free[i] * (v[i] + dv[i])
    v[i] = vi
    x[i] = x[i] + dt * vi


# ---------------------------------------------------------------- kinematic arm (two capsules) and the clock

@wp.struct
class Arm:
    """A capsule arm: upper arm shoulder -> elbow (fixed), forearm elbow -> hand rotating about the elbow
    around ``axis`` at ``omega`` rad/s from time ``t0`` until it has turned ``max_angle``."""
    active: int
    shoulder: wp.vec3
    elbow: wp.vec3
    forearm: wp.vec3          # elbow -> hand at t0 (length = forearm length)
    axis: wp.vec3             # unit rotation axis
    radius: float
    omega: float
    max_angle: float
    t0: float


@wp.func
def closest_on_segment(x: wp.vec3, a: wp.vec3, b: wp.vec3):
    ab = b - a
    t = wp.clamp(wp.dot(x - a, ab) / wp.max(wp.dot(ab, ab), 1.0e-12), 0.0, 1.0)
    return a + t * ab


@wp.func
def surface_velocity(arm: Arm, moving: float, seg: int, c: wp.vec3, n: wp.vec3, reach: float):
    """Velocity of the arm's contact surface point c + reach n (c on segment ``seg``'s axis): the forearm
    (seg 1) turns rigidly about the elbow, the upper arm is still."""
    u = wp.vec3(0.0)
    if seg == 1:
        u = wp.cross(moving * arm.omega * arm.axis, c + reach * n - arm.elbow)
    return u


@wp.kernel
def collide_arm(arms: wp.array(dtype=Arm), cloth: wp.array(dtype=int), free: wp.array(dtype=float),
                clock: wp.array(dtype=float), thickness: float, friction: float,
                x: wp.array(dtype=wp.vec3), v: wp.array(dtype=wp.vec3)):
    """Push vertices out of the arm's capsules (plus ``thickness``) and make their velocity relative to the
    arm surface non-penetrating, with Coulomb friction: the tangential slip loses at most
    ``friction`` times the normal velocity change."""
    i = wp.tid()
    arm = arms[cloth[i]]
    if arm.active == 0 or free[i] == 0.0:
        return
    t = clock[0]
    angle = wp.clamp(arm.omega * (t - arm.t0), 0.0, arm.max_angle)
    moving = float(0.0)
    if t > arm.t0 and angle < arm.max_angle:
        moving = 1.0
    q = wp.quat_from_axis_angle(arm.axis, angle)
    hand = arm.elbow + wp.quat_rotate(q, arm.forearm)
    xi = x[i]
    vi = v[i]
    for s in range(2):
        a = arm.shoulder
        b = arm.elbow
        if s == 1:
            a = arm.elbow
            b = hand
        c = closest_on_segment(xi, a, b)
        d = xi - c
        dl = wp.length(d)
        reach = arm.radius + thickness
        if dl < reach and dl > 1.0e-9:
            n = d / dl
            xi = c + n * reach
            surface_v = surface_velocity(arm, moving, s, c, n, reach)
            rel = vi - surface_v
            vn = wp.dot(rel, n)
            if vn < 0.0:
                vt = rel - vn * n
                vtl = wp.length(vt)
                scale = float(0.0)
                if vtl > 0.0:
                    scale = wp.max(0.0, 1.0 - friction * (-vn) / vtl)
                rel = vt * scale
            vi = surface_v + rel
    x[i] = xi
    v[i] = vi


@wp.kernel
def advance_clock(clock: wp.array(dtype=float), dt: float):
    clock[0] = clock[0] + dt


@wp.func
def segment_params(p0: wp.vec3, p1: wp.vec3, a: wp.vec3, b: wp.vec3):
    """Parameters (s on p0-p1, t on a-b) of the closest points of two segments (Ericson, 5.1.9)."""
    d1 = p1 - p0
    d2 = b - a
    r = p0 - a
    aa = wp.dot(d1, d1)
    ee = wp.dot(d2, d2)
    ff = wp.dot(d2, r)
    cc = wp.dot(d1, r)
    bb = wp.dot(d1, d2)
    den = aa * ee - bb * bb
    s = float(0.0)
    if den > 1.0e-12 * aa * ee:
        s = wp.clamp((bb * ff - cc * ee) / den, 0.0, 1.0)
    t = (bb * s + ff) / wp.max(ee, 1.0e-12)
    if t < 0.0:
        t = 0.0
        s = wp.clamp(-cc / wp.max(aa, 1.0e-12), 0.0, 1.0)
    elif t > 1.0:
        t = 1.0
        s = wp.clamp((bb - cc) / wp.max(aa, 1.0e-12), 0.0, 1.0)
    return wp.vec2(s, t)


@wp.kernel
def collide_arm_edges(arms: wp.array(dtype=Arm), edge: wp.array2d(dtype=int), cloth: wp.array(dtype=int),
                      free: wp.array(dtype=float), clock: wp.array(dtype=float), thickness: float, friction: float,
                      x: wp.array(dtype=wp.vec3), v: wp.array(dtype=wp.vec3),
                      dx: wp.array(dtype=wp.vec3), dvel: wp.array(dtype=wp.vec3), count: wp.array(dtype=float)):
    """Edge-capsule contact: where the inside of a cloth edge is closer than radius + thickness to a capsule's
    axis (the capsule fits between the edge's two vertices), push the edge out along the normal and make the
    velocity of its closest point non-penetrating with Coulomb friction; the corrections are split between the
    two vertices by their barycentric weights and accumulated (Jacobi) for ``apply_corrections``."""
    e = wp.tid()
    i = edge[e, 0]
    j = edge[e, 1]
    arm = arms[cloth[i]]
    if arm.active == 0:
        return
    t = clock[0]
    angle = wp.clamp(arm.omega * (t - arm.t0), 0.0, arm.max_angle)
    moving = float(0.0)
    if t > arm.t0 and angle < arm.max_angle:
        moving = 1.0
    q = wp.quat_from_axis_angle(arm.axis, angle)
    hand = arm.elbow + wp.quat_rotate(q, arm.forearm)
    xi = x[i]
    xj = x[j]
    wi = free[i]
    wj = free[j]
    reach = arm.radius + thickness
    for seg in range(2):
        a = arm.shoulder
        b = arm.elbow
        if seg == 1:
            a = arm.elbow
            b = hand
        st = segment_params(xi, xj, a, b)
        s = st[0]
        if s > 0.0 and s < 1.0:          # an end point is the vertex pass's business
            p = xi + s * (xj - xi)
            c = a + st[1] * (b - a)
            d = p - c
            dl = wp.length(d)
            if dl < reach and dl > 1.0e-9:
                n = d / dl
                bi = (1.0 - s) * wi
                bj = s * wj
                norm = bi * bi + bj * bj
                if norm > 0.0:
                    lam = (reach - dl) / norm
                    wp.atomic_add(dx, i, bi * lam * n)
                    wp.atomic_add(dx, j, bj * lam * n)
                    surface_v = surface_velocity(arm, moving, seg, c, n, reach)
                    rel = (1.0 - s) * v[i] + s * v[j] - surface_v
                    vn = wp.dot(rel, n)
                    dvp = wp.vec3(0.0)
                    if vn < 0.0:
                        vt = rel - vn * n
                        vtl = wp.length(vt)
                        scale = float(0.0)
                        if vtl > 0.0:
                            scale = wp.max(0.0, 1.0 - friction * (-vn) / vtl)
                        dvp = vt * scale - rel          # wanted change of the closest point's velocity
                    wp.atomic_add(dvel, i, (bi / norm) * dvp)
                    wp.atomic_add(dvel, j, (bj / norm) * dvp)
                    wp.atomic_add(count, i, 1.0)
                    wp.atomic_add(count, j, 1.0)


@wp.kernel
def apply_corrections(dx: wp.array(dtype=wp.vec3), dvel: wp.array(dtype=wp.vec3), count: wp.array(dtype=float),
                      x: wp.array(dtype=wp.vec3), v: wp.array(dtype=wp.vec3)):
    """Average the accumulated contact corrections of each vertex and apply them; reset the accumulators."""
    i = wp.tid()
    n = count[i]
    if n > 0.0:
        x[i] = x[i] + dx[i] / n
        v[i] = v[i] + dvel[i] / n
    dx[i] = wp.vec3(0.0)
    dvel[i] = wp.vec3(0.0)
    count[i] = 0.0


# ---------------------------------------------------------------- arm contact inside the solve (Baraff & Witkin 1998)

@wp.func
def forearm_hand(arm: Arm, t: float):
    angle = wp.clamp(arm.omega * (t - arm.t0), 0.0, arm.max_angle)
    return arm.elbow + wp.quat_rotate(wp.quat_from_axis_angle(arm.axis, angle), arm.forearm)


@wp.func
def forearm_moving(arm: Arm, t: float):
    angle = wp.clamp(arm.omega * (t - arm.t0), 0.0, arm.max_angle)
    moving = float(0.0)
    if t > arm.t0 and angle < arm.max_angle:
        moving = 1.0
    return moving


@wp.kernel
def contact_prepare(arms: wp.array(dtype=Arm), cloth: wp.array(dtype=int), free: wp.array(dtype=float),
                    clock: wp.array(dtype=float), thickness: float, tolerance: float, dt: float,
                    friction: float, slip_velocity: float,
                    x: wp.array(dtype=wp.vec3), v: wp.array(dtype=wp.vec3), released: wp.array(dtype=int),
                    jn_prev: wp.array(dtype=float),
                    cn: wp.array(dtype=wp.vec3), y: wp.array(dtype=wp.vec3), vy: wp.array(dtype=wp.vec3),
                    fc: wp.array(dtype=float), fb: wp.array(dtype=wp.vec3), recover: wp.array(dtype=wp.vec3)):
    """Contacts of this step, as velocity constraints of the implicit solve: a free vertex within
    ``tolerance`` of an arm capsule's contact surface (radius + thickness) that is not moving away from it, or
    that pushed on the arm in the previous step (``jn_prev`` > 0: a contact persists until its impulse comes out
    adhesive), gets its normal velocity prescribed: the surface's normal velocity plus what closes any
    penetration in one step (``recover``, taken back off after the step by ``contact_recovered``).
    ``cn`` is the constraint normal (zero: unconstrained), ``y`` the prescribed velocity change along it
    (the solve starts from dv = y and never changes dv along ``cn``), ``vy`` = v + y. A vertex whose
    contact force came out adhesive in the previous step (``released``) is left free for this one.

    Friction, regularised Coulomb, implicit: the contact's tangential velocity relative to the surface,
    w = P (v + dv - u) with P = I - n n^T, meets the impulse -c w, c = friction J_n / max(|P (v - u)|,
    ``slip_velocity``), J_n the contact's normal impulse of the previous step (``jn_prev``). Sliding, that
    is Coulomb's friction J_n against the slip; at rest, a stiff tangential damping that holds
    the vertex (creeping slower than ``slip_velocity``) as long as the pull stays inside the friction cone.
    ``fc`` = c goes on the vertex's mass in the system matrix (tangentially: the solve's direction has no
    normal part at a contact), ``fb`` = -c P (v - u) on the right-hand side."""
    i = wp.tid()
    vi = v[i]
    n_out = wp.vec3(0.0)
    y_out = wp.vec3(0.0)
    c_out = float(0.0)
    b_out = wp.vec3(0.0)
    rec_out = wp.vec3(0.0)
    arm = arms[cloth[i]]
    if arm.active == 1 and free[i] > 0.0 and released[i] == 0:
        t = clock[0]
        hand = forearm_hand(arm, t)
        moving = forearm_moving(arm, t)
        xi = x[i]
        reach = arm.radius + thickness
        best = tolerance
        u_out = wp.vec3(0.0)
        for seg in range(2):
            a = arm.shoulder
            b = arm.elbow
            if seg == 1:
                a = arm.elbow
                b = hand
            c = closest_on_segment(xi, a, b)
            d = xi - c
            dl = wp.length(d)
            gap = dl - reach
            if gap < best and dl > 1.0e-9:
                n = d / dl
                u = surface_velocity(arm, moving, seg, c, n, reach)
                target = wp.dot(u, n) + wp.max(-gap, 0.0) / dt
                vn = wp.dot(vi, n)
                if vn <= target or jn_prev[i] > 0.0:
                    best = gap
                    n_out = n
                    u_out = u
                    y_out = (target - vn) * n
                    rec_out = wp.max(-gap, 0.0) / dt * n
        if wp.length_sq(n_out) > 0.0 and jn_prev[i] > 0.0:
            rel = vi - u_out
            slip = rel - wp.dot(rel, n_out) * n_out
            c_out = friction * jn_prev[i] / wp.max(wp.length(slip), slip_velocity)
            b_out = -c_out * slip
    released[i] = 0
    cn[i] = n_out
    y[i] = y_out
    vy[i] = vi + y_out
    fc[i] = c_out
    fb[i] = b_out
    recover[i] = rec_out


@wp.kernel
def contact_recovered(recover: wp.array(dtype=wp.vec3), v: wp.array(dtype=wp.vec3)):
    """After ``integrate``: take the penetration-closing part of a contact's prescribed velocity back off. It
    has moved the vertex out of the arm; left on, the vertex moved away from the surface in the next step, was
    left free, fell back in, and so was in contact only every other step (no resting contact, so no friction)."""
    i = wp.tid()
    v[i] = v[i] - recover[i]


@wp.func
def filter_contact(r: wp.vec3, free: float, n: wp.vec3):
    """Project out the constrained directions: pinned vertices entirely, contact vertices along the normal."""
    return free * (r - wp.dot(r, n) * n)


@wp.kernel
def cg_start_contact(force: wp.array(dtype=wp.vec3), v: wp.array(dtype=wp.vec3), kv: wp.array(dtype=wp.vec3),
                     mass: wp.array(dtype=float), free: wp.array(dtype=float), cloth: wp.array(dtype=int),
                     dt: float, damping: float, diag: wp.array(dtype=wp.vec3),
                     cn: wp.array(dtype=wp.vec3), y: wp.array(dtype=wp.vec3), fc: wp.array(dtype=float),
                     fb: wp.array(dtype=wp.vec3), rn: wp.array(dtype=float),
                     dv: wp.array(dtype=wp.vec3), r: wp.array(dtype=wp.vec3), z: wp.array(dtype=wp.vec3),
                     p: wp.array(dtype=wp.vec3), ap: wp.array(dtype=wp.vec3),
                     rz: wp.array2d(dtype=float), pap: wp.array2d(dtype=float),
                     rr: wp.array2d(dtype=float)):
    """``cg_start`` for the modified PCG of Baraff & Witkin: dv starts at the prescribed y, the residual is
    b - A y (``kv`` holds K (v + y)), filtered; ``rn`` keeps the unfiltered residual along the contact normal
    (minus the contact impulse), to release adhesive contacts after the solve. The friction term of
    ``contact_prepare`` adds ``fc`` to the vertex's mass (M (1 + h a) + c P: P y = 0) and ``fb`` to b."""
    i = wp.tid()
    c = cloth[i]
    m_eff = mass[i] * (1.0 + dt * damping) + fc[i]
    n = cn[i]
    yi = y[i]
    res = dt * (force[i] - damping * mass[i] * v[i]) - dt * dt * kv[i] - (m_eff - fc[i]) * yi + fb[i]
    rn[i] = wp.dot(res, n)
    ri = filter_contact(res, free[i], n)
    dinv = wp.cw_div(wp.vec3(1.0), wp.vec3(m_eff) + dt * dt * diag[i])
    zi = filter_contact(wp.cw_mul(ri, dinv), free[i], n)
    diag[i] = dinv
    dv[i] = free[i] * yi
    r[i] = ri
    z[i] = zi
    p[i] = zi
    ap[i] = m_eff * zi
    wp.atomic_add(rz, 0, c, wp.dot(ri, zi))
    wp.atomic_add(pap, 0, c, m_eff * wp.dot(zi, zi))
    wp.atomic_add(rr, 0, c, wp.dot(ri, ri))


@wp.kernel
def cg_update_contact(mass: wp.array(dtype=float), free: wp.array(dtype=float), cloth: wp.array(dtype=int),
                      dinv: wp.array(dtype=wp.vec3), p: wp.array(dtype=wp.vec3), ap: wp.array(dtype=wp.vec3),
                      cn: wp.array(dtype=wp.vec3), rn: wp.array(dtype=float),
                      slot: int, active: wp.array(dtype=int), dv: wp.array(dtype=wp.vec3),
                      r: wp.array(dtype=wp.vec3), z: wp.array(dtype=wp.vec3),
                      rz: wp.array2d(dtype=float), pap: wp.array2d(dtype=float), vrz: wp.array(dtype=float),
                      vrr: wp.array(dtype=float)):
    """``cg_update`` with the contact filter."""
    i = wp.tid()
    c = cloth[i]
    if active[c] == 0:
        return
    den = pap[slot, c]
    if not cg_step_ok(den):
        vrz[i] = 0.0
        vrr[i] = 0.0
        return
    alpha = rz[slot, c] / den
    n = cn[i]
    api = ap[i]
    dv[i] = dv[i] + alpha * p[i]
    rn[i] = rn[i] - alpha * wp.dot(api, n)
    ri = r[i] - alpha * filter_contact(api, free[i], n)
    zi = filter_contact(wp.cw_mul(ri, dinv[i]), free[i], n)
    r[i] = ri
    z[i] = zi
    vrz[i] = wp.dot(ri, zi)
    vrr[i] = wp.dot(ri, ri)


@wp.kernel
def cg_direction_contact(mass: wp.array(dtype=float), cloth: wp.array(dtype=int), dt: float, damping: float,
                         fc: wp.array(dtype=float), z: wp.array(dtype=wp.vec3), slot: int,
                         active: wp.array(dtype=int), p: wp.array(dtype=wp.vec3), ap: wp.array(dtype=wp.vec3),
                         rz: wp.array2d(dtype=float), vpap: wp.array(dtype=float)):
    """``cg_direction`` with the contacts' friction term ``fc`` on the mass (p has no normal part there)."""
    i = wp.tid()
    c = cloth[i]
    if active[c] == 0:
        return
    beta = rz[slot + 1, c] / rz[slot, c]
    m_eff = mass[i] * (1.0 + dt * damping) + fc[i]
    pi = z[i] + beta * p[i]
    p[i] = pi
    ap[i] = m_eff * pi
    vpap[i] = m_eff * wp.dot(pi, pi)


@wp.kernel
def contact_release(cn: wp.array(dtype=wp.vec3), rn: wp.array(dtype=float), released: wp.array(dtype=int),
                    jn: wp.array(dtype=float)):
    """A contact whose constraint impulse (-rn along the outward normal) came out pulling the cloth onto the
    arm is released for the next step; ``jn`` keeps each contact's pushing normal impulse (zero elsewhere)
    for the next step's friction."""
    i = wp.tid()
    j = float(0.0)
    if wp.length_sq(cn[i]) > 0.0:
        if rn[i] > 0.0:
            released[i] = 1
        else:
            j = -rn[i]
    jn[i] = j
