"""The full-order step's kernels beside the reduced models' (:mod:`rtfem.reduction.tet_kernels`, whose
element helpers they call): the corotated tets' internal forces summed at the nodes straight from the
nodal displacements (the elements shared among threads), and the count of elements turned inside out
(the lagged full-order step, :mod:`rtfem.drivers.lagged_newmark`)."""

from __future__ import annotations

import math

import numpy as np

from ..fe.jit import chunked, compiled
from .tet_kernels import _deformed_nodes, _gradient, _polar_rotation, _rotation

__all__ = ["solid_node_forces", "inverted_elements"]


BLOCK = 32  # tet4s whose polar decompositions run side by side (the compiler's vector lanes)
SIDE_BY_SIDE = 4  # scaled Newton iterations taken by every element of a block (then each unconverged its own)


def _tet4_forces(u, cells, X, G, wdet, lm, Fe):
    """Fe (E, 12) = each corotated-linear tet4's nodal forces at nodal displacements u (n, 3)
    (:func:`_element_forces`'s P = 2 mu (F - R) + lambda tr(S - I) R at the tet4's one point). The
    rotations of a block of :data:`BLOCK` elements are found side by side: :data:`SIDE_BY_SIDE` of
    :func:`_polar_rotation`'s scaled Newton iterations on every element's F at once, in straight-line
    code the compiler vectorizes (a strain of up to ~10 % has converged by then: the last change
    below 1e-8); an element not converged (a larger strain) goes on from its iterate, which has F's
    polar factor, and one with det F <= 0 (turned inside out) takes the SVD's rotation, each by
    :func:`_rotation`. On the 9k-tet liver of benchmarks/fullorder.py 0.45 ms on one thread against
    1.3 ms element by element, the forces the same to 1e-13. Returns how many have det F <= 0."""
    B = BLOCK
    Fb, Rb, change, detF = np.empty((9, B)), np.empty((9, B)), np.empty(B), np.empty(B)
    Fm, R, Z = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3))
    bad = 0
    for e0 in range(0, cells.shape[0], B):
        nb = min(B, cells.shape[0] - e0)
        for j in range(nb):
            e = e0 + j
            n0, n1, n2, n3 = cells[e, 0], cells[e, 1], cells[e, 2], cells[e, 3]
            for a in range(3):
                x0, x1 = X[e, 0, a] + u[n0, a], X[e, 1, a] + u[n1, a]
                x2, x3 = X[e, 2, a] + u[n2, a], X[e, 3, a] + u[n3, a]
                for b in range(3):
                    v = x0 * G[e, 0, 0, b] + x1 * G[e, 0, 1, b] + x2 * G[e, 0, 2, b] + x3 * G[e, 0, 3, b]
                    Fb[3 * a + b, j] = v
                    Rb[3 * a + b, j] = v
        for it in range(SIDE_BY_SIDE):
            _newton_lanes(Rb, change, detF, nb, it == 0)
        for j in range(nb):
            e = e0 + j
            if not detF[j] > 0.0:
                bad += 1
            _lane_rotation(Fb, Rb, change, detF, j, Fm, R, Z)
            trS = 0.0
            for a in range(3):
                for b in range(3):
                    trS += R[a, b] * Fm[a, b]
            w = wdet[e, 0]
            m2, t = 2.0 * lm[e, 1] * w, lm[e, 0] * (trS - 3.0) * w
            for a in range(3):
                p0 = m2 * (Fm[a, 0] - R[a, 0]) + t * R[a, 0]
                p1 = m2 * (Fm[a, 1] - R[a, 1]) + t * R[a, 1]
                p2 = m2 * (Fm[a, 2] - R[a, 2]) + t * R[a, 2]
                for i in range(4):
                    Fe[e, 3 * i + a] = p0 * G[e, 0, i, 0] + p1 * G[e, 0, i, 1] + p2 * G[e, 0, i, 2]
    return bad


