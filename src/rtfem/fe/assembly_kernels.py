"""Compiled assembly (numba): the node pattern of a mesh, element blocks scattered straight into the
dof-level CSR arrays, and the linear tets' stiffness (tet4, tet10) computed and scattered in one
pass, with no element-matrix array in between. :mod:`rtfem.fe.assembly` calls these where numba is installed and
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

__all__ = ["node_pattern", "scatter_blocks", "solid_stiffness"]


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


def _cofactor(Fm, cof) -> float:
    """cof (3, 3) = the cofactor of Fm (3, 3) (det Fm Fm^-T); returns det Fm."""
    for i in range(3):
        i1, i2 = (i + 1) % 3, (i + 2) % 3
        for j in range(3):
            j1, j2 = (j + 1) % 3, (j + 2) % 3
            cof[i, j] = Fm[i1, j1] * Fm[i2, j2] - Fm[i1, j2] * Fm[i2, j1]
    return Fm[0, 0] * cof[0, 0] + Fm[0, 1] * cof[0, 1] + Fm[0, 2] * cof[0, 2]


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


def _solid_kernel(X, cells, dN, w, lam, mu, indptr, indices, data, vol):
    """data += the isoparametric tets' linear stiffness (quadrature points dN (q, k, 3), weights w),
    vol = each tet's volume sum_q w_q det J_q; returns the first tet with a non-positive det J at a
    point (nothing is added for it or after it), or -1."""
    E, k = cells.shape
    nq = w.shape[0]
    J = np.zeros((3, 3))
    C = np.zeros((3, 3))
    G = np.zeros((k, 3))
    Ke = np.zeros((3 * k, 3 * k))
    for e in range(E):
        Ke[:, :] = 0.0
        v = 0.0
        for q in range(nq):
            for i in range(3):
                for j in range(3):
                    acc = 0.0
                    for a in range(k):
                        acc += X[cells[e, a], i] * dN[q, a, j]
                    J[i, j] = acc  # dx_i / dxi_j
            det = _cofactor(J, C)  # C = cof J = det J J^-T
            if not det > 0.0:
                vol[e] = det
                return e
            for a in range(k):  # G = dN J^-1, (J^-1)[j, i] = cof(J)[i, j] / det
                for i in range(3):
                    G[a, i] = (dN[q, a, 0] * C[i, 0] + dN[q, a, 1] * C[i, 1] + dN[q, a, 2] * C[i, 2]) / det
            wd = w[q] * det
            v += wd
            for a in range(k):
                for b in range(k):
                    gg = G[a, 0] * G[b, 0] + G[a, 1] * G[b, 1] + G[a, 2] * G[b, 2]
                    for i in range(3):
                        for j in range(3):
                            # each product in the same order for (a i, b j) and (b j, a i): exactly symmetric
                            val = lam * (G[a, i] * G[b, j]) + mu * (G[a, j] * G[b, i])
                            if i == j:
                                val += mu * gg
                            Ke[3 * a + i, 3 * b + j] += wd * val
        vol[e] = v
        for a in range(k):
            node = cells[e, a]
            lo, hi = indptr[node], indptr[node + 1]
            base = 9 * lo
            width = 3 * (hi - lo)
            for b in range(k):
                s = _slot(indices, lo, hi, cells[e, b]) - lo
                for i in range(3):
                    row = base + i * width + 3 * s
                    for j in range(3):
                        data[row + j] += Ke[3 * a + i, 3 * b + j]
    return -1


def _kernel(name: str):
    table = {"pattern": (_pattern_kernel,), "scatter": (_scatter_kernel, _slot), "solid": (_solid_kernel, _slot, _cofactor)}
    kernel, *helpers = table[name]
    return compiled(f"assembly.{name}", kernel, *helpers)


def available() -> bool:
    """Whether the compiled assembly can run here (numba installed and able to compile)."""
    return all(_kernel(name) is not None for name in ("pattern", "scatter", "solid"))


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


def solid_stiffness(X, cells, dN, w, lam: float, mu: float, pattern) -> tuple[np.ndarray, np.ndarray, int]:
    """The dof-level CSR data of the linear isoparametric tets' stiffness (Lame lam, mu; quadrature
    gradients dN (q, k, 3) and weights w (q,)), the tets' volumes and the first tet with a
    non-positive Jacobian (-1: none)."""
    indptr, indices = pattern
    cells = np.ascontiguousarray(cells, dtype=np.int64)
    data = np.zeros(9 * int(indptr[-1]))
    vol = np.zeros(cells.shape[0])
    bad = _kernel("solid")(np.ascontiguousarray(X, dtype=float), cells, np.ascontiguousarray(dN, dtype=float),
                           np.ascontiguousarray(w, dtype=float), float(lam), float(mu), indptr, indices, data, vol)
    return data, vol, int(bad)
