"""The flat shell triangle's stiffness compiled (numba): each element's frame, OPT membrane and DKT
bending (:mod:`rtfem.fe.shell`: the same formulas, per element instead of batched), its rotation to
the global frame and its addition straight into the CSR arrays of the node pattern
(:mod:`rtfem.fe.assembly_kernels`), in one pass with no element-matrix array. Equal to the numpy
path to round-off (tests/test_assembly_kernels.py)."""

from __future__ import annotations

import numpy as np

from .assembly_kernels import _slot
from .jit import compiled

__all__ = ["shell_stiffness"]

# the beta index patterns of Felippa's Q1..Q3 (OPT, Eq. 29); the local dofs of membrane and bending
_PATTERNS = np.array([[[0, 1, 2], [3, 4, 5], [6, 7, 8]], [[8, 6, 7], [2, 0, 1], [5, 3, 4]],
                      [[4, 5, 3], [7, 8, 6], [1, 2, 0]]], dtype=np.int64)
_MEMBRANE = np.array([0, 1, 5, 6, 7, 11, 12, 13, 17], dtype=np.int64)
_BENDING = np.array([2, 3, 4, 8, 9, 10, 14, 15, 16], dtype=np.int64)


def _add_btdb(B, D, scale, out):
    """out += scale B^T D B for B (3, n) and D (3, 3)."""
    n = B.shape[1]
    for i in range(n):
        d0 = B[0, i] * D[0, 0] + B[1, i] * D[1, 0] + B[2, i] * D[2, 0]
        d1 = B[0, i] * D[0, 1] + B[1, i] * D[1, 1] + B[2, i] * D[2, 1]
        d2 = B[0, i] * D[0, 2] + B[1, i] * D[1, 2] + B[2, i] * D[2, 2]
        for j in range(n):
            out[i, j] += scale * (d0 * B[0, j] + d1 * B[1, j] + d2 * B[2, j])


def _membrane(x, y, A, V, Em, ab, beta, beta0, pat, W, km):
    """Felippa's OPT membrane stiffness km (9, 9) of local corners (x, y), as shell.membrane_opt;
    W holds scratch: B (3, 9), Tth (3, 9), Te (3, 3), Qm (3, 3), Enat (3, 3), S (3, 3)."""
    B, Tth, Te, Qm, Enat, S = W[0], W[1], W[2, :, :3], W[3, :, :3], W[4, :, :3], W[5, :, :3]
    x12, x23, x31 = x[0] - x[1], x[1] - x[2], x[2] - x[0]
    y12, y23, y31 = y[0] - y[1], y[1] - y[2], y[2] - y[0]
    x21, x32, x13, y21, y32, y13 = -x12, -x23, -x31, -y12, -y23, -y31
    h = ab / 6
    B[:, :] = 0.0
    B[0, 0], B[2, 0], B[1, 1], B[2, 1] = y23, x32, x32, y23
    B[0, 2], B[1, 2], B[2, 2] = y23 * (y13 - y21) * h, x32 * (x31 - x12) * h, 2 * (x31 * y13 - x12 * y21) * h
    B[0, 3], B[2, 3], B[1, 4], B[2, 4] = y31, x13, x13, y31
    B[0, 5], B[1, 5], B[2, 5] = y31 * (y21 - y32) * h, x13 * (x12 - x23) * h, 2 * (x12 * y21 - x23 * y32) * h
    B[0, 6], B[2, 6], B[1, 7], B[2, 7] = y12, x21, x21, y12
    B[0, 8], B[1, 8], B[2, 8] = y12 * (y32 - y13) * h, x21 * (x23 - x31) * h, 2 * (x23 * y32 - x31 * y13) * h
    row = (x32, y32, 0.0, x13, y13, 0.0, x21, y21, 0.0)
    for i in range(3):
        for j in range(9):
            B[i, j] /= 2 * A
            Tth[i, j] = row[j] / (4 * A)
        Tth[i, 2 + 3 * i] = 1.0
    L = (x21 * x21 + y21 * y21, x32 * x32 + y32 * y32, x13 * x13 + y13 * y13)
    c0 = (y23 * y13, x23 * x13, y23 * x31 + x32 * y13)
    c1 = (y31 * y21, x31 * x21, y31 * x12 + x13 * y21)
    c2 = (y12 * y32, x12 * x32, y12 * x23 + x21 * y32)
    for i in range(3):
        Te[i, 0], Te[i, 1], Te[i, 2] = c0[i] * L[0], c1[i] * L[1], c2[i] * L[2]
        for j in range(3):
            Te[i, j] /= 4 * A * A
    Enat[:, :] = 0.0
    _add_btdb(Te, Em, 1.0, Enat)
    S[:, :] = 0.0
    for m in range(3):  # Qm = (Q_m + Q_m+1) / 2, Q_p[r, c] = beta[pattern_p[r, c]] 2A / (3 L_r)
        p, q = m, (m + 1) % 3
        for r in range(3):
            for c in range(3):
                Qm[r, c] = 0.5 * (beta[pat[p, r, c]] + beta[pat[q, r, c]]) * (2 * A / 3) / L[r]
        _add_btdb(Qm, Enat, 1.0, S)
    km[:, :] = 0.0
    _add_btdb(B, Em, V, km)
    _add_btdb(Tth, S, 0.75 * beta0 * V, km)


