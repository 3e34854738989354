"""The compiled search of a scene step's contact points: a body's vertices against another body's
triangles (:func:`pair_block`), and a probe's vertex and face contacts (:func:`probe_block`), as
points of :class:`rtfem.interaction.scene_points.PointSet` (numpy where numba is absent: the same
numbers)."""

from __future__ import annotations

import math

import numpy as np

from .contact_points import _closest_on_triangle

#: m (and a share of the distance): faces this much farther than the closest are tied with it (one edge or
#: corner: their normals summed give its side)
TIE = 1e-9

__all__ = ["pair_block", "pair_faces", "probe_block", "probe_points"]


def _unit_normal(Ys, tri, t):
    """The unit normal (n0, n1, n2) of triangle t (corners ``tri[t]`` of the vertices Ys), by its winding."""
    a0, a1, a2 = Ys[tri[t, 0], 0], Ys[tri[t, 0], 1], Ys[tri[t, 0], 2]
    u0, u1, u2 = Ys[tri[t, 1], 0] - a0, Ys[tri[t, 1], 1] - a1, Ys[tri[t, 1], 2] - a2
    v0, v1, v2 = Ys[tri[t, 2], 0] - a0, Ys[tri[t, 2], 1] - a1, Ys[tri[t, 2], 2] - a2
    n0, n1, n2 = u1 * v2 - u2 * v1, u2 * v0 - u0 * v2, u0 * v1 - u1 * v0
    size = math.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
    return n0 / size, n1 / size, n2 / size


def _pair_faces(x, Ys, tri, tris, valid, margin, edge, best, gap, n, w, on):
    """For each point x[c] and its candidate triangles ``tris[c]`` (where ``valid``) of a surface
    whose vertices are Ys (the triangles ``tri`` number them): the nearest triangle ``best[c]``, the
    gap along its unit normal n[c], the closest point's barycentric weights w[c], and ``on[c]``:
    within ``margin`` of the face and on its normal line (as :func:`~rtfem.interaction.scene_obstacles.nearest_face_points`
    and :func:`~rtfem.interaction.scene_obstacles.on_faces` do it in numpy)."""
    q = np.empty(3)
    bary = np.empty(3)
    A = np.empty(3)
    B = np.empty(3)
    C = np.empty(3)
    for c in range(x.shape[0]):
        p = x[c]
        dmin = np.inf
        on[c] = False
        best[c] = -1
        for j in range(tris.shape[1]):
            if not valid[c, j]:
                continue
            t = tris[c, j]
            for i in range(3):
                A[i], B[i], C[i] = Ys[tri[t, 0], i], Ys[tri[t, 1], i], Ys[tri[t, 2], i]
            _closest_on_triangle(p, A, B, C, q, bary)
            d = math.sqrt((q[0] - p[0]) ** 2 + (q[1] - p[1]) ** 2 + (q[2] - p[2]) ** 2)
            if d < dmin:
                dmin = d
                best[c] = t
                w[c, 0], w[c, 1], w[c, 2] = bary[0], bary[1], bary[2]
        if best[c] < 0:
            continue
        t = best[c]
        n0, n1, n2 = _unit_normal(Ys, tri, t)
        n[c, 0], n[c, 1], n[c, 2] = n0, n1, n2
        for i in range(3):
            q[i] = w[c, 0] * Ys[tri[t, 0], i] + w[c, 1] * Ys[tri[t, 1], i] + w[c, 2] * Ys[tri[t, 2], i]
        d0, d1, d2 = p[0] - q[0], p[1] - q[1], p[2] - q[2]
        g = d0 * n0 + d1 * n1 + d2 * n2
        gap[c] = g
        l0, l1, l2 = d0 - g * n0, d1 - g * n1, d2 - g * n2
        on[c] = abs(g) < margin and math.sqrt(l0 * l0 + l1 * l1 + l2 * l2) <= 1e-3 * edge + 1e-12


def _core(p0, p1, p2, c, R, half, q):
    """q (3,): the tool core's point closest to p (the core: the box [-half, half] in the frame R at c)."""
    for k in range(3):
        l = (p0 - c[0]) * R[0, k] + (p1 - c[1]) * R[1, k] + (p2 - c[2]) * R[2, k]
        q[3 + k] = min(max(l, -half[k]), half[k])
    for i in range(3):
        q[i] = c[i] + q[3] * R[i, 0] + q[4] * R[i, 1] + q[5] * R[i, 2]


