"""The averaged-nodal-pressure tet4 at finite strain (Bonet & Burton, Commun. Numer. Meth. Engng 14
(1998) 437), for the nonlinear solvers with a hyperelastic law: ``rt.SolidModel(mesh, law,
element="tet4-anp")``.

A mesh of linear tets with one volume constraint per tet locks as the law approaches
incompressibility (kappa / mu -> infinity: there are about five tets per node, so their volumes
cannot all be kept). Here the volumetric energy lives at the nodes instead: each node a has the
volume V_a (a quarter of each of its tets', at rest) and v_a (deformed), J_a = v_a / V_a and the
energy

    Pi = sum_e V_e W_iso(F_e) + sum_a V_a kappa / 2 (J_a - 1)^2,

so a node's patch keeps one volume, not each tet. With p_a = kappa (J_a - 1) and each tet's
pressure p_e = (1/4) sum of its nodes' p_a, the volumetric forces are the tets' p_e dv_e/dx (an
element term) and the tangent is

    sum_e p_e d^2 v_e / dx^2 (element-local)  +  C^T diag(kappa / V_a) C,  C_a = dv_a / dx,

the second coupling a node's whole patch (:meth:`AnpTets.patch_tangent`, a sparse matrix the
nonlinear system adds). Linearized at rest this is the linear solvers' ``tet4-anp``
(:func:`rtfem.fe.solid.anp_volumetric`). The isochoric part is the law's own, per tet.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from .solid import HyperelasticTets

__all__ = ["AnpTets"]


def _skew(v):
    """[v]x (m, 3, 3) for vectors v (m, 3)."""
    S = np.zeros(v.shape[:-1] + (3, 3))
    S[..., 0, 1], S[..., 0, 2], S[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    S[..., 1, 0], S[..., 2, 0], S[..., 2, 1] = v[..., 2], -v[..., 1], v[..., 0]
    return S


def volume_terms(x: np.ndarray, hessian: bool):
    """Each tet's volume v (m,), its gradient dv/dx (m, 4, 3) and (``hessian``) d^2 v/dx^2
    (m, 4, 3, 4, 3), for deformed nodes x (m, 4, 3): v = det[x1 - x0, x2 - x0, x3 - x0] / 6."""
    e1, e2, e3 = x[:, 1] - x[:, 0], x[:, 2] - x[:, 0], x[:, 3] - x[:, 0]
    g = np.empty(x.shape)
    g[:, 1] = np.cross(e2, e3) / 6.0
    g[:, 2] = np.cross(e3, e1) / 6.0
    g[:, 3] = np.cross(e1, e2) / 6.0
    g[:, 0] = -(g[:, 1] + g[:, 2] + g[:, 3])
    v = np.einsum("mi,mi->m", e1, g[:, 1])
    if not hessian:
        return v, g, None
    H = np.zeros((x.shape[0], 4, 3, 4, 3))
    # d(e2 x e3)/de2 = -[e3]x, /de3 = [e2]x, and cyclically; node 0 by translation invariance
    for i, j, k in ((1, 2, 3), (2, 3, 1), (3, 1, 2)):
        ek = (e1, e2, e3)[k - 1]
        H[:, i, :, j, :] = -_skew(ek) / 6.0
        H[:, j, :, i, :] = _skew(ek) / 6.0
    H[:, 0] = -H[:, 1:].sum(axis=1)
    H[:, :, :, 0] = -H[:, :, :, 1:].sum(axis=3)
    return v, g, H


class AnpTets(HyperelasticTets):
    """tet4 with an averaged nodal pressure for a hyperelastic law (see the module's docstring):
    :meth:`evaluate` gives each tet's isochoric forces, its share p_e dv_e/dx of the nodes' pressure
    and the element-local tangent terms; :meth:`patch_tangent` the patch coupling C^T diag(kappa / V_a) C."""

    def __init__(self, X: np.ndarray, law, T: np.ndarray, n_nodes: int) -> None:
        super().__init__(X, law, "tet4")
        self.T, self.n_nodes, self.kappa = np.asarray(T), int(n_nodes), float(law.kappa)
        v0 = volume_terms(X, False)[0]
        self.Va = np.bincount(self.T.ravel(), weights=np.repeat(v0 / 4.0, 4), minlength=self.n_nodes)
        self._share = np.repeat(v0 / 4.0, 4).reshape(-1, 4) / np.maximum(self.Va[self.T], 1e-300)

    def _stress(self, F: np.ndarray, tangent: bool):
        """The law's isochoric part: P - kappa (J - 1) cof F, its energy and tangent."""
        from .viscoelastic import _split

        P, psi, dP, P_vol, psi_vol, dP_vol = _split(self.law, F, tangent)
        return P - P_vol, psi - psi_vol, (dP - dP_vol if tangent else None)

    def evaluate(self, x: np.ndarray, tangent: bool = True):
        f, K, energy = super().evaluate(x, tangent)
        v, g, H = volume_terms(x, tangent)
        Ja = np.bincount(self.T.ravel(), weights=np.repeat(v / 4.0, 4), minlength=self.n_nodes) / \
            np.maximum(self.Va, 1e-300)
        pe = (self.kappa * (Ja - 1.0))[self.T].mean(axis=1)
        m = x.shape[0]
        f = f + (pe[:, None, None] * g).reshape(m, 12)
        nodal = 0.5 * self.kappa * self.Va * (Ja - 1.0) ** 2  # each node's energy, shared by its tets
        energy = energy + np.einsum("ma,ma->m", self._share, nodal[self.T])
        if tangent:
            K = K + (pe[:, None, None, None, None] * H).reshape(m, 12, 12)
        return f, K, energy

    def patch_tangent(self, x: np.ndarray) -> sp.csr_matrix:
        """C^T diag(kappa / V_a) C (3n, 3n), C_a = dv_a/dx = sum over a's tets of dv_e/dx / 4."""
        g = volume_terms(x, False)[1]
        m = x.shape[0]
        dofs = (3 * self.T[:, :, None] + np.arange(3)).reshape(m, 12)
        rows = np.repeat(self.T, 12, axis=1).ravel()
        cols = np.tile(dofs, (1, 4)).ravel()
        vals = np.tile(g.reshape(m, 12) / 4.0, (1, 4)).ravel()
        C = sp.csr_matrix((vals, (rows, cols)), shape=(self.n_nodes, 3 * self.n_nodes))
        w = np.zeros(self.n_nodes)
        used = self.Va > 0
        w[used] = self.kappa / self.Va[used]
        return (C.T @ sp.diags(w) @ C).tocsr()
