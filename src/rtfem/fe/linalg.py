"""Sparse factorizations with the best available backend.

For a symmetric positive definite matrix (a restrained stiffness, Newmark's effective
stiffness): Intel MKL PARDISO's supernodal Cholesky (``pip install rtfem[fast]``, x86-64; the
``mkl`` wheel it pulls is about 300 MB) or CHOLMOD (scikit-sparse, which builds against
SuiteSparse) when installed; otherwise, and for other matrices, SuperLU from scipy, which
always works. ``RTFEM_BACKEND=superlu`` (or ``pardiso``, ``cholmod``) chooses one by name. A
factorization is made once and reused for every right-hand side.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import threading

import numpy as np
import scipy.sparse as sp

from ..errors import SolverError

__all__ = ["Factorization", "factorize", "available_backends", "default_backend", "nested_dissection",
           "expand_node_order", "BACKENDS", "gram", "subtract_product", "preload"]

try:  # optional, faster supernodal Cholesky
    from sksparse.cholmod import cholesky as _cholmod_cholesky  # type: ignore

    _HAVE_CHOLMOD = True
except Exception:  # pragma: no cover - depends on the environment
    _HAVE_CHOLMOD = False

BACKENDS = ("pardiso", "cholmod", "superlu")


def _mkl_pardiso():
    """MKL's ``pardiso`` entry point (its runtime library found by :func:`_load_mkl_rt`), or None."""
    if _PARDISO is False:
        with _INIT_LOCK:  # :func:`preload` may be loading it in another thread
            _find_pardiso()
    return _PARDISO


def _find_pardiso() -> None:
    global _PARDISO
    if _PARDISO is False:
        # MKL's OpenMP threads otherwise spin 200 ms after each solve, taking the cores from the
        # BLAS of the Lanczos iteration between solves (measured: ARPACK's share 2.3x slower)
        os.environ.setdefault("KMP_BLOCKTIME", "0")
        try:
            lib = _load_mkl_rt()
            fn = lib.pardiso
            try:
                setter = lib.MKL_Set_Num_Threads_Local
                setter.argtypes, setter.restype = [ctypes.c_int], ctypes.c_int
                _MKL_SET_LOCAL[0] = setter
            except AttributeError:  # an MKL without it: solves keep MKL's thread count
                pass
            try:
                gemm = lib.cblas_dgemm
                c_int, vp = ctypes.c_int, ctypes.c_void_p
                gemm.argtypes = [c_int] * 6 + [ctypes.c_double, vp, c_int, vp, c_int, ctypes.c_double, vp, c_int]
                gemm.restype = None
                _MKL_GEMM[0] = gemm
            except AttributeError:  # pragma: no cover - every MKL has cblas_dgemm
                pass
            i32, vp = ctypes.POINTER(ctypes.c_int32), ctypes.c_void_p
            # the arrays by address (an int): arr.ctypes.data_as() goes through ctypes.cast, which leaves a
            # reference cycle per call (on the full-order liver under a probe, 21,000 objects in 4.5 s for
            # the garbage collector; none now)
            fn.argtypes = [vp, i32, i32, i32, i32, i32, vp, vp, vp, vp, i32, vp, i32, vp, vp, i32]
            fn.restype = None
            _PARDISO = fn
        except Exception:  # not installed, or no mkl_rt on this platform
            _PARDISO = None


_PARDISO = False  # not looked for yet
_INIT_LOCK = threading.Lock()


def preload() -> threading.Thread | None:
    """Load MKL in a background thread, now: its runtime library, and the libraries and the OpenMP
    threads that its first PARDISO call loads and starts (a 3 x 3 factorization), so that a command
    that builds a model and then factorizes it finds them loaded. The thread runs in MKL, without
    the GIL, beside the imports, the file reading and the assembly of the main thread (issue 54: the
    first factorization of a fresh `rtfem modes` of the HRA kidney shell came 0.04-0.09 s sooner in
    A/B runs). None where another backend is chosen (RTFEM_BACKEND); errors are left to the real
    factorization to report."""
    if os.environ.get("RTFEM_BACKEND", "").strip().lower() not in ("", "pardiso"):
        return None

    def work() -> None:
        try:
            if _mkl_pardiso() is not None:
                _Pardiso(sp.identity(3, format="csr") * 2.0, "the preload's 3 x 3 identity")
        except Exception:  # pragma: no cover - reported by the factorization that needs it
            pass

    thread = threading.Thread(target=work, name="rtfem-mkl-preload", daemon=True)
    thread.start()
    return thread