def _probe(Ys, O, tri, c, R, half, radius, cutoff, reach, margin, idx, gap, n, face_w, face):
    """A probe's contacts on a surface (vertices Ys, outward normals O, triangles ``tri``) with the
    core at c: the vertices within ``reach`` of c and ``margin`` of the tool (``idx``, ``gap``, push
    direction ``n``; their count returned) as :meth:`rtfem.Tool.distance` gives them, and in ``face``
    (triangle, gap, n) and ``face_w`` the closest point of a triangle with a corner within ``cutoff``
    of c (triangle -1: none within ``margin``), as :func:`probe_points`' numpy path finds it. (A vertex
    beyond ``reach``, the tool's reach plus the margin, cannot be within the margin of it: one on the
    body's far side would be taken for a vertex the tool has passed.)"""
    q = np.empty(6)
    near = np.zeros(Ys.shape[0], dtype=np.bool_)
    count = 0
    for v in range(Ys.shape[0]):
        p0, p1, p2 = Ys[v, 0], Ys[v, 1], Ys[v, 2]
        d2 = (p0 - c[0]) ** 2 + (p1 - c[1]) ** 2 + (p2 - c[2]) ** 2
        if d2 >= cutoff * cutoff:
            continue
        near[v] = True
        if d2 >= reach * reach:
            continue
        _core(p0, p1, p2, c, R, half, q)
        v0, v1, v2 = q[0] - p0, q[1] - p1, q[2] - p2
        dist = math.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
        vn = v0 * O[v, 0] + v1 * O[v, 1] + v2 * O[v, 2]
        lateral = math.sqrt(max(v0 * v0 + v1 * v1 + v2 * v2 - vn * vn, 0.0))
        above = vn >= 0 or lateral > radius + 1e-12
        g = (dist if above else -dist) - radius
        if g >= margin:
            continue
        idx[count], gap[count] = v, g
        if above and dist > 1e-12:
            n[count, 0], n[count, 1], n[count, 2] = -v0 / dist, -v1 / dist, -v2 / dist
        else:
            n[count, 0], n[count, 1], n[count, 2] = -O[v, 0], -O[v, 1], -O[v, 2]
        count += 1
    A, B, C = np.empty(3), np.empty(3), np.empty(3)
    p, w, qq = np.empty(3), np.empty(3), np.empty(3)
    best, dmin = -1, np.inf
    dist_t = np.full(tri.shape[0], np.inf)
    for t in range(tri.shape[0]):
        if not (near[tri[t, 0]] or near[tri[t, 1]] or near[tri[t, 2]]):
            continue
        for i in range(3):
            A[i], B[i], C[i] = Ys[tri[t, 0], i], Ys[tri[t, 1], i], Ys[tri[t, 2], i]
        _core((A[0] + B[0] + C[0]) / 3.0, (A[1] + B[1] + C[1]) / 3.0, (A[2] + B[2] + C[2]) / 3.0, c, R, half, q)
        p[0], p[1], p[2] = q[0], q[1], q[2]
        _closest_on_triangle(p, A, B, C, qq, w)
        _core(qq[0], qq[1], qq[2], c, R, half, q)
        d = math.sqrt((qq[0] - q[0]) ** 2 + (qq[1] - q[1]) ** 2 + (qq[2] - q[2]) ** 2)
        dist_t[t] = d
        if d < dmin:
            dmin, best = d, t
            face_w[0], face_w[1], face_w[2] = w[0], w[1], w[2]
            face[4], face[5], face[6] = qq[0] - q[0], qq[1] - q[1], qq[2] - q[2]
    face[0] = best
    if best < 0:
        return count
    # the closest feature's normal: the sum of the faces at the closest distance (an edge's or a corner's
    # faces; of a cut's two coincident lips and the outside beside them, the outside's), else the face's
    m0 = m1 = m2 = 0.0
    for t in range(tri.shape[0]):
        if dist_t[t] <= dmin + TIE * (1.0 + dmin):
            a0, a1, a2 = _unit_normal(Ys, tri, t)
            m0, m1, m2 = m0 + a0, m1 + a1, m2 + a2
    size = math.sqrt(m0 * m0 + m1 * m1 + m2 * m2)
    if size > 1e-6:
        m0, m1, m2 = m0 / size, m1 / size, m2 / size
    else:
        m0, m1, m2 = _unit_normal(Ys, tri, best)
    v0, v1, v2 = face[4], face[5], face[6]
    outside = v0 * m0 + v1 * m1 + v2 * m2 < 0  # the core on the outer side of the face
    g = (dmin if outside else -dmin) - radius
    if g >= margin:
        face[0] = -1
        return count
    face[1] = g
    if outside and dmin > 1e-12:
        face[2], face[3], face[4] = v0 / dmin, v1 / dmin, v2 / dmin
    else:
        face[2], face[3], face[4] = -m0, -m1, -m2
    return count


