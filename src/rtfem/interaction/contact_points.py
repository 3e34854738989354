"""Where a tool touches the surface: the contact points (vertices near the tool at their predicted
positions, and the closest point of the surface on a triangle), their gaps and frames, the
right-hand side of the step and the motion after it (see :mod:`rtfem.interaction.contact`);
compiled when numba is present."""

from __future__ import annotations

import math

import numpy as np

__all__ = ["closest_points_on_triangles"]


def closest_points_on_triangles(P: np.ndarray, A: np.ndarray, B: np.ndarray, C: np.ndarray):
    """Closest points of triangles (A, B, C) (k, 3 each) to points P (k, 3): (points, barycentric
    weights (k, 3)). The projection on the plane when it falls inside, else the nearest of the
    three edges' closest points."""
    e0, e1 = B - A, C - A
    d = P - A
    a00, a01, a11 = np.einsum("ij,ij->i", e0, e0), np.einsum("ij,ij->i", e0, e1), np.einsum("ij,ij->i", e1, e1)
    b0, b1 = np.einsum("ij,ij->i", d, e0), np.einsum("ij,ij->i", d, e1)
    det = np.maximum(a00 * a11 - a01 * a01, 1e-300)
    s, t = (a11 * b0 - a01 * b1) / det, (a00 * b1 - a01 * b0) / det
    bary = np.stack([1.0 - s - t, s, t], axis=1)
    inside = (s >= 0) & (t >= 0) & (s + t <= 1)
    best = np.full(P.shape[0], np.inf)
    out_b = bary.copy()
    corners = (A, B, C)
    for i, j in ((0, 1), (1, 2), (2, 0)):
        Q0, Q1 = corners[i], corners[j]
        e = Q1 - Q0
        u = np.clip(np.einsum("ij,ij->i", P - Q0, e) / np.maximum(np.einsum("ij,ij->i", e, e), 1e-300), 0.0, 1.0)
        dist = np.linalg.norm(Q0 + u[:, None] * e - P, axis=1)
        better = ~inside & (dist < best)
        best = np.where(better, dist, best)
        wts = np.zeros_like(bary)
        wts[:, i], wts[:, j] = 1.0 - u, u
        out_b = np.where(better[:, None], wts, out_b)
    points = out_b[:, :1] * A + out_b[:, 1:2] * B + out_b[:, 2:] * C
    return points, out_b


def _core_into(p0, p1, p2, c, R, half, q):
    """q (3,) = the tool core's point closest to p (see :meth:`Tool.core`)."""
    l0 = (p0 - c[0]) * R[0, 0] + (p1 - c[1]) * R[1, 0] + (p2 - c[2]) * R[2, 0]
    l1 = (p0 - c[0]) * R[0, 1] + (p1 - c[1]) * R[1, 1] + (p2 - c[2]) * R[2, 1]
    l2 = (p0 - c[0]) * R[0, 2] + (p1 - c[1]) * R[1, 2] + (p2 - c[2]) * R[2, 2]
    l0 = min(max(l0, -half[0]), half[0])
    l1 = min(max(l1, -half[1]), half[1])
    l2 = min(max(l2, -half[2]), half[2])
    for i in range(3):
        q[i] = c[i] + l0 * R[i, 0] + l1 * R[i, 1] + l2 * R[i, 2]


def _gaps(P, Q, O, spread, c, R, half, radius, d, n):
    """Each point P[k]'s signed gap d[k] and push direction n[k] (:meth:`Tool.distance`, outward
    normals O), the normal line widened by ``spread`` |v . O| (on a concave edge, the tangent of
    its faces' cone: the points behind the edge whose closest surface point is on it), the gap
    then moved on to Q[k] along n: d += n . (Q - P)."""
    q = np.empty(3)
    for k in range(P.shape[0]):
        _core_into(P[k, 0], P[k, 1], P[k, 2], c, R, half, q)
        v0, v1, v2 = q[0] - P[k, 0], q[1] - P[k, 1], q[2] - P[k, 2]
        vv = v0 * v0 + v1 * v1 + v2 * v2
        dist = math.sqrt(vv)
        vn = v0 * O[k, 0] + v1 * O[k, 1] + v2 * O[k, 2]
        lateral = math.sqrt(max(vv - vn * vn, 0.0))
        above = vn >= 0 or lateral > radius + spread[k] * abs(vn) + 1e-12
        if above and dist > 1e-12:
            n[k, 0], n[k, 1], n[k, 2] = -v0 / dist, -v1 / dist, -v2 / dist
        else:
            n[k, 0], n[k, 1], n[k, 2] = -O[k, 0], -O[k, 1], -O[k, 2]
        g = (dist if above else -dist) - radius
        d[k] = g + n[k, 0] * (Q[k, 0] - P[k, 0]) + n[k, 1] * (Q[k, 1] - P[k, 1]) + n[k, 2] * (Q[k, 2] - P[k, 2])


