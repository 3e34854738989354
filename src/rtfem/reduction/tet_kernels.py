"""The corotated tet's compiled kernels for reduced models: the element forces a cubature step sums
and their exact tangents, which the reduced nonlinear step is linearized about.

Both are the corotated linear material of :class:`rtfem.fe.solid.CorotationalTets`
(psi = mu |F - R|^2 + lambda/2 tr(S - I)^2, F = R S) at each quadrature point, one loop over the
elements that releases the GIL: the polar rotation by Higham's scaled Newton iteration, the SVD
for an inverted element. The tangent is the closed form of dP/dF (McAdams et al., "Efficient
elasticity for character skinning with contact and collisions", SIGGRAPH 2011: dR = R [w]x with
(tr S I - S) w = axial(R^T dF - dF^T R)) contracted with the shape gradients, as
:func:`rtfem.fe.solid.corotated_stress` writes it batched; it replaced forward differences of the
force kernel (31 force evaluations an element; on the default liver 8 ms of the 12 ms a tangent
refresh took). Without numba both are batched numpy (the same numbers, slower).
"""

from __future__ import annotations

import math

import numpy as np

from ..fe.assembly_kernels import _cofactor
from ..fe.jit import compiled

__all__ = ["compiled_solid_forces", "compiled_solid_tangents", "solid_element_forces", "solid_element_tangents", "by_region",
           "law_forces", "law_tangents"]


def _polar_rotation(Fm, R, Z):
    """R (3, 3) = the rotation of the polar decomposition F = R S, for det F > 0, by Higham's scaled
    Newton iteration R <- (g R + R^-T / g) / 2 (Higham 1986; quadratic). The scaling g = (|R^-1| /
    |R|)^1/2 (Frobenius) speeds the first iterations only. The iteration stops when a step changes
    R by less than 1e-8 (Frobenius): the error it leaves is then about half the square of that
    change, ~1e-17 (on the default liver's pulled cubature points, 3.5 iterations on average, 4.2 before).
    Returns False when it does not apply (det F <= 0, or no convergence), for an SVD instead.
    Z (3, 3) scratch."""
    for i in range(3):
        for j in range(3):
            R[i, j] = Fm[i, j]
    for it in range(30):
        # Z = cof(R) = det(R) R^-T
        Z[0, 0] = R[1, 1] * R[2, 2] - R[1, 2] * R[2, 1]
        Z[0, 1] = R[1, 2] * R[2, 0] - R[1, 0] * R[2, 2]
        Z[0, 2] = R[1, 0] * R[2, 1] - R[1, 1] * R[2, 0]
        Z[1, 0] = R[0, 2] * R[2, 1] - R[0, 1] * R[2, 2]
        Z[1, 1] = R[0, 0] * R[2, 2] - R[0, 2] * R[2, 0]
        Z[1, 2] = R[0, 1] * R[2, 0] - R[0, 0] * R[2, 1]
        Z[2, 0] = R[0, 1] * R[1, 2] - R[0, 2] * R[1, 1]
        Z[2, 1] = R[0, 2] * R[1, 0] - R[0, 0] * R[1, 2]
        Z[2, 2] = R[0, 0] * R[1, 1] - R[0, 1] * R[1, 0]
        det = R[0, 0] * Z[0, 0] + R[0, 1] * Z[0, 1] + R[0, 2] * Z[0, 2]
        if not det > 0.0:
            return False
        inv = 1.0 / det
        if it < 4:
            nr = 0.0
            nz = 0.0
            for i in range(3):
                for j in range(3):
                    nr += R[i, j] * R[i, j]
                    nz += Z[i, j] * Z[i, j]
            g = math.sqrt(math.sqrt(nz / nr) * inv)  # |R^-T| = |Z| / det
            a, b = 0.5 * g, 0.5 * inv / g
        else:
            a, b = 0.5, 0.5 * inv
        change = 0.0
        for i in range(3):
            for j in range(3):
                y = a * R[i, j] + b * Z[i, j]
                change += (y - R[i, j]) ** 2
                R[i, j] = y
        if change < 1e-16:
            return True
    return False


