"""A scene step's contact points in arrays (one row a point), and the compiled search of a body's
vertices against another body's triangles; see :mod:`rtfem.interaction.scene`.

Each point has its frame (columns: the normal from the other side, two tangents), its gap after
the trial steps, Coulomb's coefficient, the pair it is recorded under (``a``: a body's
index; ``b``: the index of the body, obstacle or tool it touches among the scene's names) and up
to two sides, each a body's index (or -1), three nodes and their weights: the first side gets
+frame r, the second -frame r (a vertex: its node at weight 1; a face point: the triangle's
corners at their barycentric weights, negated on the second side)."""

from __future__ import annotations

import math

import numpy as np

from .contact_points import _closest_on_triangle

__all__ = ["PointSet", "assemble", "contact_solve", "pair_block", "pair_faces", "probe_block", "probe_points", "rhs",
           "spread"]

FIELDS = ("normal", "gap", "mu", "a", "b", "tool", "sk", "sn", "sw")


class PointSet:
    """Blocks of contact points gathered one by one, joined into arrays by :meth:`join`."""

    def __init__(self) -> None:
        self.blocks: list[tuple] = []

    def vertices(self, normal, gap, mu: float, a: int, b: int, body: int, nodes, tool: int = -1) -> None:
        """Points on single vertices ``nodes`` of ``body`` (first side only)."""
        m = len(gap)
        if m == 0:
            return
        sn = np.zeros((m, 2, 3), dtype=np.int64)
        sn[:, 0, :] = np.asarray(nodes)[:, None]
        sw = np.zeros((m, 2, 3))
        sw[:, 0, 0] = 1.0
        self.add(normal, gap, mu, a, b, tool, (body, -1), sn, sw)

    def add(self, normal, gap, mu, a, b, tool, sides, sn, sw) -> None:
        """Points with their unit normals (m, 3) (from the other side), gaps, Coulomb's coefficient,
        pair (a, b), tool (or -1), the bodies of their two sides (``sides``: two indices, -1 for
        none), and the sides' nodes (m, 2, 3) and weights (m, 2, 3)."""
        m = len(gap)
        if m:
            sk = np.empty((m, 2), dtype=np.int64)
            sk[:, 0], sk[:, 1] = sides
            self.blocks.append((normal, np.asarray(gap, dtype=float), np.full(m, float(mu)), np.full(m, a),
                                np.full(m, b), np.full(m, tool), sk, sn, sw))

    @property
    def m(self) -> int:
        return sum(len(blk[1]) for blk in self.blocks)

    def join(self, compiled: bool = True) -> dict | None:
        """{field: the points' array, and "frame" (m, 3, 3): columns the normal and two tangents}, or
        None without points."""
        if not self.blocks:
            return None
        out = {name: np.concatenate([blk[i] for blk in self.blocks]) for i, name in enumerate(FIELDS)}
        if compiled and _frames_compiled is not None:
            out["frame"] = np.empty((out["gap"].size, 3, 3))
            _frames_compiled(np.ascontiguousarray(out["normal"], dtype=float), out["frame"])
        else:
            from .scene_tools import _frames

            out["frame"] = _frames(out["normal"])
        return out


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
        a0, a1, a2 = Ys[tri[t, 0], 0], Ys[tri[t, 0], 1], Ys[tri[t, 0], 2]
        u0, u1, u2 = Ys[tri[t, 1], 0] - a0, Ys[tri[t, 1], 1] - a1, Ys[tri[t, 1], 2] - a2
        v0, v1, v2 = Ys[tri[t, 2], 0] - a0, Ys[tri[t, 2], 1] - a1, Ys[tri[t, 2], 2] - a2
        n0, n1, n2 = u1 * v2 - u2 * v1, u2 * v0 - u0 * v2, u0 * v1 - u1 * v0
        size = math.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
        n0, n1, n2 = n0 / size, n1 / size, n2 / size
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
        if d < dmin:
            dmin, best = d, t
            face_w[0], face_w[1], face_w[2] = w[0], w[1], w[2]
            face[4], face[5], face[6] = qq[0] - q[0], qq[1] - q[1], qq[2] - q[2]
    face[0] = best
    if best < 0:
        return count
    a0, a1, a2 = Ys[tri[best, 0], 0], Ys[tri[best, 0], 1], Ys[tri[best, 0], 2]
    u0, u1, u2 = Ys[tri[best, 1], 0] - a0, Ys[tri[best, 1], 1] - a1, Ys[tri[best, 1], 2] - a2
    e0, e1, e2 = Ys[tri[best, 2], 0] - a0, Ys[tri[best, 2], 1] - a1, Ys[tri[best, 2], 2] - a2
    m0, m1, m2 = u1 * e2 - u2 * e1, u2 * e0 - u0 * e2, u0 * e1 - u1 * e0
    size = math.sqrt(m0 * m0 + m1 * m1 + m2 * m2)
    m0, m1, m2 = m0 / size, m1 / size, m2 / size
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


