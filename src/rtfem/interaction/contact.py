"""Tool-tissue contact over patches: rigid tools against the deformed surface, with friction.

A tool is a convex "core" (a point, a segment or a rectangle) swept by a radius: a sphere, a
capsule (an instrument shaft) or a flat jaw. Its signed distance is d(x) = |x - core(x)| - R, with
unit gradient n(x) = (x - core(x)) / |x - core(x)|, the direction the tool pushes the tissue.

Contact points. Every surface vertex near the tool is a candidate, at its *predicted* position
(where it would be after one more step with no new load, :func:`~rtfem.drivers.base.predictions`), and
so is the one point of the deformed surface closest to the tool's core, on a triangle (barycentric
weights b): with the vertices alone a small probe would pass between them and feel the vertex
spacing. The gap of a contact point y = sum_k b_k x_k is d0 = d(y); its frame F = [n, t1, t2].

The solve (James & Pai's capacitance matrix). With the driver's one-step cross compliances W_SS
(:func:`~rtfem.drivers.base.step_compliances`) the contact points move as y(k+1) = y_free + B W_SS B^T f.
The tool is coupled to the device by a virtual spring of stiffness k (``coupling="spring"``; a
"constraint" is k = infinity): its proxy sits at x_t = x_d - (1/k) sum f. In each point's frame
(r_c = F_c^T f_c) the gap and the tangential slip of the step are

    w = b + A r,   A_cd = F_c^T (B W_SS B^T + 1/k)_cd F_d,
    b_c = [d0_c - n_c . (x_d(k+1) - x_e);  T_c^T ((y_free,c - y_c(k)) - (x_d(k+1) - x_t(k)))],

The contact points are found with the tool where it was, x_t(k) (a point stuck to the tool is
found at the same material point again), and their gaps d0 and frames F are evaluated against
the tool where it will end the step with last step's force, x_e = x_d(k+1) + (1/k) f_hand(k) (the
device itself for a constraint), so that the friction directions do not lag a step behind a
large quasi-static move; the coupling's change over the step is linear through A, and the slip
takes the tool's whole move over the step, x_d(k+1) - x_t(k). A direction the supports hold has
no compliance; the tangential diagonal gets 1e-9 of the point's compliance, so that the tool
slides on such a point with friction (the supports take the force) instead of dividing by zero.
With the Signorini conditions w_n >= 0, r_n >= 0, w_n r_n = 0 and Coulomb's law |r_t| <= mu r_n
(stick: w_t = 0; slip: r_t opposes w_t at |r_t| = mu r_n). This is solved by projected
Gauss-Seidel over the 3x3 contact blocks (the normal by its row, the tangential pair by its 2x2
block, a sliding pair on the friction circle opposite its slip), warm-started from the previous
step's forces, with subspace steps (Silcowitz, Niebe & Erleben's PGS-SM): once a sweep leaves
every contact's state (apart, sliding, stuck) unchanged, the equalities of those states are solved
directly, kept when they bring the forces closer to a solution (:func:`pgs`, compiled when numba
is present). The step is then taken with the vertex forces B^T F r; the hand feels -sum f.

The compliances of the vertices touched lately are kept from step to step in one pool: when the
set changes only the rows and columns of newly touched vertices are computed, and the set's block
is read in place (for drivers whose W follows the motion, ``compliance_changes``, the whole block
each step). What a vertex needs from the driver first
(its static-correction or compliance columns: sparse solves, milliseconds) is prepared by a
background thread while the tool is still ``lookahead`` away, so a sliding tool does not stall
the force loop; a vertex not ready when touched is prepared in the loop, so the numbers never
depend on the timing.
"""

from __future__ import annotations

import math
import threading
import weakref

import numpy as np
from scipy.spatial import cKDTree

from .. import validate
from ..errors import ModelError
from ..mesh.surface import TriMesh
from ..drivers.base import as_driver, displacements_at, predictions, prepare, step_compliances
from ..threads import background, runtime

__all__ = ["Tool", "ToolContact", "pgs", "closest_points_on_triangles", "hold_patch", "nodes_to_prepare"]


class Tool:
    """A rigid tool: a convex core swept by a radius (sphere, capsule, flat jaw).

    The core is the box [-a, a] x [-b, b] x {0} in the tool's frame (``orientation``: the 3x3
    rotation whose columns are the frame's axes in the world): a = b = 0 a point (a sphere), b = 0 a
    segment along the first axis (a capsule), both > 0 a rectangle (a jaw, whose face normal is the
    third axis). Use the constructors :meth:`sphere`, :meth:`capsule` and :meth:`jaw`.
    """

    def __init__(self, radius: float, half_extents=(0.0, 0.0), orientation=None, *, kind: str = "tool") -> None:
        self.radius = validate.nonnegative(radius, "radius", "the tool's radius in m")
        if isinstance(half_extents, (str, bytes)) or np.ndim(half_extents) != 1 or len(half_extents) != 2:
            raise ModelError(f"half_extents={validate.show(half_extents)} must be two half-lengths (a, b) in m: the "
                             "core's segment (b = 0) or rectangle (0, 0: a point)")
        a, b = (validate.nonnegative(v, n, "a half-length in m") for v, n in zip(half_extents, ("a", "b")))
        self.half_extents = np.array([a, b, 0.0])
        self.orientation = np.ascontiguousarray(np.eye(3) if orientation is None else _rotation_matrix(orientation), dtype=float)
        self.kind = kind

    @classmethod
    def sphere(cls, radius: float) -> "Tool":
        """A sphere of ``radius`` (m); 0 is a point probe."""
        return cls(radius, kind="sphere")

    @classmethod
    def capsule(cls, radius: float, length: float, axis=(1.0, 0.0, 0.0)) -> "Tool":
        """A capsule (an instrument shaft): a segment of ``length`` along ``axis`` swept by ``radius``."""
        length = validate.positive(length, "length", "the capsule's length in m")
        return cls(radius, (0.5 * length, 0.0), _frame(axis), kind="capsule")

    @classmethod
    def jaw(cls, width: float, length: float, thickness: float, normal=(0.0, 0.0, 1.0), along=None) -> "Tool":
        """A flat jaw: a ``length`` x ``width`` plate of ``thickness`` (rounded edges) whose faces
        look along ``normal``; ``along`` the direction of its length (any direction across the normal
        when not given)."""
        width = validate.positive(width, "width", "the jaw's width in m")
        length = validate.positive(length, "length", "the jaw's length in m")
        thickness = validate.positive(thickness, "thickness", "the jaw's thickness in m")
        n = _unit(normal, "normal")
        t = _frame(n)[:, 1] if along is None else _unit(along, "along")
        t = t - (t @ n) * n
        if np.linalg.norm(t) < 1e-9:
            raise ModelError("the jaw's length direction `along` must not be parallel to its normal")
        t /= np.linalg.norm(t)
        R = np.column_stack([t, np.cross(n, t), n])
        return cls(0.5 * thickness, (0.5 * length, 0.5 * width), R, kind="jaw")

    @property
    def reach(self) -> float:
        """The radius of a ball around the tool's position that contains the tool."""
        return float(np.linalg.norm(self.half_extents) + self.radius)

    def core(self, points: np.ndarray, position: np.ndarray) -> np.ndarray:
        """The closest core point (k, 3) to each of ``points`` with the tool at ``position``."""
        R = self.orientation
        local = (points - position) @ R
        local = np.clip(local, -self.half_extents, self.half_extents)
        return position + local @ R.T

    def distance(self, points: np.ndarray, position: np.ndarray, outward: np.ndarray):
        """Signed gaps (k,) between surface ``points`` and the tool at ``position``, and the unit
        directions (k, 3) the tool pushes them along; ``outward`` (k, 3) the surface's outward
        normals there. Away from the core, |x - core(x)| - R; a point the core has passed (the core
        behind the surface, within R of the normal line) gets a negative gap and the inward normal,
        so that it is pushed on, not back; so does a point on the core itself. (The force loop's
        compiled :func:`_gaps` is this, with the normal line widened on a concave edge.)"""
        v = self.core(points, position) - points
        dist = np.sqrt(np.einsum("ij,ij->i", v, v))
        above = _outside(v, outward, self.radius)
        n = np.where((above & (dist > 1e-12))[:, None], -v / np.maximum(dist, 1e-300)[:, None], -outward)
        return np.where(above, dist, -dist) - self.radius, n

    def __repr__(self) -> str:
        a, b, _ = self.half_extents
        return f"Tool.{self.kind}(radius={self.radius:g}, half_extents=({a:g}, {b:g}))"