def _rotation(Fm, R, Z):
    """R (3, 3) = the proper rotation of F = R S: the polar iteration, or for an inverted or
    degenerate F the SVD's (the smallest principal stretch then negative). Z (3, 3) scratch."""
    if _polar_rotation(Fm, R, Z):
        return
    u, sv, vt = np.linalg.svd(Fm)
    du = u[0, 0] * (u[1, 1] * u[2, 2] - u[1, 2] * u[2, 1]) - u[0, 1] * (u[1, 0] * u[2, 2] - u[1, 2] * u[2, 0]) \
        + u[0, 2] * (u[1, 0] * u[2, 1] - u[1, 1] * u[2, 0])
    dv = vt[0, 0] * (vt[1, 1] * vt[2, 2] - vt[1, 2] * vt[2, 1]) \
        - vt[0, 1] * (vt[1, 0] * vt[2, 2] - vt[1, 2] * vt[2, 0]) \
        + vt[0, 2] * (vt[1, 0] * vt[2, 1] - vt[1, 1] * vt[2, 0])
    if du * dv < 0.0:
        for i in range(3):
            u[i, 2] = -u[i, 2]
    for a in range(3):
        for b in range(3):
            R[a, b] = u[a, 0] * vt[0, b] + u[a, 1] * vt[1, b] + u[a, 2] * vt[2, b]


def _gradient(x, Ge, Fm):
    """Fm (3, 3) = the deformation gradient sum_i x_i G_i^T at one quadrature point."""
    k = x.shape[0]
    for a in range(3):
        for b in range(3):
            s = 0.0
            for i in range(k):
                s += x[i, a] * Ge[i, b]
            Fm[a, b] = s


def _deformed_nodes(X, V, e, x):
    """x (k, 3) = element e's rest nodes X[e] plus its dofs V[e] (node-major)."""
    for i in range(x.shape[0]):
        for c in range(3):
            x[i, c] = X[e, i, c] + V[e, 3 * i + c]


def _add_stress_forces(P, Ge, w, Fe):
    """Fe (3k) += w P G_i at each node i: one quadrature point's share of the nodal forces, for its
    first Piola stress P (3, 3), shape gradients Ge (k, 3) and weight w."""
    for i in range(Ge.shape[0]):
        for a in range(3):
            s = 0.0
            for b in range(3):
                s += P[a, b] * Ge[i, b]
            Fe[3 * i + a] += w * s


def _element_forces(x, Ge, we, lam, mu, Fe, Fm, R, Z, P):
    """Fe (3k) = one corotated-linear tet's nodal forces at its deformed nodes x (k, 3): at each
    quadrature point (shape gradients Ge (nq, k, 3), weights we (nq)) f_i += w P G_i with
    P = 2 mu (F - R) + lambda tr(S - I) R, tr S = tr(R^T F). Fm, R, Z, P (3, 3) scratch."""
    Fe[:] = 0.0
    for q in range(Ge.shape[0]):
        _gradient(x, Ge[q], Fm)
        _rotation(Fm, R, Z)
        trS = 0.0
        for a in range(3):
            for b in range(3):
                trS += R[a, b] * Fm[a, b]
        t = lam * (trS - 3.0)
        for a in range(3):
            for b in range(3):
                P[a, b] = 2.0 * mu * (Fm[a, b] - R[a, b]) + t * R[a, b]
        _add_stress_forces(P, Ge[q], we[q], Fe)


def _solid_element_forces(V, X, G, wdet, lm, F):
    """F (E, 3k) = the corotated-linear tets' nodal forces (mu |F - R|^2 + lambda/2 tr(S - I)^2, as
    :class:`rtfem.fe.solid.CorotationalTets`) at element dofs V (E, 3k): X (E, k, 3) rest nodes,
    G (E, nq, k, 3) the shape gradients and wdet (E, nq) the weights of each quadrature point,
    lm (E, 2) the Lame constants (:func:`_element_forces` each)."""
    E, k = G.shape[0], G.shape[2]
    x = np.zeros((k, 3))
    Fm, R, Z, P = np.zeros((3, 3)), np.zeros((3, 3)), np.zeros((3, 3)), np.zeros((3, 3))
    for e in range(E):
        _deformed_nodes(X, V, e, x)
        _element_forces(x, G[e], wdet[e], lm[e, 0], lm[e, 1], F[e], Fm, R, Z, P)