def _pair_block(x, Ys, tri, tris, valid, margin, edge, ids_a, ids_b, best, gap, n, w, on, out_n, out_g, sn, sw):
    """:func:`_pair_faces`, then its contacts as points: normal, gap, the vertex (``ids_a``: each
    point's node) at weight 1 and, on the second side, the triangle's corners (``ids_b``: the surface
    vertices' nodes) at minus their barycentric weights. Returns their count."""
    _pair_faces(x, Ys, tri, tris, valid, margin, edge, best, gap, n, w, on)
    m = 0
    for c in range(x.shape[0]):
        if not on[c]:
            continue
        out_g[m] = gap[c]
        for i in range(3):
            out_n[m, i] = n[c, i]
            sn[m, 0, i] = ids_a[c]
            sn[m, 1, i] = ids_b[tri[best[c], i]]
            sw[m, 0, i] = 1.0 if i == 0 else 0.0
            sw[m, 1, i] = -w[c, i]
        m += 1
    return m


def _probe_block(Ys, O, tri, c, R, half, radius, cutoff, reach, margin, ids, idx, gap, n, face_w, face, out_n, out_g,
                 sn, sw):
    """:func:`_probe`, then its contacts as points (the vertices, then the face point's corners at
    their barycentric weights; ``ids``: the surface vertices' nodes). Returns their count."""
    count = _probe(Ys, O, tri, c, R, half, radius, cutoff, reach, margin, idx, gap, n, face_w, face)
    for k in range(count):
        out_g[k] = gap[k]
        for i in range(3):
            out_n[k, i] = n[k, i]
            sn[k, 0, i] = ids[idx[k]]
            sw[k, 0, i] = 1.0 if i == 0 else 0.0
            sn[k, 1, i] = 0
            sw[k, 1, i] = 0.0
    if face[0] < 0:
        return count
    t = int(face[0])
    out_g[count] = face[1]
    for i in range(3):
        out_n[count, i] = face[2 + i]
        sn[count, 0, i] = ids[tri[t, i]]
        sw[count, 0, i] = face_w[i]
        sn[count, 1, i] = 0
        sw[count, 1, i] = 0.0
    return count + 1


_pair_faces_compiled = _probe_compiled = _pair_block_compiled = _probe_block_compiled = None
try:  # compiled when numba is present (the same code)
    import numba as _numba

    _opts = dict(cache=True, nogil=True, error_model="numpy")
    _unit_normal = _numba.njit(**_opts)(_unit_normal)  # the kernels below call it
    _pair_faces = _pair_faces_compiled = _numba.njit(**_opts)(_pair_faces)  # the block kernels call these
    _core = _numba.njit(**_opts)(_core)
    _probe = _probe_compiled = _numba.njit(**_opts)(_probe)
    _pair_block_compiled = _numba.njit(**_opts)(_pair_block)
    _probe_block_compiled = _numba.njit(**_opts)(_probe_block)
except Exception:  # pragma: no cover - numba absent
    pass


