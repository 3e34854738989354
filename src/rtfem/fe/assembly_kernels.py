"""Compiled assembly (numba): the node pattern of a mesh, element blocks scattered straight into the
dof-level CSR arrays, and the linear tet's stiffness computed and scattered in one pass, with no
element-matrix array in between. :mod:`rtfem.fe.assembly` calls these where numba is installed and
keeps its numpy path otherwise; the two agree to round-off (tests/test_assembly_kernels.py).

Layout. The node pattern is a CSR (indptr p, sorted indices c) of the pairs of nodes that share an
element. With d dofs per node numbered node-major (d a + i), row d a + i of the dof-level matrix
holds d deg(a) entries, node by node of row a and dof by dof within a node: the entry of (a, i; b, j),
b the s-th neighbour of a, sits at d d p[a] + i d deg(a) + d s + j, so the dof-level indices are
sorted and the arrays are filled in place, without a COO stage, duplicates to sum or a sort.
"""

from __future__ import annotations

import numpy as np

from .jit import compiled

__all__ = ["node_pattern", "scatter_blocks", "tet4_stiffness"]


def _pattern_kernel(cells, n_nodes, indptr, indices, counting):
    """Fill indptr (counting) or indices (not counting) of the node pattern of ``cells``."""
    E, k = cells.shape
    first = np.zeros(n_nodes + 1, np.int64)  # node -> elements, by counting sort
    for e in range(E):
        for p in range(k):
            first[cells[e, p] + 1] += 1
    for a in range(n_nodes):
        first[a + 1] += first[a]
    fill = first[:-1].copy()
    elems = np.empty(E * k, np.int64)
    for e in range(E):
        for p in range(k):
            a = cells[e, p]
            elems[fill[a]] = e
            fill[a] += 1
    mark = np.full(n_nodes, -1, np.int64)
    for a in range(n_nodes):
        start = indptr[a]
        m = 0
        for t in range(first[a], first[a + 1]):
            e = elems[t]
            for q in range(k):
                b = cells[e, q]
                if mark[b] != a:
                    mark[b] = a
                    if not counting:
                        indices[start + m] = b
                    m += 1
        if counting:
            indptr[a + 1] = indptr[a] + m
        else:
            indices[start:start + m].sort()


def _slot(indices, lo, hi, b):
    """The position of b among the sorted indices[lo:hi] (binary search)."""
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if indices[mid] <= b:
            lo = mid
        else:
            hi = mid
    return lo


def _scatter_kernel(cells, Ke, d, indptr, indices, data):
    """data += the symmetrized blocks 0.5 (Ke + Ke^T) of every element, in element order."""
    E, k = cells.shape
    for e in range(E):
        for p in range(k):
            a = cells[e, p]
            lo, hi = indptr[a], indptr[a + 1]
            base = d * d * lo
            width = d * (hi - lo)
            for q in range(k):
                s = _slot(indices, lo, hi, cells[e, q]) - lo
                for i in range(d):
                    row = base + i * width + d * s
                    for j in range(d):
                        data[row + j] += 0.5 * (Ke[e, p * d + i, q * d + j] + Ke[e, q * d + j, p * d + i])