def _closest_on_triangle(p, A, B, C, out, bary):
    """The point ``out`` (3,) of triangle ABC closest to p, and its barycentric weights (see
    :func:`closest_points_on_triangles`)."""
    e00, e01, e02 = B[0] - A[0], B[1] - A[1], B[2] - A[2]
    e10, e11, e12 = C[0] - A[0], C[1] - A[1], C[2] - A[2]
    d0, d1, d2 = p[0] - A[0], p[1] - A[1], p[2] - A[2]
    a00 = e00 * e00 + e01 * e01 + e02 * e02
    a01 = e00 * e10 + e01 * e11 + e02 * e12
    a11 = e10 * e10 + e11 * e11 + e12 * e12
    b0 = d0 * e00 + d1 * e01 + d2 * e02
    b1 = d0 * e10 + d1 * e11 + d2 * e12
    det = max(a00 * a11 - a01 * a01, 1e-300)
    s, t = (a11 * b0 - a01 * b1) / det, (a00 * b1 - a01 * b0) / det
    if s >= 0 and t >= 0 and s + t <= 1:
        bary[0], bary[1], bary[2] = 1.0 - s - t, s, t
    else:
        best = np.inf
        for e in range(3):
            i, j = e, (e + 1) % 3
            Q0 = A if i == 0 else (B if i == 1 else C)
            Q1 = A if j == 0 else (B if j == 1 else C)
            f0, f1, f2 = Q1[0] - Q0[0], Q1[1] - Q0[1], Q1[2] - Q0[2]
            u = ((p[0] - Q0[0]) * f0 + (p[1] - Q0[1]) * f1 + (p[2] - Q0[2]) * f2) / max(f0 * f0 + f1 * f1 + f2 * f2, 1e-300)
            u = min(max(u, 0.0), 1.0)
            g0, g1, g2 = Q0[0] + u * f0 - p[0], Q0[1] + u * f1 - p[1], Q0[2] + u * f2 - p[2]
            dist = math.sqrt(g0 * g0 + g1 * g1 + g2 * g2)
            if dist < best:
                best = dist
                bary[0] = bary[1] = bary[2] = 0.0
                bary[i], bary[j] = 1.0 - u, u
    for i in range(3):
        out[i] = bary[0] * A[i] + bary[1] * B[i] + bary[2] * C[i]


def _face_points(Y, local, c, R, half, iters, bary, P, O):
    """For each triangle (corners ``local``, rows of Y): the point P[k] closest to the tool's core at c
    (``iters`` alternating projections from the centroid's core point), its weights ``bary[k]`` and
    the face's unit normal O[k]."""
    q, p, A, B, C = np.empty(3), np.empty(3), np.empty(3), np.empty(3), np.empty(3)
    for k in range(local.shape[0]):
        for i in range(3):
            A[i], B[i], C[i] = Y[local[k, 0], i], Y[local[k, 1], i], Y[local[k, 2], i]
        _core_into((A[0] + B[0] + C[0]) / 3.0, (A[1] + B[1] + C[1]) / 3.0, (A[2] + B[2] + C[2]) / 3.0, c, R, half, q)
        for _ in range(iters):
            _closest_on_triangle(q, A, B, C, p, bary[k])
            _core_into(p[0], p[1], p[2], c, R, half, q)
        P[k, 0], P[k, 1], P[k, 2] = p[0], p[1], p[2]
        o0 = (B[1] - A[1]) * (C[2] - A[2]) - (B[2] - A[2]) * (C[1] - A[1])
        o1 = (B[2] - A[2]) * (C[0] - A[0]) - (B[0] - A[0]) * (C[2] - A[2])
        o2 = (B[0] - A[0]) * (C[1] - A[1]) - (B[1] - A[1]) * (C[0] - A[0])
        size = max(math.sqrt(o0 * o0 + o1 * o1 + o2 * o2), 1e-300)
        O[k, 0], O[k, 1], O[k, 2] = o0 / size, o1 / size, o2 / size


