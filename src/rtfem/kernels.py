"""Compiled run-time kernels (numba), with the pure-Python definitions they are compiled from.

The haptic step of :class:`~rtfem.ModalSimulator` under one point load, and the read-back of one
node, are a few hundred flops; from numpy they cost microseconds of call overhead. Here they
are single compiled loops that release the GIL (``nogil``), evaluated in the same order as the
numpy path (C1 x + C2 v, then + G1 f, then + G0 f_old; no fused multiply-add), so both paths
give the same state to round-off. Without numba (``pip install numba``, part of
``rtfem[fast]``) ``HAVE_NUMBA`` is False and the simulators use numpy.

Signatures are given explicitly, so compilation happens once at import (cached on disk by
numba when the package folder is writable), never inside a force loop.
"""

from __future__ import annotations

import os

import numpy as np

__all__ = ["HAVE_NUMBA", "point_step", "point_displacement"]


def _point_step(coef, S, f_old, phi, node, fx, fy, fz, newmark):
    """One modal step under a force (fx, fy, fz) on ``node`` (node < 0: no load).

    coef (8, r): C1 (x, v), C2 (x, v), G1 (x, v), G0 (x, v) rows; S (2, r) state [x; v],
    updated in place; f_old (r,) the previous modal force (Newmark only); phi (n, 3, r).
    """
    r = S.shape[1]
    for j in range(r):
        f = 0.0
        if node >= 0:
            f = phi[node, 0, j] * fx + phi[node, 1, j] * fy + phi[node, 2, j] * fz
        x = S[0, j]
        v = S[1, j]
        xn = coef[0, j] * x + coef[2, j] * v
        vn = coef[1, j] * v + coef[3, j] * x
        xn = xn + coef[4, j] * f
        vn = vn + coef[5, j] * f
        if newmark:
            xn = xn + coef[6, j] * f_old[j]
            vn = vn + coef[7, j] * f_old[j]
            f_old[j] = f
        S[0, j] = xn
        S[1, j] = vn


def _point_displacement(phi, S, node, out):
    """out (3,) = phi[node] @ S[0]."""
    r = S.shape[1]
    a = 0.0
    b = 0.0
    c = 0.0
    for j in range(r):
        q = S[0, j]
        a += phi[node, 0, j] * q
        b += phi[node, 1, j] * q
        c += phi[node, 2, j] * q
    out[0] = a
    out[1] = b
    out[2] = c


HAVE_NUMBA = False
point_step = None
point_displacement = None
if os.environ.get("RTFEM_NUMBA", "1") != "0":
    try:
        import numba

        _opts = dict(cache=True, nogil=True, fastmath=False, error_model="numpy")
        point_step = numba.njit("void(f8[:, ::1], f8[:, ::1], f8[::1], f8[:, :, ::1], i8, f8, f8, f8, b1)",
                                **_opts)(_point_step)
        point_displacement = numba.njit("void(f8[:, :, ::1], f8[:, ::1], i8, f8[::1])", **_opts)(_point_displacement)
        HAVE_NUMBA = True
    except Exception:  # numba absent or unable to compile here: the numpy path is used
        HAVE_NUMBA = False
        point_step = point_displacement = None


def reference_step(coef: np.ndarray, S: np.ndarray, f_old: np.ndarray, phi: np.ndarray, node: int, force, newmark: bool):
    """The kernel's arithmetic in plain Python (for tests; slow)."""
    _point_step(coef, S, f_old, phi, int(node), float(force[0]), float(force[1]), float(force[2]), bool(newmark))
