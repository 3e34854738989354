"""Compiled kernels of a :class:`rtfem.Prony` law's step on a reduced model's elements (the cubature's,
at haptic rates): the step's algorithmic forces and the history's update after it, as
:func:`rtfem.fe.viscoelastic.prony_step` and :func:`rtfem.fe.viscoelastic.prony_commit` compute them in
numpy (equal to round-off, tested), for an instantaneous neo-Hookean, Mooney-Rivlin or Ogden law: one
pass over the points gives both (the reduced step takes the history at the configuration its forces
are evaluated at, its predictor; see :class:`rtfem.drivers.reduced_nonlinear.ReducedNonlinearSimulator`).

At a quadrature point with deformation gradient F, the instantaneous law's P, its volumetric part
P_vol = kappa (J - 1) cof F and S_iso = F^-1 (P - P_vol) = cof^T (P - P_vol) / J; with the step's
coefficients (a_i, b_i, c_i) (:meth:`rtfem.Prony.coefficients`) and the point's history (Q_i, S_iso(n)):

    P_alg = P_vol + (1 - sum c) (P - P_vol) - F H,   H = sum_i a_i Q_i + (sum b) S_iso(n),
    Q_i(n+1) = a_i Q_i + b_i S_iso(n) + c_i S_iso(n+1).

The history is laid out as the numpy functions keep it: (points, elements, terms + 1, 3, 3).
"""

from __future__ import annotations

import numpy as np

from ..fe.jit import compiled
from .tet_kernels import (_add_stress_forces, _cofactor, _deformed_nodes, _gradient, _invariant_point, _jacobi3,
                          _ogden_point, _right_cauchy_green)

__all__ = ["prony_forces", "law_parameters"]


def _point(Fm, kind, prm, P, cof, C, N, lam2, beta, S) -> float:
    """The instantaneous law's P (3, 3) at Fm and cof = cof Fm; returns J (0 where J <= 0)."""
    if kind == 0:  # the invariant law fills cof itself
        if not _invariant_point(Fm, prm, P, cof, C):
            return 0.0
        return Fm[0, 0] * cof[0, 0] + Fm[0, 1] * cof[0, 1] + Fm[0, 2] * cof[0, 2]
    if not _ogden_point(Fm, prm, P, C, N, lam2, beta, S):
        return 0.0
    return _cofactor(Fm, cof)


def _prony_forces(V, X, G, wdet, kind, prm, kappa, a, b, c, hist, F, out):
    """F (E, 3k) = the step's algorithmic forces and out the history after the step, both at element
    dofs V (see the module's docstring); NaN on an element with J <= 0 at a point."""
    E, nq, k = G.shape[0], G.shape[1], G.shape[2]
    n = a.shape[0]
    keep = 1.0 - np.sum(c)
    bs = np.sum(b)
    x = np.zeros((k, 3))
    W = np.zeros((7, 3, 3))
    Fm, P, cof, C, N, S, H = W[0], W[1], W[2], W[3], W[4], W[5], W[6]
    lam2, beta = np.zeros(3), np.zeros(3)
    for e in range(E):
        _deformed_nodes(X, V, e, x)
        F[e, :] = 0.0
        for q in range(nq):
            _gradient(x, G[e, q], Fm)
            J = _point(Fm, kind, prm, P, cof, C, N, lam2, beta, S)
            if not J > 0.0:
                for i in range(3 * k):
                    F[e, i] = np.nan
                break
            kv = kappa * (J - 1.0)
            for i in range(3):
                for j in range(3):
                    s = bs * hist[q, e, n, i, j]
                    for t in range(n):
                        s += a[t] * hist[q, e, t, i, j]
                    H[i, j] = s
            for i in range(3):
                for j in range(3):
                    fh = 0.0
                    for m in range(3):
                        fh += Fm[i, m] * H[m, j]
                    pv = kv * cof[i, j]
                    S[i, j] = pv + keep * (P[i, j] - pv) - fh
            _add_stress_forces(S, G[e, q], wdet[e, q], F[e])
            _commit_point(P, cof, J, kv, a, b, c, hist, out, q, e, S)


def _commit_point(P, cof, J, kv, a, b, c, hist, out, q, e, Sn):
    """out[q, e] = point (q, e)'s history after the step: S_iso(n+1) = cof^T (P - P_vol) / J and
    each Q_i(n+1); Sn (3, 3) work."""
    n = a.shape[0]
    for i in range(3):
        for j in range(3):
            s = 0.0
            for m in range(3):
                s += cof[m, i] * (P[m, j] - kv * cof[m, j])
            Sn[i, j] = s / J if J > 0.0 else np.nan
    for t in range(n):
        for i in range(3):
            for j in range(3):
                out[q, e, t, i, j] = a[t] * hist[q, e, t, i, j] + b[t] * hist[q, e, n, i, j] + c[t] * Sn[i, j]
    for i in range(3):
        for j in range(3):
            out[q, e, n, i, j] = Sn[i, j]


def law_parameters(law):
    """(kind, parameters, kappa) of an instantaneous law the kernels take: 0 for neo-Hookean and
    Mooney-Rivlin ([C10, C01, kappa]), 1 for Ogden ([kappa, mu1, alpha1, ...]); None for another law."""
    from ..fe.hyperelastic import MooneyRivlin, NeoHookean, Ogden

    if isinstance(law, (NeoHookean, MooneyRivlin)):
        return 0, np.array([law.c10, law.c01, law.kappa]), float(law.kappa)
    if isinstance(law, Ogden):
        return 1, np.concatenate([[law.kappa], np.column_stack([law.mus, law.alphas]).ravel()]), float(law.kappa)
    return None


_HELPERS = (_point, _invariant_point, _ogden_point, _jacobi3, _gradient, _deformed_nodes, _add_stress_forces, _cofactor,
            _right_cauchy_green)


def prony_forces(V, X, G, wdet, law, h, dt, F):
    """F (E, 3k) = the step's algorithmic forces of the tets (element dofs V (E, 3k), rest nodes X,
    shape gradients G (E, nq, k, 3), weights wdet (E, nq)) with the :class:`~rtfem.Prony` ``law``, a
    step dt from the flat history h; returns the history after that step at the same V (flat). None
    (F untouched) where no kernel applies (numba absent, or another instantaneous law): the caller
    takes the numpy path."""
    fn, prm = compiled("prony-forces", _prony_forces, _commit_point, *_HELPERS), law_parameters(law.instantaneous)
    if fn is None or prm is None:
        return None
    a, b, c = law.coefficients(dt)
    shape = (G.shape[1], G.shape[0], a.size + 1, 3, 3)
    out = np.empty(shape)
    fn(V, X, G, wdet, prm[0], prm[1], prm[2], a, b, c, np.ascontiguousarray(h).reshape(shape), F, out)
    return out.reshape(-1)