def _assemble(F, slot, sw, W, tool, inv_k, A):
    """A (3m, 3m): in the points' frames F (m, 3, 3), point d's displacement relative to its other
    side per unit force at point c, sum over the sides' nodes (``slot`` into W's 3x3 blocks, -1
    unused; weights ``sw``) of w_c w_d F_c^T W_pq F_d, plus F_c^T F_d / k for two points of a tool
    held by a spring of stiffness k (``tool``: each point's tool or -1; ``inv_k``: each tool's 1/k,
    0 for none). Blocks of nodes of different bodies are zero in W (block diagonal by body)."""
    m = F.shape[0]
    M = np.empty((3, 3))
    T = np.empty((3, 3))
    for c in range(m):
        for d in range(m):
            M[:] = 0.0
            for s in range(2):
                for i in range(3):
                    p = slot[c, s, i]
                    if p < 0:
                        continue
                    for t in range(2):
                        for j in range(3):
                            q = slot[d, t, j]
                            if q < 0:
                                continue
                            w = sw[c, s, i] * sw[d, t, j]
                            for x in range(3):
                                for y in range(3):
                                    M[x, y] += w * W[3 * p + x, 3 * q + y]
            if tool[c] >= 0 and tool[c] == tool[d]:
                for x in range(3):
                    M[x, x] += inv_k[tool[c]]
            for x in range(3):
                for b in range(3):
                    T[x, b] = M[x, 0] * F[d, 0, b] + M[x, 1] * F[d, 1, b] + M[x, 2] * F[d, 2, b]
            for a in range(3):
                for b in range(3):
                    A[3 * c + a, 3 * d + b] = F[c, 0, a] * T[0, b] + F[c, 1, a] * T[1, b] + F[c, 2, a] * T[2, b]


def assemble(F: np.ndarray, slot: np.ndarray, sw: np.ndarray, W: np.ndarray, tool: np.ndarray,
             inv_k: np.ndarray, compiled: bool = True) -> np.ndarray:
    """The contact problem's A (3m, 3m) in the points' frames: A = G^T (sum_k P_k W_k P_k^T + C) G with
    G the frames F (m, 3, 3), each point's sides' nodes ``slot`` (m, 2, 3) into the blocks of W (3u,
    3u; the bodies' one-step compliances, block diagonal by body; -1 for none) at weights ``sw``, and
    C the couplings of the tools' points (``tool`` (m,): each point's tool or -1): I / k between two
    points of a tool held by a spring k (``inv_k``: each tool's 1/k, 0 for a tool at its device)."""
    m = F.shape[0]
    tool = np.ascontiguousarray(tool, dtype=np.int64)
    inv_k = np.ascontiguousarray(inv_k, dtype=float).reshape(-1)
    if compiled and _assemble_compiled is not None:
        A = np.empty((3 * m, 3 * m))
        _assemble_compiled(np.ascontiguousarray(F), np.ascontiguousarray(slot), np.ascontiguousarray(sw),
                           np.ascontiguousarray(W), tool, inv_k if inv_k.size else np.zeros(1), A)
        return A
    u = W.shape[0] // 3
    B = np.zeros((m, 3, u, 3))  # B[(c, a), (p, x)] = sum of w F[c, x, a] over c's nodes at slot p
    c, s, i = np.nonzero(slot >= 0)
    np.add.at(B, (c, slice(None), slot[c, s, i]), sw[c, s, i][:, None, None] * F[c].transpose(0, 2, 1))
    B = B.reshape(3 * m, 3 * u)
    A = B @ W @ B.T
    for j in np.unique(tool[tool >= 0]).tolist():
        mine = np.flatnonzero(tool == j)
        E = F[mine].transpose(0, 2, 1).reshape(3 * mine.size, 3)  # the points' frames against the world's
        rows3 = (3 * mine[:, None] + np.arange(3)).ravel()
        A[np.ix_(rows3, rows3)] += E @ E.T * inv_k[j]
    return A


def _frames_into(N, out):
    """out[k] (3, 3): columns the unit normal N[k] and two unit tangents, as
    :func:`~rtfem.interaction.scene_tools._frames` writes them."""
    for k in range(N.shape[0]):
        size = math.sqrt(N[k, 0] ** 2 + N[k, 1] ** 2 + N[k, 2] ** 2)
        x, y, z = N[k, 0] / size, N[k, 1] / size, N[k, 2] / size
        if abs(x) < 0.9:  # n x e_x = (0, z, -y); else n x e_y = (-z, 0, x)
            a, b, c = 0.0 * x, z, -y
        else:
            a, b, c = -z, 0.0 * x, x
        size = math.sqrt(a * a + b * b + c * c)
        a, b, c = a / size, b / size, c / size
        out[k, 0, 0], out[k, 1, 0], out[k, 2, 0] = x, y, z
        out[k, 0, 1], out[k, 1, 1], out[k, 2, 1] = a, b, c
        out[k, 0, 2], out[k, 1, 2], out[k, 2, 2] = y * c - z * b, z * a - x * c, x * b - y * a


