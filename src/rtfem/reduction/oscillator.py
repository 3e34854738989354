"""Exact solutions of damped scalar oscillators x'' + a x' + lam x = f (Eq. 9, 16-18).

Shared by the modal simulator (exact discrete-time update of each mode) and SLDM (explicit
step response of each spectral component). With d = a/2, q = lam - d^2 and

    C(t) = cos(wd t),        S(t) = sin(wd t)/wd        (q > 0, wd = sqrt(q), under-damped)
    C(t) = 1,                S(t) = t                   (q = 0, critically damped)
    C(t) = cosh(mu t),       S(t) = sinh(mu t)/mu       (q < 0, mu = sqrt(-q), over-damped)

and c = e^{-d t} C, s = e^{-d t} S, the solution from (x0, v0) under a force f held constant is

    x(t) = (c + d s) x0 + s v0 + (1 - c - d s)/lam f
    v(t) = -lam s x0 + (c - d s) v0 + s f.

This is the paper's Eq. 18 with its typos corrected (the exponent is -a t/2, not -a/2, and
the sine term enters with a minus sign inside the bracket). Where lam t^2 is small (near-rigid
modes, lam = 0 included) the term (1 - c - d s)/lam cancels catastrophically, so there the
3x3 matrix exponential of [[0, 1, 0], [-lam, -a, 1], [0, 0, 0]] t is used: exact in every regime.
"""

from __future__ import annotations

import numpy as np

__all__ = ["transition", "step_response"]

_SMALL = 1e-3  # lam t^2 below this: matrix exponential instead of the closed form


def _cs(lam: np.ndarray, a: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """c = e^{-d t} C(t) and s = e^{-d t} S(t), overflow-free in every regime."""
    d = 0.5 * a
    q = lam - d * d
    c = np.empty(np.broadcast(lam, a, t).shape)
    s = np.empty_like(c)
    lam, d, q, t = np.broadcast_arrays(lam, d, q, t)
    e = np.exp(-d * t)
    under = q >= 0
    if under.any():
        wd = np.sqrt(q[under])
        tt = t[under]
        c[under] = e[under] * np.cos(wd * tt)
        s[under] = e[under] * tt * np.sinc(wd * tt / np.pi)
    over = ~under
    if over.any():
        mu = np.sqrt(-q[over])
        tt, dd = t[over], d[over]
        mt = mu * tt
        small = mt < 1e-3
        co = np.empty(mu.shape)
        so = np.empty(mu.shape)
        eo = e[over]
        # series for tiny mu t (sinh x / x = 1 + x^2/6 + ...)
        co[small] = eo[small] * np.cosh(mt[small])
        so[small] = eo[small] * tt[small] * (1 + mt[small] ** 2 / 6 + mt[small] ** 4 / 120)
        big = ~small
        slow = np.exp(-(dd[big] - mu[big]) * tt[big])  # e^{-(d - mu) t} <= 1
        fast = np.exp(-(dd[big] + mu[big]) * tt[big])
        co[big] = 0.5 * (slow + fast)
        so[big] = 0.5 * (slow - fast) / mu[big]
        c[over] = co
        s[over] = so
    return c, s


def _expm_blocks(lam: np.ndarray, a: np.ndarray, t: np.ndarray) -> np.ndarray:
    """exp([[0, 1, 0], [-lam, -a, 1], [0, 0, 0]] t) for many (lam, a, t) at once.

    The block is balanced first: A t = D B D^-1 with D = diag(t, 1, 1/t) and
    B = [[0, 1, 0], [-lam t^2, -a t, 1], [0, 0, 0]], whose entries are O(1) where this is
    used (lam t^2 < 1e-3); then exp(B) by scaling and squaring with a degree-16 Taylor
    polynomial, vectorized over the blocks (scipy's expm takes one small matrix at a time,
    far too slowly for SLDM's many (Ritz value, time) pairs).
    """
    lam, a, t = np.broadcast_arrays(lam, a, t)
    B = np.zeros(lam.shape + (3, 3))
    B[..., 0, 1] = 1.0
    B[..., 1, 0] = -lam * t * t
    B[..., 1, 1] = -a * t
    B[..., 1, 2] = 1.0
    norm = np.abs(B).sum(axis=-1).max(axis=-1)
    s = np.maximum(0, np.ceil(np.log2(norm / 0.5))).astype(int)
    B = B / (2.0 ** s)[..., None, None]
    E = np.broadcast_to(np.eye(3), B.shape).copy()
    term = E.copy()
    for k in range(1, 17):
        term = np.matmul(term, B) / k
        E += term
    for _ in range(int(s.max()) if s.size else 0):
        more = s > 0
        E[more] = np.matmul(E[more], E[more])
        s = s - 1
    # undo the balancing: E_ij * D_i / D_j, with exp(0) = I at t = 0
    with np.errstate(divide="ignore", invalid="ignore"):
        d = np.stack([t, np.ones_like(t), 1.0 / t], axis=-1)
        E = E * d[..., :, None] / d[..., None, :]
    E[t == 0] = np.eye(3)
    return E


def transition(lam, a, dt) -> tuple[np.ndarray, np.ndarray]:
    """Exact one-step update of oscillators with the force held over the step.

    Returns ``Phi`` (..., 2, 2) and ``Gamma`` (..., 2) such that
    [x, v](t + dt) = Phi @ [x, v](t) + Gamma * f.
    """
    lam, a, dt = np.broadcast_arrays(*(np.asarray(v, dtype=float) for v in (lam, a, dt)))
    c, s = _cs(lam, a, dt)
    d = 0.5 * a
    Phi = np.empty(lam.shape + (2, 2))
    Phi[..., 0, 0] = c + d * s
    Phi[..., 0, 1] = s
    Phi[..., 1, 0] = -lam * s
    Phi[..., 1, 1] = c - d * s
    Gamma = np.empty(lam.shape + (2,))
    with np.errstate(divide="ignore", invalid="ignore"):
        Gamma[..., 0] = (1.0 - c - d * s) / lam
    Gamma[..., 1] = s
    small = lam * dt * dt < _SMALL
    if small.any():
        E = _expm_blocks(lam[small], a[small], dt[small])
        Phi[small] = E[..., :2, :2]
        Gamma[small] = E[..., :2, 2]
    return Phi, Gamma


def step_response(lam, a, t) -> np.ndarray:
    """x(t) of x'' + a x' + lam x = H(t) from rest (unit step force): f(lam, t) of SLDM.

    ``lam``, ``a`` and ``t`` broadcast against each other (e.g. lam (m, 1), t (1, k)).
    """
    lam, a, t = np.broadcast_arrays(*(np.asarray(v, dtype=float) for v in (lam, a, t)))
    c, s = _cs(lam, a, t)
    with np.errstate(divide="ignore", invalid="ignore"):
        x = (1.0 - c - 0.5 * a * s) / lam
    small = lam * t * t < _SMALL
    if small.any():
        x[small] = _expm_blocks(lam[small], a[small], t[small])[..., 0, 2]
    return x
