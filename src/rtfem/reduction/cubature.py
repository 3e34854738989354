"""Reduced internal forces on a few weighted elements (optimized cubature, An, Kim & James,
ACM TOG 27 (2008) 165), and the compiled kernel that evaluates them at haptic rates.

The reduced force of a Galerkin model is a sum over elements, g_r(q) = sum_e U_e^T g_e(U_e q).
Cubature replaces the sum by a few elements with non-negative weights, chosen so that the sum
is reproduced on training poses: greedy selection of the element whose contribution best
matches what is left, then non-negative least squares for all the weights so far (An et al.,
Sec. 4), until the relative error on the training forces is below the tolerance.

The compiled kernel (numba) evaluates the corotational shell triangle's forces (the same
deformational dofs and first derivatives as :class:`rtfem.fe.shell.CorotationalTriangles`, to
round-off) in one loop that releases the GIL; the element dofs before it and the projection
after it are BLAS products. Without numba the loop runs in Python (the same numbers, slower).
The corotated tet's kernels are in :mod:`rtfem.reduction.tet_kernels`.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import nnls

from ..errors import ModelError
from ..fe.jit import compiled as _compiled

__all__ = ["train", "compiled_forces", "element_forces"]

# axial(skew(A))_c = (A[p, q] - A[q, p]) / 2 for (p, q) = (2, 1), (0, 2), (1, 0)
_AP = np.array([2, 0, 1])
_AQ = np.array([1, 2, 0])


def _exp_series(t, th, sn, cs, jacobian, K, out):
    """out (3, 3) = I + a [t]x + b [t]x^2: exp([t]x) (Rodrigues; a = sin|t|/|t|, b = (1 - cos|t|)/|t|^2),
    or with ``jacobian`` the left Jacobian of SO(3) (a = (1 - cos|t|)/|t|^2, b = (|t| - sin|t|)/|t|^3).
    th = |t|, sn = sin th, cs = cos th (a corner's exponential and Jacobian share them); K (3, 3)
    scratch for [t]x."""
    if jacobian:
        if th < 1e-6:
            a, b = 0.5 - th * th / 24.0, 1.0 / 6.0 - th * th / 120.0
        else:
            a, b = (1.0 - cs) / (th * th), (th - sn) / (th * th * th)
    elif th < 1e-8:
        a, b = 1.0 - th * th / 6.0, 0.5 - th * th / 24.0
    else:
        a, b = sn / th, (1.0 - cs) / (th * th)
    K[0, 0] = 0.0
    K[1, 1] = 0.0
    K[2, 2] = 0.0
    K[0, 1] = -t[2]
    K[0, 2] = t[1]
    K[1, 0] = t[2]
    K[1, 2] = -t[0]
    K[2, 0] = -t[1]
    K[2, 1] = t[0]
    for i in range(3):
        for j in range(3):
            s = 0.0
            for m in range(3):
                s += K[i, m] * K[m, j]
            out[i, j] = a * K[i, j] + b * s + (1.0 if i == j else 0.0)


def _rotation_vector(y, th, D):
    """th (3) = the rotation vector theta n of a rotation A from y = (axial(skew(A)), (tr A - 1)/2),
    and D (3, 4) its derivatives over y: th = 2 G(v) s / (r + c), r = sqrt(|s|^2 + c^2),
    v = |s|^2 / (r + c)^2, G(v) = atan(sqrt v) / sqrt v (as :func:`rtfem.fe.shell._rotation_vector`,
    whose derivatives come from forward differentiation; these are written out)."""
    u = y[0] * y[0] + y[1] * y[1] + y[2] * y[2]
    c = y[3]
    r = np.sqrt(u + c * c)
    den = r + c
    v = u / (den * den)
    if v < 0.05:
        G = 1.0  # the series sum (-v)^j / (2j + 1) and its derivative
        G1 = 0.0
        p = 1.0  # v^(j-1)
        for j in range(1, 16):
            coef = (1.0 if j % 2 == 0 else -1.0) / (2 * j + 1)
            G1 += coef * j * p
            p *= v
            G += coef * p
    else:
        sv = np.sqrt(v)
        G = np.arctan(sv) / sv
        G1 = (1.0 / (1.0 + v) - G) / (2.0 * v)
    k = 2.0 * G / den
    dden_u, dden_c = 0.5 / r, c / r + 1.0
    dv_u = 1.0 / (den * den) - u / (r * den * den * den)
    dv_c = -2.0 * u / (den * den * den) * dden_c
    dk_u = 2.0 * G1 * dv_u / den - 2.0 * G / (den * den) * dden_u
    dk_c = 2.0 * G1 * dv_c / den - 2.0 * G / (den * den) * dden_c
    for a in range(3):
        th[a] = k * y[a]
        for b in range(3):
            D[a, b] = 2.0 * y[a] * y[b] * dk_u + (k if a == b else 0.0)
        D[a, 3] = y[a] * dk_c


def _element_frame(x, a, b, R, de1, de3, dR, dn):
    """The deformed triangle's frame R (rows e1, e2, e3) from its corners x (3, 3), and its
    derivatives over z = (a, b), the edges from corner 0 (de1, de3 (3, 6); dR (3, 3, 6)): e1 = a/|a|,
    n = a x b, e3 = n/|n|, e2 = e3 x e1. Fills a and b; dn (3, 6) scratch. Returns |a|."""
    for c in range(3):
        a[c] = x[1, c] - x[0, c]
        b[c] = x[2, c] - x[0, c]
    la = np.sqrt(a[0] * a[0] + a[1] * a[1] + a[2] * a[2])
    n0 = a[1] * b[2] - a[2] * b[1]
    n1 = a[2] * b[0] - a[0] * b[2]
    n2 = a[0] * b[1] - a[1] * b[0]
    ln = np.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
    for c in range(3):
        R[0, c] = a[c] / la
    R[2, 0], R[2, 1], R[2, 2] = n0 / ln, n1 / ln, n2 / ln
    R[1, 0] = R[2, 1] * R[0, 2] - R[2, 2] * R[0, 1]
    R[1, 1] = R[2, 2] * R[0, 0] - R[2, 0] * R[0, 2]
    R[1, 2] = R[2, 0] * R[0, 1] - R[2, 1] * R[0, 0]
    for c in range(3):
        for m in range(6):
            de1[c, m] = 0.0
            dn[c, m] = 0.0
    for c in range(3):
        for m in range(3):
            de1[c, m] = ((1.0 if c == m else 0.0) - R[0, c] * R[0, m]) / la
    for m in range(3):  # e_m x b and a x e_m
        m1, m2 = (m + 1) % 3, (m + 2) % 3
        dn[m1, m] = -b[m2]
        dn[m2, m] = b[m1]
        dn[m1, 3 + m] = a[m2]
        dn[m2, 3 + m] = -a[m1]
    for m in range(6):
        s = R[2, 0] * dn[0, m] + R[2, 1] * dn[1, m] + R[2, 2] * dn[2, m]
        for c in range(3):
            de3[c, m] = (dn[c, m] - R[2, c] * s) / ln
    for m in range(6):
        for c in range(3):
            dR[0, c, m] = de1[c, m]
            dR[2, c, m] = de3[c, m]
        # de2 = de3 x e1 + e3 x de1
        dR[1, 0, m] = (de3[1, m] * R[0, 2] - de3[2, m] * R[0, 1]) + (R[2, 1] * de1[2, m] - R[2, 2] * de1[1, m])
        dR[1, 1, m] = (de3[2, m] * R[0, 0] - de3[0, m] * R[0, 2]) + (R[2, 2] * de1[0, m] - R[2, 0] * de1[2, m])
        dR[1, 2, m] = (de3[0, m] * R[0, 1] - de3[1, m] * R[0, 0]) + (R[2, 0] * de1[1, m] - R[2, 1] * de1[0, m])
    return la


def _corner_rotations(v, R, R0e, AP, AQ, trig, C, Dphi, d, t, Kx, Q, A, yv, th3):
    """Each corner's rotation relative to the element frame: C_i = Q_i R0^T (Q_i = exp of the
    corner's rotation vector in v), A = R C_i, its rotation vector into d[6 i + 3 ..] and that
    vector's derivatives over y = (axial(skew(A)), (tr A - 1)/2) into Dphi[i]; trig[i] keeps the
    corner's |theta|, sin and cos. t, Kx, Q, A, yv, th3 scratch."""
    for i in range(3):
        for c in range(3):
            t[c] = v[6 * i + 3 + c]
        th = np.sqrt(t[0] * t[0] + t[1] * t[1] + t[2] * t[2])
        trig[i, 0] = th
        trig[i, 1] = np.sin(th)
        trig[i, 2] = np.cos(th)
        _exp_series(t, th, trig[i, 1], trig[i, 2], False, Kx, Q)
        for p in range(3):
            for s_ in range(3):
                acc = 0.0
                for m in range(3):
                    acc += Q[p, m] * R0e[s_, m]
                C[i, p, s_] = acc
        for p in range(3):
            for s_ in range(3):
                acc = 0.0
                for m in range(3):
                    acc += R[p, m] * C[i, m, s_]
                A[p, s_] = acc
        for c in range(3):
            yv[c] = 0.5 * (A[AP[c], AQ[c]] - A[AQ[c], AP[c]])
        yv[3] = 0.5 * (A[0, 0] + A[1, 1] + A[2, 2] - 1.0)
        _rotation_vector(yv, th3, Dphi[i])
        for c in range(3):
            d[6 * i + 3 + c] = th3[c]


def _translation_rows(g, R, de1, dR, b, fz):
    """The local forces g's work through the frame on z = (a, b): fz[0:6] += d(d_6, d_12, d_13)/dz^T g
    (d_6 = |a|, d_12 = e1 . b, d_13 = e2 . b: the corners' in-plane positions)."""
    for m in range(3):
        fz[m] += g[6] * R[0, m]
        s12 = 0.0
        s13 = 0.0
        for c in range(3):
            s12 += de1[c, m] * b[c]
            s13 += dR[1, c, m] * b[c]
        fz[m] += g[12] * s12 + g[13] * s13
        s12 = 0.0
        s13 = 0.0
        for c in range(3):
            s12 += de1[c, 3 + m] * b[c]
            s13 += dR[1, c, 3 + m] * b[c]
        fz[3 + m] += g[12] * (s12 + R[0, m]) + g[13] * (s13 + R[1, m])


def _rotation_rows(g, R, C, dR, Dphi, AP, AQ, fz, dA, gy):
    """The corners' rotation vectors' work: over z = (a, b) (through the frame) into fz[0:6] and over
    each corner's spin w_l (d/dw_l of R exp([w]x) Q R0^T at w = 0: R [e_l]x C) into fz[6 + 3 i + l].
    dA (3, 3, 6), gy (4,) scratch."""
    for i in range(3):
        for p in range(3):
            for s_ in range(3):
                for m in range(6):
                    acc = 0.0
                    for u in range(3):
                        acc += dR[p, u, m] * C[i, u, s_]
                    dA[p, s_, m] = acc
        for m in range(4):  # the weights on y = (axial(skew(A)), (tr A - 1)/2): D^T g
            acc = 0.0
            for c in range(3):
                acc += g[6 * i + 3 + c] * Dphi[i, c, m]
            gy[m] = acc
        for m in range(6):
            fz[m] += gy[3] * 0.5 * (dA[0, 0, m] + dA[1, 1, m] + dA[2, 2, m])
        for ll in range(3):
            l1, l2 = (ll + 1) % 3, (ll + 2) % 3
            acc = 0.0
            for p in range(3):
                acc += R[p, l2] * C[i, l1, p] - R[p, l1] * C[i, l2, p]
            fz[6 + 3 * i + ll] += gy[3] * 0.5 * acc
        for c in range(3):
            gi = gy[c]
            p, qq = AP[c], AQ[c]
            for m in range(6):
                fz[m] += gi * 0.5 * (dA[p, qq, m] - dA[qq, p, m])
            for ll in range(3):
                # (R [e_l]x C)[p, q] = R[p, l+2] C[l+1, q] - R[p, l+1] C[l+2, q]
                l1, l2 = (ll + 1) % 3, (ll + 2) % 3
                xp = R[p, l2] * C[i, l1, qq] - R[p, l1] * C[i, l2, qq]
                xq = R[qq, l2] * C[i, l1, p] - R[qq, l1] * C[i, l2, p]
                fz[6 + 3 * i + ll] += gi * 0.5 * (xp - xq)


def _generalized_forces(v, trig, fz, f, t, Kx, Jl):
    """f (18) from fz: the corners' translations (z = (x1 - x0, x2 - x0)) and the generalized moments
    J(theta)^T m on the rotation vectors (J the left Jacobian of SO(3)). t, Kx, Jl scratch."""
    for c in range(3):
        f[c] = -fz[c] - fz[3 + c]
        f[6 + c] = fz[c]
        f[12 + c] = fz[3 + c]
    for i in range(3):
        for c in range(3):
            t[c] = v[6 * i + 3 + c]
        _exp_series(t, trig[i, 0], trig[i, 1], trig[i, 2], True, Kx, Jl)
        for c in range(3):
            s = 0.0
            for m in range(3):
                s += Jl[m, c] * fz[6 + 3 * i + m]
            f[6 * i + 3 + c] = s


def _shell_element_forces(V, X, R0, x2, x3, y3, k, AP, AQ, F):
    """F (E, 18) = g_e(V_e), the generalized forces of corotational triangles at element dofs V
    (E, 18) (V_e = U_e q: one BLAS product before; the projection U_e^T F_e is one after).
    X (E, 3, 3) rest corners, R0 (E, 3, 3) rest frames, x2, x3, y3 (E,) local rest coordinates,
    k (E, 18, 18) local stiffnesses. g_e: the forces on the corners' translations and
    J(theta)^T m on their rotation vectors. Per element: the frame (:func:`_element_frame`), the
    local deformation d (the corners' in-plane positions and rotations relative to the frame,
    :func:`_corner_rotations`), g = k d, and g's work back on the element dofs
    (:func:`_translation_rows`, :func:`_rotation_rows`, :func:`_generalized_forces`)."""
    E = V.shape[0]
    Kx, Q, Jl, A, R = np.zeros((3, 3)), np.zeros((3, 3)), np.zeros((3, 3)), np.zeros((3, 3)), np.zeros((3, 3))
    trig = np.zeros((3, 3))  # each corner's |theta|, sin and cos (for its exponential and its Jacobian)
    x = np.zeros((3, 3))
    C = np.zeros((3, 3, 3))  # each corner's Q_i R0^T
    dR, dA = np.zeros((3, 3, 6)), np.zeros((3, 3, 6))
    de1, dn, de3 = np.zeros((3, 6)), np.zeros((3, 6)), np.zeros((3, 6))
    v, d, g, f, fz = np.zeros(18), np.zeros(18), np.zeros(18), np.zeros(18), np.zeros(15)
    a, b, t, th3 = np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(3)
    yv, gy = np.zeros(4), np.zeros(4)
    Dphi = np.zeros((3, 3, 4))  # each corner's rotation vector's derivatives over its y
    for e in range(E):
        for i in range(18):
            v[i] = V[e, i]
        for i in range(3):
            for c in range(3):
                x[i, c] = X[e, i, c] + v[6 * i + c]
        la = _element_frame(x, a, b, R, de1, de3, dR, dn)
        for i in range(18):
            d[i] = 0.0
        d[6] = la - x2[e]
        d[12] = R[0, 0] * b[0] + R[0, 1] * b[1] + R[0, 2] * b[2] - x3[e]
        d[13] = R[1, 0] * b[0] + R[1, 1] * b[1] + R[1, 2] * b[2] - y3[e]
        _corner_rotations(v, R, R0[e], AP, AQ, trig, C, Dphi, d, t, Kx, Q, A, yv, th3)
        for i in range(18):
            s = 0.0
            for j in range(18):
                s += k[e, i, j] * d[j]
            g[i] = s
        for m in range(15):
            fz[m] = 0.0
        _translation_rows(g, R, de1, dR, b, fz)
        _rotation_rows(g, R, C, dR, Dphi, AP, AQ, fz, dA, gy)
        _generalized_forces(v, trig, fz, f, t, Kx, Jl)
        for i in range(18):
            F[e, i] = f[i]


def compiled_forces():
    """The compiled shell kernel (numba), or None where numba is absent or cannot compile it."""
    return _compiled("shell", _shell_element_forces, _exp_series, _rotation_vector, _element_frame, _corner_rotations,
                     _translation_rows, _rotation_rows, _generalized_forces)


def element_forces(V, X, R0, x2, x3, y3, k, F) -> None:
    """F (E, 18) = g_e(V_e) for element dofs V (E, 18): the compiled kernel, or without numba the
    same loop in Python (slow: machines without the ``fast`` extra). One thread: on this 2-core
    machine a two-thread kernel (numba prange, OpenMP) did not shorten the reduced step, whose
    BLAS passes over the basis rows then compete with OpenMP's spinning threads."""
    fn = compiled_forces()
    (_shell_element_forces if fn is None else fn)(V, X, R0, x2, x3, y3, k, _AP, _AQ, F)


def train(contributions, targets, tol: float = 0.02, max_elements: int | None = None, seed: int = 0):
    """Optimized cubature (An et al. 2008): elements and non-negative weights w with
    sum_e w_e contributions[:, e] ~ targets.

    Parameters
    ----------
    contributions : ndarray (T, E)
        Each element's reduced force on the training poses, stacked (each pose's rows scaled to
        unit norm of its target).
    targets : ndarray (T,)
        The full sums.
    tol : float
        Stop when |A w - b| <= tol |b|.
    max_elements : int, optional
        At most this many elements.
    seed : int
        The seed of the random candidates.

    Returns
    -------
    tuple
        (elements, weights, relative error).

    Candidates are drawn at random (a quarter of
    the elements per pick, at least 64) and the ones best aligned with the residual are taken
    (one at first, then an eighth of the number chosen so far).
    """
    A = np.asarray(contributions, float)
    b = np.asarray(targets, float)
    if not (np.isfinite(A).all() and np.isfinite(b).all()):
        raise ModelError("cubature training: some training forces are not finite (an element turned inside out under "
                         "a law without energy there?); train on smaller poses")
    T, E = A.shape
    max_elements = E if max_elements is None else min(E, max_elements)
    norms = np.linalg.norm(A, axis=0)
    norms[norms == 0] = np.inf
    rng = np.random.default_rng(seed)
    chosen: list[int] = []
    w = np.zeros(0)
    res = b.copy()
    bn = float(np.linalg.norm(b))
    if bn == 0:
        raise ModelError("cubature training: the training forces are all zero (poses at rest?)")
    err = 1.0
    while err > tol and len(chosen) < max_elements:
        cand = rng.choice(E, size=min(E, max(64, E // 4)), replace=False)
        score = (A[:, cand].T @ res) / norms[cand]
        score[np.isin(cand, chosen)] = -np.inf
        if not np.isfinite(score.max()) or score.max() <= 0:
            break
        batch = max(1, len(chosen) // 8)  # several at a time once many are in (fewer NNLS solves)
        best = cand[np.argsort(score)[::-1][:batch]]
        chosen.extend(int(c) for c in best if np.isfinite(score[cand == c][0]) and score[cand == c][0] > 0)
        w, _ = nnls(A[:, chosen], b, maxiter=50 * len(chosen))
        keep = w > 0
        chosen = [c for c, k in zip(chosen, keep) if k]
        w = w[keep]
        res = b - A[:, chosen] @ w
        err = float(np.linalg.norm(res)) / bn
    return np.array(chosen, dtype=int), w, err



def fit_error(contributions: np.ndarray, targets: np.ndarray, elements: np.ndarray, weights: np.ndarray) -> float:
    """|sum_e w_e contributions[:, e] - targets| / |targets| over the chosen ``elements``: the relative
    error of a cubature on stacked pose rows (as :func:`train` measures it)."""
    return float(np.linalg.norm(contributions[:, elements] @ weights - targets) / np.linalg.norm(targets))

def region_tol(tol: float, own: np.ndarray, whole: np.ndarray, regions: int) -> float:
    """The relative tolerance of one region's fit (:func:`train` on its elements against ``own``, its
    share of the training forces ``whole``) among ``regions``: ``tol`` of its own forces, and no more than
    ``tol / regions`` of the whole's, so that the regions' fits together meet ``tol`` on the whole as a
    single fit must (their residuals add at most: the triangle inequality) while each region, however
    small its share, is fitted to ``tol`` of its own forces. The regions' forces can be far larger than
    their sum (they cancel where regions press on each other), which a fit to each one's own alone
    would let through."""
    mine = float(np.linalg.norm(own))
    return tol * min(1.0, float(np.linalg.norm(whole)) / (regions * max(mine, 1e-300)))