def _load_mkl_rt() -> ctypes.CDLL:
    """MKL's runtime library: $PYPARDISO_MKL_RT, else the file the ``mkl`` wheel installed (its
    RECORD lists it: 1 ms), else the dynamic loader's. pypardiso's own constructor globs the whole
    environment recursively for it (0.63 s), and importing pypardiso builds one such solver: the
    first factorization of a process paid 1.06 s for the lookup alone. Raises OSError when none loads."""
    import importlib.metadata
    from ctypes.util import find_library

    candidates = [os.environ["PYPARDISO_MKL_RT"]] if os.environ.get("PYPARDISO_MKL_RT") else []
    try:
        files = importlib.metadata.files("mkl") or []
        candidates += sorted((str(f.locate()) for f in files if "mkl_rt" in f.name), key=len)
    except importlib.metadata.PackageNotFoundError:
        pass
    candidates += [name for name in (find_library("mkl_rt"), find_library("mkl_rt.1")) if name]
    for path in candidates:
        try:
            return ctypes.CDLL(path)
        except OSError:
            continue
    raise OSError("MKL's runtime library (mkl_rt) is not installed: pip install 'rtfem[fast]'")


def available_backends() -> list[str]:
    """The sparse direct solvers :func:`factorize` can use here.

    Returns
    -------
    list of str
        Best first, among "pardiso" (MKL's supernodal Cholesky: the ``fast`` extra), "cholmod"
        (scikit-sparse) and "superlu" (scipy, always): the first is the default for symmetric
        positive definite matrices (``RTFEM_BACKEND`` overrides it).

    Raises
    ------
    Nothing: a solver that cannot be loaded is left out.
    """
    return (["pardiso"] if _mkl_pardiso() is not None else []) + (["cholmod"] if _HAVE_CHOLMOD else []) + ["superlu"]


def default_backend() -> str:
    """The backend used for SPD matrices: ``RTFEM_BACKEND`` if set and available, else the best."""
    want = os.environ.get("RTFEM_BACKEND", "").strip().lower()
    have = available_backends()
    if want:
        if want not in BACKENDS:
            raise SolverError(f"RTFEM_BACKEND={want!r} names no backend; choose from {', '.join(BACKENDS)}")
        if want not in have:
            raise SolverError(f"RTFEM_BACKEND={want!r} is not installed here (available: {', '.join(have)})")
        return want
    return have[0]


