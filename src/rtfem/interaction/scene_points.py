"""A scene step's contact points in arrays (one row a point) and their frictional problem, solved
in one compiled call (:func:`contact_solve`); see :mod:`rtfem.interaction.scene` (the points are
found by :mod:`rtfem.interaction.scene_search`).

Each point has its frame (columns: the normal from the other side, two tangents), its gap after
the trial steps, Coulomb's coefficient, the pair it is recorded under (``a``: a body's
index; ``b``: the index of the body, obstacle or tool it touches among the scene's names) and up
to two sides, each a body's index (or -1), three nodes and their weights: the first side gets
+frame r, the second -frame r (a vertex: its node at weight 1; a face point: the triangle's
corners at their barycentric weights, negated on the second side)."""

from __future__ import annotations

import math

import numpy as np


__all__ = ["PointSet", "assemble", "contact_solve", "rhs", "spread"]

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


def rhs(F, slot, sw, moved, gap, tool, move, force, inv_k) -> np.ndarray:
    """The contact problem's b (m, 3) of :func:`_rhs_into`, in numpy (the path without numba: the
    compiled one runs inside :func:`contact_solve`)."""
    m = F.shape[0]
    b = np.empty((m, 3))
    on = slot >= 0
    slip = np.zeros((m, 3))
    np.add.at(slip, np.nonzero(on)[0], sw[on][:, None] * moved[slot[on]])
    probe = tool >= 0
    slip[probe] -= move[tool[probe]]
    b[:, 0] = gap
    b[probe, 0] -= np.einsum("ci,ci->c", F[probe, :, 0], force[tool[probe]]) * inv_k[tool[probe]]
    b[:, 1:] = np.einsum("cij,ci->cj", F[:, :, 1:], slip)
    return b


def spread(F, r, slot, sw, n_used: int):
    """(f (m, 3), node_force (n_used, 3)) of :func:`_spread`, in numpy (the path without numba: the
    compiled one runs inside :func:`contact_solve`)."""
    m = F.shape[0]
    f = np.einsum("cij,cj->ci", F, r.reshape(m, 3))
    node_force = np.zeros((n_used, 3))
    c, s, i = np.nonzero(slot >= 0)
    np.add.at(node_force, slot[c, s, i], sw[c, s, i][:, None] * f[c])
    return f, node_force


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
    b = rhs(F, slot, sw, moved, gap, tool, move, force, inv_k)
    A = assemble(F, slot, sw, W, tool, inv_k, False)
    normal = np.diag(A)[0::3]
    free = normal > 1e-12 * max(float(normal.max()), 1e-300)
    r, sweeps = np.zeros(3 * m), 0
    if free.any():
        rows3 = (3 * np.flatnonzero(free)[:, None] + np.arange(3)).ravel()
        r[rows3], sweeps = pgs(A[np.ix_(rows3, rows3)], b[free].reshape(-1), mu[free])
    f, node_force = spread(F, r, slot, sw, u)
    return f, node_force, sweeps


_assemble_compiled = _frames_compiled = _rhs_compiled = _spread_compiled = _contact_compiled = None
try:  # compiled when numba is present (the same code)
    import numba as _numba

    _opts = dict(cache=True, nogil=True, error_model="numpy")
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