def _counted(local, bary, O, outward, spread, ok):
    """Which faces' points count (``ok``): inside a face, or on an edge once (the first face of the
    edge), that edge's points taking the edge's normal (its faces' mean: ``outward``) and the cone
    its faces spread around it (``spread``, the tangent of the half-angle)."""
    f = local.shape[0]
    on = np.zeros(f, np.int64)
    lo = np.full(f, -1, np.int64)  # the edge's corners (rows of Y), for a point on an edge
    hi = np.full(f, -1, np.int64)
    for k in range(f):
        for a in range(3):
            if bary[k, a] > 1e-9:
                on[k] += 1
                if lo[k] < 0:
                    lo[k] = local[k, a]
                else:
                    hi[k] = local[k, a]
        if on[k] == 2 and lo[k] > hi[k]:
            lo[k], hi[k] = hi[k], lo[k]
    for k in range(f):
        ok[k] = on[k] >= 2
        if on[k] != 2:
            continue
        s0, s1, s2 = 0.0, 0.0, 0.0
        first = True
        for j in range(f):
            if on[j] == 2 and lo[j] == lo[k] and hi[j] == hi[k]:
                s0, s1, s2 = s0 + O[j, 0], s1 + O[j, 1], s2 + O[j, 2]
                if j < k:
                    first = False
        size = max(math.sqrt(s0 * s0 + s1 * s1 + s2 * s2), 1e-300)
        u0, u1, u2 = s0 / size, s1 / size, s2 / size
        cos = u0 * O[k, 0] + u1 * O[k, 1] + u2 * O[k, 2]
        spread[k] = math.sqrt(max(1.0 - cos * cos, 0.0)) / max(cos, 1e-3)
        outward[k, 0], outward[k, 1], outward[k, 2] = u0, u1, u2
        ok[k] = first


def _kept(P, ok, Y, Yf, local, bary, n, gaps, reach, margin, same, V, keep):
    """The counted face points to keep (their indices into ``keep``; returns how many): a gap below
    ``reach`` before and ``margin`` after the linearization to the free positions Yf (written back
    into ``gaps``), and not within ``same`` of a vertex contact (rows of V) or of a face point kept
    before."""
    kept = 0
    for k in range(P.shape[0]):
        if not ok[k] or not gaps[k] < reach:
            continue
        g = gaps[k]
        for a in range(3):
            w = bary[k, a]
            for i in range(3):
                g += n[k, i] * w * (Yf[local[k, a], i] - Y[local[k, a], i])
        if not g < margin:
            continue
        fresh = True
        for j in range(V.shape[0]):
            if (V[j, 0] - P[k, 0]) ** 2 + (V[j, 1] - P[k, 1]) ** 2 + (V[j, 2] - P[k, 2]) ** 2 <= same * same:
                fresh = False
        for j in range(kept):
            i = keep[j]
            if (P[i, 0] - P[k, 0]) ** 2 + (P[i, 1] - P[k, 1]) ** 2 + (P[i, 2] - P[k, 2]) ** 2 <= same * same:
                fresh = False
        if fresh:
            gaps[k] = g
            keep[kept] = k
            kept += 1
    return kept


def _faces(Y, Yf, local, c, cg, R, half, radius, iters, reach, margin, same, V, bary, n, gaps, keep):
    """The ring's face contacts (every face of the ring is a contact of its own: where the probe
    sits in its own dent, a concave crease, the closest point would jump across the crease, while
    the set of faces' points moves continuously): for each triangle
    (corners ``local``, rows of Y) the point closest to the tool's core at ``c`` (``iters`` alternating
    projections), its weights ``bary``, push direction ``n`` and gap against the tool at ``cg`` (``gaps``, linearized to the
    free positions Yf); kept (``keep``, the count returned) when inside the face or on an edge
    (once per edge, judged by the edge's mean normal and its cone), its gap below ``reach`` before
    and ``margin`` after the linearization, and not within ``same`` of a vertex contact (rows of V)
    or of a face point kept before."""
    f = local.shape[0]
    P = np.empty((f, 3))
    O = np.empty((f, 3))
    _face_points(Y, local, c, R, half, iters, bary, P, O)
    spread = np.zeros(f)
    outward = O.copy()
    ok = np.zeros(f, np.bool_)
    _counted(local, bary, O, outward, spread, ok)
    _gaps(P, P, outward, spread, cg, R, half, radius, gaps, n)
    return _kept(P, ok, Y, Yf, local, bary, n, gaps, reach, margin, same, V, keep)