class _Pardiso:
    """MKL PARDISO, real symmetric positive definite (mtype 2), on the upper triangle in CSR with
    zero-based indices (iparm[34] = 1), METIS nested-dissection ordering in its OpenMP version
    (iparm[1] = 3; the same order run to run here). The index arrays are converted once; a solve
    is one call (phase 33), on one MKL thread where the factor has fewer than 3 million nonzeros
    (measured on 2 cores: the embedded liver shell's 14 block solves 102 -> 64 ms, the 4-million
    tet4 liver's alike either way, the OpenHELP liver's 15 million 1.52 s on two threads against
    1.93 s on one). Memory is released when the object goes away (phase -1). Calls are
    serialized: one factor, one solve at a time."""

    def __init__(self, A: sp.csr_matrix, what: str, refactorable: bool = False) -> None:
        self._fn = _mkl_pardiso()
        # a handle to be factorized again (refactor) runs every phase on the same MKL threads: after a
        # solve on one thread, a numeric factorization read past PARDISO's buffers (a segmentation fault
        # on a 1,500-dof tet10 tangent, whatever the threads of that factorization); one thread below
        # 100,000 dofs (the solves' rule, and the other core stays free), MKL's threads above
        self._fixed_threads = (1 if A.shape[0] < 100_000 else 0) if refactorable else None
        d = A.diagonal()
        if not np.all(d > 0):  # PARDISO's SPD Cholesky needs every diagonal entry, positive
            i = int(np.flatnonzero(~(d > 0))[0])
            raise SolverError(f"{what} is singular or not positive definite (diagonal entry {i} is {d[i]:.3g})")
        self.n = A.shape[0]
        self._ia, self._ja, self._a = _upper_triangle(A)
        self._pt = np.zeros(64, dtype=np.int64)
        self._iparm = np.zeros(64, dtype=np.int32)
        self._iparm[[0, 1, 34]] = (1, 3, 1)  # own settings, METIS ordering (OpenMP: 0.8x the time), zero-based indices
        self._iparm[9] = 13  # pivot perturbation 1e-13 (unused for SPD, set as MKL's default for mtype 11)
        self._iparm[17] = -1  # report the factor's nonzeros
        self._lock = threading.Lock()
        self._alive = False
        with _mkl_threads(self._fixed_threads or 0):
            err = self._call(12, np.zeros(1), np.zeros(1), 1)
        if err:
            self._release()
            if err == -4:
                raise SolverError(f"{what} is singular or not positive definite (PARDISO: zero pivot)")
            raise SolverError(f"PARDISO could not factorize {what} (error {err})")
        self._alive = True
        self.factor_nnz = int(self._iparm[17])
        # a small factor's solve is faster on one thread: waking MKL's threads for each supernode
        # level costs more than they save (benchmarks/precompute.py, 2 cores)
        self._solve_threads = 1 if self.factor_nnz < _ONE_THREAD_SOLVE else 0
        if self._fixed_threads is not None:
            self._solve_threads = self._fixed_threads

    def refactor(self, A: sp.spmatrix) -> bool:
        """Factorize new values of the same pattern again, numerically only (phase 22: METIS's order
        and the symbolic factor are kept). False, nothing changed, where the pattern differs or the
        handle was not made refactorable."""
        if self._fixed_threads is None:
            return False
        ia, ja, a = _upper_triangle(A)
        if ia.shape != self._ia.shape or ja.shape != self._ja.shape or not np.array_equal(ja, self._ja) \
                or not np.array_equal(ia, self._ia):
            return False
        with self._lock, _mkl_threads(self._fixed_threads):
            self._a = a
            err = self._call(22, np.zeros(1), np.zeros(1), 1)
        if err:
            raise SolverError(f"PARDISO could not factorize the matrix again (error {err}: not positive definite)")
        return True

    def _call(self, phase: int, b: np.ndarray, x: np.ndarray, nrhs: int) -> int:
        err = ctypes.c_int32(0)
        one = ctypes.c_int32(1)
        self._fn(self._pt.ctypes.data, ctypes.byref(one), ctypes.byref(one),
                 ctypes.byref(ctypes.c_int32(2)), ctypes.byref(ctypes.c_int32(phase)), ctypes.byref(ctypes.c_int32(self.n)),
                 self._a.ctypes.data, self._ia.ctypes.data, self._ja.ctypes.data, None, ctypes.byref(ctypes.c_int32(nrhs)),
                 self._iparm.ctypes.data, ctypes.byref(ctypes.c_int32(0)), b.ctypes.data, x.ctypes.data, ctypes.byref(err))
        return int(err.value)

    def solve(self, b: np.ndarray) -> np.ndarray:
        b = np.asarray(b, dtype=np.float64)
        nrhs = 1 if b.ndim == 1 else b.shape[1]
        bf = np.asfortranarray(b)
        x = np.zeros_like(bf, order="F")
        with self._lock, _mkl_threads(self._solve_threads):
            err = self._call(33, bf, x, nrhs)
        if err:
            raise SolverError(f"PARDISO solve failed (error {err})")
        return x if bf is b else np.ascontiguousarray(x)  # a column-major block comes back column-major, uncopied

    def _release(self) -> None:
        self._call(-1, np.zeros(1), np.zeros(1), 1)

    def __del__(self) -> None:
        if getattr(self, "_alive", False):
            try:
                self._release()
            except Exception:  # interpreter shutting down
                pass


_ONE_THREAD_SOLVE = 3_000_000  # factor nonzeros below which a solve runs on one thread (see _Pardiso)


@contextlib.contextmanager
def _mkl_threads(n: int):
    """MKL's threads for this thread, n (0: leave them as they are)."""
    setter = _MKL_SET_LOCAL[0] if n else None
    if setter is None:
        yield
        return
    previous = setter(n)
    try:
        yield
    finally:
        setter(previous)


