"""Tetrahedral solid elements, batched over all elements: linear (4-node, constant strain) and
quadratic (10-node, isoparametric) tets, small-strain isotropic elasticity.

Stiffness: k_(ia)(jb) = int lambda g_ia g_jb + mu (g_ib g_ja + delta_ab g_i . g_j) dV with g_i the
gradient of shape function i (Zienkiewicz & Taylor, The Finite Element Method, vol. 1, ch. 6 and 8;
the same B^T D B written without forming B). Mass: consistent rho int N_i N_j dV (x I_3), or
lumped: rho V / 4 per corner for the linear tet, HRZ diagonal scaling for the quadratic one
(Hinton, Rock & Zienkiewicz 1976: the consistent diagonal scaled to the element mass; row sums
would give negative corner masses). Quadrature: Stroud's conical product rule (Gauss-Jacobi in
collapsed coordinates), exact to degree 2n - 1 with n points per direction: 8 points for the
quadratic tet's stiffness and corotational forces. (CalculiX's C3D10 takes 4 points, exact to
degree 2: the same linear stiffness on a straight-sided tet10, tests/verification/test_calculix.py.
With them the corotational forces cost half, but the default liver's reduced model moved from 6.0
to 10.1 % of its own full order's grasped equilibrium, benchmarks/viewer_settings.py: the grasp's
local large strain is where the two rules differ.)

Element dof order is node-major: dof 3 i + a is node i's translation a.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from ..errors import MeshError
from .material import Material
from .rotations import cross_matrices

__all__ = ["ELEMENTS", "MASSES", "shape_functions", "tet_rule", "element_matrices"]

ELEMENTS = ("tet4", "tet10", "tet4-anp")
MASSES = ("lumped", "consistent")


@lru_cache(maxsize=None)
def tet_rule(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Points (q, 3) in the reference tet {x, y, z >= 0, x + y + z <= 1} and weights (q,)
    summing to 1/6: Stroud's conical product rule with n points per direction, exact for
    polynomials of degree 2n - 1."""
    from scipy.special import roots_jacobi  # here: importing scipy.special is 30-45 ms of a fresh process

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
    if element in ("tet4", "tet4-anp"):
        return L, np.broadcast_to(dL, (xi.shape[0], 4, 3)).copy()
    from ..mesh.tetmesh import TET10_EDGES

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


def element_lame(material: Material, element: str) -> tuple[float, float]:
    """Lame's (lam, mu) of the element's own stiffness: tet4-anp's is the deviatoric part only
    (lam = -2 mu / 3), its volumetric part being the nodes' (:func:`anp_volumetric`)."""
    lam, mu = _lame(material)
    return (-2.0 * mu / 3.0 if element == "tet4-anp" else lam), mu


def stiffness_rule(element: str) -> tuple[np.ndarray, np.ndarray]:
    """The stiffness's quadrature: reference gradients dN (q, k, 3) and weights (q,) summing to 1/6
    (one point for tet4, whose gradients are constant; Stroud's 4 points for tet10: exact)."""
    if element in ("tet4", "tet4-anp"):
        return shape_functions("tet4", np.zeros((1, 3)))[1], np.array([1.0 / 6.0])
    pts, w = tet_rule(2)
    return shape_functions("tet10", pts)[1], w


def element_matrices(X: np.ndarray, material: Material, element: str, mass: str) -> tuple[np.ndarray, np.ndarray]:
    """Element stiffness (m, 3k, 3k) and mass (m, k, k) per translation component (the full
    element mass is this matrix times I_3; diagonal for ``mass='lumped'``), for nodes X (m, k, 3)."""
    lam, mu = element_lame(material, element)
    m, k = X.shape[0], X.shape[1]
    dN, w = stiffness_rule(element)
    Ke = np.zeros((m, 3 * k, 3 * k))
    vol = np.zeros(m)
    for q in range(w.size):
        G, det = _gradients(X, dN[q])
        Ke += _stiffness_point(G, w[q] * det, lam, mu)
        vol += w[q] * det
    return Ke, element_mass(X, material, element, mass, vol)