def _newton_lanes(Rb, change, detF, nb, first):
    """One scaled Newton step R <- (g R + R^-T / g) / 2 of :func:`_polar_rotation` on each of the first nb
    lanes of Rb (9, B) (row-major 3 x 3), its squared change in change, det of F (the first iterate) in
    detF where ``first``: straight-line arithmetic over the lanes, which the compiler vectorizes (an
    inverted lane's NaN is redone by the caller)."""
    for j in range(nb):
        r0, r1, r2, r3, r4, r5, r6, r7, r8 = Rb[0, j], Rb[1, j], Rb[2, j], Rb[3, j], Rb[4, j], Rb[5, j], Rb[6, j], \
            Rb[7, j], Rb[8, j]
        z0, z1, z2 = r4 * r8 - r5 * r7, r5 * r6 - r3 * r8, r3 * r7 - r4 * r6  # cof(R) = det(R) R^-T
        z3, z4, z5 = r2 * r7 - r1 * r8, r0 * r8 - r2 * r6, r1 * r6 - r0 * r7
        z6, z7, z8 = r1 * r5 - r2 * r4, r2 * r3 - r0 * r5, r0 * r4 - r1 * r3
        det = r0 * z0 + r1 * z1 + r2 * z2
        if first:
            detF[j] = det
        inv = 1.0 / det
        nr = r0 * r0 + r1 * r1 + r2 * r2 + r3 * r3 + r4 * r4 + r5 * r5 + r6 * r6 + r7 * r7 + r8 * r8
        nz = z0 * z0 + z1 * z1 + z2 * z2 + z3 * z3 + z4 * z4 + z5 * z5 + z6 * z6 + z7 * z7 + z8 * z8
        g = math.sqrt(math.sqrt(nz / nr) * inv)
        a, b = 0.5 * g, 0.5 * inv / g
        y0, y1, y2, y3, y4 = a * r0 + b * z0, a * r1 + b * z1, a * r2 + b * z2, a * r3 + b * z3, a * r4 + b * z4
        y5, y6, y7, y8 = a * r5 + b * z5, a * r6 + b * z6, a * r7 + b * z7, a * r8 + b * z8
        change[j] = (y0 - r0) ** 2 + (y1 - r1) ** 2 + (y2 - r2) ** 2 + (y3 - r3) ** 2 + (y4 - r4) ** 2 \
            + (y5 - r5) ** 2 + (y6 - r6) ** 2 + (y7 - r7) ** 2 + (y8 - r8) ** 2
        Rb[0, j], Rb[1, j], Rb[2, j], Rb[3, j], Rb[4, j] = y0, y1, y2, y3, y4
        Rb[5, j], Rb[6, j], Rb[7, j], Rb[8, j] = y5, y6, y7, y8


def _node_element_forces(u, cells, X, G, wdet, lm, Fe):
    """Fe (E, 3k) = each corotated-linear element's nodal forces at nodal displacements u (n, 3), any
    element (a tet10's four points): the rotations of :data:`BLOCK` (element, point) pairs at a time
    side by side, as :func:`_tet4_forces` does (the 960-tet10 block of issue 56: 1.03 ms on one
    thread against 1.86 ms element by element), each point's share w P G_i added to its element's.
    Returns 0 (the inversion check of a tet10 looks at its corners too: :func:`inverted_elements`)."""
    E, nq, k = G.shape[0], G.shape[1], G.shape[2]
    B = BLOCK
    Fb, Rb, change, detF = np.empty((9, B)), np.empty((9, B)), np.empty(B), np.empty(B)
    Fm, R, Z = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3))
    Fe[:] = 0.0
    for s0 in range(0, E * nq, B):
        nb = min(B, E * nq - s0)
        for j in range(nb):
            e, q = (s0 + j) // nq, (s0 + j) % nq
            for a in range(3):
                for b in range(3):
                    Fm[a, b] = 0.0
            for i in range(k):
                node = cells[e, i]
                for a in range(3):
                    xa = X[e, i, a] + u[node, a]
                    for b in range(3):
                        Fm[a, b] += xa * G[e, q, i, b]
            for a in range(3):
                for b in range(3):
                    Fb[3 * a + b, j] = Fm[a, b]
                    Rb[3 * a + b, j] = Fm[a, b]
        for it in range(SIDE_BY_SIDE):
            _newton_lanes(Rb, change, detF, nb, it == 0)
        for j in range(nb):
            e, q = (s0 + j) // nq, (s0 + j) % nq
            _lane_rotation(Fb, Rb, change, detF, j, Fm, R, Z)
            trS = 0.0
            for a in range(3):
                for b in range(3):
                    trS += R[a, b] * Fm[a, b]
            w = wdet[e, q]
            m2, t = 2.0 * lm[e, 1] * w, lm[e, 0] * (trS - 3.0) * w
            for a in range(3):
                p0 = m2 * (Fm[a, 0] - R[a, 0]) + t * R[a, 0]
                p1 = m2 * (Fm[a, 1] - R[a, 1]) + t * R[a, 1]
                p2 = m2 * (Fm[a, 2] - R[a, 2]) + t * R[a, 2]
                for i in range(k):
                    Fe[e, 3 * i + a] += p0 * G[e, q, i, 0] + p1 * G[e, q, i, 1] + p2 * G[e, q, i, 2]
    return 0