_MKL_SET_LOCAL: list = [None]
_MKL_GEMM: list = [None]
_THREADED_GEMM = 1_000_000  # entries of A below which the products run on one MKL thread (waking more costs more)


def _column_major(A: np.ndarray) -> int:
    """The leading dimension of a float64 matrix stored column by column (unit row stride), else 0."""
    if A.ndim != 2 or A.dtype != np.float64 or A.strides[0] != 8 or A.strides[1] < 8 * A.shape[0]:
        return 0
    return A.strides[1] // 8 if A.strides[1] % 8 == 0 else 0


def gram(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """A^T B (column-major) for tall column-major A (n, m) and B (n, k): MKL's dgemm where PARDISO's
    MKL is loaded, else numpy. The Lanczos basis's products are tall and memory-bound: MKL reads
    the basis 1.6x as fast as OpenBLAS on one thread and 3x on two (46,000 x 160 times 8 columns,
    2 cores); below a million entries of A one MKL thread is used (waking the others costs more)."""
    if np.ndim(A) != 2 or np.ndim(B) != 2 or A.shape[0] != B.shape[0]:
        raise SolverError(f"gram needs A (n, m) and B (n, k) with the same rows, got {np.shape(A)} and {np.shape(B)}")
    gemm, lda, ldb = _MKL_GEMM[0], _column_major(A), _column_major(B)
    if gemm is None or not lda or not ldb or 0 in A.shape or B.shape[1] == 0:
        return np.asfortranarray(A.T @ B)
    m, k = A.shape[1], B.shape[1]
    C = np.empty((m, k), order="F")
    with _mkl_threads(1 if A.size < _THREADED_GEMM else 0):
        gemm(102, 112, 111, m, k, A.shape[0], 1.0, A.ctypes.data, lda, B.ctypes.data, ldb, 0.0, C.ctypes.data, m)
    return C


def subtract_product(C: np.ndarray, A: np.ndarray, B: np.ndarray) -> None:
    """C -= A B in place, for column-major C (n, k) and A (n, m): MKL's dgemm where loaded, else numpy."""
    if np.ndim(A) != 2 or np.ndim(B) != 2 or np.ndim(C) != 2 or A.shape[1] != B.shape[0] or \
            (A.shape[0], B.shape[1]) != C.shape:
        raise SolverError(f"subtract_product needs C (n, k), A (n, m), B (m, k), got {np.shape(C)}, {np.shape(A)}, "
                          f"{np.shape(B)}")
    gemm, lda, ldc = _MKL_GEMM[0], _column_major(A), _column_major(C)
    if gemm is None or not lda or not ldc or 0 in A.shape or C.shape[1] == 0:
        C -= A @ B
        return
    B = np.asfortranarray(B, dtype=np.float64)
    n, m, k = A.shape[0], A.shape[1], C.shape[1]
    with _mkl_threads(1 if A.size < _THREADED_GEMM else 0):
        gemm(102, 111, 111, n, k, m, -1.0, A.ctypes.data, lda, B.ctypes.data, m, 1.0, C.ctypes.data, ldc)


def _upper_triangle(A: sp.spmatrix) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(indptr, indices, data) in int32/int32/float64 of the upper triangle of a symmetric matrix,
    sorted CSR. A CSC matrix is read as the CSR of its transpose, the same matrix: no conversion."""
    S = A.T if sp.isspmatrix_csc(A) else sp.csr_matrix(A)
    if not S.has_sorted_indices:
        S = S.copy()
        S.sort_indices()
    n = S.shape[0]
    rows = np.repeat(np.arange(n, dtype=S.indices.dtype), np.diff(S.indptr))
    keep = S.indices >= rows
    indptr = np.zeros(n + 1, np.int32)
    np.cumsum(np.bincount(rows[keep], minlength=n), out=indptr[1:])
    return indptr, S.indices[keep].astype(np.int32), np.ascontiguousarray(S.data[keep], dtype=np.float64)


class Factorization:
    """A sparse factorization of a square matrix: ``solve(b)`` for (n,) or (n, k) right-hand sides.
    Solves from several threads (a contact's background preparation beside the force loop) take
    turns: no backend promises that two solves on one factor may overlap."""

    def __init__(self, A: sp.spmatrix, backend: str, solver, refactor=None) -> None:
        self.shape = A.shape
        self.nnz = A.nnz
        self.backend = backend
        self._solver = solver
        self._refactor = refactor
        self._lock = threading.Lock()

    def refactor(self, A: sp.spmatrix) -> bool:
        """Factorize ``A``, new values on the pattern this was made of, in place (PARDISO: numerically
        only, its ordering and symbolic factor kept; a lagged tangent's refresh). False, nothing
        changed, where the backend cannot or the pattern differs: make a new factorization then."""
        if self._refactor is None or A.shape != self.shape:
            return False
        with self._lock:
            return bool(self._refactor(A))

    def solve(self, b: np.ndarray) -> np.ndarray:
        b = np.asarray(b, dtype=float)
        if b.shape[0] != self.shape[0]:
            raise SolverError(f"right-hand side has {b.shape[0]} rows, the matrix {self.shape[0]}")
        with self._lock:
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
    refactorable: bool = False,
) -> Factorization:
    """Factorize a sparse square matrix.

    Parameters
    ----------
    A : sparse matrix.
    spd : the matrix is symmetric positive definite (a stiffness with enough supports).
    backend : "pardiso", "cholmod" or "superlu"; default: :func:`default_backend` for SPD
        matrices, SuperLU otherwise.
    what : a name for the matrix in error messages.
    order : a fill-reducing symmetric permutation (e.g. from :func:`nested_dissection`), or a
        callable returning one, used by SuperLU instead of its own ordering; PARDISO (METIS)
        and CHOLMOD order by themselves (the callable is then never called).
    norm : the 1-norm used in the singularity check (default ||A||_1); a penalized matrix
        passes the norm of the physical stiffness, whose conditioning is what matters.
    refactorable : to be factorized again on the same pattern (:meth:`Factorization.refactor`).

    Raises
    ------
    SolverError : the matrix is singular (to working precision) or not positive definite.
    """
    if A.shape[0] != A.shape[1]:
        raise SolverError(f"{what} is not square: {A.shape}")
    if backend is None:
        backend = default_backend() if spd else "superlu"
    if backend == "pardiso":  # the upper triangle, as CSR, of the matrix in the format it came in
        A = A if (sp.isspmatrix_csr(A) or sp.isspmatrix_csc(A)) and A.dtype == float else sp.csr_matrix(A, dtype=float)
        if _mkl_pardiso() is None:
            raise SolverError("PARDISO is not installed: pip install pypardiso (or rtfem[fast]; x86-64 only)")
        if not spd:
            raise SolverError("the PARDISO backend here is the SPD Cholesky: use backend='superlu' for other matrices")
        f = _Pardiso(A, what, refactorable)
        _check_not_singular(A, f.solve, what, norm)
        return Factorization(A, "pardiso", f.solve, f.refactor)
    A = sp.csc_matrix(A, dtype=float)
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
    if callable(order):  # computed only when SuperLU needs it
        order = order()
    if order is not None:
        order = np.asarray(order)
        if order.shape != (A.shape[0],):
            raise SolverError(f"ordering has {order.size} entries, the matrix {A.shape[0]} rows")
        A = A[order][:, order].tocsc()
    lu = _splu(A, spd, order is not None, what)
    _check_not_singular(A, lu.solve, what, norm)
    if order is None:
        return Factorization(A, "superlu", lu.solve)

    def solve(b: np.ndarray) -> np.ndarray:
        x = np.empty_like(b)
        x[order] = lu.solve(b[order])
        return x

    return Factorization(A, "superlu", solve)


def _splu(A: sp.csc_matrix, spd: bool, ordered: bool, what: str):
    """SuperLU's factors of A (symmetric mode for an SPD matrix, in the given order when ``ordered``);
    scipy.sparse.linalg is imported here: 0.1 s of a fresh process that the PARDISO path need not pay."""
    import scipy.sparse.linalg as spla

    try:
        if spd:
            return spla.splu(A, permc_spec="NATURAL" if ordered else "MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                             options={"SymmetricMode": True})
        return spla.splu(A)
    except RuntimeError as exc:  # "Factor is exactly singular"
        raise SolverError(f"{what} is singular: {exc}") from None


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
