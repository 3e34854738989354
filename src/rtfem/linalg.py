"""Sparse factorizations with the best available backend.

CHOLMOD (through scikit-sparse, ``pip install rtfem[cholmod]``) when it is installed and the
matrix is symmetric positive definite, SuperLU (scipy) otherwise. A factorization is made
once and reused for every right-hand side.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from .errors import SolverError

__all__ = ["Factorization", "factorize", "available_backends"]

try:  # optional, faster supernodal Cholesky
    from sksparse.cholmod import cholesky as _cholmod_cholesky  # type: ignore

    _HAVE_CHOLMOD = True
except Exception:  # pragma: no cover - depends on the environment
    _HAVE_CHOLMOD = False


def available_backends() -> list[str]:
    """Backends that :func:`factorize` can use here, best first."""
    return (["cholmod"] if _HAVE_CHOLMOD else []) + ["superlu"]


class Factorization:
    """A sparse factorization of a square matrix: ``solve(b)`` for (n,) or (n, k) right-hand sides."""

    def __init__(self, A: sp.spmatrix, backend: str, solver) -> None:
        self.shape = A.shape
        self.nnz = A.nnz
        self.backend = backend
        self._solver = solver

    def solve(self, b: np.ndarray) -> np.ndarray:
        b = np.asarray(b, dtype=float)
        if b.shape[0] != self.shape[0]:
            raise SolverError(f"right-hand side has {b.shape[0]} rows, the matrix {self.shape[0]}")
        return self._solver(b)

    def __repr__(self) -> str:
        return f"Factorization({self.shape[0]}x{self.shape[1]}, nnz={self.nnz}, backend={self.backend!r})"


def factorize(A: sp.spmatrix, *, spd: bool = True, backend: str | None = None, what: str = "matrix") -> Factorization:
    """Factorize a sparse square matrix.

    Parameters
    ----------
    A : sparse matrix.
    spd : the matrix is symmetric positive definite (a stiffness with enough supports).
    backend : "cholmod" or "superlu"; default: the best available.
    what : a name for the matrix in error messages.

    Raises
    ------
    SolverError : the matrix is singular (to working precision) or not positive definite.
    """
    A = sp.csc_matrix(A, dtype=float)
    if A.shape[0] != A.shape[1]:
        raise SolverError(f"{what} is not square: {A.shape}")
    if backend is None:
        backend = "cholmod" if (spd and _HAVE_CHOLMOD) else "superlu"
    if backend == "cholmod":
        if not _HAVE_CHOLMOD:
            raise SolverError("CHOLMOD is not installed: pip install scikit-sparse (or rtfem[cholmod])")
        try:
            f = _cholmod_cholesky(A)
        except Exception as exc:  # CholmodNotPositiveDefiniteError and friends
            raise SolverError(f"{what} is singular or not positive definite ({exc})") from None
        return Factorization(A, "cholmod", f)
    if backend != "superlu":
        raise SolverError(f"unknown backend {backend!r}; choose from {available_backends()}")
    try:
        if spd:
            lu = spla.splu(A, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True})
        else:
            lu = spla.splu(A)
    except RuntimeError as exc:  # "Factor is exactly singular"
        raise SolverError(f"{what} is singular: {exc}") from None
    d = np.abs(lu.U.diagonal())
    if d.size and (not np.all(np.isfinite(d)) or d.min() <= 10 * np.finfo(float).eps * d.max()):
        raise SolverError(
            f"{what} is singular to working precision (smallest/largest pivot = {d.min() / d.max():.1e})"
        )
    return Factorization(A, "superlu", lu.solve)
