"""The frictional contact solve: projected Gauss-Seidel over the 3x3 contact blocks with subspace
steps (PGS-SM, Silcowitz, Niebe & Erleben), on w = b + A r with the Signorini conditions and
Coulomb's law (see :mod:`rtfem.interaction.contact`); compiled when numba is present."""

from __future__ import annotations

import math

import numpy as np

from ..errors import ModelError

__all__ = ["pgs"]


def _lu_solve(M, x):
    """Solve M y = x in place (y in x) by Gaussian elimination with complete pivoting; M (k, k) is
    overwritten. A rank-deficient M (contact points that interpolate others: a face point and its
    corners, whose forces are not unique) gets a basic solution: elimination stops where the
    largest remaining entry is below 1e-11 of the first pivot, and the unknowns left get zero."""
    k = x.shape[0]
    perm = np.arange(k)
    first = 0.0
    rank = k
    for j in range(k):
        p, q, big = j, j, 0.0
        for i in range(j, k):
            for c in range(j, k):
                if abs(M[i, c]) > big:
                    p, q, big = i, c, abs(M[i, c])
        if j == 0:
            first = big
        if big <= 1e-11 * first or big == 0.0:
            rank = j
            break
        if p != j:
            for c in range(k):
                M[j, c], M[p, c] = M[p, c], M[j, c]
            x[j], x[p] = x[p], x[j]
        if q != j:
            for i in range(k):
                M[i, j], M[i, q] = M[i, q], M[i, j]
            perm[j], perm[q] = perm[q], perm[j]
        for i in range(j + 1, k):
            f = M[i, j] / M[j, j]
            if f != 0.0:
                for c in range(j + 1, k):
                    M[i, c] -= f * M[j, c]
                x[i] -= f * x[j]
    y = np.zeros(k)
    for j in range(rank - 1, -1, -1):
        s = x[j]
        for c in range(j + 1, rank):
            s -= M[j, c] * y[c]
        y[j] = s / M[j, j]
    for j in range(k):
        x[perm[j]] = y[j]
    return rank > 0


