"""Tetrahedral solid elements, batched over all elements: linear (4-node, constant strain) and
quadratic (10-node, isoparametric) tets, small-strain isotropic elasticity.

Stiffness: k_(ia)(jb) = int lambda g_ia g_jb + mu (g_ib g_ja + delta_ab g_i . g_j) dV with g_i the
gradient of shape function i (Zienkiewicz & Taylor, The Finite Element Method, vol. 1, ch. 6 and 8;
the same B^T D B written without forming B). Mass: consistent rho int N_i N_j dV (x I_3), or
lumped: rho V / 4 per corner for the linear tet, HRZ diagonal scaling for the quadratic one
(Hinton, Rock & Zienkiewicz 1976: the consistent diagonal scaled to the element mass; row sums
would give negative corner masses). Quadrature: Stroud's conical product rule (Gauss-Jacobi in
collapsed coordinates), exact to degree 2n - 1 with n points per direction.

Element dof order is node-major: dof 3 i + a is node i's translation a.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from scipy.special import roots_jacobi

from .errors import MeshError
from .material import Material

__all__ = ["ELEMENTS", "MASSES", "shape_functions", "tet_rule", "element_matrices"]

ELEMENTS = ("tet4", "tet10")
MASSES = ("lumped", "consistent")


@lru_cache(maxsize=None)
def tet_rule(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Points (q, 3) in the reference tet {x, y, z >= 0, x + y + z <= 1} and weights (q,)
    summing to 1/6: Stroud's conical product rule with n points per direction, exact for
    polynomials of degree 2n - 1."""
    ta, wa = roots_jacobi(n, 2.0, 0.0)
    tb, wb = roots_jacobi(n, 1.0, 0.0)
    tc, wc = roots_jacobi(n, 0.0, 0.0)
    a, b, c = (ta + 1) / 2, (tb + 1) / 2, (tc + 1) / 2
    wa, wb, wc = wa / 8, wb / 4, wc / 2
    A, B, C = np.meshgrid(a, b, c, indexing="ij")
    W = (wa[:, None, None] * wb[None, :, None] * wc[None, None, :]).ravel()
    x = A.ravel()
    y = ((1 - A) * B).ravel()
    z = ((1 - A) * (1 - B) * C).ravel()
    return np.column_stack([x, y, z]), W


def shape_functions(element: str, xi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Shape functions (q, k) and their reference gradients (q, k, 3) at points xi (q, 3)."""
    xi = np.atleast_2d(xi)
    L = np.column_stack([1 - xi.sum(axis=1), xi])  # barycentric (q, 4)
    dL = np.array([[-1.0, -1.0, -1.0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])  # dL_i/dxi (4, 3)
    if element == "tet4":
        return L, np.broadcast_to(dL, (xi.shape[0], 4, 3)).copy()
    from .tetmesh import TET10_EDGES

    N = np.empty((xi.shape[0], 10))
    dN = np.empty((xi.shape[0], 10, 3))
    N[:, :4] = L * (2 * L - 1)
    dN[:, :4] = (4 * L - 1)[:, :, None] * dL[None]
    for k, (i, j) in enumerate(TET10_EDGES):
        N[:, 4 + k] = 4 * L[:, i] * L[:, j]
        dN[:, 4 + k] = 4 * (L[:, i, None] * dL[j] + L[:, j, None] * dL[i])
    return N, dN


def _lame(material: Material) -> tuple[float, float]:
    E, nu = material.E, material.nu
    return E * nu / ((1 + nu) * (1 - 2 * nu)), E / (2 * (1 + nu))


def _gradients(X: np.ndarray, dN: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Physical shape gradients (m, k, 3) and det J (m,) at one point, from reference gradients (k, 3)."""
    J = np.einsum("mki,kj->mij", X, dN)  # dx_i / dxi_j
    det = np.linalg.det(J)
    if np.any(det <= 0):
        bad = int(np.flatnonzero(det <= 0)[0])
        raise MeshError(f"element {bad} has a non-positive Jacobian ({det[bad]:.3g}) at a quadrature point: a curved "
                        "10-node tet folded over itself; straighten its mid-edge nodes or re-mesh")
    return np.einsum("kj,mji->mki", dN, np.linalg.inv(J)), det


def element_matrices(X: np.ndarray, material: Material, element: str, mass: str) -> tuple[np.ndarray, np.ndarray]:
    """Element stiffness (m, 3k, 3k) and mass (m, k, k) per translation component (the full
    element mass is this matrix times I_3; diagonal for ``mass='lumped'``), for nodes X (m, k, 3)."""
    lam, mu = _lame(material)
    m, k = X.shape[0], X.shape[1]
    rho = material.density
    if element == "tet4":
        G, det = _gradients(X, shape_functions("tet4", np.zeros((1, 3)))[1][0])
        vol = det / 6.0
        Ke = _stiffness_point(G, vol, lam, mu)
        if mass == "lumped":
            Me = np.zeros((m, 4, 4))
            Me[:, range(4), range(4)] = (rho * vol / 4)[:, None]
        else:
            Me = (rho * vol / 20)[:, None, None] * (np.ones((4, 4)) + np.eye(4))[None]
        return Ke, Me
    pts, w = tet_rule(2)
    _, dN = shape_functions("tet10", pts)
    Ke = np.zeros((m, 3 * k, 3 * k))
    for q in range(pts.shape[0]):
        G, det = _gradients(X, dN[q])
        Ke += _stiffness_point(G, w[q] * det, lam, mu)
    pts, w = tet_rule(3)
    N, dN = shape_functions("tet10", pts)
    Me = np.zeros((m, k, k))
    for q in range(pts.shape[0]):
        det = np.linalg.det(np.einsum("mki,kj->mij", X, dN[q]))
        Me += (rho * w[q] * det)[:, None, None] * np.outer(N[q], N[q])[None]
    if mass == "lumped":
        d = np.einsum("mii->mi", Me)
        total = Me.sum(axis=(1, 2))
        Me = np.zeros_like(Me)
        Me[:, range(k), range(k)] = d * (total / d.sum(axis=1))[:, None]
    return Ke, Me


def _stiffness_point(G: np.ndarray, wdet: np.ndarray, lam: float, mu: float) -> np.ndarray:
    """sum over one quadrature point of B^T D B w det J, written with the gradients G (m, k, 3)."""
    m, k = G.shape[:2]
    gg = np.einsum("mia,mja->mij", G, G)
    K = lam * np.einsum("mia,mjb->miajb", G, G) + mu * np.einsum("mib,mja->miajb", G, G)
    K += mu * gg[:, :, None, :, None] * np.eye(3)[None, None, :, None, :]
    return (wdet[:, None, None, None, None] * K).reshape(m, 3 * k, 3 * k)
