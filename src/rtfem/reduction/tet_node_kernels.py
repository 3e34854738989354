"""The full-order step's kernels beside the reduced models' (:mod:`rtfem.reduction.tet_kernels`, whose
element helpers they call): the corotated tets' internal forces summed at the nodes straight from the
nodal displacements (the elements shared among threads), and the count of elements turned inside out
(the lagged full-order step, :mod:`rtfem.drivers.lagged_newmark`)."""

from __future__ import annotations

import math  # noqa: F401  (the helpers compiled here resolve their names in this module's globals)

import numpy as np

from ..fe.jit import chunked, compiled
from .tet_kernels import _add_stress_forces, _deformed_nodes, _element_forces, _gradient, _polar_rotation, _rotation

__all__ = ["solid_node_forces", "inverted_elements"]


def _tet4_forces(u, cells, X, G, wdet, lm, Fe):
    """Fe (E, 12) = each corotated-linear tet4's nodal forces at nodal displacements u (n, 3)
    (:func:`_element_forces`'s P = 2 mu (F - R) + lambda tr(S - I) R at the tet4's one point, unrolled:
    2.4x faster than the generic loop on a 9k-tet liver). Returns how many have det F <= 0 (turned
    inside out: their rotation is the SVD's)."""
    Fm, R, Z = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3))
    bad = 0
    for e in range(cells.shape[0]):
        n0, n1, n2, n3 = cells[e, 0], cells[e, 1], cells[e, 2], cells[e, 3]
        for a in range(3):
            x0, x1 = X[e, 0, a] + u[n0, a], X[e, 1, a] + u[n1, a]
            x2, x3 = X[e, 2, a] + u[n2, a], X[e, 3, a] + u[n3, a]
            for b in range(3):
                Fm[a, b] = x0 * G[e, 0, 0, b] + x1 * G[e, 0, 1, b] + x2 * G[e, 0, 2, b] + x3 * G[e, 0, 3, b]
        det = Fm[0, 0] * (Fm[1, 1] * Fm[2, 2] - Fm[1, 2] * Fm[2, 1]) \
            - Fm[0, 1] * (Fm[1, 0] * Fm[2, 2] - Fm[1, 2] * Fm[2, 0]) \
            + Fm[0, 2] * (Fm[1, 0] * Fm[2, 1] - Fm[1, 1] * Fm[2, 0])
        if not det > 0.0:
            bad += 1
        _rotation(Fm, R, Z)
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


def _node_element_forces(u, cells, X, G, wdet, lm, Fe):
    """Fe (E, 3k) = each corotated-linear element's nodal forces at nodal displacements u (n, 3), any
    element (a tet10's four points): :func:`_element_forces` on its nodes gathered from u. Returns 0
    (the inversion check of a tet10 looks at its corners too: :func:`inverted_elements`)."""
    k = cells.shape[1]
    x = np.zeros((k, 3))
    Fm, R, Z, P = np.zeros((3, 3)), np.zeros((3, 3)), np.zeros((3, 3)), np.zeros((3, 3))
    for e in range(cells.shape[0]):
        for i in range(k):
            for c in range(3):
                x[i, c] = X[e, i, c] + u[cells[e, i], c]
        _element_forces(x, G[e], wdet[e], lm[e, 0], lm[e, 1], Fe[e], Fm, R, Z, P)
    return 0


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
    fn = compiled("solid-tet4", _tet4_forces, _polar_rotation, _rotation) if tet4 else \
        compiled("solid-node-elements", _node_element_forces, _element_forces, _polar_rotation, _rotation, _gradient,
                 _add_stress_forces)
    scatter = compiled("scatter", _scatter)
    if fn is None or scatter is None:
        return None
    Fe = np.empty((cells.shape[0], 3 * cells.shape[1]))
    counts = chunked(cells.shape[0], lambda lo, hi: fn(u, cells[lo:hi], X[lo:hi], G[lo:hi], wdet[lo:hi], lm[lo:hi],
                                                         Fe[lo:hi]))
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