def element_mass(X: np.ndarray, material: Material, element: str, mass: str, vol: np.ndarray) -> np.ndarray:
    """The element mass (m, k, k) per translation component, for nodes X (m, k, 3) of tets of
    volumes ``vol`` (m,): diagonal for ``mass='lumped'`` (a quarter each for tet4, HRZ for tet10)."""
    m, k = X.shape[0], X.shape[1]
    rho = material.density
    if element in ("tet4", "tet4-anp"):
        if mass == "lumped":
            Me = np.zeros((m, 4, 4))
            Me[:, range(4), range(4)] = (rho * vol / 4)[:, None]
        else:
            Me = (rho * vol / 20)[:, None, None] * (np.ones((4, 4)) + np.eye(4))[None]
        return Me
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
    return Me


def anp_volumetric(X: np.ndarray, T: np.ndarray, material: Material, n_nodes: int):
    """The volumetric stiffness of the averaged-nodal-pressure tet4 (Bonet & Burton, Commun. Numer.
    Meth. Engng 14 (1998) 437, linearized): each node a gets the volume V_a = sum of a quarter of its
    tets' volumes and the volumetric strain theta_a = sum_e (V_e / 4) div u_e / V_a; the energy
    sum_a kappa / 2 V_a theta_a^2 gives K_vol = C^T diag(kappa / V_a) C with the rows c_a = sum_e
    (V_e / 4) grad(div u_e) (sparse over the node's patch). With the elements' deviatoric stiffness
    (lambda -> -2 mu / 3) it is the whole stiffness: one pressure per node instead of per tet, so a
    mesh of tets is no longer over-constrained as nu -> 0.5 (locking). Returns K_vol (3n, 3n, CSR)."""
    import scipy.sparse as sp

    lam, mu = _lame(material)
    kappa = lam + 2.0 * mu / 3.0
    G, det = _gradients(X[T], shape_functions("tet4", np.zeros((1, 3)))[1][0])
    vol = det / 6.0
    ne = T.shape[0]
    Va = np.bincount(T.ravel(), weights=np.repeat(vol / 4.0, 4), minlength=n_nodes)
    dofs = (3 * T[:, :, None] + np.arange(3)).reshape(ne, 12)
    rows = np.repeat(T, 12, axis=1).ravel()  # node a of tet e, for each of e's 12 dofs
    cols = np.tile(dofs, (1, 4)).ravel()
    vals = np.tile((vol / 4.0)[:, None] * G.reshape(ne, 12), (1, 4)).ravel()
    C = sp.csr_matrix((vals, (rows, cols)), shape=(n_nodes, 3 * n_nodes))
    used = Va > 0
    w = np.zeros(n_nodes)
    w[used] = kappa / Va[used]
    return (C.T @ sp.diags(w) @ C).tocsr()


def _stiffness_point(G: np.ndarray, wdet: np.ndarray, lam: float, mu: float) -> np.ndarray:
    """sum over one quadrature point of B^T D B w det J, written with the gradients G (m, k, 3)."""
    m, k = G.shape[:2]
    gg = G @ np.swapaxes(G, 1, 2)  # (m, k, k): G_i . G_j
    Gw = G.reshape(m, 3 * k) * wdet[:, None]
    outer = (Gw[:, :, None] * G.reshape(m, 1, 3 * k)).reshape(m, k, 3, k, 3)  # w G_ia G_jb (broadcast: 3x einsum's speed)
    K = lam * outer + mu * outer.transpose(0, 1, 4, 3, 2)  # + mu w G_ib G_ja
    K += (mu * wdet)[:, None, None, None, None] * gg[:, :, None, :, None] * np.eye(3)[None, None, :, None, :]
    return K.reshape(m, 3 * k, 3 * k)