def _bending(x, y, A, Db, Hx, Hy, Bk, kb):
    """The DKT bending stiffness kb (9, 9) of local corners (x, y), as shell.bending_dkt (Hx, Hy
    (9, 6) and Bk (3, 9) are scratch)."""
    xs = (x[1] - x[2], x[2] - x[0], x[0] - x[1])
    ys = (y[1] - y[2], y[2] - y[0], y[0] - y[1])
    Hx[:, :] = 0.0
    Hy[:, :] = 0.0
    for i in range(3):  # corner i with the side that starts at it (m) and the side that ends at it (k)
        m, k = (2, 0, 1)[i], (1, 2, 0)[i]
        r, nm, nk = 3 * i, 3 + m, 3 + k
        lm, lk = xs[m] ** 2 + ys[m] ** 2, xs[k] ** 2 + ys[k] ** 2
        am, ak, dm, dk = -xs[m] / lm, -xs[k] / lk, -ys[m] / lm, -ys[k] / lk
        bm, bk = 0.75 * xs[m] * ys[m] / lm, 0.75 * xs[k] * ys[k] / lk
        cm, ck = (0.25 * xs[m] ** 2 - 0.5 * ys[m] ** 2) / lm, (0.25 * xs[k] ** 2 - 0.5 * ys[k] ** 2) / lk
        em, ek = (0.25 * ys[m] ** 2 - 0.5 * xs[m] ** 2) / lm, (0.25 * ys[k] ** 2 - 0.5 * xs[k] ** 2) / lk
        Hx[r, nm], Hx[r, nk], Hx[r + 1, nm], Hx[r + 1, nk] = 1.5 * am, -1.5 * ak, bm, bk
        Hx[r + 2, i], Hx[r + 2, nm], Hx[r + 2, nk] = 1.0, -cm, -ck
        Hy[r, nm], Hy[r, nk], Hy[r + 1, i], Hy[r + 1, nm], Hy[r + 1, nk] = 1.5 * dm, -1.5 * dk, -1.0, em, ek
        Hy[r + 2, nm], Hy[r + 2, nk] = -bm, -bk
    x21, x31, y21, y31 = x[1] - x[0], x[2] - x[0], y[1] - y[0], y[2] - y[0]
    det = x21 * y31 - x31 * y21
    kb[:, :] = 0.0
    for xi, eta in ((0.5, 0.0), (0.5, 0.5), (0.0, 0.5)):  # the mid-side rule: exact
        l1 = 1.0 - xi - eta
        dxi = (1 - 4 * l1, 4 * xi - 1, 0.0, 4 * eta, -4 * eta, 4 * (l1 - xi))
        deta = (1 - 4 * l1, 0.0, 4 * eta - 1, 4 * xi, 4 * (l1 - eta), -4 * xi)
        for r in range(9):
            hx_xi = hx_eta = hy_xi = hy_eta = 0.0
            for c in range(6):
                hx_xi += Hx[r, c] * dxi[c]
                hx_eta += Hx[r, c] * deta[c]
                hy_xi += Hy[r, c] * dxi[c]
                hy_eta += Hy[r, c] * deta[c]
            hx_x = (y31 * hx_xi - y21 * hx_eta) / det
            hx_y = (-x31 * hx_xi + x21 * hx_eta) / det
            hy_x = (y31 * hy_xi - y21 * hy_eta) / det
            hy_y = (-x31 * hy_xi + x21 * hy_eta) / det
            Bk[0, r], Bk[1, r], Bk[2, r] = hx_x, hy_y, hx_y + hy_x
        _add_btdb(Bk, Db, A / 3.0, kb)


