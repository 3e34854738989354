"""The full-order step's kernels beside the reduced models' (:mod:`rtfem.reduction.tet_kernels`, whose
element helpers they call): the corotated tets' internal forces summed at the nodes straight from the
nodal displacements, and the count of elements turned inside out (the lagged full-order step,
:mod:`rtfem.drivers.lagged_newmark`)."""

from __future__ import annotations

import math  # noqa: F401  (the helpers compiled here resolve their names in this module's globals)

import numpy as np

from ..fe.jit import compiled
from .tet_kernels import _add_stress_forces, _deformed_nodes, _element_forces, _gradient, _polar_rotation, _rotation

__all__ = ["solid_node_forces", "inverted_elements"]


def _solid_node_forces(u, cells, X, G, wdet, lm, f):
    """f (3n,) = the corotated-linear tets' internal forces summed at the nodes, at nodal displacements
    u (n, 3): :func:`_solid_element_forces` on u[cells] with the gather and the sum in the same loop
    (a full-order step's force evaluation: no (E, 3k) arrays in between)."""
    E, k = G.shape[0], G.shape[2]
    x = np.zeros((k, 3))
    Fm, R, Z, P = np.zeros((3, 3)), np.zeros((3, 3)), np.zeros((3, 3)), np.zeros((3, 3))
    Fe = np.zeros(3 * k)
    f[:] = 0.0
    for e in range(E):
        for i in range(k):
            for c in range(3):
                x[i, c] = X[e, i, c] + u[cells[e, i], c]
        _element_forces(x, G[e], wdet[e], lm[e, 0], lm[e, 1], Fe, Fm, R, Z, P)
        for i in range(k):
            for c in range(3):
                f[3 * cells[e, i] + c] += Fe[3 * i + c]


def solid_node_forces(u, cells, X, G, wdet, lm, f) -> bool:
    """f (3n,) = :func:`_solid_node_forces` compiled; False (f untouched) without numba."""
    fn = compiled("solid-nodes", _solid_node_forces, _element_forces, _polar_rotation, _rotation, _gradient,
                  _add_stress_forces)
    if fn is None:
        return False
    fn(u, cells, X, G, wdet, lm, f)
    return True


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