def _residual(A, r, w, mu):
    """The largest change of Alart and Curnier's fixed-point map, r_n <- max(0, r_n - w_n / A_nn),
    r_t <- (r_t - rho w_t) projected onto the disk of radius mu r_n (rho = 1 / the mean tangential
    diagonal, one number, so that a force on the rim is opposite the slip): zero exactly at a
    solution of the Signorini-Coulomb conditions."""
    res = 0.0
    for c in range(r.shape[0] // 3):
        i = 3 * c
        rn = max(0.0, r[i] - w[i] / A[i, i])
        res = max(res, abs(rn - r[i]))
        att = A[i + 1, i + 1] + A[i + 2, i + 2]
        if mu[c] > 0.0 and att > 0.0:
            rho = 2.0 / att
            t1 = r[i + 1] - rho * w[i + 1]
            t2 = r[i + 2] - rho * w[i + 2]
            t = math.sqrt(t1 * t1 + t2 * t2)
            lim = mu[c] * rn
            if t > lim:
                s = lim / t if t > 0.0 else 0.0
                t1 *= s
                t2 *= s
            res = max(res, abs(t1 - r[i + 1]), abs(t2 - r[i + 2]))
    return res


def _slide(a11, a12, a21, a22, t1, t2, lim):
    """The tangential force of a sliding contact: s = (A_tt + lam I)^-1 t on the friction circle
    |s| = lim, lam > 0, so that the slip w_t = A_tt s - t = -lam s opposes it (Coulomb's maximal
    dissipation; a radial projection of A_tt^-1 t is not opposite the slip unless A_tt is a multiple
    of I). Newton on 1/|s(lam)| (nearly linear in lam), kept inside a bisection bracket."""
    lo, hi = 0.0, math.sqrt(t1 * t1 + t2 * t2) / lim  # |s(hi)| <= lim for a positive definite A_tt
    lam = 0.0
    s1, s2 = 0.0, 0.0
    for _ in range(60):
        b11, b22 = a11 + lam, a22 + lam
        det = b11 * b22 - a12 * a21
        s1 = (b22 * t1 - a12 * t2) / det
        s2 = (b11 * t2 - a21 * t1) / det
        norm = math.sqrt(s1 * s1 + s2 * s2)
        if abs(norm - lim) <= 1e-13 * lim:
            break
        if norm > lim:
            lo = lam
        else:
            hi = lam
        # d|s|/dlam = -s.(A + lam I)^-1 s / |s|
        q1 = (b22 * s1 - a12 * s2) / det
        q2 = (b11 * s2 - a21 * s1) / det
        slope = (s1 * q1 + s2 * q2) / (norm * norm * norm)  # d(1/|s|)/dlam
        step = lam + (1.0 / lim - 1.0 / norm) / slope if slope > 0.0 else -1.0
        lam = step if lo < step < hi else 0.5 * (lo + hi)
    norm = math.sqrt(s1 * s1 + s2 * s2)
    if norm > 0.0:  # on the circle to round-off
        s1 *= lim / norm
        s2 *= lim / norm
    return s1, s2


def _slide_directions(r, status, mu, d1, d2):
    """Each sliding contact's tangential direction (d1, d2) as its force has it now (zero else)."""
    for c in range(status.shape[0]):
        i = 3 * c
        if status[c] == 1 and mu[c] > 0.0:
            t = math.sqrt(r[i + 1] * r[i + 1] + r[i + 2] * r[i + 2])
            if t > 0.0:
                d1[c], d2[c] = r[i + 1] / t, r[i + 2] / t


def _active_rows(status, rows):
    """The unknowns the states leave (stuck: all three, pressed or sliding: the normal one) into
    rows; returns how many."""
    k = 0
    for c in range(status.shape[0]):
        i = 3 * c
        if status[c] == 2:
            rows[k], rows[k + 1], rows[k + 2] = i, i + 1, i + 2
            k += 3
        elif status[c] == 1:
            rows[k] = i
            k += 1
    return k


def _state_system(A, b, rows, k, status, mu, d1, d2):
    """The equalities of the states on the unknowns ``rows[:k]``: M (k, k) x = -b[rows], a sliding
    contact's tangential force mu r_n d carried by its normal unknown."""
    M = np.empty((k, k))
    x = np.empty(k)
    for a in range(k):
        ia = rows[a]
        x[a] = -b[ia]
        for j in range(k):
            ij = rows[j]
            c = ij // 3
            v = A[ia, ij]
            if status[c] == 1 and mu[c] > 0.0:  # r_t = mu r_n d: the normal unknown carries it
                v += mu[c] * (d1[c] * A[ia, ij + 1] + d2[c] * A[ia, ij + 2])
            M[a, j] = v
    return M, x


def _scatter(x, rows, k, status, mu, d1, d2, r):
    """r from the system's solution x: its unknowns, a sliding contact's tangential force along d,
    zero elsewhere."""
    for i in range(r.shape[0]):
        r[i] = 0.0
    for j in range(k):
        r[rows[j]] = x[j]
    for c in range(status.shape[0]):
        if status[c] == 1 and mu[c] > 0.0:
            i = 3 * c
            r[i + 1], r[i + 2] = mu[c] * r[i] * d1[c], mu[c] * r[i] * d2[c]


def _project_onto_cone(r, mu):
    """Each contact's force onto Coulomb's cone: r_n >= 0, |r_t| <= mu r_n."""
    for c in range(mu.shape[0]):
        i = 3 * c
        if r[i] < 0.0:
            r[i] = 0.0
        lim = mu[c] * r[i]
        t = math.sqrt(r[i + 1] * r[i + 1] + r[i + 2] * r[i + 2])
        if t > lim:
            s = lim / t if t > 0.0 else 0.0
            r[i + 1] *= s
            r[i + 2] *= s


def _subspace(A, have, W, Bi, Bv, F, inv_k, b, mu, r, w, status, tol):
    """The subspace step of PGS-SM (Silcowitz, Niebe & Erleben 2010): with the contacts' states
    as the last sweeps left them (status: 0 apart, 1 pressed and sliding or frictionless, 2 stuck),
    solve the equalities they imply in one linear system (pressed: w_n = 0, the tangential force
    mu r_n along its present direction when sliding; stuck: w = 0; apart: r = 0). Where that
    solution pulls (r_n < 0) the contacts are let go, and where it leaves a contact apart
    penetrating (w_n < 0 beyond ``tol`` of the largest force, in force units w_n / A_nn) it is
    pressed, and the system is solved again (block principal pivoting, Judice & Pires 1994), up to
    eight times; the result is projected onto the cone and w recomputed. Returns False (r, w
    unchanged) when nothing is pressed. ``status`` is left as the last solve's."""
    n3 = b.shape[0]
    m = n3 // 3
    rows = np.empty(n3, np.int64)
    d1 = np.zeros(m)
    d2 = np.zeros(m)
    _slide_directions(r, status, mu, d1, d2)
    r_in = r.copy()
    for _ in range(8):
        k = _active_rows(status, rows)
        if k == 0:
            r[:] = r_in
            return False
        for j in range(k):  # the columns the system needs
            _column(W, Bi, Bv, F, inv_k, rows[j] // 3, A, have)
        M, x = _state_system(A, b, rows, k, status, mu, d1, d2)
        if not _lu_solve(M, x):
            r[:] = r_in
            return False
        _scatter(x, rows, k, status, mu, d1, d2, r)
        switched = False
        size = 0.0
        for c in range(m):
            size = max(size, r[3 * c])
        for c in range(m):  # a pulling contact is let go
            if status[c] != 0 and r[3 * c] < 0.0:
                status[c] = 0
                switched = True
        if not switched:  # a contact left apart but penetrating is pressed
            _forces_into(A, have, W, Bi, Bv, F, inv_k, b, r, w)
            for c in range(m):
                i = 3 * c
                if status[c] == 0 and -w[i] / A[i, i] > tol * size:
                    status[c] = 1 if mu[c] == 0.0 else 2
                    switched = True
        if not switched:
            break
    _project_onto_cone(r, mu)
    _forces_into(A, have, W, Bi, Bv, F, inv_k, b, r, w)
    return True


def _forces_into(A, have, W, Bi, Bv, F, inv_k, b, r, w):
    """w = b + A r, from the block columns of the contacts with a force (computed when missing)."""
    for i in range(b.shape[0]):
        w[i] = b[i]
    for c in range(b.shape[0] // 3):
        i = 3 * c
        if r[i] != 0.0 or r[i + 1] != 0.0 or r[i + 2] != 0.0:
            _column(W, Bi, Bv, F, inv_k, c, A, have)
            for k in range(b.shape[0]):
                w[k] += A[k, i] * r[i] + A[k, i + 1] * r[i + 1] + A[k, i + 2] * r[i + 2]


def _pgs(A, have, W, Bi, Bv, F, inv_k, b, mu, r, max_sweeps, tol):
    """Projected Gauss-Seidel on w = b + A r over 3x3 contact blocks [n, t1, t2]: r_n >= 0,
    w_n >= 0, complementary; |r_t| <= mu r_n (stick: w_t = 0). ``r`` (3m,) is the warm start,
    updated in place. When a sweep leaves every contact's state (apart, sliding, stuck) as the
    sweep before did, a subspace step solves those states' equalities directly (:func:`_subspace`),
    kept when it lowers the fixed-point residual (:func:`_residual`): PGS alone crawls on strongly
    coupled contacts (a rigid jaw on a shell: hundreds of sweeps, often not converged in 500).
    Converged when a sweep changes no force by more than ``tol`` of the largest normal force.
    A = F^T (B W B^T + E E^T / k) F (point k moves as sum_a Bv[k, a] u[Bi[k, a]], its corners in the
    block W; F the points' frames; E the stacked identities, the coupling spring moving every point
    with the tool): its block columns are computed (:func:`_column`) only for contacts that get a
    force, unless ``have`` marks them given: O(m m_pressed), not O(m^2).
    Returns the number of sweeps (max_sweeps + 1: not converged)."""
    n3 = b.shape[0]
    m = n3 // 3
    for c in range(m):  # the diagonal blocks; a column when its contact first gets a force
        if not have[c]:
            _block(W, Bi, Bv, F, inv_k, c, c, A)
    w = np.empty(n3)
    _forces_into(A, have, W, Bi, Bv, F, inv_k, b, r, w)
    status = np.zeros(m, np.int64)
    before = np.full(m, -1, np.int64)
    try_subspace = True
    for sweep in range(max_sweeps):
        change = 0.0
        size = 0.0
        for c in range(m):
            i = 3 * c
            r0, r1, r2 = r[i], r[i + 1], r[i + 2]
            # the local problem with the other contacts' forces held
            bn = w[i] - A[i, i] * r0 - A[i, i + 1] * r1 - A[i, i + 2] * r2
            b1 = w[i + 1] - A[i + 1, i] * r0 - A[i + 1, i + 1] * r1 - A[i + 1, i + 2] * r2
            b2 = w[i + 2] - A[i + 2, i] * r0 - A[i + 2, i + 1] * r1 - A[i + 2, i + 2] * r2
            rn = -(bn + A[i, i + 1] * r1 + A[i, i + 2] * r2) / A[i, i]
            if rn < 0.0:
                rn = 0.0
            s1 = 0.0
            s2 = 0.0
            state = 1 if rn > 0.0 else 0
            if mu[c] > 0.0 and rn > 0.0:
                t1 = -(b1 + A[i + 1, i] * rn)
                t2 = -(b2 + A[i + 2, i] * rn)
                a11, a12, a21, a22 = A[i + 1, i + 1], A[i + 1, i + 2], A[i + 2, i + 1], A[i + 2, i + 2]
                det = a11 * a22 - a12 * a21
                s1 = (a22 * t1 - a12 * t2) / det
                s2 = (a11 * t2 - a21 * t1) / det
                norm = math.sqrt(s1 * s1 + s2 * s2)
                lim = mu[c] * rn
                if norm > lim:
                    s1, s2 = _slide(a11, a12, a21, a22, t1, t2, lim)
                else:
                    state = 2
            status[c] = state
            d0, d1, d2 = rn - r0, s1 - r1, s2 - r2
            if d0 != 0.0 or d1 != 0.0 or d2 != 0.0:
                _column(W, Bi, Bv, F, inv_k, c, A, have)
                for k in range(n3):
                    w[k] += A[k, i] * d0 + A[k, i + 1] * d1 + A[k, i + 2] * d2
            r[i], r[i + 1], r[i + 2] = rn, s1, s2
            change = max(change, abs(d0), abs(d1), abs(d2))
            size = max(size, abs(rn))
        if change <= tol * size:  # with no force anywhere: only when none changed (a zero start, nothing touching)
            return sweep + 1
        same = True
        for c in range(m):
            if status[c] != before[c]:
                same = False
            before[c] = status[c]
        if same and try_subspace:  # kept only when it brings r closer to a solution
            r_old, w_old = r.copy(), w.copy()
            if _subspace(A, have, W, Bi, Bv, F, inv_k, b, mu, r, w, status, tol) and \
                    _residual(A, r, w, mu) >= _residual(A, r_old, w_old, mu):
                r[:] = r_old
                w[:] = w_old
                try_subspace = False  # not again before the states change
        elif not same:
            try_subspace = True
    return max_sweeps + 1


def _block(W, Bi, Bv, F, inv_k, c, d, A):
    """A's block (c, d): F_c^T (sum_ab Bv[c, a] Bv[d, b] W(Bi[c, a], Bi[d, b]) + I / k) F_d."""
    m00, m01, m02, m10, m11, m12, m20, m21, m22 = inv_k, 0.0, 0.0, 0.0, inv_k, 0.0, 0.0, 0.0, inv_k
    for a in range(3):
        wa = Bv[c, a]
        if wa == 0.0:
            continue
        p = 3 * Bi[c, a]
        for e in range(3):
            we = wa * Bv[d, e]
            if we == 0.0:
                continue
            q = 3 * Bi[d, e]
            m00 += we * W[p, q]
            m01 += we * W[p, q + 1]
            m02 += we * W[p, q + 2]
            m10 += we * W[p + 1, q]
            m11 += we * W[p + 1, q + 1]
            m12 += we * W[p + 1, q + 2]
            m20 += we * W[p + 2, q]
            m21 += we * W[p + 2, q + 1]
            m22 += we * W[p + 2, q + 2]
    for be in range(3):  # M F_d, then F_c^T (M F_d)
        x0 = m00 * F[d, 0, be] + m01 * F[d, 1, be] + m02 * F[d, 2, be]
        x1 = m10 * F[d, 0, be] + m11 * F[d, 1, be] + m12 * F[d, 2, be]
        x2 = m20 * F[d, 0, be] + m21 * F[d, 1, be] + m22 * F[d, 2, be]
        for al in range(3):
            A[3 * c + al, 3 * d + be] = F[c, 0, al] * x0 + F[c, 1, al] * x1 + F[c, 2, al] * x2
    if c == d:  # a direction the supports hold (a point on a symmetry plane under a rigid tool) has no
        # compliance, and its tangential block would be singular: 1e-9 of the point's compliance there
        # makes it a rigid surface, on which the tool slides with friction (the supports take it)
        eps = 1e-9 * (m00 + m11 + m22)
        A[3 * c + 1, 3 * c + 1] += eps
        A[3 * c + 2, 3 * c + 2] += eps


def _column(W, Bi, Bv, F, inv_k, d, A, have):
    """A's block column d (all contacts' rows), once: ``have[d]`` marks it computed."""
    if have[d]:
        return
    for c in range(Bi.shape[0]):
        _block(W, Bi, Bv, F, inv_k, c, d, A)
    have[d] = True


def _diagonal(W, Bi, Bv, F, inv_k, A):
    """A's diagonal blocks only."""
    for c in range(Bi.shape[0]):
        _block(W, Bi, Bv, F, inv_k, c, c, A)


try:  # compiled when numba is present (the same code)
    import numba as _numba

    _opts = dict(cache=True, nogil=True, error_model="numpy")  # no exceptions from the kernels
    _block = _numba.njit(**_opts)(_block)  # the names _pgs calls: compiled too
    _column = _numba.njit(**_opts)(_column)
    _forces_into = _numba.njit(**_opts)(_forces_into)
    _lu_solve = _numba.njit(**_opts)(_lu_solve)
    _residual = _numba.njit(**_opts)(_residual)
    _slide = _numba.njit(**_opts)(_slide)
    _slide_directions = _numba.njit(**_opts)(_slide_directions)
    _active_rows = _numba.njit(**_opts)(_active_rows)
    _state_system = _numba.njit(**_opts)(_state_system)
    _scatter = _numba.njit(**_opts)(_scatter)
    _project_onto_cone = _numba.njit(**_opts)(_project_onto_cone)
    _subspace = _numba.njit(**_opts)(_subspace)
    _pgs_compiled = _numba.njit("i8(f8[:, ::1], b1[::1], f8[:, ::1], i8[:, ::1], f8[:, ::1], f8[:, :, ::1], f8, f8[::1], "
                                "f8[::1], f8[::1], i8, f8)", **_opts)(_pgs)
    _diagonal = _numba.njit("void(f8[:, ::1], i8[:, ::1], f8[:, ::1], f8[:, :, ::1], f8, f8[:, ::1])",
                            **_opts)(_diagonal)
except Exception:  # pragma: no cover - numba absent
    _pgs_compiled = None


def pgs(A, b, mu, r=None, *, max_sweeps: int = 500, tol: float = 1e-10) -> tuple[np.ndarray, int]:
    """Solve the frictional contact problem w = b + A r (see :mod:`rtfem.interaction.contact`) by projected
    Gauss-Seidel; ``A`` (3m, 3m) with positive diagonal, ``b`` (3m,), ``mu`` (m,) friction
    coefficients, ``r`` a warm start. Returns (r, sweeps); sweeps > max_sweeps: not converged."""
    A = np.ascontiguousarray(A, dtype=float)
    b = np.ascontiguousarray(b, dtype=float)
    mu = np.array(np.broadcast_to(np.asarray(mu, dtype=float), (b.size // 3,)))
    r = np.zeros_like(b) if r is None else np.array(r, dtype=float)
    if A.shape != (b.size, b.size) or b.size % 3:
        raise ModelError(f"pgs needs A (3m, 3m) and b (3m,), got {A.shape} and {b.shape}")
    if b.size and not np.all(np.diag(A)[::3] > 0):
        raise ModelError("the contact compliance has a zero or negative normal diagonal: a contact point on held nodes")
    m = b.size // 3
    return _solve(A, np.ones(m, dtype=bool), np.zeros((1, 1)), np.zeros((m, 3), dtype=np.int64), np.zeros((m, 3)),
                  np.zeros((m, 3, 3)), 0.0, b, mu, r, max_sweeps, tol)


def _solve(A, have, W, Bi, Bv, F, inv_k, b, mu, r, max_sweeps, tol):
    """:func:`_pgs` (compiled where numba is present) on contiguous arrays; returns (r, sweeps)."""
    fn = _pgs_compiled if _pgs_compiled is not None else _pgs
    sweeps = fn(A, have, W, Bi, Bv, F, float(inv_k), b, mu, r, int(max_sweeps), float(tol)) if b.size else 0
    return r, int(sweeps)
