"""Rotation maps shared by the corotational elements, the nonlinear solver and modal warping,
batched over any leading shape: cross-product matrices, exp (Rodrigues) and the integrated
rotation of modal warping."""

from __future__ import annotations

import numpy as np

__all__ = ["cross_matrices", "rotation", "integrated_rotation"]


def cross_matrices(w: np.ndarray) -> np.ndarray:
    """[w]x (..., 3, 3) for vectors w (..., 3): [w]x v = w x v."""
    w = np.asarray(w, float)
    W = np.zeros(w.shape[:-1] + (3, 3))
    W[..., 0, 1], W[..., 0, 2], W[..., 1, 2] = -w[..., 2], w[..., 1], -w[..., 0]
    W[..., 1, 0], W[..., 2, 0], W[..., 2, 1] = w[..., 2], -w[..., 1], w[..., 0]
    return W


def rotation(w: np.ndarray) -> np.ndarray:
    """exp([w]x) for rotation vectors (..., 3): Rodrigues' formula."""
    w = np.asarray(w, float)
    t = np.linalg.norm(w, axis=-1)
    big = t > 1e-4
    ts = np.where(big, t, 1.0)
    a = np.where(big, np.sin(ts) / ts, 1.0 - t * t / 6.0)
    b = np.where(big, (1.0 - np.cos(ts)) / ts**2, 0.5 - t * t / 24.0)
    W = cross_matrices(w)
    return np.eye(3) + a[..., None, None] * W + b[..., None, None] * (W @ W)


def integrated_rotation(w: np.ndarray) -> np.ndarray:
    """Rt(w) = int_0^1 exp(s [w]x) ds for rotation vectors (..., 3): the map of a linear
    displacement along a path whose rotation grows uniformly to w (Choi & Ko 2005, Eq. 9),
    I + (1 - cos t)/t^2 [w]x + (t - sin t)/t^3 [w]x^2 with t = |w|."""
    w = np.asarray(w, float)
    t = np.linalg.norm(w, axis=-1)
    big = t > 1e-3
    ts = np.where(big, t, 1.0)
    t2 = t * t
    b = np.where(big, (1.0 - np.cos(ts)) / ts**2, 0.5 - t2 / 24.0)
    c = np.where(big, (ts - np.sin(ts)) / ts**3, 1.0 / 6.0 - t2 / 120.0)
    W = cross_matrices(w)
    return np.eye(3) + b[..., None, None] * W + c[..., None, None] * (W @ W)