# ---------------------------------------------------------------------------------------------
# corotational (geometrically nonlinear) tets: the corotated linear material at each
# quadrature point. With the polar decomposition F = R S, the first Piola stress
# P = 2 mu (F - R) + lambda tr(S - I) R is exactly R times the linear stress of the strain
# S - I (the warped-stiffness force R k (R^T x - X) of Mueller et al. 2002 and SOFA's
# corotational tets, for the linear tet); it is the gradient of the energy density
# mu |F - R|^2 + lambda/2 tr(S - I)^2 (McAdams et al., SIGGRAPH 2011), whose exact
# derivative dP/dF gives the consistent (symmetric) tangent: rotation invariant, and the
# linear element at small strain.

def polar(F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation R and symmetric stretch S of F = R S for a batch (m, 3, 3); an inverted F
    (det < 0) keeps a proper rotation with the smallest principal stretch negative."""
    U, s, Vt = np.linalg.svd(F)
    flip = np.linalg.det(U @ Vt) < 0
    if flip.any():
        U[flip, :, 2] *= -1.0
        s[flip, 2] *= -1.0
    R = U @ Vt
    S = np.einsum("mki,mk,mkj->mij", Vt, s, Vt)
    return R, S


def corotated_stress(F: np.ndarray, lam: float, mu: float, tangent: bool = True):
    """First Piola stress P (m, 3, 3), energy density (m,) and, if ``tangent``, dP/dF
    (m, 3, 3, 3, 3) (dP_ab / dF_cd) of the corotated linear material."""
    R, S = polar(F)
    I = np.eye(3)
    trE = np.einsum("mii->m", S) - 3.0
    P = 2 * mu * (F - R) + (lam * trE)[:, None, None] * R
    psi = mu * np.einsum("mij,mij->m", F - R, F - R) + 0.5 * lam * trE**2
    if not tangent:
        return P, psi, None
    m = F.shape[0]
    # unit perturbations dF = e_c e_d^T: R^T dF - dF^T R is skew with axial vector y, and
    # (tr S I - S) w = y gives dR = R [w]x (from F = R S, dS symmetric)
    B = np.zeros((m, 3, 3, 3, 3))  # [c, d] -> R^T e_c e_d^T
    for c in range(3):
        for d in range(3):
            B[:, c, d, :, d] = R[:, c, :]
    A = B - B.swapaxes(-1, -2)
    y = np.stack([A[..., 2, 1], A[..., 0, 2], A[..., 1, 0]], axis=-1)  # (m, 3, 3, 3)
    Tm = (trE + 3.0)[:, None, None] * I - S
    try:
        w = np.linalg.solve(Tm[:, None, None], y[..., None])[..., 0]
    except np.linalg.LinAlgError:  # two principal stretches sum to zero (an element flattened or turned
        # inside out through a symmetric state): dR is not unique there; the least-norm one keeps the
        # tangent finite, and the solvers refuse such a state (CorotationalTets.inverted)
        w = np.einsum("mij,mcdj->mcdi", np.linalg.pinv(Tm), y)
    dR = np.einsum("mab,mcdbe->mcdae", R, cross_matrices(w))
    dP = (2 * mu * np.eye(9).reshape(3, 3, 3, 3)[None].transpose(0, 3, 4, 1, 2)
          + (lam * trE - 2 * mu)[:, None, None, None, None] * dR
          + lam * R[:, :, :, None, None] * R[:, None, None])  # tr(R^T e_c e_d^T) = R_cd
    return P, psi, dP.transpose(0, 3, 4, 1, 2)  # -> [a, b, c, d]


def _tangent_point(G: np.ndarray, dP: np.ndarray) -> np.ndarray:
    """G_ib dP_abcd G_jd -> (m, i, a, j, c) as two batched matrix products (np.einsum's loop over
    the five free indices took 3 s a tangent of the 4,633-tet10 liver, 30 times longer)."""
    m, k = G.shape[:2]
    T = G @ dP.transpose(0, 2, 1, 3, 4).reshape(m, 3, 27)  # [m, i, (a, c, d)]
    K = T.reshape(m, k * 9, 3) @ G.transpose(0, 2, 1)  # [m, (i, a, c), j]
    return K.reshape(m, k, 3, 3, k).transpose(0, 1, 2, 4, 3)


class CorotationalTets:
    """The corotational tets of one mesh: reference shape gradients and weights per
    quadrature point, kept once; :meth:`evaluate` gives element forces, tangents, energies."""

    def __init__(self, X: np.ndarray, material: Material, element: str) -> None:
        self.lam, self.mu = _lame(material)
        self._X = X  # the reference nodes (the inversion check's corner gradients are taken from them)
        pts, wts = (np.zeros((1, 3)), np.full(1, 1.0 / 6.0)) if element == "tet4" else tet_rule(2)
        _, dN = shape_functions(element, pts)
        self.G, self.wdet = [], []
        for q in range(pts.shape[0]):
            G, det = _gradients(X, dN[q])
            self.G.append(G)
            self.wdet.append(wts[q] * det)

    def _stress(self, F: np.ndarray, tangent: bool):
        return corotated_stress(F, self.lam, self.mu, tangent)

    def inverted(self, x: np.ndarray) -> np.ndarray:
        """(m,) mask of the elements turned inside out in deformed nodes x (m, k, 3): det F <= 0 at a
        quadrature point, or (tet10) at a corner, where the curved element can fold while its
        quadrature points do not. The corotated law's polar decomposition gives such a state a
        finite energy and force (a proper rotation with a negative stretch), so a solve can
        converge onto it: the solvers refuse it instead."""
        bad = np.zeros(x.shape[0], dtype=bool)
        for G in self.check_gradients(x.shape[1]):
            bad |= np.linalg.det(np.einsum("mka,mkb->mab", x, G)) <= 0.0
        return bad

    def check_gradients(self, k: int) -> list:
        """The gradients :meth:`inverted` evaluates det F with, made once: the quadrature points' and (tet10,
        ``k`` = 10 nodes) the corners'."""
        if not hasattr(self, "_G_check"):
            self._G_check = list(self.G)
            if k == 10:
                _, dN = shape_functions("tet10", np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0],
                                                            [0.0, 0.0, 1.0]]))
                X0 = self._X
                self._G_check += [_gradients(X0, dN[q])[0] for q in range(4)]
        return self._G_check

    def evaluate(self, x: np.ndarray, tangent: bool = True):
        """Element forces (m, 3k), tangents (m, 3k, 3k) (None unless ``tangent``) and energies
        (m,) for deformed nodes x (m, k, 3)."""
        m, k = x.shape[:2]
        f = np.zeros((m, k, 3))
        K = np.zeros((m, k, 3, k, 3)) if tangent else None
        energy = np.zeros(m)
        for G, wdet in zip(self.G, self.wdet):
            F = np.einsum("mka,mkb->mab", x, G)
            P, psi, dP = self._stress(F, tangent)
            f += wdet[:, None, None] * np.einsum("mab,mib->mia", P, G)
            energy += wdet * psi
            if tangent:
                K += wdet[:, None, None, None, None] * _tangent_point(G, dP)
        return f.reshape(m, 3 * k), (K.reshape(m, 3 * k, 3 * k) if tangent else None), energy


class HyperelasticTets(CorotationalTets):
    """The tets of one mesh with a hyperelastic law (:mod:`rtfem.fe.hyperelastic`) instead of the
    corotated linear material: the same quadrature, the law's P and dP/dF at each point."""

    def __init__(self, X: np.ndarray, law, element: str) -> None:
        super().__init__(X, law.linearized(), element)
        self.law = law

    def _stress(self, F: np.ndarray, tangent: bool):
        return self.law.stress(F, tangent)