def _lane_rotation(Fb, Rb, change, detF, j, Fm, R, Z):
    """Fm, R (3, 3) = lane j's deformation gradient and its rotation after the side-by-side iterations:
    the lane's own where it converged, else :func:`_rotation` from its iterate (F's polar factor), or
    from F itself where det F <= 0 (the SVD's)."""
    for a in range(3):
        for b in range(3):
            Fm[a, b] = Fb[3 * a + b, j]
            R[a, b] = Rb[3 * a + b, j]
    if not detF[j] > 0.0:
        _rotation(Fm, R, Z)
    elif not change[j] < 1e-16:
        for a in range(3):
            for b in range(3):
                Z[a, b] = R[a, b]
        _rotation(Z, R, Fm)
        for a in range(3):
            for b in range(3):
                Fm[a, b] = Fb[3 * a + b, j]


def _scatter(cells, Fe, f):
    """f (3n,) = the element forces Fe (E, 3k) summed at the nodes, element by element (the same
    order whatever the threads that made Fe: a run is reproducible bit for bit)."""
    f[:] = 0.0
    for e in range(cells.shape[0]):
        for i in range(cells.shape[1]):
            for c in range(3):
                f[3 * cells[e, i] + c] += Fe[e, 3 * i + c]


def solid_node_forces(u, cells, X, G, wdet, lm, f):
    """f (3n,) = the corotated-linear elements' internal forces summed at the nodes at nodal
    displacements u (n, 3) (:func:`_tet4_forces` for tet4s, else :func:`_node_element_forces`), the
    elements shared among the threads of :func:`rtfem.fe.jit.chunked`. Returns how many tet4s are
    turned inside out (0 for other elements), or None (f untouched) without numba."""
    tet4 = cells.shape[1] == 4 and G.shape[1] == 1
    fn = compiled("solid-tet4", _tet4_forces, _newton_lanes, _lane_rotation, _polar_rotation, _rotation) \
        if tet4 else compiled("solid-node-elements", _node_element_forces, _newton_lanes, _lane_rotation, _polar_rotation,
                              _rotation)
    scatter = compiled("scatter", _scatter)
    if fn is None or scatter is None:
        return None
    Fe = np.empty((cells.shape[0], 3 * cells.shape[1]))
    counts = chunked(cells.shape[0], lambda lo, hi: fn(u, cells[lo:hi], X[lo:hi], G[lo:hi], wdet[lo:hi], lm[lo:hi],
                                                         Fe[lo:hi]), G.shape[1])
    scatter(cells, Fe, f)
    return int(sum(counts))


def _inverted(V, X, G, out):
    """out (E,) = whether each element has det F <= 0 at any of the points of G (E, np, k, 3) (its
    quadrature points, and a tet10's corners): an element turned inside out. Returns how many."""
    E, npt, k = G.shape[0], G.shape[1], G.shape[2]
    x = np.zeros((k, 3))
    Fm = np.zeros((3, 3))
    count = 0
    for e in range(E):
        _deformed_nodes(X, V, e, x)
        bad = False
        for q in range(npt):
            _gradient(x, G[e, q], Fm)
            d = Fm[0, 0] * (Fm[1, 1] * Fm[2, 2] - Fm[1, 2] * Fm[2, 1]) \
                - Fm[0, 1] * (Fm[1, 0] * Fm[2, 2] - Fm[1, 2] * Fm[2, 0]) \
                + Fm[0, 2] * (Fm[1, 0] * Fm[2, 1] - Fm[1, 1] * Fm[2, 0])
            if not d > 0.0:
                bad = True
        out[e] = bad
        count += bad
    return count


def inverted_elements(V, X, G) -> np.ndarray:
    """(E,) whether each element has det F <= 0 at a point of G (E, np, k, 3), at element dofs V
    (E, 3k) on rest nodes X (E, k, 3): compiled, or batched numpy without numba."""
    out = np.zeros(G.shape[0], dtype=np.bool_)
    fn = compiled("inverted", _inverted, _gradient, _deformed_nodes)
    if fn is not None:
        fn(np.ascontiguousarray(V), X, G, out)
        return out
    x = X + V.reshape(X.shape)
    for q in range(G.shape[1]):
        out |= ~(np.linalg.det(np.einsum("eka,ekb->eab", x, G[:, q])) > 0.0)
    return out