def _rhs_into(F, slot, sw, moved, gap, tool, move, force, inv_k, b):
    """b (m, 3): each point's gap (a coupled probe's shifted by its last force / k along the normal)
    and its slip over the trial step in its frame's tangents: the sides' nodes' displacements
    ``moved`` at their weights, less the probe's move."""
    for c in range(F.shape[0]):
        s0 = s1 = s2 = 0.0
        for s in range(2):
            for i in range(3):
                p = slot[c, s, i]
                if p >= 0:
                    s0 += sw[c, s, i] * moved[p, 0]
                    s1 += sw[c, s, i] * moved[p, 1]
                    s2 += sw[c, s, i] * moved[p, 2]
        b[c, 0] = gap[c]
        j = tool[c]
        if j >= 0:
            s0, s1, s2 = s0 - move[j, 0], s1 - move[j, 1], s2 - move[j, 2]
            b[c, 0] -= (F[c, 0, 0] * force[j, 0] + F[c, 1, 0] * force[j, 1] + F[c, 2, 0] * force[j, 2]) * inv_k[j]
        b[c, 1] = F[c, 0, 1] * s0 + F[c, 1, 1] * s1 + F[c, 2, 1] * s2
        b[c, 2] = F[c, 0, 2] * s0 + F[c, 1, 2] * s1 + F[c, 2, 2] * s2


def _spread(F, r, slot, sw, f, node_force):
    """f (m, 3): each point's force on its first side, F r; node_force (u, 3): at each side's nodes,
    w f (the second side's weights negative: the reaction)."""
    node_force[:] = 0.0
    for c in range(F.shape[0]):
        for x in range(3):
            f[c, x] = F[c, x, 0] * r[3 * c] + F[c, x, 1] * r[3 * c + 1] + F[c, x, 2] * r[3 * c + 2]
        for s in range(2):
            for i in range(3):
                p = slot[c, s, i]
                if p >= 0:
                    for x in range(3):
                        node_force[p, x] += sw[c, s, i] * f[c, x]


def rhs(F, slot, sw, moved, gap, tool, move, force, inv_k, compiled: bool = True) -> np.ndarray:
    """The contact problem's b (m, 3) (see :func:`_rhs_into`); numpy where numba is absent."""
    m = F.shape[0]
    b = np.empty((m, 3))
    if compiled and _rhs_compiled is not None:
        _rhs_compiled(F, slot, sw, moved, gap, tool, move, force, inv_k, b)
        return b
    on = slot >= 0
    slip = np.zeros((m, 3))
    np.add.at(slip, np.nonzero(on)[0], sw[on][:, None] * moved[slot[on]])
    probe = tool >= 0
    slip[probe] -= move[tool[probe]]
    b[:, 0] = gap
    b[probe, 0] -= np.einsum("ci,ci->c", F[probe, :, 0], force[tool[probe]]) * inv_k[tool[probe]]
    b[:, 1:] = np.einsum("cij,ci->cj", F[:, :, 1:], slip)
    return b


def spread(F, r, slot, sw, n_used: int, compiled: bool = True):
    """(f (m, 3), node_force (n_used, 3)) (see :func:`_spread`); numpy where numba is absent."""
    m = F.shape[0]
    if compiled and _spread_compiled is not None:
        f, node_force = np.empty((m, 3)), np.empty((n_used, 3))
        _spread_compiled(F, r, slot, sw, f, node_force)
        return f, node_force
    f = np.einsum("cij,cj->ci", F, r.reshape(m, 3))
    node_force = np.zeros((n_used, 3))
    c, s, i = np.nonzero(slot >= 0)
    np.add.at(node_force, slot[c, s, i], sw[c, s, i][:, None] * f[c])
    return f, node_force


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