def _point_tangent(Ge, R, Fm, lam, mu, w, K, RG, RW, T):
    """Add w G_ib dP_ab/dF_cd G_jd to K (3k, 3k) (only the blocks j >= i) at one quadrature point
    with shape gradients Ge (k, 3), rotation R and gradient Fm. With dR = R [w_cd]x and
    sum_d G_jd w_cd = W_jc = (tr S I - S)^-1 (G_j x R_c) (R_c row c of R; McAdams et al. 2011),
    dP_cd = 2 mu e_c e_d^T + (lambda tr(S - I) - 2 mu) dR + lambda R_cd R gives the block (i, j)
    K_ac = 2 mu (G_i . G_j) delta_ac + lambda (R G_i)_a (R G_j)_c + alpha ((R W_jc) x (R G_i))_a
    (a rotation carries cross products: R (W x G) = R W x R G). RG (k, 3), RW (k, 3, 3), T (3, 3)
    scratch. A singular tr S I - S (an inverted element at a limit) drops the rotation's term."""
    k = Ge.shape[0]
    trS = 0.0
    for a in range(3):
        for b in range(3):
            trS += R[a, b] * Fm[a, b]
    for a in range(3):  # T = tr S I - S, S = R^T F (symmetrized against round-off)
        for b in range(3):
            s = 0.0
            for c in range(3):
                s += R[c, a] * Fm[c, b] + R[c, b] * Fm[c, a]
            T[a, b] = -0.5 * s
        T[a, a] += trS
    c00 = T[1, 1] * T[2, 2] - T[1, 2] * T[2, 1]
    c01 = T[1, 2] * T[2, 0] - T[1, 0] * T[2, 2]
    c02 = T[1, 0] * T[2, 1] - T[1, 1] * T[2, 0]
    det = T[0, 0] * c00 + T[0, 1] * c01 + T[0, 2] * c02
    alpha = lam * (trS - 3.0) - 2.0 * mu
    if abs(det) <= 1e-300:
        alpha = 0.0
        det = 1.0
    inv = 1.0 / det  # T^-1 = cof(T)^T / det, T symmetric
    i00, i01, i02 = c00 * inv, c01 * inv, c02 * inv
    i11 = (T[0, 0] * T[2, 2] - T[0, 2] * T[2, 0]) * inv
    i12 = (T[0, 2] * T[1, 0] - T[0, 0] * T[1, 2]) * inv
    i22 = (T[0, 0] * T[1, 1] - T[0, 1] * T[1, 0]) * inv
    for j in range(k):
        g0, g1, g2 = Ge[j, 0], Ge[j, 1], Ge[j, 2]
        for a in range(3):
            RG[j, a] = R[a, 0] * g0 + R[a, 1] * g1 + R[a, 2] * g2
        for c in range(3):
            r0, r1, r2 = R[c, 0], R[c, 1], R[c, 2]
            y0, y1, y2 = g1 * r2 - g2 * r1, g2 * r0 - g0 * r2, g0 * r1 - g1 * r0  # G_j x R_c
            w0 = i00 * y0 + i01 * y1 + i02 * y2
            w1 = i01 * y0 + i11 * y1 + i12 * y2
            w2 = i02 * y0 + i12 * y1 + i22 * y2
            for a in range(3):
                RW[j, c, a] = R[a, 0] * w0 + R[a, 1] * w1 + R[a, 2] * w2
    m2 = 2.0 * mu * w
    la, al = lam * w, alpha * w
    for i in range(k):
        p0, p1, p2 = RG[i, 0], RG[i, 1], RG[i, 2]
        for j in range(i, k):
            gg = m2 * (Ge[i, 0] * Ge[j, 0] + Ge[i, 1] * Ge[j, 1] + Ge[i, 2] * Ge[j, 2])
            for c in range(3):
                u0, u1, u2 = RW[j, c, 0], RW[j, c, 1], RW[j, c, 2]
                lc = la * RG[j, c]
                K[3 * i, 3 * j + c] += lc * p0 + al * (u1 * p2 - u2 * p1)
                K[3 * i + 1, 3 * j + c] += lc * p1 + al * (u2 * p0 - u0 * p2)
                K[3 * i + 2, 3 * j + c] += lc * p2 + al * (u0 * p1 - u1 * p0)
                K[3 * i + c, 3 * j + c] += gg


