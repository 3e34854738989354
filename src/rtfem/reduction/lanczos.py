"""Symmetric Lanczos with full reorthogonalization (paper section 4, Eq. 19).

Builds an orthonormal Krylov basis Q_m = [q_1 .. q_m] of a symmetric operator A from a
start vector b, and the tridiagonal T_m = Q_m^T A Q_m (alpha on the diagonal, beta off it).
Two ways of keeping Q_m orthogonal to working precision:

* ``"cgs2"`` (default): classical Gram-Schmidt applied twice against all previous vectors
  ("twice is enough", Giraud, Langou & Rozloznik 2005);
* ``"householder"``: the paper's choice: the basis is kept as a product of Householder
  reflections, q_j = P_1 P_2 ... P_j e_j (Golub & Van Loan, sec. 9.2; Walker 1988), which
  is orthogonal by construction. About twice the work of CGS2.

A breakdown (beta_j ~ 0: an invariant subspace was found, so the Krylov answer is exact)
ends the iteration early instead of dividing by zero.
"""

from __future__ import annotations

import time
from typing import Callable

import numpy as np
import scipy.linalg as sla

from ..errors import SolverError
from ..fe.linalg import gram, subtract_product

__all__ = ["Lanczos", "REORTHOGONALIZATIONS"]

REORTHOGONALIZATIONS = ("cgs2", "householder")


