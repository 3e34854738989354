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

__all__ = ["Factorization", "factorize", "available_backends", "nested_dissection", "expand_node_order"]

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


def nested_dissection(adjacency: sp.csr_matrix, coords: np.ndarray, leaf: int = 64) -> np.ndarray:
    """Fill-reducing elimination order of mesh nodes by geometric nested dissection.

    The nodes are split at the median of the coordinate of largest extent; the nodes of one
    half that touch the other form the separator, ordered last; both halves are ordered
    recursively (George 1973). On a triangulated surface the separators hold O(sqrt(n))
    nodes, so the Cholesky fill is O(n log n): at 41,000 vertices SuperLU factorizes the
    stiffness 10 times faster in this order than in its own MMD order.
    """
    A = sp.csr_matrix(adjacency)
    X = np.asarray(coords, dtype=float)
    n = A.shape[0]
    mark = np.zeros(n, bool)
    parts: list[np.ndarray] = []
    # explicit stack of (nodes, is_separator): children are pushed so that the post-order
    # "first half, second half, separator" comes out of the stack
    stack: list[tuple[np.ndarray, bool]] = [(np.arange(n), False)]
    while stack:
        nodes, is_sep = stack.pop()
        if is_sep or nodes.size <= leaf:
            parts.append(nodes)
            continue
        P = X[nodes]
        axis = int(np.argmax(P.max(axis=0) - P.min(axis=0)))
        first = P[:, axis] <= np.median(P[:, axis])
        if first.all() or not first.any():
            parts.append(nodes)
            continue
        L, R = nodes[first], nodes[~first]
        mark[R] = True
        sub = A[L]
        touches = np.zeros(L.size, bool)
        np.logical_or.at(touches, np.repeat(np.arange(L.size), np.diff(sub.indptr)), mark[sub.indices])
        mark[R] = False
        stack += [(L[touches], True), (R, False), (L[~touches], False)]
    return np.concatenate(parts)


def expand_node_order(node_order: np.ndarray, dofs_per_node: int, kept: np.ndarray) -> np.ndarray:
    """Turn a node order into an order of the kept dofs (positions within ``kept``)."""
    n_dofs = int(node_order.size) * dofs_per_node
    pos = np.full(n_dofs, -1, dtype=np.int64)
    pos[kept] = np.arange(kept.size)
    p = pos[(dofs_per_node * node_order[:, None] + np.arange(dofs_per_node)).ravel()]
    return p[p >= 0]


def factorize(
    A: sp.spmatrix,
    *,
    spd: bool = True,
    backend: str | None = None,
    what: str = "matrix",
    order: np.ndarray | None = None,
    norm: float | None = None,
) -> Factorization:
    """Factorize a sparse square matrix.

    Parameters
    ----------
    A : sparse matrix.
    spd : the matrix is symmetric positive definite (a stiffness with enough supports).
    backend : "cholmod" or "superlu"; default: the best available.
    what : a name for the matrix in error messages.
    order : a fill-reducing symmetric permutation (e.g. from :func:`nested_dissection`) used
        by SuperLU instead of its own ordering; CHOLMOD orders by itself.
    norm : the 1-norm used in the singularity check (default ||A||_1); a penalized matrix
        passes the norm of the physical stiffness, whose conditioning is what matters.

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
    if order is not None:
        order = np.asarray(order)
        if order.shape != (A.shape[0],):
            raise SolverError(f"ordering has {order.size} entries, the matrix {A.shape[0]} rows")
        A = A[order][:, order].tocsc()
    try:
        if spd:
            spec = "NATURAL" if order is not None else "MMD_AT_PLUS_A"
            lu = spla.splu(A, permc_spec=spec, diag_pivot_thresh=0.0, options={"SymmetricMode": True})
        else:
            lu = spla.splu(A)
    except RuntimeError as exc:  # "Factor is exactly singular"
        raise SolverError(f"{what} is singular: {exc}") from None
    _check_not_singular(A, lu.solve, what, norm)
    if order is None:
        return Factorization(A, "superlu", lu.solve)

    def solve(b: np.ndarray) -> np.ndarray:
        x = np.empty_like(b)
        x[order] = lu.solve(b[order])
        return x

    return Factorization(A, "superlu", solve)


def _check_not_singular(A: sp.csc_matrix, solve, what: str, norm: float | None = None) -> None:
    """Refuse a numerically singular matrix: one solve with a random right-hand side.

    ||A||_1 ||x|| / ||b|| is a lower bound of the condition number; a (near) null vector of A
    shows up in x divided by a round-off pivot, which puts the estimate past 1/eps.
    """
    b = np.random.default_rng(12345).standard_normal(A.shape[0])
    x = solve(b)
    norm_a = abs(A).sum(axis=0).max() if norm is None else norm
    est = norm_a * np.linalg.norm(x) / np.linalg.norm(b)
    if not np.isfinite(est) or est > 1e-2 / np.finfo(float).eps:
        raise SolverError(f"{what} is singular to working precision (condition number at least {est:.1e})")