def _solid_element_tangents(V, X, G, wdet, lm, K):
    """K (E, 3k, 3k) = the exact tangents d f_e / d v_e of :func:`_solid_element_forces` at
    element dofs V (E, 3k) (:func:`_point_tangent` at each quadrature point), symmetric."""
    E, nq, k = G.shape[0], G.shape[1], G.shape[2]
    x = np.zeros((k, 3))
    Fm = np.zeros((3, 3))
    R = np.zeros((3, 3))
    Z = np.zeros((3, 3))
    RG = np.zeros((k, 3))
    RW = np.zeros((k, 3, 3))
    n = 3 * k
    for e in range(E):
        Ke = K[e]
        _deformed_nodes(X, V, e, x)
        for a in range(n):
            for b in range(n):
                Ke[a, b] = 0.0
        for q in range(nq):
            _gradient(x, G[e, q], Fm)
            _rotation(Fm, R, Z)
            _point_tangent(G[e, q], R, Fm, lm[e, 0], lm[e, 1], wdet[e, q], Ke, RG, RW, Z)
        for i in range(k):  # the blocks below the diagonal from those above (the tangent is symmetric)
            for j in range(i + 1, k):
                for a in range(3):
                    for c in range(3):
                        Ke[3 * j + c, 3 * i + a] = Ke[3 * i + a, 3 * j + c]
        for i in range(k):  # the diagonal blocks' own symmetry, exact
            for a in range(3):
                for c in range(a + 1, 3):
                    s = 0.5 * (Ke[3 * i + a, 3 * i + c] + Ke[3 * i + c, 3 * i + a])
                    Ke[3 * i + a, 3 * i + c] = s
                    Ke[3 * i + c, 3 * i + a] = s


def solid_forces_numpy(V, X, G, wdet, lm, F) -> None:
    """The same forces as :func:`_solid_element_forces`, batched in numpy (the polar decomposition
    by SVD, as the full-order kernel): the path without numba."""
    from ..fe.solid import polar

    E, nq, k = G.shape[0], G.shape[1], G.shape[2]
    x = X + V.reshape(E, k, 3)
    out = np.zeros((E, k, 3))
    for q in range(nq):
        Fm = np.einsum("eka,ekb->eab", x, G[:, q])
        R, S = polar(Fm)
        trE = np.einsum("eii->e", S) - 3.0
        P = 2 * lm[:, 1, None, None] * (Fm - R) + (lm[:, 0] * trE)[:, None, None] * R
        out += wdet[:, q, None, None] * np.einsum("eab,eib->eia", P, G[:, q])
    F[:] = out.reshape(E, 3 * k)


def solid_tangents_numpy(V, X, G, wdet, lm, K) -> None:
    """The same tangents as :func:`_solid_element_tangents`, batched in numpy
    (:func:`rtfem.fe.solid.corotated_stress`, element by element's Lame constants): the path without numba."""
    from ..fe.solid import _tangent_point, corotated_stress

    E, nq, k = G.shape[0], G.shape[1], G.shape[2]
    x = X + V.reshape(E, k, 3)
    out = np.zeros((E, k, 3, k, 3))
    for lam, mu in np.unique(lm, axis=0):
        m = np.flatnonzero((lm[:, 0] == lam) & (lm[:, 1] == mu))
        for q in range(nq):
            Gq = np.ascontiguousarray(G[m, q])
            dP = corotated_stress(np.einsum("eka,ekb->eab", x[m], Gq), lam, mu)[2]
            out[m] += wdet[m, q, None, None, None, None] * _tangent_point(Gq, dP)
    Kf = out.reshape(E, 3 * k, 3 * k)
    K[:] = 0.5 * (Kf + Kf.transpose(0, 2, 1))