def _tet4_kernel(X, cells, lam, mu, indptr, indices, data, vol):
    """data += the linear tet's stiffness, vol = each tet's volume; returns the first tet whose
    Jacobian is not positive (then nothing is added for it or after it), or -1."""
    E = cells.shape[0]
    J = np.zeros((3, 3))
    C = np.zeros((3, 3))
    G = np.zeros((4, 3))
    for e in range(E):
        for i in range(3):
            for j in range(3):
                J[i, j] = X[cells[e, j + 1], i] - X[cells[e, 0], i]  # dx_i / dxi_j
        C[0, 0] = J[1, 1] * J[2, 2] - J[1, 2] * J[2, 1]  # the cofactors of J
        C[0, 1] = J[1, 2] * J[2, 0] - J[1, 0] * J[2, 2]
        C[0, 2] = J[1, 0] * J[2, 1] - J[1, 1] * J[2, 0]
        C[1, 0] = J[0, 2] * J[2, 1] - J[0, 1] * J[2, 2]
        C[1, 1] = J[0, 0] * J[2, 2] - J[0, 2] * J[2, 0]
        C[1, 2] = J[0, 1] * J[2, 0] - J[0, 0] * J[2, 1]
        C[2, 0] = J[0, 1] * J[1, 2] - J[0, 2] * J[1, 1]
        C[2, 1] = J[0, 2] * J[1, 0] - J[0, 0] * J[1, 2]
        C[2, 2] = J[0, 0] * J[1, 1] - J[0, 1] * J[1, 0]
        det = J[0, 0] * C[0, 0] + J[0, 1] * C[0, 1] + J[0, 2] * C[0, 2]
        if not det > 0.0:
            vol[e] = det / 6.0
            return e
        for m in range(3):  # G = dN J^-1: node m + 1's gradient is row m of J^-1 = column m of cof J / det
            for i in range(3):
                G[m + 1, i] = C[i, m] / det
        for i in range(3):
            G[0, i] = -(G[1, i] + G[2, i] + G[3, i])
        v = det / 6.0
        vol[e] = v
        for p in range(4):
            a = cells[e, p]
            lo, hi = indptr[a], indptr[a + 1]
            base = 9 * lo
            width = 3 * (hi - lo)
            for q in range(4):
                s = _slot(indices, lo, hi, cells[e, q]) - lo
                gg = G[p, 0] * G[q, 0] + G[p, 1] * G[q, 1] + G[p, 2] * G[q, 2]
                for i in range(3):
                    row = base + i * width + 3 * s
                    for j in range(3):
                        # v (lam G_pi G_qj + mu G_pj G_qi + mu delta_ij G_p . G_q): each product taken
                        # in the same order for (p i, q j) and (q j, p i), so the matrix is exactly symmetric
                        val = lam * (G[p, i] * G[q, j]) + mu * (G[p, j] * G[q, i])
                        if i == j:
                            val += mu * gg
                        data[row + j] += v * val
    return -1


def _kernel(name: str):
    table = {"pattern": (_pattern_kernel,), "scatter": (_scatter_kernel, _slot), "tet4": (_tet4_kernel, _slot)}
    kernel, *helpers = table[name]
    return compiled(f"assembly.{name}", kernel, *helpers)


def available() -> bool:
    """Whether the compiled assembly can run here (numba installed and able to compile)."""
    return all(_kernel(name) is not None for name in ("pattern", "scatter", "tet4"))


def node_pattern(cells: np.ndarray, n_nodes: int) -> tuple[np.ndarray, np.ndarray]:
    """(indptr, indices) of the node pattern of ``cells`` (E, k): row a lists, sorted, every node
    sharing an element with a, a itself included."""
    cells = np.ascontiguousarray(cells, dtype=np.int64)
    indptr = np.zeros(n_nodes + 1, np.int64)
    kernel = _kernel("pattern")
    kernel(cells, n_nodes, indptr, np.zeros(0, np.int64), True)
    indices = np.empty(int(indptr[-1]), np.int64)
    kernel(cells, n_nodes, indptr, indices, False)
    return indptr, indices


def dof_arrays(indptr: np.ndarray, indices: np.ndarray, d: int) -> tuple[np.ndarray, np.ndarray]:
    """The dof-level (indptr, indices) of a node pattern, d dofs per node (see the module's docstring)."""
    deg = np.diff(indptr)
    n = deg.size
    row_len = np.repeat(d * deg, d)
    dptr = np.zeros(d * n + 1, np.int64)
    np.cumsum(row_len, out=dptr[1:])
    cols = (d * indices[:, None] + np.arange(d)).reshape(-1)  # each node row's columns, node-major
    starts = np.repeat(d * indptr[:-1], d)  # where each dof row's columns start in cols
    take = np.repeat(starts - dptr[:-1], row_len) + np.arange(int(dptr[-1]))
    return dptr, cols[take]


def scatter_blocks(cells, Ke, pattern, d: int) -> np.ndarray:
    """The dof-level CSR data of the symmetrized element matrices ``Ke`` (E, k d, k d) on ``cells``."""
    indptr, indices = pattern
    data = np.zeros(d * d * int(indptr[-1]))
    _kernel("scatter")(np.ascontiguousarray(cells, dtype=np.int64), np.ascontiguousarray(Ke, dtype=float), d,
                       indptr, indices, data)
    return data


def tet4_stiffness(X, cells, lam: float, mu: float, pattern) -> tuple[np.ndarray, np.ndarray, int]:
    """The dof-level CSR data of the linear tet4 stiffness (Lame lam, mu), the tets' volumes and the
    first tet with a non-positive Jacobian (-1: none)."""
    indptr, indices = pattern
    cells = np.ascontiguousarray(cells, dtype=np.int64)
    data = np.zeros(9 * int(indptr[-1]))
    vol = np.zeros(cells.shape[0])
    bad = _kernel("tet4")(np.ascontiguousarray(X, dtype=float), cells, float(lam), float(mu), indptr, indices, data, vol)
    return data, vol, int(bad)