def _points(g, n, Y, Yf, verts, margin, loc, bw, nf, df, fid, pos, S, Bi, Bv, F, gaps, y_free, y_now, ids):
    """The contact points from the candidates' gaps ``g`` (k,) (moved on to their free positions)
    and push directions n: each vertex whose gap is below ``margin``, then the kept face
    points (corners ``loc``, rows of Y, weights ``bw``, directions ``nf``, gaps ``df``, ids
    ``fid``). Fills the points' corners Bi (rows of S) and weights Bv, frames F, gaps, free and
    current positions and ids (vertex number, or -1 - triangle); S (the candidates the points
    use, ascending rows of Y). Returns (m points, s nodes)."""
    k = g.shape[0]
    for i in range(k):
        pos[i] = -1
    m = 0
    for i in range(k):
        if g[i] < margin:
            pos[i] = 0
            Bi[m, 0] = Bi[m, 1] = Bi[m, 2] = i
            Bv[m, 0], Bv[m, 1], Bv[m, 2] = 1.0, 0.0, 0.0
            _frame_into(n[i, 0], n[i, 1], n[i, 2], F, m)
            gaps[m] = g[i]
            for j in range(3):
                y_free[m, j], y_now[m, j] = Yf[i, j], Y[i, j]
            ids[m] = verts[i]
            m += 1
    for f in range(loc.shape[0]):
        for a in range(3):
            pos[loc[f, a]] = 0
            Bi[m, a] = loc[f, a]
            Bv[m, a] = bw[f, a]
        _frame_into(nf[f, 0], nf[f, 1], nf[f, 2], F, m)
        gaps[m] = df[f]
        for j in range(3):
            y_free[m, j] = bw[f, 0] * Yf[loc[f, 0], j] + bw[f, 1] * Yf[loc[f, 1], j] + bw[f, 2] * Yf[loc[f, 2], j]
            y_now[m, j] = bw[f, 0] * Y[loc[f, 0], j] + bw[f, 1] * Y[loc[f, 1], j] + bw[f, 2] * Y[loc[f, 2], j]
        ids[m] = fid[f]
        m += 1
    s = 0
    for i in range(k):
        if pos[i] == 0:
            pos[i] = s
            S[s] = i
            s += 1
    for c in range(m):
        for a in range(3):
            Bi[c, a] = pos[Bi[c, a]]
    return m, s


def _rhs(F, gaps, y_free, y_now, move, slide, ids, warm_ids, warm_r, b, r):
    """b (m, 3) of the solve (see the module's docstring: the gap and the slip in each point's
    frame; ``move`` the device from where the geometry was evaluated, linear in the gap; ``slide``
    the tool's move over the step, x_d(k+1) - x_t(k), in the slip), and the warm start r (m, 3):
    last step's forces at the points (by id) still here."""
    for c in range(gaps.shape[0]):
        s0 = y_free[c, 0] - y_now[c, 0] - slide[0]
        s1 = y_free[c, 1] - y_now[c, 1] - slide[1]
        s2 = y_free[c, 2] - y_now[c, 2] - slide[2]
        b[c, 0] = gaps[c] - (F[c, 0, 0] * move[0] + F[c, 1, 0] * move[1] + F[c, 2, 0] * move[2])
        b[c, 1] = F[c, 0, 1] * s0 + F[c, 1, 1] * s1 + F[c, 2, 1] * s2
        b[c, 2] = F[c, 0, 2] * s0 + F[c, 1, 2] * s1 + F[c, 2, 2] * s2
        r[c, 0] = r[c, 1] = r[c, 2] = 0.0
        for j in range(warm_ids.shape[0]):
            if warm_ids[j] == ids[c]:
                r[c, 0], r[c, 1], r[c, 2] = warm_r[j, 0], warm_r[j, 1], warm_r[j, 2]
                break