def compiled_solid_forces():
    """The compiled corotated-tet force kernel (numba), or None where numba is absent or cannot compile it."""
    return compiled("solid", _solid_element_forces, _element_forces, _polar_rotation, _rotation, _gradient,
                    _deformed_nodes, _add_stress_forces)


def compiled_solid_tangents():
    """The compiled corotated-tet tangent kernel (numba), or None where numba is absent or cannot compile it."""
    return compiled("solid-tangent", _solid_element_tangents, _polar_rotation, _rotation, _gradient, _point_tangent,
                    _deformed_nodes)


def solid_element_forces(V, X, G, wdet, lm, F) -> None:
    """F (E, 3k) = the corotated tets' forces at element dofs V (E, 3k) (see
    :func:`_solid_element_forces`): compiled, or batched numpy without numba."""
    fn = compiled_solid_forces()
    (solid_forces_numpy if fn is None else fn)(V, X, G, wdet, lm, F)


def solid_element_tangents(V, X, G, wdet, lm, K) -> None:
    """K (E, 3k, 3k) = the corotated tets' tangents at element dofs V (E, 3k) (see
    :func:`_solid_element_tangents`): compiled, or batched numpy without numba."""
    fn = compiled_solid_tangents()
    (solid_tangents_numpy if fn is None else fn)(V, X, G, wdet, lm, K)


def by_region(parts, V, X, G, wdet, lm, out, corotated, by_law, share=None) -> np.ndarray:
    """``out`` (E, ...) filled region by region: ``parts`` [(the region's elements (an index array, or
    None for all), its law or None)], a region of the corotated material by ``corotated`` (V, X, G,
    wdet, lm, out), a hyperelastic law's by ``by_law`` (V, X, G, wdet, law, out) (the element forces'
    or tangents' kernels above); ``share(n, work)`` runs work(lo, hi) over a region's elements (the
    full-order step's :func:`rtfem.fe.jit.chunked`), else one call does."""
    for idx, law in parts:
        if idx is not None and idx.size == 0:
            continue
        args = (V, X, G, wdet, lm) if idx is None else tuple(np.ascontiguousarray(a[idx]) for a in (V, X, G, wdet, lm))
        res = out if idx is None else np.empty((idx.size,) + out.shape[1:])

        def work(lo, hi, args=args, res=res, law=law):
            if law is None:
                corotated(*(a[lo:hi] for a in args), res[lo:hi])
            else:
                by_law(*(a[lo:hi] for a in args[:4]), law, res[lo:hi])
        if share is None:
            work(0, res.shape[0])
        else:
            share(res.shape[0], work)
        if idx is not None:
            out[idx] = res
    return out


# ---------------------------------------------------------------- hyperelastic laws (batched numpy)
def _gradients(V, X, G):
    """The deformation gradients (E nq, 3, 3) at every quadrature point of every element."""
    E, nq, k = G.shape[0], G.shape[1], G.shape[2]
    x = X + V.reshape(E, k, 3)
    return np.einsum("eka,eqkb->eqab", x, G).reshape(E * nq, 3, 3)


def _right_cauchy_green(Fm, C) -> None:
    """C (3, 3) = Fm^T Fm."""
    for a in range(3):
        for b in range(3):
            s = 0.0
            for m in range(3):
                s += Fm[m, a] * Fm[m, b]
            C[a, b] = s