def pair_faces(x: np.ndarray, Ys: np.ndarray, tri: np.ndarray, tris: np.ndarray, valid: np.ndarray,
               margin: float, edge: float, compiled: bool = True):
    """Points x (c, 3) against their candidate triangles ``tris`` (c, k) (``valid`` (c, k)) of the
    surface Ys (vertices, numbered by ``tri``): (each point's nearest triangle (c,), gap (c,), unit
    face normal (c, 3), barycentric weights (c, 3), whether it is a contact (c,)). Compiled where
    numba is present, else numpy (the same numbers)."""
    c = x.shape[0]
    best, gap, n, w = np.zeros(c, dtype=np.int64), np.zeros(c), np.zeros((c, 3)), np.zeros((c, 3))
    on = np.zeros(c, dtype=np.bool_)
    if c == 0:
        return best, gap, n, w, on
    if compiled and _pair_faces_compiled is not None:
        _pair_faces_compiled(np.ascontiguousarray(x), np.ascontiguousarray(Ys), np.ascontiguousarray(tri),
                             np.ascontiguousarray(tris), np.ascontiguousarray(valid), float(margin), float(edge),
                             best, gap, n, w, on)
        return best, gap, n, w, on
    from .scene_obstacles import nearest_face_points, on_faces

    used, inverse = np.unique(tris, return_inverse=True)
    Y = Ys[tri[used]]
    normals = np.cross(Y[:, 1] - Y[:, 0], Y[:, 2] - Y[:, 0])
    normals /= np.linalg.norm(normals, axis=1)[:, None]
    t_loc = inverse.reshape(tris.shape)
    rows = np.arange(c)
    col, q, w, _ = nearest_face_points(x, Y, t_loc, valid)
    best = tris[rows, col]
    n = normals[t_loc[rows, col]]
    gap, on = on_faces(x, q, n, margin, edge)
    return best, gap, n, w, on


def probe_points(Ys: np.ndarray, O: np.ndarray, tri: np.ndarray, tool, position: np.ndarray, cutoff: float,
                 margin: float, compiled: bool = True):
    """A probe ``tool`` (an :class:`~rtfem.Tool`) at ``position`` against a surface (vertices Ys (s, 3),
    outward normals O, triangles ``tri`` numbering Ys): the vertices within ``margin`` of it (indices,
    gaps, push directions; those within the tool's reach plus the margin of ``position``) and the
    closest point on a triangle with a corner within ``cutoff``: (triangle, gap, push direction (3,),
    barycentric weights (3,)), or None beyond ``margin``."""
    reach = tool.reach + margin
    if compiled and _probe_compiled is not None:
        s = Ys.shape[0]
        idx, gap, n = np.empty(s, dtype=np.int64), np.empty(s), np.empty((s, 3))
        face_w, face = np.zeros(3), np.zeros(7)
        count = _probe_compiled(Ys, O, tri, np.asarray(position, dtype=float), tool.orientation, tool.half_extents,
                                float(tool.radius), float(cutoff), float(reach), float(margin), idx, gap, n, face_w, face)
        found = None if face[0] < 0 else (int(face[0]), float(face[1]), face[2:5].copy(), face_w)
        return idx[:count], gap[:count], n[:count], found
    from .contact_points import closest_points_on_triangles

    d = Ys - position
    d2 = np.einsum("ij,ij->i", d, d)
    cand = np.flatnonzero(d2 < cutoff * cutoff)
    close = cand[d2[cand] < reach * reach]
    gaps, n = tool.distance(Ys[close], position, O[close])
    touching = np.flatnonzero(gaps < margin)
    mark = np.zeros(Ys.shape[0], dtype=bool)
    mark[cand] = True
    near = np.flatnonzero(mark[tri].any(axis=1))
    found = None
    if near.size:
        Yn = Ys[tri[near]]
        q, w = closest_points_on_triangles(tool.core(Yn.mean(axis=1), position), Yn[:, 0], Yn[:, 1], Yn[:, 2])
        v = q - tool.core(q, position)
        dist = np.linalg.norm(v, axis=1)
        best = int(np.argmin(dist))
        normals = np.cross(Yn[:, 1] - Yn[:, 0], Yn[:, 2] - Yn[:, 0])
        normals /= np.linalg.norm(normals, axis=1)[:, None]
        normal = normals[dist <= dist[best] + TIE * (1.0 + dist[best])].sum(axis=0)  # the closest feature's (above)
        size = np.linalg.norm(normal)
        normal = normal / size if size > 1e-6 else normals[best]
        outside = v[best] @ normal < 0  # the core on the outer side of the face
        g = (dist[best] if outside else -dist[best]) - tool.radius
        if g < margin:
            push = v[best] / dist[best] if outside and dist[best] > 1e-12 else -normal
            found = (int(near[best]), float(g), push, w[best])
    return close[touching], gaps[touching], n[touching], found