class Lanczos:
    """Incremental Lanczos process: call :meth:`extend` to grow the basis.

    Parameters
    ----------
    matvec : y = A x for the symmetric operator A (n x n).
    b : start vector (n,); q_1 = b / |b|.
    reorth : "cgs2" or "householder".
    capacity : initial number of basis vectors to allocate (grows as needed).
    """

    def __init__(self, matvec: Callable[[np.ndarray], np.ndarray], b: np.ndarray, reorth: str = "cgs2", capacity: int = 64):
        if reorth not in REORTHOGONALIZATIONS:
            raise SolverError(f"reorth={reorth!r}; choose one of {REORTHOGONALIZATIONS}")
        b = np.asarray(b, dtype=float)
        self.beta0 = float(np.linalg.norm(b))
        if not np.isfinite(self.beta0):
            raise SolverError("the start vector contains NaN or infinite values")
        if self.beta0 == 0.0:
            raise SolverError("the start vector is zero: there is nothing to respond to")
        self.n = b.size
        self.matvec = matvec
        self.reorth = reorth
        self.alpha: list[float] = []
        self.beta: list[float] = []  # beta[j] couples q_{j+1} and q_{j+2}
        self.breakdown = False
        cap = max(2, min(capacity, self.n + 1))
        self._Q = np.zeros((cap, self.n))  # rows are the Lanczos vectors
        self._m = 0
        if reorth == "householder":
            # reflectors P_j = I - 2 v_j v_j^T / |v_j|^2, v_j zero above index j
            self._V = np.zeros((cap, self.n))
            v = b.copy()
            self._first_reflector(v)
        else:
            self._Q[0] = b / self.beta0
        self._m = 1

    # ---------------------------------------------------------------- storage
    def _grow(self) -> None:
        cap = self._Q.shape[0]
        new = min(2 * cap, self.n + 1)
        if new <= cap:
            return
        Q = np.zeros((new, self.n))
        Q[:cap] = self._Q
        self._Q = Q
        if self.reorth == "householder":
            V = np.zeros((new, self.n))
            V[:cap] = self._V
            self._V = V

    @property
    def m(self) -> int:
        """Dimension of T_m (number of completed Lanczos steps)."""
        return len(self.alpha)

    @property
    def Q(self) -> np.ndarray:
        """The basis as an (n, m) array (a copy-free transpose view)."""
        return self._Q[: self.m].T

    def tridiagonal(self) -> tuple[np.ndarray, np.ndarray]:
        """(alpha, beta) of T_m: diagonal (m,) and off-diagonal (m - 1,)."""
        k = len(self.alpha)
        return np.array(self.alpha), np.array(self.beta[: k - 1])

    @property
    def last_beta(self) -> float:
        """beta_m: the coupling of q_m to the next vector q_{m+1} (0 after a breakdown)."""
        return self.beta[-1] if self.beta else 0.0

    def next_vector(self) -> np.ndarray | None:
        """q_{m+1} (None after a breakdown): the direction of the Lanczos residual."""
        return None if self.breakdown or not self.alpha else self._Q[self.m]

    # ---------------------------------------------------------------- Householder pieces
    def _first_reflector(self, b: np.ndarray) -> None:
        # P_1 b = -sign(b_0) |b| e_1; q_1 = P_1 e_1 = b/|b| up to sign: choose the sign so q_1 = b/|b|
        v = b.copy()
        s = 1.0 if v[0] >= 0 else -1.0
        v[0] += s * self.beta0
        self._V[0] = v
        q = self._apply_reflectors(np.eye(1, self.n, 0).ravel(), 1)
        # P_1 e_1 = -s b/|b|: flip so that q_1 = +b/|b|
        self._sign = [-s]
        self._Q[0] = q * -s

    def _reflect(self, x: np.ndarray, j: int) -> None:
        v = self._V[j]
        vv = v[j:] @ v[j:]
        if vv > 0:
            x[j:] -= (2.0 * (v[j:] @ x[j:]) / vv) * v[j:]

    def _apply_reflectors(self, x: np.ndarray, k: int, reverse: bool = False) -> np.ndarray:
        """P_1 P_2 ... P_k x (or P_k ... P_1 x with reverse=True), in place on a copy."""
        x = x.copy()
        order = range(k) if reverse else range(k - 1, -1, -1)
        for j in order:
            self._reflect(x, j)
        return x

    # ---------------------------------------------------------------- iteration
    def extend(self, steps: int = 1) -> int:
        """Run up to ``steps`` more Lanczos steps; returns the number actually taken."""
        taken = 0
        while taken < steps and not self.breakdown and len(self.alpha) < self.n:
            j = len(self.alpha)  # computing alpha_j, beta_j from q_j (0-based)
            q = self._Q[j]
            w = np.asarray(self.matvec(q), dtype=float).ravel()
            if w.shape != (self.n,) or not np.all(np.isfinite(w)):
                raise SolverError("the operator returned NaN/inf or a wrong shape during Lanczos")
            if self.reorth == "cgs2":
                a = float(q @ w)
                Q = self._Q[: j + 1]
                for _ in range(2):
                    w -= Q.T @ (Q @ w)
                beta = float(np.linalg.norm(w))
            else:
                # z = P_{j+1} ... P_1 w: its first j+1 entries are the coefficients on q_1..q_{j+1}
                z = self._apply_reflectors(w, j + 1, reverse=True)
                a = float(z[j] * self._sign[j])
                tail = z[j + 1 :]
                beta = float(np.linalg.norm(tail))
            self.alpha.append(a)
            scale = max(abs(a), self.alpha_max(), 1e-300)
            if beta <= 1e-12 * scale or j + 1 >= self.n:
                # lucky breakdown: span(Q_j) is invariant, the projection is exact
                self.beta.append(0.0)
                self.breakdown = True
                taken += 1
                break
            self.beta.append(beta)
            if self._m >= self._Q.shape[0]:
                self._grow()
            if self.reorth == "cgs2":
                self._Q[j + 1] = w / beta
            else:
                v = np.zeros(self.n)
                v[j + 1 :] = tail
                s = 1.0 if tail[0] >= 0 else -1.0
                v[j + 1] += s * beta
                self._V[j + 1] = v
                e = np.zeros(self.n)
                e[j + 1] = 1.0
                qn = self._apply_reflectors(e, j + 2)
                # P_{j+1} maps tail to -s beta e_{j+1}; choose q_{j+1} so that beta_j > 0
                self._sign.append(-s)
                self._Q[j + 1] = -s * qn
            self._m = j + 2
            taken += 1
        return taken

    def alpha_max(self) -> float:
        return max((abs(x) for x in self.alpha), default=0.0)

    def orthogonality_loss(self) -> float:
        """max |Q^T Q - I| of the current basis (a diagnostic, O(n m^2))."""
        Q = self._Q[: self.m]
        return float(np.abs(Q @ Q.T - np.eye(Q.shape[0])).max())