def _contact(F, slot, sw, W, tool, inv_k, move, force, moved, gap, mu, max_sweeps, tol, A, b, r, f, node_force):
    """The whole contact solve in one call: b (:func:`_rhs_into`), A (:func:`_assemble`), the points
    whose normal compliance is not zero (a point on held nodes on both sides moves nothing: the
    supports take it) solved by the projected Gauss-Seidel of :mod:`rtfem.interaction.friction`, then
    the forces f and node_force (:func:`_spread`). Returns the sweeps."""
    m = F.shape[0]
    _rhs_into(F, slot, sw, moved, gap, tool, move, force, inv_k, b)
    _assemble(F, slot, sw, W, tool, inv_k, A)
    top = 0.0
    for c in range(m):
        top = max(top, A[3 * c, 3 * c])
    free = np.empty(m, dtype=np.int64)
    n = 0
    for c in range(m):
        if A[3 * c, 3 * c] > 1e-12 * max(top, 1e-300):
            free[n] = c
            n += 1
    r[:] = 0.0
    sweeps = 0
    if n > 0:
        As = np.empty((3 * n, 3 * n))
        bs = np.empty(3 * n)
        ms = np.empty(n)
        for i in range(n):
            ms[i] = mu[free[i]]
            for x in range(3):
                bs[3 * i + x] = b[free[i], x]
                for j in range(n):
                    for y in range(3):
                        As[3 * i + x, 3 * j + y] = A[3 * free[i] + x, 3 * free[j] + y]
        rs = np.zeros(3 * n)
        sweeps = _pgs_solver(As, np.ones(n, dtype=np.bool_), np.zeros((1, 1)), np.zeros((n, 3), dtype=np.int64),
                             np.zeros((n, 3)), np.zeros((n, 3, 3)), 0.0, bs, ms, rs, max_sweeps, tol)
        for i in range(n):
            for x in range(3):
                r[3 * free[i] + x] = rs[3 * i + x]
    _spread(F, r, slot, sw, f, node_force)
    return sweeps


def contact_solve(F, slot, sw, W, tool, inv_k, move, force, moved, gap, mu, compiled: bool = True):
    """The contact forces of all points: (each point's force on its first side f (m, 3), each used
    node's force (u, 3), PGS sweeps), from the frames F, the sides' slots and weights, the bodies'
    compliances W, the probes' couplings and moves, the nodes' displacements over the trial step,
    the gaps and Coulomb's coefficients (see :func:`_contact`); numpy where numba is absent."""
    from .friction import pgs

    m, u = F.shape[0], W.shape[0] // 3
    if compiled and _contact_compiled is not None:
        A, b, r = np.empty((3 * m, 3 * m)), np.empty((m, 3)), np.empty(3 * m)
        f, node_force = np.empty((m, 3)), np.empty((u, 3))
        sweeps = _contact_compiled(F, slot, sw, W, tool, inv_k, move, force, moved, gap, mu, 500, 1e-10,
                                   A, b, r, f, node_force)
        return f, node_force, int(sweeps)
    b = rhs(F, slot, sw, moved, gap, tool, move, force, inv_k, False)
    A = assemble(F, slot, sw, W, tool, inv_k, False)
    normal = np.diag(A)[0::3]
    free = normal > 1e-12 * max(float(normal.max()), 1e-300)
    r, sweeps = np.zeros(3 * m), 0
    if free.any():
        rows3 = (3 * np.flatnonzero(free)[:, None] + np.arange(3)).ravel()
        r[rows3], sweeps = pgs(A[np.ix_(rows3, rows3)], b[free].reshape(-1), mu[free])
    f, node_force = spread(F, r, slot, sw, u, False)
    return f, node_force, sweeps


_pair_faces_compiled = _probe_compiled = _assemble_compiled = _frames_compiled = _rhs_compiled = None
_spread_compiled = _pair_block_compiled = _probe_block_compiled = _contact_compiled = None
try:  # compiled when numba is present (the same code)
    import numba as _numba

    _opts = dict(cache=True, nogil=True, error_model="numpy")
    _pair_faces = _pair_faces_compiled = _numba.njit(**_opts)(_pair_faces)  # the block kernels call these
    _core = _numba.njit(**_opts)(_core)
    _probe = _probe_compiled = _numba.njit(**_opts)(_probe)
    _pair_block_compiled = _numba.njit(**_opts)(_pair_block)
    _probe_block_compiled = _numba.njit(**_opts)(_probe_block)
    _assemble_compiled = _numba.njit(**_opts)(_assemble)
    _frames_compiled = _numba.njit(**_opts)(_frames_into)
    _rhs_compiled = _numba.njit(**_opts)(_rhs_into)
    _spread_compiled = _numba.njit(**_opts)(_spread)
    from .friction import _pgs_compiled as _pgs_solver

    if _pgs_solver is not None:
        _rhs_into, _assemble, _spread = _rhs_compiled, _assemble_compiled, _spread_compiled  # for _contact
        _contact_compiled = _numba.njit(**_opts)(_contact)
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
        normal = np.cross(Yn[best, 1] - Yn[best, 0], Yn[best, 2] - Yn[best, 0])
        normal /= np.linalg.norm(normal)
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