def _shell_kernel(X, cells, Em, Db, t, ab, beta, beta0, pat, mem, bend, indptr, indices, data, area):
    """data += every triangle's global stiffness (symmetrized, as assemble_blocks adds it); area =
    each triangle's area; returns the first degenerate triangle (zero area), or -1."""
    E = cells.shape[0]
    R = np.zeros((3, 3))
    x, y = np.zeros(3), np.zeros(3)
    W = np.zeros((6, 3, 9))
    Hx, Hy, Bk = np.zeros((9, 6)), np.zeros((9, 6)), np.zeros((3, 9))
    km, kb = np.zeros((9, 9)), np.zeros((9, 9))
    K, KR, Kg = np.zeros((18, 18)), np.zeros((18, 18)), np.zeros((18, 18))
    for e in range(E):
        p0, p1, p2 = cells[e, 0], cells[e, 1], cells[e, 2]
        a = (X[p1, 0] - X[p0, 0], X[p1, 1] - X[p0, 1], X[p1, 2] - X[p0, 2])
        b = (X[p2, 0] - X[p0, 0], X[p2, 1] - X[p0, 1], X[p2, 2] - X[p0, 2])
        n = (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])
        twice = np.sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2])
        la = np.sqrt(a[0] * a[0] + a[1] * a[1] + a[2] * a[2])
        if not twice > 0.0:
            return e
        for i in range(3):
            R[0, i] = a[i] / la
            R[2, i] = n[i] / twice
        R[1, 0] = R[2, 1] * R[0, 2] - R[2, 2] * R[0, 1]  # e2 = e3 x e1
        R[1, 1] = R[2, 2] * R[0, 0] - R[2, 0] * R[0, 2]
        R[1, 2] = R[2, 0] * R[0, 1] - R[2, 1] * R[0, 0]
        for k in range(3):
            pk = cells[e, k]
            d = (X[pk, 0] - X[p0, 0], X[pk, 1] - X[p0, 1], X[pk, 2] - X[p0, 2])
            x[k] = R[0, 0] * d[0] + R[0, 1] * d[1] + R[0, 2] * d[2]
            y[k] = R[1, 0] * d[0] + R[1, 1] * d[1] + R[1, 2] * d[2]
        A = 0.5 * twice
        area[e] = A
        _membrane(x, y, A, A * t, Em, ab, beta, beta0, pat, W, km)
        _bending(x, y, A, Db, Hx, Hy, Bk, kb)
        K[:, :] = 0.0
        for i in range(9):
            for j in range(9):
                K[mem[i], mem[j]] = km[i, j]
                K[bend[i], bend[j]] = kb[i, j]
        for r in range(18):  # K T: each 3-column block times R
            for bb in range(6):
                for j in range(3):
                    KR[r, 3 * bb + j] = K[r, 3 * bb] * R[0, j] + K[r, 3 * bb + 1] * R[1, j] + K[r, 3 * bb + 2] * R[2, j]
        for aa in range(6):  # T^T (K T): each 3-row block times R^T
            for i in range(3):
                for c in range(18):
                    Kg[3 * aa + i, c] = R[0, i] * KR[3 * aa, c] + R[1, i] * KR[3 * aa + 1, c] + R[2, i] * KR[3 * aa + 2, c]
        for p in range(3):
            node = cells[e, p]
            lo, hi = indptr[node], indptr[node + 1]
            base, width = 36 * lo, 6 * (hi - lo)
            for q in range(3):
                s = _slot(indices, lo, hi, cells[e, q]) - lo
                for i in range(6):
                    row = base + i * width + 6 * s
                    for j in range(6):
                        data[row + j] += 0.5 * (Kg[6 * p + i, 6 * q + j] + Kg[6 * q + j, 6 * p + i])
    return -1


def shell_stiffness(X, cells, material, pattern, alpha_b: float, beta: np.ndarray):
    """The dof-level CSR data (6 dof per node) of the shell's global stiffness (OPT membrane, DKT
    bending), the triangles' areas and the first degenerate triangle (-1: none); None where numba
    does not run."""
    kernel = compiled("assembly.shell", _shell_kernel, _add_btdb, _membrane, _bending, _slot)
    if kernel is None:
        return None
    indptr, indices = pattern
    cells = np.ascontiguousarray(cells, dtype=np.int64)
    Em = np.ascontiguousarray(material.plane_stress(), dtype=float)
    data = np.zeros(36 * int(indptr[-1]))
    area = np.zeros(cells.shape[0])
    beta0 = max(0.5 * (1.0 - 4.0 * material.nu**2), 0.01)
    bad = kernel(np.ascontiguousarray(X, dtype=float), cells, Em, Em * (material.thickness**3 / 12.0),
                 float(material.thickness), float(alpha_b), np.ascontiguousarray(beta, dtype=float), float(beta0),
                 _PATTERNS, _MEMBRANE, _BENDING, indptr, indices, data, area)
    return data, area, int(bad)