def _invariant_point(Fm, prm, P, cof, C) -> bool:
    """P (3, 3) of W = C10 (I1bar - 3) + C01 (I2bar - 3) + kappa / 2 (J - 1)^2 at one deformation
    gradient Fm (prm = [C10, C01, kappa]), as :class:`rtfem.fe.hyperelastic.MooneyRivlin` writes it;
    cof gets Fm's cofactor. False (P untouched) where det Fm <= 0. C: a work array."""
    c10, c01, kappa = prm[0], prm[1], prm[2]
    J = _cofactor(Fm, cof)
    if not J > 0.0:
        return False
    _right_cauchy_green(Fm, C)
    I1 = C[0, 0] + C[1, 1] + C[2, 2]
    trC2 = 0.0
    for a in range(3):
        for b in range(3):
            trC2 += C[a, b] * C[b, a]
    I2 = 0.5 * (I1 * I1 - trC2)
    j23 = J ** (-2.0 / 3.0)
    a1 = c10 * j23
    a2 = c01 * j23 * j23
    g1 = (2.0 / 3.0) * a1 * I1 / J + (4.0 / 3.0) * a2 * I2 / J
    kv = kappa * (J - 1.0)
    for a in range(3):
        for b in range(3):
            fc = 0.0
            for m in range(3):
                fc += Fm[a, m] * C[m, b]
            P[a, b] = 2.0 * a1 * Fm[a, b] + a2 * (2.0 * I1 * Fm[a, b] - 2.0 * fc) - g1 * cof[a, b] + kv * cof[a, b]
    return True


def _invariant_forces(V, X, G, wdet, prm, F):
    """F (E, 3k) = the tets' forces with W = C10 (I1bar - 3) + C01 (I2bar - 3) + kappa / 2 (J - 1)^2
    (prm = [C10, C01, kappa]: neo-Hookean and Mooney-Rivlin; :func:`_invariant_point`); an element
    with J <= 0 at a point gets NaN."""
    E, nq, k = G.shape[0], G.shape[1], G.shape[2]
    x = np.zeros((k, 3))
    Fm = np.zeros((3, 3))
    cof = np.zeros((3, 3))
    C = np.zeros((3, 3))
    P = np.zeros((3, 3))
    for e in range(E):
        _deformed_nodes(X, V, e, x)
        F[e, :] = 0.0
        for q in range(nq):
            _gradient(x, G[e, q], Fm)
            if not _invariant_point(Fm, prm, P, cof, C):
                for i in range(3 * k):
                    F[e, i] = np.nan
                break
            _add_stress_forces(P, G[e, q], wdet[e, q], F[e])


def _jacobi3(A, w, N):
    """The eigenvalues w (3,) and eigenvectors N (3, 3, columns) of the symmetric A (3, 3) by cyclic
    Jacobi rotations (A overwritten): to round-off, repeated eigenvalues included, no allocation."""
    for i in range(3):
        for j in range(3):
            N[i, j] = 1.0 if i == j else 0.0
    for _ in range(30):
        off = A[0, 1] * A[0, 1] + A[0, 2] * A[0, 2] + A[1, 2] * A[1, 2]
        if off <= 1e-32 * (A[0, 0] * A[0, 0] + A[1, 1] * A[1, 1] + A[2, 2] * A[2, 2]) + 1e-300:
            break
        for p, q in ((0, 1), (0, 2), (1, 2)):
            apq = A[p, q]
            if apq == 0.0:
                continue
            theta = (A[q, q] - A[p, p]) / (2.0 * apq)
            t = (1.0 if theta >= 0.0 else -1.0) / (abs(theta) + np.sqrt(theta * theta + 1.0))
            c = 1.0 / np.sqrt(t * t + 1.0)
            sn = t * c
            for k in range(3):  # A <- J^T A J on columns p, q, then rows
                akp, akq = A[k, p], A[k, q]
                A[k, p], A[k, q] = c * akp - sn * akq, sn * akp + c * akq
            for k in range(3):
                apk, aqk = A[p, k], A[q, k]
                A[p, k], A[q, k] = c * apk - sn * aqk, sn * apk + c * aqk
            A[p, q] = A[q, p] = 0.0
            for k in range(3):
                nkp, nkq = N[k, p], N[k, q]
                N[k, p], N[k, q] = c * nkp - sn * nkq, sn * nkp + c * nkq
    for i in range(3):
        w[i] = A[i, i]