def _unit(v, name: str) -> np.ndarray:
    v = validate.vector(v, name, 3)
    n = float(np.linalg.norm(v))
    if n < 1e-300:
        raise ModelError(f"{name} must be a nonzero direction")
    return v / n


def _frame(axis) -> np.ndarray:
    """A rotation whose first column is ``axis``."""
    e = _unit(axis, "axis")
    helper = np.eye(3)[int(np.argmin(np.abs(e)))]
    t1 = np.cross(e, helper)
    t1 /= np.linalg.norm(t1)
    return np.column_stack([e, t1, np.cross(e, t1)])


def _rotation_matrix(R) -> np.ndarray:
    R = validate.real_array(R, "orientation", 2)
    if R.shape != (3, 3) or np.abs(R.T @ R - np.eye(3)).max() > 1e-6 or np.linalg.det(R) < 0:
        raise ModelError("orientation must be a 3x3 rotation matrix (orthonormal columns, determinant +1)")
    return R


def closest_points_on_triangles(P: np.ndarray, A: np.ndarray, B: np.ndarray, C: np.ndarray):
    """Closest points of triangles (A, B, C) (k, 3 each) to points P (k, 3): (points, barycentric
    weights (k, 3)). The projection on the plane when it falls inside, else the nearest of the
    three edges' closest points."""
    e0, e1 = B - A, C - A
    d = P - A
    a00, a01, a11 = np.einsum("ij,ij->i", e0, e0), np.einsum("ij,ij->i", e0, e1), np.einsum("ij,ij->i", e1, e1)
    b0, b1 = np.einsum("ij,ij->i", d, e0), np.einsum("ij,ij->i", d, e1)
    det = np.maximum(a00 * a11 - a01 * a01, 1e-300)
    s, t = (a11 * b0 - a01 * b1) / det, (a00 * b1 - a01 * b0) / det
    bary = np.stack([1.0 - s - t, s, t], axis=1)
    inside = (s >= 0) & (t >= 0) & (s + t <= 1)
    best = np.full(P.shape[0], np.inf)
    out_b = bary.copy()
    corners = (A, B, C)
    for i, j in ((0, 1), (1, 2), (2, 0)):
        Q0, Q1 = corners[i], corners[j]
        e = Q1 - Q0
        u = np.clip(np.einsum("ij,ij->i", P - Q0, e) / np.maximum(np.einsum("ij,ij->i", e, e), 1e-300), 0.0, 1.0)
        dist = np.linalg.norm(Q0 + u[:, None] * e - P, axis=1)
        better = ~inside & (dist < best)
        best = np.where(better, dist, best)
        wts = np.zeros_like(bary)
        wts[:, i], wts[:, j] = 1.0 - u, u
        out_b = np.where(better[:, None], wts, out_b)
    points = out_b[:, :1] * A + out_b[:, 1:2] * B + out_b[:, 2:] * C
    return points, out_b


# ------------------------------------------------------------------------------ the contact solve
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