_NEGLIGIBLE = 1e-12


class BlockLanczosFailed(SolverError):
    """The block iteration stopped short (a rank-deficient block or the Krylov dimension cap);
    the caller falls back to ARPACK."""


def block_eigs(
    apply: Callable[[np.ndarray], np.ndarray],
    n: int,
    k: int,
    *,
    block: int = 8,
    tol: float = 1e-10,
    max_dim: int | None = None,
    seed: int = 0,
    report: Callable[[int, int], None] | None = None,
    check_every: int | None = None,
    vectors: bool = True,
) -> tuple[np.ndarray, np.ndarray | None, dict]:
    """The k largest eigenpairs of a symmetric positive semi-definite operator C (n x n) by
    block Lanczos with full reorthogonalization and no restart.

    ``apply(Y)`` returns C Y for a block Y (n, b): one call solves b right-hand sides at once,
    which is what makes the block method pay with a supernodal factorization (a PARDISO solve
    of 8 right-hand sides costs about 3 of one). Each new block Z = C Q_j first loses its
    components on Q_j and Q_{j-1} (the block three-term recurrence), then is orthogonalized once
    against the whole basis (classical Gram-Schmidt, BLAS-3; skipped where all its coefficients
    are below 1e-12 of the block's norm), a second time only for a block whose norm that pass cut
    below half (the Daniel-Gragg-Kaufman-Stewart test): on a large mesh the reads of the basis
    (column-major), not the arithmetic, are the cost. T = Q^T C Q is built block column by block
    column. Every ``check_every`` blocks the Ritz pairs of T are formed (None: after each block while that
    costs under a quarter of a block solve, else every second one); the iteration stops when
    each of the k largest has |C y - theta y| <= tol * theta, read off the last block row as
    |R_{j+1} S_j| (Golub & Underwood 1977; Golub & Van Loan sec. 10.3.6).

    Returns theta (k,) descending, Y (n, k) orthonormal Ritz vectors (None with ``vectors=False``,
    for a caller who needs only the image below) and a dict of counts and
    seconds (``solve_seconds``, ``other_seconds``, ``block_solves``, ``krylov_dim``,
    ``reorthogonalized`` / ``skipped``: the blocks that needed the second pass / no subtraction),
    ``coefficients`` S (dim, k) with Y = Q S, so that a caller who kept something per block (rows
    of the solves that the operator drops) can combine it the same way, and ``image`` = C Y from
    the Lanczos relation C Q = Q T + Q_{m+1} R_m E_m^T (no further application of C).
    Raises :class:`BlockLanczosFailed` when a block loses rank or the basis reaches max_dim.
    """
    b = int(block)
    max_dim = int(max_dim if max_dim is not None else min(n, max(4 * k, k + 256)))
    max_dim = max(b, min(max_dim, n) // b * b)
    if k + b > max_dim:
        raise BlockLanczosFailed(f"{k} eigenpairs need a basis of more than {max_dim} vectors")
    t_start = time.perf_counter()
    solve_seconds = 0.0
    Q = np.empty((n, max_dim), order="F")
    T = np.zeros((max_dim, max_dim))
    Q[:, :b] = np.linalg.qr(np.random.default_rng(seed).standard_normal((n, b)))[0]
    j, blocks, second, skipped, ritz_cost = 0, 0, 0, 0, 0.0  # ritz_cost: seconds the last Ritz check took
    R_prev = None
    while True:
        t0 = time.perf_counter()
        Z = np.array(apply(Q[:, j:j + b]), dtype=float, order="F")
        solve_seconds += (block_cost := time.perf_counter() - t0)
        blocks += 1
        if Z.shape != (n, b) or not np.all(np.isfinite(Z)):
            raise SolverError("the operator returned NaN/inf or a wrong shape during block Lanczos")
        dim = j + b
        P = Q[:, :dim]
        passes = _orthogonalize(Q, T, Z, j, b, R_prev)
        second += passes == 2
        skipped += passes == 0
        V, R = sla.qr(Z, mode="economic", overwrite_a=True, check_finite=False)
        if report is not None:
            report(dim, max(dim + b, int(3.4 * k)))
        due = blocks % (check_every or 2) == 0 or (check_every is None and ritz_cost < 0.25 * block_cost)
        if dim >= k + b and (due or dim + b > max_dim):
            ritz, ritz_cost = _timed(_ritz_pairs, T, R, j, dim, k, tol)
            if ritz is not None:
                info = {"solve_seconds": solve_seconds, "block_solves": blocks, "krylov_dim": dim, "block": b,
                        "reorthogonalized": second, "skipped": skipped}
                return _result(P, V, ritz, vectors, info, t_start)
        if dim + b > max_dim:
            raise BlockLanczosFailed(f"{k} eigenpairs did not converge within a basis of {max_dim} vectors")
        if np.abs(np.diag(R)).min() <= 1e-10 * np.abs(T[:dim, :dim]).max():
            raise BlockLanczosFailed("the Krylov block lost rank (an invariant subspace was found)")
        Q[:, dim:dim + b] = V
        T[dim:dim + b, j:dim] = R
        R_prev = R
        j = dim


def _timed(fn, *args):
    """(fn(*args), the seconds it took)."""
    t0 = time.perf_counter()
    out = fn(*args)
    return out, time.perf_counter() - t0


def _result(P: np.ndarray, V: np.ndarray, ritz, vectors: bool, info: dict, t_start: float):
    """block_eigs's answer from converged Ritz pairs: theta, Y = P S (or None), and info with S,
    C Y = P S theta + V R S_j (the Lanczos relation: no further application of C) and the times."""
    theta, S, RS, worst = ritz
    image = P @ (S * theta)
    image += V @ RS
    info.update(coefficients=S, image=image, max_residual=worst,
                other_seconds=time.perf_counter() - t_start - info["solve_seconds"])
    return theta, (P @ S if vectors else None), info


def _orthogonalize(Q: np.ndarray, T: np.ndarray, Z: np.ndarray, j: int, b: int, R_prev: np.ndarray | None) -> int:
    """Z = C Q_j (n, b), in place: without its components on Q_j and Q_{j-1} (the block three-term
    recurrence), then orthogonalized against the whole basis Q[:, :j+b] once (classical
    Gram-Schmidt), and a second time when that pass cut a column below half its norm; the
    coefficients go into T's block column. Returns the subtractions made against the whole basis:
    0 (the coefficients were negligible), 1 or 2 (the second pass)."""
    dim = j + b
    P = Q[:, :dim]
    Qj = Q[:, j:dim]
    A = gram(Qj, Z)
    subtract_product(Z, Qj, A)
    T[j:dim, j:dim] = A
    if R_prev is not None:
        subtract_product(Z, Q[:, j - b:j], R_prev.T)
        T[j - b:j, j:dim] = R_prev.T
    before = np.linalg.norm(Z, axis=0)
    H = gram(P, Z)
    if np.abs(H).max(initial=0.0) <= _NEGLIGIBLE * before.min(initial=np.inf):
        return 0  # Z is orthogonal to the basis to working precision: subtracting P H changes nothing
    subtract_product(Z, P, H)
    second = bool(np.any(np.linalg.norm(Z, axis=0) < 0.5 * before))
    if second:
        H2 = gram(P, Z)
        subtract_product(Z, P, H2)
        H += H2
    T[:dim, j:dim] += H
    return 2 if second else 1


def _ritz_pairs(T: np.ndarray, R: np.ndarray, j: int, dim: int, k: int, tol: float):
    """The k largest Ritz pairs of T[:dim, :dim] when each has |C y - theta y| <= tol theta (read off
    the last block row, |R S_j|), else None: (theta descending, S, R S_j, the largest relative residual)."""
    Ts = 0.5 * (T[:dim, :dim] + T[:dim, :dim].T)
    theta, S = sla.eigh(Ts, subset_by_index=[dim - k, dim - 1])
    RS = R @ S[j:dim]
    residual = np.linalg.norm(RS, axis=0)
    if not np.all(residual <= tol * np.abs(theta)):
        return None
    order = np.argsort(theta)[::-1]
    return theta[order], S[:, order], RS[:, order], float((residual / np.abs(theta)).max())