def _ogden_point(Fm, prm, P, C, N, lam2, beta, S):
    """P (3, 3) of Ogden's law at one deformation gradient Fm (prm as :func:`_ogden_forces`); False
    (P untouched) where det Fm <= 0. C, N, lam2, beta, S: work arrays."""
    kappa, terms = prm[0], (prm.shape[0] - 1) // 2
    J = (Fm[0, 0] * (Fm[1, 1] * Fm[2, 2] - Fm[1, 2] * Fm[2, 1])
         - Fm[0, 1] * (Fm[1, 0] * Fm[2, 2] - Fm[1, 2] * Fm[2, 0])
         + Fm[0, 2] * (Fm[1, 0] * Fm[2, 1] - Fm[1, 1] * Fm[2, 0]))
    if not J > 0.0:
        return False
    _right_cauchy_green(Fm, C)
    _jacobi3(C, lam2, N)
    jb = J ** (-1.0 / 3.0)
    mean = 0.0
    for a in range(3):
        lb = np.sqrt(max(lam2[a], 0.0)) * jb
        beta[a] = 0.0
        for i in range(terms):
            mu, al = prm[1 + 2 * i], prm[2 + 2 * i]
            beta[a] += (2.0 * mu / al) * lb ** al
        mean += beta[a] / 3.0
    kv = kappa * J * (J - 1.0)
    for a in range(3):
        for b in range(3):
            s = 0.0
            for c in range(3):
                s += N[a, c] * (beta[c] - mean + kv) / lam2[c] * N[b, c]
            S[a, b] = s
    for a in range(3):
        for b in range(3):
            P[a, b] = Fm[a, 0] * S[0, b] + Fm[a, 1] * S[1, b] + Fm[a, 2] * S[2, b]
    return True


def _ogden_forces(V, X, G, wdet, prm, F):
    """F (E, 3k) = the tets' forces with Ogden's W = sum_i 2 mu_i / alpha_i^2 (sum_a lambda_a bar^alpha_i
    - 3) + kappa / 2 (J - 1)^2 (prm = [kappa, mu_1, alpha_1, mu_2, alpha_2, ...]), P as
    :class:`rtfem.fe.hyperelastic.Ogden` writes it (the principal stretches of C by :func:`_jacobi3`);
    an element with J <= 0 at a point gets NaN."""
    E, nq, k = G.shape[0], G.shape[1], G.shape[2]
    x = np.zeros((k, 3))
    Fm, C, N, S, P = np.zeros((3, 3)), np.zeros((3, 3)), np.zeros((3, 3)), np.zeros((3, 3)), np.zeros((3, 3))
    lam2, beta = np.zeros(3), np.zeros(3)
    for e in range(E):
        _deformed_nodes(X, V, e, x)
        F[e, :] = 0.0
        for q in range(nq):
            _gradient(x, G[e, q], Fm)
            if not _ogden_point(Fm, prm, P, C, N, lam2, beta, S):
                for i in range(3 * k):
                    F[e, i] = np.nan
                break
            _add_stress_forces(P, G[e, q], wdet[e, q], F[e])


def _ogden_dP(Fs, prm, h, dP):
    """dP (m, 3, 3, 3, 3) = dP_ab / dF_cd at the gradients Fs (m, 3, 3) by central differences of
    :func:`_ogden_point` (step h, as :meth:`rtfem.fe.hyperelastic.Hyperelastic._tangent`); NaN where
    a perturbed gradient is inverted."""
    Fm, C, N, S = np.zeros((3, 3)), np.zeros((3, 3)), np.zeros((3, 3)), np.zeros((3, 3))
    Pp, Pm = np.zeros((3, 3)), np.zeros((3, 3))
    lam2, beta = np.zeros(3), np.zeros(3)
    for m in range(Fs.shape[0]):
        for c in range(3):
            for d in range(3):
                for i in range(3):
                    for j in range(3):
                        Fm[i, j] = Fs[m, i, j]
                Fm[c, d] += h
                ok = _ogden_point(Fm, prm, Pp, C, N, lam2, beta, S)
                Fm[c, d] -= 2.0 * h
                ok = _ogden_point(Fm, prm, Pm, C, N, lam2, beta, S) and ok
                for a in range(3):
                    for b in range(3):
                        dP[m, a, b, c, d] = (Pp[a, b] - Pm[a, b]) / (2.0 * h) if ok else np.nan