def _subspace(A, have, W, Bi, Bv, F, inv_k, b, mu, r, w, status, tol):  # noqa: C901 - a compiled kernel, to split (issue 38)
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
    for c in range(m):
        i = 3 * c
        if status[c] == 1 and mu[c] > 0.0:
            t = math.sqrt(r[i + 1] * r[i + 1] + r[i + 2] * r[i + 2])
            if t > 0.0:
                d1[c], d2[c] = r[i + 1] / t, r[i + 2] / t
    r_in = r.copy()
    for _ in range(8):
        k = 0
        for c in range(m):
            i = 3 * c
            if status[c] == 2:
                rows[k], rows[k + 1], rows[k + 2] = i, i + 1, i + 2
                k += 3
            elif status[c] == 1:
                rows[k] = i
                k += 1
        if k == 0:
            r[:] = r_in
            return False
        for j in range(k):  # the columns the system needs
            _column(W, Bi, Bv, F, inv_k, rows[j] // 3, A, have)
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
        if not _lu_solve(M, x):
            r[:] = r_in
            return False
        for i in range(n3):
            r[i] = 0.0
        for j in range(k):
            r[rows[j]] = x[j]
        for c in range(m):
            if status[c] == 1 and mu[c] > 0.0:
                i = 3 * c
                r[i + 1], r[i + 2] = mu[c] * r[i] * d1[c], mu[c] * r[i] * d2[c]
        switched = False
        size = 0.0
        for c in range(m):
            size = max(size, r[3 * c])
        for c in range(m):
            if status[c] != 0 and r[3 * c] < 0.0:
                status[c] = 0
                switched = True
        if not switched:
            _forces_into(A, have, W, Bi, Bv, F, inv_k, b, r, w)
            for c in range(m):
                i = 3 * c
                if status[c] == 0 and -w[i] / A[i, i] > tol * size:
                    status[c] = 1 if mu[c] == 0.0 else 2
                    switched = True
        if not switched:
            break
    for c in range(m):
        i = 3 * c
        if r[i] < 0.0:
            r[i] = 0.0
        lim = mu[c] * r[i]
        t = math.sqrt(r[i + 1] * r[i + 1] + r[i + 2] * r[i + 2])
        if t > lim:
            s = lim / t if t > 0.0 else 0.0
            r[i + 1] *= s
            r[i + 2] *= s
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


# ------------------------------------------------------------------------------ compiled geometry
def _core_into(p0, p1, p2, c, R, half, q):
    """q (3,) = the tool core's point closest to p (see :meth:`Tool.core`)."""
    l0 = (p0 - c[0]) * R[0, 0] + (p1 - c[1]) * R[1, 0] + (p2 - c[2]) * R[2, 0]
    l1 = (p0 - c[0]) * R[0, 1] + (p1 - c[1]) * R[1, 1] + (p2 - c[2]) * R[2, 1]
    l2 = (p0 - c[0]) * R[0, 2] + (p1 - c[1]) * R[1, 2] + (p2 - c[2]) * R[2, 2]
    l0 = min(max(l0, -half[0]), half[0])
    l1 = min(max(l1, -half[1]), half[1])
    l2 = min(max(l2, -half[2]), half[2])
    for i in range(3):
        q[i] = c[i] + l0 * R[i, 0] + l1 * R[i, 1] + l2 * R[i, 2]


def _gaps(P, Q, O, spread, c, R, half, radius, d, n):
    """Each point P[k]'s signed gap d[k] and push direction n[k] (:meth:`Tool.distance`, outward
    normals O), the normal line widened by ``spread`` |v . O| (on a concave edge, the tangent of
    its faces' cone: the points behind the edge whose closest surface point is on it), the gap
    then moved on to Q[k] along n: d += n . (Q - P)."""
    q = np.empty(3)
    for k in range(P.shape[0]):
        _core_into(P[k, 0], P[k, 1], P[k, 2], c, R, half, q)
        v0, v1, v2 = q[0] - P[k, 0], q[1] - P[k, 1], q[2] - P[k, 2]
        vv = v0 * v0 + v1 * v1 + v2 * v2
        dist = math.sqrt(vv)
        vn = v0 * O[k, 0] + v1 * O[k, 1] + v2 * O[k, 2]
        lateral = math.sqrt(max(vv - vn * vn, 0.0))
        above = vn >= 0 or lateral > radius + spread[k] * abs(vn) + 1e-12
        if above and dist > 1e-12:
            n[k, 0], n[k, 1], n[k, 2] = -v0 / dist, -v1 / dist, -v2 / dist
        else:
            n[k, 0], n[k, 1], n[k, 2] = -O[k, 0], -O[k, 1], -O[k, 2]
        g = (dist if above else -dist) - radius
        d[k] = g + n[k, 0] * (Q[k, 0] - P[k, 0]) + n[k, 1] * (Q[k, 1] - P[k, 1]) + n[k, 2] * (Q[k, 2] - P[k, 2])


def _closest_on_triangle(p, A, B, C, out, bary):
    """The point ``out`` (3,) of triangle ABC closest to p, and its barycentric weights (see
    :func:`closest_points_on_triangles`)."""
    e00, e01, e02 = B[0] - A[0], B[1] - A[1], B[2] - A[2]
    e10, e11, e12 = C[0] - A[0], C[1] - A[1], C[2] - A[2]
    d0, d1, d2 = p[0] - A[0], p[1] - A[1], p[2] - A[2]
    a00 = e00 * e00 + e01 * e01 + e02 * e02
    a01 = e00 * e10 + e01 * e11 + e02 * e12
    a11 = e10 * e10 + e11 * e11 + e12 * e12
    b0 = d0 * e00 + d1 * e01 + d2 * e02
    b1 = d0 * e10 + d1 * e11 + d2 * e12
    det = max(a00 * a11 - a01 * a01, 1e-300)
    s, t = (a11 * b0 - a01 * b1) / det, (a00 * b1 - a01 * b0) / det
    if s >= 0 and t >= 0 and s + t <= 1:
        bary[0], bary[1], bary[2] = 1.0 - s - t, s, t
    else:
        best = np.inf
        for e in range(3):
            i, j = e, (e + 1) % 3
            Q0 = A if i == 0 else (B if i == 1 else C)
            Q1 = A if j == 0 else (B if j == 1 else C)
            f0, f1, f2 = Q1[0] - Q0[0], Q1[1] - Q0[1], Q1[2] - Q0[2]
            u = ((p[0] - Q0[0]) * f0 + (p[1] - Q0[1]) * f1 + (p[2] - Q0[2]) * f2) / max(f0 * f0 + f1 * f1 + f2 * f2, 1e-300)
            u = min(max(u, 0.0), 1.0)
            g0, g1, g2 = Q0[0] + u * f0 - p[0], Q0[1] + u * f1 - p[1], Q0[2] + u * f2 - p[2]
            dist = math.sqrt(g0 * g0 + g1 * g1 + g2 * g2)
            if dist < best:
                best = dist
                bary[0] = bary[1] = bary[2] = 0.0
                bary[i], bary[j] = 1.0 - u, u
    for i in range(3):
        out[i] = bary[0] * A[i] + bary[1] * B[i] + bary[2] * C[i]


def _faces(Y, Yf, local, c, cg, R, half, radius, iters, reach, margin, same, V, bary, n, gaps,  # noqa: C901
           keep):  # a compiled kernel, to split (issue 38)
    """The ring's face contacts (every face of the ring is a contact of its own: where the probe
    sits in its own dent, a concave crease, the closest point would jump across the crease, while
    the set of faces' points moves continuously): for each triangle
    (corners ``local``, rows of Y) the point closest to the tool's core at ``c`` (``iters`` alternating
    projections), its weights ``bary``, push direction ``n`` and gap against the tool at ``cg`` (``gaps``, linearized to the
    free positions Yf); kept (``keep``, the count returned) when inside the face or on an edge
    (once per edge, judged by the edge's mean normal and its cone), its gap below ``reach`` before
    and ``margin`` after the linearization, and not within ``same`` of a vertex contact (rows of V)
    or of a face point kept before."""
    f = local.shape[0]
    P = np.empty((f, 3))
    O = np.empty((f, 3))
    q = np.empty(3)
    p = np.empty(3)
    A = np.empty(3)
    B = np.empty(3)
    C = np.empty(3)
    for k in range(f):
        for i in range(3):
            A[i], B[i], C[i] = Y[local[k, 0], i], Y[local[k, 1], i], Y[local[k, 2], i]
        _core_into((A[0] + B[0] + C[0]) / 3.0, (A[1] + B[1] + C[1]) / 3.0, (A[2] + B[2] + C[2]) / 3.0, c, R, half, q)
        for _ in range(iters):
            _closest_on_triangle(q, A, B, C, p, bary[k])
            _core_into(p[0], p[1], p[2], c, R, half, q)
        P[k, 0], P[k, 1], P[k, 2] = p[0], p[1], p[2]
        o0 = (B[1] - A[1]) * (C[2] - A[2]) - (B[2] - A[2]) * (C[1] - A[1])
        o1 = (B[2] - A[2]) * (C[0] - A[0]) - (B[0] - A[0]) * (C[2] - A[2])
        o2 = (B[0] - A[0]) * (C[1] - A[1]) - (B[1] - A[1]) * (C[0] - A[0])
        size = max(math.sqrt(o0 * o0 + o1 * o1 + o2 * o2), 1e-300)
        O[k, 0], O[k, 1], O[k, 2] = o0 / size, o1 / size, o2 / size
    # which faces' points count: inside, or on an edge once (the edge's normal: its faces' mean)
    on = np.zeros(f, np.int64)
    lo = np.full(f, -1, np.int64)  # the edge's corners (rows of Y), for a point on an edge
    hi = np.full(f, -1, np.int64)
    for k in range(f):
        for a in range(3):
            if bary[k, a] > 1e-9:
                on[k] += 1
                if lo[k] < 0:
                    lo[k] = local[k, a]
                else:
                    hi[k] = local[k, a]
        if on[k] == 2 and lo[k] > hi[k]:
            lo[k], hi[k] = hi[k], lo[k]
    spread = np.zeros(f)
    outward = O.copy()
    ok = np.zeros(f, np.bool_)
    for k in range(f):
        ok[k] = on[k] >= 2
        if on[k] != 2:
            continue
        s0, s1, s2 = 0.0, 0.0, 0.0
        first = True
        for j in range(f):
            if on[j] == 2 and lo[j] == lo[k] and hi[j] == hi[k]:
                s0, s1, s2 = s0 + O[j, 0], s1 + O[j, 1], s2 + O[j, 2]
                if j < k:
                    first = False
        size = max(math.sqrt(s0 * s0 + s1 * s1 + s2 * s2), 1e-300)
        u0, u1, u2 = s0 / size, s1 / size, s2 / size
        cos = u0 * O[k, 0] + u1 * O[k, 1] + u2 * O[k, 2]
        spread[k] = math.sqrt(max(1.0 - cos * cos, 0.0)) / max(cos, 1e-3)
        outward[k, 0], outward[k, 1], outward[k, 2] = u0, u1, u2
        ok[k] = first
    _gaps(P, P, outward, spread, cg, R, half, radius, gaps, n)
    kept = 0
    for k in range(f):
        if not ok[k] or not gaps[k] < reach:
            continue
        g = gaps[k]
        for a in range(3):
            w = bary[k, a]
            for i in range(3):
                g += n[k, i] * w * (Yf[local[k, a], i] - Y[local[k, a], i])
        if not g < margin:
            continue
        fresh = True
        for j in range(V.shape[0]):
            if (V[j, 0] - P[k, 0]) ** 2 + (V[j, 1] - P[k, 1]) ** 2 + (V[j, 2] - P[k, 2]) ** 2 <= same * same:
                fresh = False
        for j in range(kept):
            i = keep[j]
            if (P[i, 0] - P[k, 0]) ** 2 + (P[i, 1] - P[k, 1]) ** 2 + (P[i, 2] - P[k, 2]) ** 2 <= same * same:
                fresh = False
        if fresh:
            gaps[k] = g
            keep[kept] = k
            kept += 1
    return kept


def _points(g, n, Y, Yf, verts, margin, loc, bw, nf, df, fid, pos, S, Bi, Bv, F, gaps, y_free, y_now, ids):
    """The contact points from the candidates' gaps ``g`` (k,) (moved on to their free positions)
    and push directions n: each vertex whose gap is below ``margin``, then the kept face
    points (corners ``loc``, rows of Y, weights ``bw``, directions ``nf``, gaps ``df``, ids
    ``fid``). Fills the points' corners Bi (rows of S) and weights Bv, frames F, gaps, free and
    current positions and ids (vertex number, or -1 - triangle); S (the candidates the points
    use, ascending rows of Y). Returns (m points, s nodes)."""
    k = g.shape[0]
    for i in range(k):
        pos[i] = -1
    m = 0
    for i in range(k):
        if g[i] < margin:
            pos[i] = 0
            Bi[m, 0] = Bi[m, 1] = Bi[m, 2] = i
            Bv[m, 0], Bv[m, 1], Bv[m, 2] = 1.0, 0.0, 0.0
            _frame_into(n[i, 0], n[i, 1], n[i, 2], F, m)
            gaps[m] = g[i]
            for j in range(3):
                y_free[m, j], y_now[m, j] = Yf[i, j], Y[i, j]
            ids[m] = verts[i]
            m += 1
    for f in range(loc.shape[0]):
        for a in range(3):
            pos[loc[f, a]] = 0
            Bi[m, a] = loc[f, a]
            Bv[m, a] = bw[f, a]
        _frame_into(nf[f, 0], nf[f, 1], nf[f, 2], F, m)
        gaps[m] = df[f]
        for j in range(3):
            y_free[m, j] = bw[f, 0] * Yf[loc[f, 0], j] + bw[f, 1] * Yf[loc[f, 1], j] + bw[f, 2] * Yf[loc[f, 2], j]
            y_now[m, j] = bw[f, 0] * Y[loc[f, 0], j] + bw[f, 1] * Y[loc[f, 1], j] + bw[f, 2] * Y[loc[f, 2], j]
        ids[m] = fid[f]
        m += 1
    s = 0
    for i in range(k):
        if pos[i] == 0:
            pos[i] = s
            S[s] = i
            s += 1
    for c in range(m):
        for a in range(3):
            Bi[c, a] = pos[Bi[c, a]]
    return m, s


def _rhs(F, gaps, y_free, y_now, move, slide, ids, warm_ids, warm_r, b, r):
    """b (m, 3) of the solve (see the module's docstring: the gap and the slip in each point's
    frame; ``move`` the device from where the geometry was evaluated, linear in the gap; ``slide``
    the tool's move over the step, x_d(k+1) - x_t(k), in the slip), and the warm start r (m, 3):
    last step's forces at the points (by id) still here."""
    for c in range(gaps.shape[0]):
        s0 = y_free[c, 0] - y_now[c, 0] - slide[0]
        s1 = y_free[c, 1] - y_now[c, 1] - slide[1]
        s2 = y_free[c, 2] - y_now[c, 2] - slide[2]
        b[c, 0] = gaps[c] - (F[c, 0, 0] * move[0] + F[c, 1, 0] * move[1] + F[c, 2, 0] * move[2])
        b[c, 1] = F[c, 0, 1] * s0 + F[c, 1, 1] * s1 + F[c, 2, 1] * s2
        b[c, 2] = F[c, 0, 2] * s0 + F[c, 1, 2] * s1 + F[c, 2, 2] * s2
        r[c, 0] = r[c, 1] = r[c, 2] = 0.0
        for j in range(warm_ids.shape[0]):
            if warm_ids[j] == ids[c]:
                r[c, 0], r[c, 1], r[c, 2] = warm_r[j, 0], warm_r[j, 1], warm_r[j, 2]
                break


def _after(W, slots, Bi, Bv, F, r, y_free, f_points, f_nodes, y_after):
    """After the solve: each point's force on the organ f_points = F r (m, 3), the nodes' forces
    f_nodes = B^T f (s, 3), and each pressed point's position after the step y_free + B W f
    (y_after, only rows with r_n > 0; W's rows and columns at the nodes' ``slots``)."""
    m = r.shape[0]
    for i in range(f_nodes.shape[0]):
        f_nodes[i, 0] = f_nodes[i, 1] = f_nodes[i, 2] = 0.0
    for c in range(m):
        for j in range(3):
            f_points[c, j] = F[c, j, 0] * r[c, 0] + F[c, j, 1] * r[c, 1] + F[c, j, 2] * r[c, 2]
        for a in range(3):
            w = Bv[c, a]
            if w != 0.0:
                for j in range(3):
                    f_nodes[Bi[c, a], j] += w * f_points[c, j]
    for c in range(m):
        if not r[c, 0] > 0.0:
            continue
        for j in range(3):
            y_after[c, j] = y_free[c, j]
        for a in range(3):
            w = Bv[c, a]
            if w == 0.0:
                continue
            p = 3 * slots[Bi[c, a]]
            for e in range(f_nodes.shape[0]):
                f0, f1, f2 = f_nodes[e, 0], f_nodes[e, 1], f_nodes[e, 2]
                if f0 == 0.0 and f1 == 0.0 and f2 == 0.0:
                    continue
                q = 3 * slots[e]
                for j in range(3):
                    y_after[c, j] += w * (W[p + j, q] * f0 + W[p + j, q + 1] * f1 + W[p + j, q + 2] * f2)


def _frame_into(n0, n1, n2, F, k):
    """F[k] (3, 3): the contact frame of unit normal n, columns n, t1, t2 (right-handed,
    orthonormal; t1 = n x e, e the x axis, or the y axis where n is near x)."""
    h0, h1, h2 = (1.0, 0.0, 0.0) if abs(n0) < 0.6 else (0.0, 1.0, 0.0)
    t0, t1, t2 = n1 * h2 - n2 * h1, n2 * h0 - n0 * h2, n0 * h1 - n1 * h0
    size = math.sqrt(t0 * t0 + t1 * t1 + t2 * t2)
    t0, t1, t2 = t0 / size, t1 / size, t2 / size
    F[k, 0, 0], F[k, 1, 0], F[k, 2, 0] = n0, n1, n2
    F[k, 0, 1], F[k, 1, 1], F[k, 2, 1] = t0, t1, t2
    F[k, 0, 2], F[k, 1, 2], F[k, 2, 2] = n1 * t2 - n2 * t1, n2 * t0 - n0 * t2, n0 * t1 - n1 * t0


try:  # compiled when numba is present (the same code)
    import numba as _numba

    _opts = dict(cache=True, nogil=True, error_model="numpy")  # no exceptions from the kernels
    _block = _numba.njit(**_opts)(_block)  # the names _pgs calls: compiled too
    _column = _numba.njit(**_opts)(_column)
    _forces_into = _numba.njit(**_opts)(_forces_into)
    _lu_solve = _numba.njit(**_opts)(_lu_solve)
    _residual = _numba.njit(**_opts)(_residual)
    _slide = _numba.njit(**_opts)(_slide)
    _subspace = _numba.njit(**_opts)(_subspace)
    _pgs_compiled = _numba.njit("i8(f8[:, ::1], b1[::1], f8[:, ::1], i8[:, ::1], f8[:, ::1], f8[:, :, ::1], f8, f8[::1], "
                                "f8[::1], f8[::1], i8, f8)", **_opts)(_pgs)
    _diagonal = _numba.njit("void(f8[:, ::1], i8[:, ::1], f8[:, ::1], f8[:, :, ::1], f8, f8[:, ::1])",
                            **_opts)(_diagonal)
    _core_into = _numba.njit(**_opts)(_core_into)
    _closest_on_triangle = _numba.njit(**_opts)(_closest_on_triangle)
    _gaps = _numba.njit("void(f8[:, ::1], f8[:, ::1], f8[:, ::1], f8[::1], f8[::1], f8[:, ::1], f8[::1], f8, f8[::1], "
                        "f8[:, ::1])", **_opts)(_gaps)
    _faces = _numba.njit("i8(f8[:, ::1], f8[:, ::1], i8[:, ::1], f8[::1], f8[::1], f8[:, ::1], f8[::1], f8, i8, f8, f8, "
                         "f8, f8[:, ::1], f8[:, ::1], f8[:, ::1], f8[::1], i8[::1])", **_opts)(_faces)
    _frame_into = _numba.njit(**_opts)(_frame_into)
    _points = _numba.njit("UniTuple(i8, 2)(f8[::1], f8[:, ::1], f8[:, ::1], f8[:, ::1], i8[::1], f8, i8[:, ::1], "
                          "f8[:, ::1], f8[:, ::1], f8[::1], i8[::1], i8[::1], i8[::1], i8[:, ::1], f8[:, ::1], "
                          "f8[:, :, ::1], f8[::1], f8[:, ::1], f8[:, ::1], i8[::1])", **_opts)(_points)
    _rhs = _numba.njit("void(f8[:, :, ::1], f8[::1], f8[:, ::1], f8[:, ::1], f8[::1], f8[::1], i8[::1], i8[::1], "
                       "f8[:, ::1], f8[:, ::1], f8[:, ::1])", **_opts)(_rhs)
    _after = _numba.njit("void(f8[:, ::1], i8[::1], i8[:, ::1], f8[:, ::1], f8[:, :, ::1], f8[:, ::1], f8[:, ::1], "
                         "f8[:, ::1], f8[:, ::1], f8[:, ::1])", **_opts)(_after)
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


_LOCKS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # driver -> its preparations' lock


def _driver_lock(driver) -> threading.Lock:
    """One lock per driver, shared by every ToolContact on it (two tools' background threads would
    otherwise prepare the same vertices at once); a fresh lock for a driver without weak
    references."""
    try:
        return _LOCKS.setdefault(driver, threading.Lock())
    except TypeError:  # not weakly referenceable (__slots__ without __weakref__)
        return threading.Lock()


class _Preparer:
    """Prepares driver nodes (static-correction or compliance columns: sparse solves of
    milliseconds each) before the force loop needs them: :meth:`want` names the vertices the tool
    is about to reach and a background thread prepares them, nearest first, in small batches;
    :meth:`ensure` (the loop) prepares whatever is still missing itself, so the results never
    depend on the timing. One lock keeps the driver's preparation to one thread at a time. The
    thread ends after a second with nothing to do and starts again on the next :meth:`want`; an
    error there stops the background work (the loop's own preparation then raises it)."""

    BATCH = 4  # nodes per background preparation: short lock holds, multi-column solves

    def __init__(self, driver) -> None:
        self.driver = driver
        self.ready: set[int] = set()
        self.lock = _driver_lock(driver)  # shared by every tool on this driver
        self._cv = threading.Condition()
        self._pending = np.zeros(0, dtype=np.int64)
        self._where = np.zeros((0, 3))  # rest positions of the pending vertices
        self._at = np.zeros(3)
        self._thread = None
        self.failed: BaseException | None = None
        self.background = 0  # nodes prepared by the thread (for benchmarks)

    def ensure(self, nodes: np.ndarray) -> int:
        """Prepare ``nodes`` now (those not ready); returns how many this call prepared."""
        missing = [v for v in nodes.tolist() if v not in self.ready]
        if missing:
            with self.lock:
                missing = [v for v in missing if v not in self.ready]
                if missing:
                    prepare(self.driver, np.asarray(missing, dtype=np.int64))
                    self.ready.update(missing)
        return len(missing)

    def want(self, nodes: np.ndarray, where: np.ndarray, at: np.ndarray) -> None:
        """Prepare ``nodes`` (rest positions ``where``) in the background, nearest ``at`` first."""
        if self.failed is not None:
            return
        fresh = np.fromiter((v not in self.ready for v in nodes.tolist()), dtype=bool, count=nodes.size)
        with self._cv:
            self._pending, self._where, self._at = nodes[fresh], where[fresh], np.asarray(at, dtype=float)
            if self._pending.size and (self._thread is None or not self._thread.is_alive()):
                self._thread = threading.Thread(target=self._run, name="rtfem-prepare", daemon=True)
                background(self._thread, self.close)
                self._thread.start()
            self._cv.notify()

    def close(self) -> None:
        """Drop what is pending: the thread ends after the batch in hand (the interpreter's exit)."""
        with self._cv:
            self._pending, self._where = self._pending[:0], self._where[:0]
            self._cv.notify_all()

    def _run(self) -> None:
        # BLAS and MKL held to one thread while this thread lives (the run-time limit the loops
        # share): their worker threads (spinning after each call) took the loop's core on 2 cores,
        # p99 of the slide 1.7 -> 4.8 ms
        with runtime():
            while True:
                with self._cv:
                    if not self._pending.size and not self._cv.wait_for(lambda: self._pending.size > 0, timeout=1.0):
                        return
                    gap = np.einsum("ij,ij->i", self._where - self._at, self._where - self._at)
                    first = np.argsort(gap, kind="stable")[:self.BATCH]
                    batch = self._pending[first]
                    rest = np.setdiff1d(np.arange(self._pending.size), first)
                    self._pending, self._where = self._pending[rest], self._where[rest]
                try:
                    with self.lock:
                        todo = [v for v in batch.tolist() if v not in self.ready]
                        if todo:
                            prepare(self.driver, np.asarray(todo, dtype=np.int64))
                            self.ready.update(todo)
                            self.background += len(todo)
                except BaseException as exc:  # noqa: BLE001 - the loop's own preparation raises it
                    self.failed = exc
                    return


class _ComplianceBlock:
    """The driver's cross compliances W of the vertices touched lately, kept between steps in one
    buffer (a pool of slots): a vertex touched for the first time gets a slot, and its rows and
    columns against the pool are computed then; a contact set's block is read in place through
    its vertices' slots, so a set that changes costs only its new vertices. When the pool is full
    the vertices of the current set are kept (copied to the front) and the rest let go. Drivers
    whose W follows the motion (``compliance_changes``) get the set's whole block each step."""

    def __init__(self, driver, slots: int = 64) -> None:
        self.driver = driver
        self.min_slots = slots
        self.preparer = _Preparer(driver)
        self.slot = np.full(driver.n_nodes, -1, dtype=np.int64)  # node -> slot (-1: not in the pool)
        self.nodes = np.zeros(0, dtype=np.int64)  # the pool's nodes, by slot
        self.W = np.zeros((3 * slots, 3 * slots))
        self.new_rows = 0  # vertices whose rows were computed in the last call (for benchmarks)
        self.prepared_here = 0  # of them, vertices the loop had to prepare itself (for benchmarks)

    def block(self, nodes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(W, slots): the compliance of ``nodes`` (ascending) is W at rows and columns 3 slot + (0, 1, 2)."""
        d = self.driver
        if getattr(d, "compliance_changes", False):
            self.new_rows = nodes.size
            return np.ascontiguousarray(step_compliances(d, nodes)), np.arange(nodes.size, dtype=np.int64)
        slots = self.slot[nodes]
        fresh = nodes[slots < 0]
        self.new_rows = self.prepared_here = int(fresh.size)
        if not fresh.size:
            return self.W, slots
        self.prepared_here = self.preparer.ensure(fresh)
        used, cap = self.nodes.size, self.W.shape[0] // 3
        if used + fresh.size > cap:  # full: keep the current set's vertices, let the others go
            kept = nodes[slots >= 0]
            need = kept.size + fresh.size
            cap = max(cap, 2 * need, self.min_slots) if need > cap // 2 else cap
            idx = (3 * self.slot[kept][:, None] + np.arange(3)).reshape(-1)
            W = np.empty((3 * cap, 3 * cap))
            W[:idx.size, :idx.size] = self.W[idx][:, idx]
            self.slot[self.nodes] = -1
            self.slot[kept] = np.arange(kept.size)
            self.nodes, self.W, used = kept, W, kept.size
        old = self.nodes
        self.slot[fresh] = used + np.arange(fresh.size)
        self.nodes = np.concatenate([old, fresh])
        j = slice(3 * used, 3 * self.nodes.size)
        self.W[:3 * self.nodes.size, j] = step_compliances(d, self.nodes, fresh)
        if used:
            self.W[j, :3 * used] = step_compliances(d, fresh, old)
        return self.W, self.slot[nodes]


class ToolContact:
    """A rigid :class:`Tool` in frictional contact with an organ through any Driver, coupled to a
    haptic device by a virtual spring. ``update(position)`` is one haptic step (a HapticLoop drives
    it like a Probe); it returns the force on the device (N).

    Parameters
    ----------
    mesh : the organ surface (the driver's mesh).
    driver : a ModalSimulator (linear or warped), a DirectSimulator (linear or large-deformation),
        an ImpedanceMap or any Driver.
    tool : a :class:`Tool` (default: a 5 mm sphere).
    coupling : "spring" (virtual coupling of ``stiffness`` N/m, default) or "constraint" (the tool
        sits at the device; points the supports hold, which a rigid tool cannot move, are left out
        of its contacts).
    friction : Coulomb's coefficient mu (0: frictionless).
    margin : candidates within this distance of the tool (m) enter the solve (default: a quarter of
        the median edge), so that a point about to touch is in the set.
    surface_point : also the surface point closest to the tool's core, on a triangle (default True;
        False: vertices only, for a tool much larger than the edges).
    lookahead : vertices within this distance beyond the tool's reach (m; default two median edges)
        are prepared on a background thread before the tool touches them (their static-correction
        or compliance columns: a few ms each), so that a tool sliding onto new vertices does not
        stall the force loop; 0: prepared in the loop when touched. Either way the same numbers.
    """

    def __init__(self, mesh: TriMesh, driver, tool: Tool | None = None, *, coupling: str = "spring",
                 stiffness: float = 200.0, friction: float = 0.0, margin: float | None = None,
                 surface_point: bool = True, lookahead: float | None = None, max_sweeps: int = 500,
                 tol: float = 1e-10) -> None:
        from ..drivers.base import check_driver_mesh

        driver = as_driver(driver, "tool")
        check_driver_mesh(mesh, driver, "tool")
        self.tool = Tool.sphere(0.005) if tool is None else tool
        if not isinstance(self.tool, Tool):
            raise ModelError(f"tool={validate.show(tool)} must be an rt.Tool (Tool.sphere, Tool.capsule, Tool.jaw)")
        self.coupling = validate.choice(coupling, "coupling", ("spring", "constraint"))
        self.stiffness = validate.positive(stiffness, "stiffness", "the coupling stiffness in N/m")
        self.friction = friction
        self.surface_point = validate.flag(surface_point, "surface_point")
        self.max_sweeps = validate.count(max_sweeps, "max_sweeps", 1, 10**6)
        self.tol = validate.positive(tol, "tol", "a relative tolerance")
        self.mesh, self.driver = mesh, driver
        touched = mesh.contact_surface()  # quadratic faces: their corner and mid-edge triangles
        self.X = np.asarray(touched.vertices, dtype=float)
        self.normals = touched.vertex_normals()
        self._touchable = touched.used_vertices()
        self._tree = cKDTree(self.X[self._touchable])
        T = np.asarray(touched.triangles, dtype=np.int64)
        self._tri = T  # vertex -> triangles (CSR): _vt_tris[_vt_start[v]:_vt_start[v + 1]]
        order = np.argsort(T.reshape(-1), kind="stable")
        self._vt_tris = order // 3
        self._vt_start = np.searchsorted(T.reshape(-1)[order], np.arange(self.X.shape[0] + 1))
        edges = touched.edges()
        self.edge = float(np.median(np.linalg.norm(self.X[edges[:, 0]] - self.X[edges[:, 1]], axis=1)))
        self.margin = 0.25 * self.edge if margin is None else validate.nonnegative(margin, "margin", "a distance in m")
        self.lookahead = 2 * self.edge if lookahead is None else validate.nonnegative(lookahead, "lookahead",
                                                                                      "a distance in m")
        self._block = _ComplianceBlock(driver)
        self._ahead = getattr(driver, "prepare", None) is not None and not getattr(driver, "compliance_changes", False)
        self._asked_at: np.ndarray | None = None  # where the tool was when the vertices ahead were last named
        self._warm_ids, self._warm_r = np.zeros(0, dtype=np.int64), np.zeros((0, 3))  # last step's forces
        self._cand: np.ndarray | None = None  # the candidate vertices (see _candidates)
        self._cand_at = np.zeros(3)
        self._buf: tuple | None = None  # the contact set's arrays (see _contact_set), reused
        self._A = np.empty(0)  # the contact operator's buffer (see _operator)
        self._offset = np.zeros(3)
        self.proxy: np.ndarray | None = None  # the tool's position after the coupling (m)
        self.force = np.zeros(3)  # force on the device (N); the organ gets -force in total
        self.contacts = 0  # active contact points (positive normal force) in the last step
        self.sweeps = 0  # PGS sweeps of the last step
        self.points = np.zeros((0, 3))  # the active contact points after the last step (deformed, m)
        self.contact_forces = np.zeros((0, 3))  # and the force on the organ at each (N)
        self.contact_normals = np.zeros((0, 3))  # and the direction the tool pushes at each

    @property
    def friction(self) -> float:
        """Coulomb's coefficient mu (0: frictionless); may be changed between steps, mid-contact
        (checked: a finite number from 0 to 10, else ModelError and the old value kept)."""
        return self._friction

    @friction.setter
    def friction(self, mu) -> None:
        self._friction = validate.in_range(mu, "friction", 0.0, 10.0, what="Coulomb's friction coefficient")

    # ---------------------------------------------------------------- preparation
    def prepare(self, nodes=None, *, around=None, radius: float = 0.01) -> int:
        """Compute what contacts at these vertices will need (static-correction columns, compliance
        columns, maps) before the force loop; as :meth:`Probe.prepare`. Returns how many."""
        nodes = nodes_to_prepare(self._touchable, self._tree, self.X.shape[0], nodes, around, radius)
        if nodes.size:
            self._block.preparer.ensure(nodes)
        return int(nodes.size)

    def displacements(self) -> np.ndarray:
        return self.driver.displacements()

    # ---------------------------------------------------------------- the contact set
    def _candidates(self, c: np.ndarray) -> np.ndarray:
        """The surface vertices that may touch the tool at ``c`` (ascending), from a ball query
        one edge wider than needed, kept until the tool has moved that edge (relative to the
        vertices' mean motion)."""
        at = c - self._offset
        if self._cand is None or np.sum((at - self._cand_at) ** 2) > self.edge**2:
            reach = self.tool.reach + self.margin + 2 * self.edge
            verts = self._touchable[np.asarray(self._tree.query_ball_point(at, reach), dtype=np.int64)]
            verts.sort()
            self._cand, self._cand_at = verts, at
        return self._cand

    def _contact_set(self, c: np.ndarray, ahead: np.ndarray):
        """Contact points near the tool at ``c`` (where it was: a stuck face point is found at the
        same material point again), their gaps and frames against the tool at ``ahead`` (where it
        will end the step): (nodes S, corners Bi (m, 3) (rows of S) and weights Bv, frames
        (m, 3, 3), gaps (m,), free positions (m, 3), current positions (m, 3), ids (m,)), or None."""
        verts = self._candidates(c)
        if verts.size == 0:
            return None
        tool = self.tool
        R, half, radius = tool.orientation, tool.half_extents, float(tool.radius)
        k = verts.size
        d, n, O = np.empty(k), np.empty((k, 3)), self.normals[verts]
        # the triangles around the candidate nearest the tool, by the rest shape moved by the
        # candidates' mean motion (a stable choice: by the deformed shape a flat jaw over many
        # vertices at one gap would pick another ring each step)
        X = self.X[verts]
        P = X + self._offset
        _gaps(P, P, O, np.zeros(k), c, R, half, radius, d, n)
        v = int(verts[np.argmin(d)])
        ring = self._vt_tris[self._vt_start[v]:self._vt_start[v + 1]]
        corners = self._tri[ring]
        loc = np.searchsorted(verts, corners)
        if np.any(verts[np.minimum(loc, k - 1)] != corners):  # the ring reaches past the candidates
            self._cand = np.union1d(verts, corners)
            return self._contact_set(c, ahead)
        u_free = predictions(self.driver, verts)
        u_now = displacements_at(self.driver, verts)
        self._offset = u_now.mean(axis=0)
        # the geometry of the surface now (continuous from step to step), its free motion linearly
        Y, Yf = X + u_now, X + u_free
        _gaps(Y, Y, O, np.zeros(k), ahead, R, half, radius, d, n)
        g = d + np.einsum("ki,ki->k", n, Yf - Y)  # each gap moved on to the free position, linearly
        f = ring.size if self.surface_point else 0
        bw, nf, df, keep = np.empty((f, 3)), np.empty((f, 3)), np.empty(f), np.empty(f, dtype=np.int64)
        if f:  # a face point within 1e-3 edge of a vertex contact or of another kept point is the
            # same contact twice (a probe sitting on a vertex): dropped
            kept = _faces(Y, Yf, loc, c, ahead, R, half, radius, 1 if not half.any() else 4,
                          self.margin + 2 * self.edge, self.margin, 1e-3 * self.edge, Y[g < self.margin], bw, nf, df,
                          keep)
            keep = keep[:kept]
        loc, bw, nf, df, fid = loc[keep], bw[keep], nf[keep], df[keep], -1 - ring[keep]
        size = k + loc.shape[0]
        if self._buf is None or self._buf[0].size < size:
            cap = 2 * size
            self._buf = (np.empty(cap, dtype=np.int64), np.empty(cap, dtype=np.int64), np.empty((cap, 3), dtype=np.int64),
                         np.empty((cap, 3)), np.empty((cap, 3, 3)), np.empty(cap), np.empty((cap, 3)),
                         np.empty((cap, 3)), np.empty(cap, dtype=np.int64))
        pos, S, Bi, Bv, F, gaps, y_free, y_now, ids = self._buf
        m, ns = _points(g, n, Y, Yf, verts, self.margin, np.ascontiguousarray(loc), np.ascontiguousarray(bw), nf, df,
                        np.ascontiguousarray(fid), pos, S, Bi, Bv, F, gaps, y_free, y_now, ids)
        if m == 0:
            return None
        return verts[S[:ns]], Bi[:m], Bv[:m], F[:m], gaps[:m], y_free[:m], y_now[:m], ids[:m]

    # ---------------------------------------------------------------- the step
    def update(self, position) -> np.ndarray:
        """One step with the device at ``position``; returns the force on the device (N)."""
        c = validate.point(position, "tool position")
        inv_k = 1.0 / self.stiffness if self.coupling == "spring" else 0.0
        # the geometry (gaps, frames) where the tool will end the step with last step's force (at the
        # device for a constraint), so that large steps bring no lag in the friction directions; the
        # coupling's change over the step is linear in the solve, and the slip takes the tool's whole
        # move over the step, x_d(k+1) - x_t(k)
        ahead = c + inv_k * self.force
        last = c if self.proxy is None else self.proxy
        if self.lookahead > 0 and self._ahead:
            self._look_ahead(c)
        found = self._contact_set(last, ahead)
        if found is None:
            return self._apart(c)
        S, Bi, Bv, F, gaps, y_free, y_now, ids = found
        deepest = -float(gaps.min())
        if deepest > max(self.tool.radius, self.edge):  # nothing stepped: the state is as it was
            raise ModelError(f"the tool would be {deepest * 1e3:.3g} mm inside the organ at once, more than its radius "
                             f"({self.tool.radius * 1e3:.3g} mm) and an edge ({1e3 * self.edge:.3g} mm): a jump of the "
                             "device (or a tool placed inside the organ) has no contact answer. Move it there in steps "
                             "from outside")
        m = gaps.size
        W, slots = self._block.block(S)
        Bs = slots[Bi]  # the points' corners as the pool's slots
        A = self._operator(m)  # the contact operator (see _pgs), filled as the solve needs it
        if inv_k == 0.0:  # a rigid tool cannot press a point the supports hold (zero compliance): left out
            _diagonal(W, Bs, Bv, F, inv_k, A)
            normal = np.diagonal(A)[::3]
            soft = normal > 1e-12 * max(float(normal.max()), 1e-300)
            if not soft.all():
                if not soft.any():
                    return self._apart(c)
                Bi, Bs, Bv, F, gaps, y_free, y_now, ids = (np.ascontiguousarray(x[soft]) for x in
                                                           (Bi, Bs, Bv, F, gaps, y_free, y_now, ids))
                m = gaps.size
                A = self._operator(m)
        b, r = np.empty((m, 3)), np.empty((m, 3))
        _rhs(F, gaps, y_free, y_now, c - ahead, c - last, ids, self._warm_ids, self._warm_r, b, r)
        r, sweeps = _solve(A, np.zeros(m, dtype=bool), W, Bs, Bv, F, inv_k, b.reshape(-1), np.full(m, self.friction),
                           r.reshape(-1), self.max_sweeps, self.tol)
        r = r.reshape(m, 3)
        f_points, f_nodes, y_after = np.empty((m, 3)), np.empty((S.size, 3)), np.empty((m, 3))
        _after(W, slots, Bi, Bv, F, r, y_free, f_points, f_nodes, y_after)
        pushed = np.flatnonzero(f_nodes.any(axis=1))
        loads = dict(zip(S[pushed].tolist(), map(tuple, f_nodes[pushed].tolist())))
        self.driver.step(loads or None)
        total = f_points.sum(axis=0)
        self.proxy = c - inv_k * total
        self.force = -total
        self.sweeps = sweeps
        active = r[:, 0] > 0
        self.contacts = int(np.count_nonzero(active))
        self._warm_ids, self._warm_r = ids[active], r[active]
        self.points, self.contact_forces, self.contact_normals = y_after[active], f_points[active], F[active, :, 0]
        return self.force

    def _operator(self, m: int) -> np.ndarray:
        """A (3m, 3m) for the solve, in a buffer kept between steps (filled by the solve itself)."""
        if self._A.size < 9 * m * m:
            self._A = np.empty(max(9 * m * m, 2 * self._A.size))
        return self._A[:9 * m * m].reshape(3 * m, 3 * m)

    def _look_ahead(self, c: np.ndarray) -> None:
        """Name the vertices within the lookahead to the background preparer, when the tool has
        moved a quarter edge since it last did (a ball query, some 10-50 us)."""
        at = c - self._offset
        if self._asked_at is not None and np.sum((at - self._asked_at) ** 2) < (0.25 * self.edge) ** 2:
            return
        self._asked_at = at
        reach = self.tool.reach + self.margin + self.edge + self.lookahead
        verts = self._touchable[np.asarray(self._tree.query_ball_point(at, reach), dtype=np.int64)]
        if verts.size:
            self._block.preparer.want(verts, self.X[verts], at)

    def _apart(self, c: np.ndarray) -> np.ndarray:
        """A step with nothing touched: the organ moves freely, the tool sits at the device."""
        self.driver.step(None)
        self.proxy, self.force, self.contacts, self.sweeps = c.copy(), np.zeros(3), 0, 0
        self.points = self.contact_forces = self.contact_normals = np.zeros((0, 3))
        self._warm_ids, self._warm_r = np.zeros(0, dtype=np.int64), np.zeros((0, 3))
        return self.force


def nodes_to_prepare(touchable: np.ndarray, tree: cKDTree, n_nodes: int, nodes=None, around=None,
                     radius: float = 0.01) -> np.ndarray:
    """The vertices a tool's ``prepare`` names: ``nodes`` (checked indices), or the surface vertices
    (``touchable``, indexed by ``tree`` at their rest positions) within ``radius`` of ``around``."""
    if nodes is not None:
        return validate.nodes(nodes, n_nodes)
    if around is None:
        raise ModelError("give nodes, or a point around which to prepare the contact compliances")
    centre = validate.point(around, "around")
    radius = validate.positive(radius, "radius", "a distance in m")
    return touchable[np.asarray(tree.query_ball_point(centre, radius), dtype=np.int64)]


def _outside(v: np.ndarray, outward: np.ndarray, radius: float) -> np.ndarray:
    """Whether the tool's core is outside the tissue, given v (k, 3) from a surface point to its
    closest core point and the surface's outward normals: it has passed the surface only when it is
    behind it and within the tool's radius of the normal line (a core merely beside the point, as a
    shaft lying on the surface, is not through it)."""
    vn = np.einsum("ij,ij->i", v, outward)
    lateral = np.sqrt(np.maximum(np.einsum("ij,ij->i", v, v) - vn * vn, 0.0))
    return (vn >= 0) | (lateral > radius + 1e-12)


def hold_patch(W: np.ndarray, h: np.ndarray, g: np.ndarray, k: float, grip: float) -> tuple[np.ndarray, np.ndarray]:
    """The forces (m, 3) of a jaw holding m vertices and the jaw's translation delta (3,).

    Each held vertex is tied to the jaw by a grip spring (stiffness ``grip``), the jaw to the hand
    by the grasp spring k: (W + I/grip) f - E delta = h (h = displacements at the grab minus the
    free prediction), E^T f + k delta = g (g = k (hand - jaw's grab position)), E the stacked 3x3
    identities; one symmetric (3m + 3) solve."""
    m = h.size // 3
    sol = np.linalg.solve(patch_system(W, k, grip), np.concatenate([h, g]))
    return sol[:-3].reshape(m, 3), sol[-3:]


def patch_system(W: np.ndarray, k: float, grip: float) -> np.ndarray:
    """The (3m + 3) matrix of :func:`hold_patch`: [[W + I/grip, -E], [E^T, k I]]."""
    m = W.shape[0] // 3
    E = np.tile(np.eye(3), (m, 1))
    return np.block([[W + np.eye(3 * m) / grip, -E], [E.T, k * np.eye(3)]])
