"""Sparse assembly of element matrices through the node graph: the pattern is the nodes' (each pair of
nodes sharing an element: a tenth of the entries of the dof-level pattern of a tet4 mesh). Where numba
is installed (:mod:`rtfem.fe.assembly_kernels`) the pattern is built and the element blocks are added
straight into the dof-level CSR arrays in compiled loops, and the linear tets' stiffness is computed
in the same pass; otherwise the blocks are summed into the node pattern by ``np.bincount`` and the
block matrix becomes CSR with sorted indices. ``benchmarks/assembly_compiled.py`` measures both.

A process that has not loaded numba yet takes the numpy path for a mesh whose assembly the
compiled kernels would shorten by less than numba's start costs (importing it, its CPU target and
the cached kernels: 0.35-0.4 s of CPU on 2 cores, more than the liver shell's whole modal
analysis): a cold `rtfem modes` of a small or mid-size organ (issue 54, ``benchmarks/precompute_cold.py``).
Once numba is loaded (a warm process, the drivers' compiled steps) the compiled path is taken
at any size; ``RTFEM_ASSEMBLY=compiled`` or ``numpy`` chooses one always."""

from __future__ import annotations

import os
import sys

import numpy as np
import scipy.sparse as sp

from ..errors import MeshError, ModelError
from . import assembly_kernels as kernels
from . import shell_kernels
from .shell import _OPT_ALPHA_B, _OPT_BETA

__all__ = ["assemble_blocks", "assemble_solid", "assemble_shell", "compiled_assembly"]


#: CPU seconds that numba's start costs a process which has not loaded it (its import, its CPU target,
#: the cached kernels; measured 0.35-0.4 s on 2 cores): the compiled assembly must save more
JIT_START = 0.3
#: seconds the compiled assembly saves per element, by nodes per element (benchmarks/assembly_compiled.py,
#: numpy minus compiled: the liver shell 65.1 - 13.3 ms for 5,120 triangles, tet4 127.1 - 24.0 ms for
#: 23,067 tets, tet10 2,099 - 336 ms for 12,412 tets)
_SAVES_PER_ELEMENT = {3: 10e-6, 4: 4.5e-6, 10: 140e-6}


def compiled_assembly(cells: np.ndarray | None = None) -> bool:
    """Whether the compiled assembly runs here (for ``cells``): numba installed and ``RTFEM_ASSEMBLY``
    "compiled", or unset or empty where numba is already loaded in this process or the compiled
    kernels would save more than its start (:data:`JIT_START`) on ``cells`` (E, k) ("numpy" turns it
    off; another value is refused with a ModelError)."""
    how = os.environ.get("RTFEM_ASSEMBLY", "").strip().lower()
    if how not in ("", "compiled", "numpy"):
        raise ModelError(f"RTFEM_ASSEMBLY={how!r} names no assembly; choose 'compiled' or 'numpy' (or leave it unset)")
    if how == "numpy":
        return False
    if how == "" and cells is not None and "numba" not in sys.modules:
        E, k = np.shape(cells)[0], np.shape(cells)[-1]
        if _SAVES_PER_ELEMENT.get(k, 0.0) * E < JIT_START:
            return False  # a cold process: numba's start would cost more than it saves here
    return kernels.available()