def compiled_ogden_forces():
    """The compiled Ogden force kernel (numba), or None."""
    return compiled("solid-ogden", _ogden_forces, _gradient, _deformed_nodes, _add_stress_forces, _jacobi3,
                    _right_cauchy_green,
                    _ogden_point)


def compiled_ogden_dP():
    """The compiled Ogden tangent by differences (numba), or None."""
    return compiled("solid-ogden-dP", _ogden_dP, _jacobi3, _ogden_point, _right_cauchy_green)


def compiled_invariant_forces():
    """The compiled neo-Hookean / Mooney-Rivlin force kernel (numba), or None."""
    return compiled("solid-invariants", _invariant_forces, _gradient, _deformed_nodes, _add_stress_forces,
                    _invariant_point, _cofactor, _right_cauchy_green)


def law_forces(V, X, G, wdet, law, F) -> None:
    """F (E, 3k) = the tets' forces sum_q wdet P G_i at element dofs V (E, 3k) with a hyperelastic
    ``law`` (:mod:`rtfem.fe.hyperelastic`), as :class:`rtfem.fe.solid.HyperelasticTets`: neo-Hookean
    and Mooney-Rivlin compiled (:func:`_invariant_forces`), Ogden too (:func:`_ogden_forces`), other
    laws with their P at all quadrature points in one batched numpy call."""
    from ..fe.hyperelastic import MooneyRivlin, NeoHookean, Ogden

    if isinstance(law, (NeoHookean, MooneyRivlin)):
        fn, prm = compiled_invariant_forces(), np.array([law.c10, law.c01, law.kappa])
    elif isinstance(law, Ogden):
        fn, prm = compiled_ogden_forces(), np.concatenate([[law.kappa], np.column_stack([law.mus, law.alphas]).ravel()])
    else:
        fn = prm = None
    if fn is not None:
        fn(V, X, G, wdet, prm, F)
    else:
        law_forces_numpy(V, X, G, wdet, law, F)


def law_forces_numpy(V, X, G, wdet, law, F) -> None:
    """:func:`law_forces` batched in numpy (any law; the path without numba)."""
    E, nq, k = G.shape[0], G.shape[1], G.shape[2]
    P = law.stress(_gradients(V, X, G), False)[0].reshape(E, nq, 3, 3) * wdet[:, :, None, None]
    F[:] = np.einsum("eqab,eqib->eia", P, G).reshape(E, 3 * k)


def law_tangents(V, X, G, wdet, law, K) -> None:
    """K (E, 3k, 3k) = the tangents of :func:`law_forces` (the law's dP/dF contracted with the
    shape gradients), symmetric."""
    from ..fe.solid import _tangent_point

    from ..fe.hyperelastic import Ogden

    E, nq, k = G.shape[0], G.shape[1], G.shape[2]
    fn = compiled_ogden_dP() if isinstance(law, Ogden) else None
    if fn is not None:  # Ogden's differences of an eigen-decomposition, compiled
        Fs = np.ascontiguousarray(_gradients(V, X, G))
        dP = np.empty(Fs.shape + (3, 3))
        fn(Fs, np.concatenate([[law.kappa], np.column_stack([law.mus, law.alphas]).ravel()]), 1e-6, dP)
        dP *= wdet.reshape(-1)[:, None, None, None, None]
    else:
        dP = law.stress(_gradients(V, X, G))[2] * wdet.reshape(-1)[:, None, None, None, None]
    Kq = _tangent_point(np.ascontiguousarray(G.reshape(E * nq, k, 3)), dP)
    Kf = Kq.reshape(E, nq, 3 * k, 3 * k).sum(axis=1)
    K[:] = 0.5 * (Kf + Kf.transpose(0, 2, 1))