def _after(W, slots, Bi, Bv, F, r, y_free, f_points, f_nodes, y_after):
    """After the solve: each point's force on the organ f_points = F r (m, 3), the nodes' forces
    f_nodes = B^T f (s, 3), and each pressed point's position after the step y_free + B W f
    (y_after, only rows with r_n > 0; W's rows and columns at the nodes' ``slots``)."""
    m = r.shape[0]
    for i in range(f_nodes.shape[0]):
        f_nodes[i, 0] = f_nodes[i, 1] = f_nodes[i, 2] = 0.0
    for c in range(m):
        for j in range(3):
            f_points[c, j] = F[c, j, 0] * r[c, 0] + F[c, j, 1] * r[c, 1] + F[c, j, 2] * r[c, 2]
        for a in range(3):
            w = Bv[c, a]
            if w != 0.0:
                for j in range(3):
                    f_nodes[Bi[c, a], j] += w * f_points[c, j]
    for c in range(m):
        if not r[c, 0] > 0.0:
            continue
        for j in range(3):
            y_after[c, j] = y_free[c, j]
        for a in range(3):
            w = Bv[c, a]
            if w == 0.0:
                continue
            p = 3 * slots[Bi[c, a]]
            for e in range(f_nodes.shape[0]):
                f0, f1, f2 = f_nodes[e, 0], f_nodes[e, 1], f_nodes[e, 2]
                if f0 == 0.0 and f1 == 0.0 and f2 == 0.0:
                    continue
                q = 3 * slots[e]
                for j in range(3):
                    y_after[c, j] += w * (W[p + j, q] * f0 + W[p + j, q + 1] * f1 + W[p + j, q + 2] * f2)


def _frame_into(n0, n1, n2, F, k):
    """F[k] (3, 3): the contact frame of unit normal n, columns n, t1, t2 (right-handed,
    orthonormal; t1 = n x e, e the x axis, or the y axis where n is near x)."""
    h0, h1, h2 = (1.0, 0.0, 0.0) if abs(n0) < 0.6 else (0.0, 1.0, 0.0)
    t0, t1, t2 = n1 * h2 - n2 * h1, n2 * h0 - n0 * h2, n0 * h1 - n1 * h0
    size = math.sqrt(t0 * t0 + t1 * t1 + t2 * t2)
    t0, t1, t2 = t0 / size, t1 / size, t2 / size
    F[k, 0, 0], F[k, 1, 0], F[k, 2, 0] = n0, n1, n2
    F[k, 0, 1], F[k, 1, 1], F[k, 2, 1] = t0, t1, t2
    F[k, 0, 2], F[k, 1, 2], F[k, 2, 2] = n1 * t2 - n2 * t1, n2 * t0 - n0 * t2, n0 * t1 - n1 * t0


try:  # compiled when numba is present (the same code)
    import numba as _numba

    _opts = dict(cache=True, nogil=True, error_model="numpy")  # no exceptions from the kernels
    _core_into = _numba.njit(**_opts)(_core_into)
    _closest_on_triangle = _numba.njit(**_opts)(_closest_on_triangle)
    _gaps = _numba.njit("void(f8[:, ::1], f8[:, ::1], f8[:, ::1], f8[::1], f8[::1], f8[:, ::1], f8[::1], f8, f8[::1], "
                        "f8[:, ::1])", **_opts)(_gaps)
    _face_points = _numba.njit(**_opts)(_face_points)
    _counted = _numba.njit(**_opts)(_counted)
    _kept = _numba.njit(**_opts)(_kept)
    _faces = _numba.njit("i8(f8[:, ::1], f8[:, ::1], i8[:, ::1], f8[::1], f8[::1], f8[:, ::1], f8[::1], f8, i8, f8, f8, "
                         "f8, f8[:, ::1], f8[:, ::1], f8[:, ::1], f8[::1], i8[::1])", **_opts)(_faces)
    _frame_into = _numba.njit(**_opts)(_frame_into)
    _points = _numba.njit("UniTuple(i8, 2)(f8[::1], f8[:, ::1], f8[:, ::1], f8[:, ::1], i8[::1], f8, i8[:, ::1], "
                          "f8[:, ::1], f8[:, ::1], f8[::1], i8[::1], i8[::1], i8[::1], i8[:, ::1], f8[:, ::1], "
                          "f8[:, :, ::1], f8[::1], f8[:, ::1], f8[:, ::1], i8[::1])", **_opts)(_points)
    _rhs = _numba.njit("void(f8[:, :, ::1], f8[::1], f8[:, ::1], f8[:, ::1], f8[::1], f8[::1], i8[::1], i8[::1], "
                       "f8[:, ::1], f8[:, ::1], f8[:, ::1])", **_opts)(_rhs)
    _after = _numba.njit("void(f8[:, ::1], i8[::1], i8[:, ::1], f8[:, ::1], f8[:, :, ::1], f8[:, ::1], f8[:, ::1], "
                         "f8[:, ::1], f8[:, ::1], f8[:, ::1])", **_opts)(_after)
except Exception:  # pragma: no cover - numba absent
    pass