def pair_block(x: np.ndarray, Ys: np.ndarray, tri: np.ndarray, tris: np.ndarray, valid: np.ndarray, margin: float,
               edge: float, ids_a: np.ndarray, ids_b: np.ndarray, compiled: bool = True):
    """:func:`pair_faces`' contacts as points: (normals (m, 3), gaps (m,), sides' nodes (m, 2, 3),
    weights (m, 2, 3)): the vertex (``ids_a``: each point's node) at weight 1, and the triangle's
    corners (``ids_b``: the surface vertices' nodes) at minus their barycentric weights."""
    c = x.shape[0]
    if compiled and _pair_block_compiled is not None:
        out_n, out_g, sn, sw = np.empty((c, 3)), np.empty(c), np.empty((c, 2, 3), dtype=np.int64), np.empty((c, 2, 3))
        m = _pair_block_compiled(np.ascontiguousarray(x), Ys, tri, tris, valid, float(margin), float(edge), ids_a, ids_b,
                                 np.empty(c, dtype=np.int64), np.empty(c), np.empty((c, 3)), np.empty((c, 3)),
                                 np.empty(c, dtype=np.bool_), out_n, out_g, sn, sw)
        return out_n[:m], out_g[:m], sn[:m], sw[:m]
    best, gap, n, w, on = pair_faces(x, Ys, tri, tris, valid, margin, edge, compiled=False)
    keep = np.flatnonzero(on)
    sn = np.empty((keep.size, 2, 3), dtype=np.int64)
    sn[:, 0, :] = ids_a[keep][:, None]
    sn[:, 1, :] = ids_b[tri[best[keep]]]
    sw = np.zeros((keep.size, 2, 3))
    sw[:, 0, 0] = 1.0
    sw[:, 1, :] = -w[keep]
    return n[keep], gap[keep], sn, sw


def probe_block(Ys: np.ndarray, O: np.ndarray, tri: np.ndarray, tool, position: np.ndarray, cutoff: float,
                margin: float, ids: np.ndarray, compiled: bool = True):
    """:func:`probe_points`' contacts as points: (push directions (m, 3), gaps (m,), sides' nodes
    (m, 2, 3), weights (m, 2, 3)): each vertex (``ids``: the surface vertices' nodes) at weight 1,
    then the face point's corners at their barycentric weights."""
    if compiled and _probe_block_compiled is not None:
        s = Ys.shape[0]
        out_n, out_g = np.empty((s + 1, 3)), np.empty(s + 1)
        sn, sw = np.empty((s + 1, 2, 3), dtype=np.int64), np.empty((s + 1, 2, 3))
        m = _probe_block_compiled(Ys, O, tri, np.asarray(position, dtype=float), tool.orientation, tool.half_extents,
                                  float(tool.radius), float(cutoff), float(tool.reach + margin), float(margin), ids,
                                  np.empty(s, dtype=np.int64),
                                  np.empty(s), np.empty((s, 3)), np.zeros(3), np.zeros(7), out_n, out_g, sn, sw)
        return out_n[:m], out_g[:m], sn[:m], sw[:m]
    i, gaps, n, face = probe_points(Ys, O, tri, tool, position, cutoff, margin, compiled=False)
    m = i.size + (face is not None)
    sn, sw = np.zeros((m, 2, 3), dtype=np.int64), np.zeros((m, 2, 3))
    sn[:i.size, 0, :] = ids[i][:, None]
    sw[:i.size, 0, 0] = 1.0
    normals, gap = n, gaps
    if face is not None:
        t, g, push, w = face
        sn[-1, 0] = ids[tri[t]]
        sw[-1, 0] = w
        normals, gap = np.vstack([n, push[None]]), np.append(gaps, g)
    return normals, gap, sn, sw