def _checked(X, cells, n_nodes: int, k: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
    """X (n_nodes, 3) finite floats and cells (E, k) node indices within range, k one of ``k``: the
    compiled kernels index without bounds checks, so nothing else reaches them."""
    cells = np.asarray(cells)
    if cells.ndim != 2 or cells.shape[1] not in k or not np.issubdtype(cells.dtype, np.integer):
        raise MeshError(f"cells must be an integer array (E, {' or '.join(map(str, k))}), got {cells.dtype} {cells.shape}")
    if cells.size and (cells.min() < 0 or cells.max() >= n_nodes):
        raise MeshError(f"cells name nodes {cells.min()}..{cells.max()}, outside 0..{n_nodes - 1}")
    if X is not None:
        X = np.asarray(X, dtype=float)
        if X.shape != (n_nodes, 3) or not np.all(np.isfinite(X)):
            raise MeshError(f"the node coordinates must be ({n_nodes}, 3) finite numbers, got {X.shape}")
    return X, cells


def _csr(data: np.ndarray, pattern, n_nodes: int, d: int) -> sp.csr_matrix:
    indptr, indices = kernels.dof_arrays(*pattern, d)
    A = sp.csr_matrix((data, indices, indptr), shape=(d * n_nodes, d * n_nodes))
    A.has_sorted_indices = True
    return A


def assemble_solid(X: np.ndarray, cells: np.ndarray, dN: np.ndarray, w: np.ndarray, lam: float, mu: float,
                   n_nodes: int):
    """The linear isoparametric tets' stiffness (Lame lam, mu; quadrature gradients dN (q, k, 3) and
    weights w (q,)) and their volumes computed and assembled in one compiled pass, or None where
    the compiled assembly does not run (the caller takes the numpy path). Raises MeshError for a
    tet with a non-positive Jacobian at a point."""
    X, cells = _checked(X, cells, n_nodes, (4, 10))
    if not compiled_assembly(cells):
        return None
    pattern = kernels.node_pattern(cells, n_nodes)
    data, vol, bad = kernels.solid_stiffness(X, cells, dN, w, lam, mu, pattern)
    if bad >= 0:
        raise MeshError(f"element {bad} has a non-positive Jacobian ({vol[bad]:.3g}) at a quadrature point: an "
                        "inverted or flat tet, or a 10-node tet folded over itself; straighten its mid-edge nodes or re-mesh")
    return _csr(data, pattern, n_nodes, 3), vol


def assemble_shell(X: np.ndarray, cells: np.ndarray, material, n_nodes: int):
    """The flat shell's global stiffness (OPT membrane, DKT bending; 6 dof per node) and the
    triangles' areas computed and assembled in one compiled pass, or None where the compiled
    assembly does not run. Raises MeshError for a triangle of zero area."""
    X, cells = _checked(X, cells, n_nodes, (3,))
    if not compiled_assembly(cells):
        return None
    pattern = kernels.node_pattern(cells, n_nodes)
    done = shell_kernels.shell_stiffness(X, cells, material, pattern, _OPT_ALPHA_B, _OPT_BETA)
    if done is None:
        return None
    data, area, bad = done
    if bad >= 0:
        raise MeshError(f"triangle {bad} has zero area: remove it (rt.load_mesh repairs such faces) or re-mesh")
    return _csr(data, pattern, n_nodes, 6), area


def assemble_blocks(cells: np.ndarray, Ke: np.ndarray, n_nodes: int, d: int) -> sp.csr_matrix:
    """The global matrix (d n, d n) of element matrices ``Ke`` (E, k d, k d) on ``cells`` (E, k),
    dofs d per node numbered node-major (d a + i). Each element matrix is symmetrized first, so the
    result is exactly symmetric (entries (i, j) and (j, i) are sums of the same numbers in the same
    element order).

    Parameters
    ----------
    cells : (E, k) node indices of each element.
    Ke : (E, k d, k d) element matrices.
    n_nodes : the number of nodes.
    d : dofs per node.

    Returns
    -------
    scipy.sparse.csr_matrix
        With sorted indices (explicit zeros where a block holds some).
    """
    _, cells = _checked(None, cells, n_nodes, tuple(range(1, 11)))
    if np.shape(Ke) != (cells.shape[0], cells.shape[1] * d, cells.shape[1] * d):
        raise ModelError(f"element matrices must be ({cells.shape[0]}, {cells.shape[1] * d}, {cells.shape[1] * d}) for these "
                         f"cells and {d} dofs per node, got {np.shape(Ke)}")
    if compiled_assembly(cells):
        pattern = kernels.node_pattern(cells, n_nodes)
        return _csr(kernels.scatter_blocks(cells, Ke, pattern, d), pattern, n_nodes, d)
    E, k = cells.shape
    r = np.repeat(cells, k, axis=1).ravel()
    c = np.tile(cells, (1, k)).ravel()
    P = sp.coo_matrix((np.ones(r.size, np.int8), (r, c)), shape=(n_nodes, n_nodes)).tocsr()
    P.sum_duplicates()
    P.sort_indices()
    keys = np.repeat(np.arange(n_nodes, dtype=np.int64), np.diff(P.indptr)) * n_nodes + P.indices
    pos = np.searchsorted(keys, r.astype(np.int64) * n_nodes + c)
    sym = 0.5 * (Ke + np.swapaxes(Ke, 1, 2))
    blocks = sym.reshape(E, k, d, k, d).transpose(0, 1, 3, 2, 4).reshape(-1, d * d)  # rows in (r, c) order
    data = np.empty((keys.size, d * d))
    for q in range(d * d):
        data[:, q] = np.bincount(pos, blocks[:, q], minlength=keys.size)
    return sp.bsr_matrix((data.reshape(-1, d, d), P.indices, P.indptr), shape=(d * n_nodes, d * n_nodes)).tocsr()
