"""Checks and repairs of surface meshes (the arrays, finiteness, degenerate and duplicate
triangles, merged vertices, non-manifold edges, orientation) and the report of what was found
and changed (:class:`MeshReport`); :class:`~rtfem.TriMesh` and :class:`~rtfem.TetMesh` run them."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Mapping

import numpy as np

from .. import validate
from ..errors import MeshError

__all__ = ["MeshReport"]

_MAX_LISTED = 5


def _listing(idx: np.ndarray) -> str:
    idx = np.asarray(idx).ravel()
    head = ", ".join(str(int(i)) for i in idx[:_MAX_LISTED])
    return head + (f", ... ({idx.size} in all)" if idx.size > _MAX_LISTED else "")


@dataclass
class MeshReport:
    """What validation found and what repair changed (``mesh.report``; ``str(report)`` says it in
    words). Filled in by the mesh's checks, which raise :class:`~rtfem.MeshError` for what they
    cannot repair.

    Parameters
    ----------
    n_vertices_in, n_triangles_in : the input mesh's sizes.
    merged_vertices : coincident vertices merged (within ``merge_tol``).
    dropped_unreferenced : vertices no triangle used, dropped.
    removed_degenerate, removed_duplicate_triangles : triangles removed.
    flipped_triangles : triangles turned to agree with their neighbours' orientation.
    n_components : connected pieces.
    closed, n_boundary_edges : whether the surface is closed; its boundary edges.
    orientable : whether a consistent orientation exists.
    nonmanifold_vertices : vertices where the surface is not a disc.
    min_angle_deg : the smallest triangle angle (degrees).
    notes : remarks in words.

    Raises
    ------
    Nothing itself: a record.
    """

    n_vertices_in: int = 0
    n_triangles_in: int = 0
    merged_vertices: int = 0
    dropped_unreferenced: int = 0
    removed_degenerate: int = 0
    removed_duplicate_triangles: int = 0
    flipped_triangles: int = 0
    n_components: int = 0
    closed: bool = False
    n_boundary_edges: int = 0
    orientable: bool = True
    nonmanifold_vertices: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    min_angle_deg: float = float("nan")
    notes: list[str] = field(default_factory=list)

    @property
    def repaired(self) -> bool:
        """True when repair changed the mesh."""
        return bool(
            self.merged_vertices
            or self.dropped_unreferenced
            or self.removed_degenerate
            or self.removed_duplicate_triangles
            or self.flipped_triangles
        )

    def __str__(self) -> str:
        lines = [
            f"input: {self.n_vertices_in} vertices, {self.n_triangles_in} triangles",
            f"components: {self.n_components}, "
            + ("closed" if self.closed else f"open ({self.n_boundary_edges} boundary edges)")
            + ("" if self.orientable else ", NOT orientable"),
            f"smallest angle: {self.min_angle_deg:.2f} deg",
        ]
        rep = [
            (self.merged_vertices, "duplicate vertices merged"),
            (self.dropped_unreferenced, "unreferenced vertices dropped"),
            (self.removed_degenerate, "degenerate (zero-area) triangles removed"),
            (self.removed_duplicate_triangles, "duplicate triangles removed"),
            (self.flipped_triangles, "triangles flipped to a consistent orientation"),
        ]
        done = [f"{n} {what}" for n, what in rep if n]
        lines.append("repairs: " + ("; ".join(done) if done else "none"))
        if self.nonmanifold_vertices.size:
            lines.append(
                f"warning: {self.nonmanifold_vertices.size} non-manifold vertices (surfaces touching at "
                f"a single point: {_listing(self.nonmanifold_vertices)}); they act as hinges"
            )
        lines.extend(self.notes)
        return "\n".join(lines)


def _check_groups(groups, n: int) -> dict[str, np.ndarray]:
    if groups is None:
        return {}
    if not isinstance(groups, Mapping):
        raise MeshError(f"groups={validate.show(groups)} must be a mapping {{name: vertex indices}}")
    out = {}
    for name, idx in groups.items():
        if not isinstance(name, str) or not name:
            raise MeshError(f"group name {validate.show(name)} must be a non-empty string")
        out[name] = validate.nodes(idx, n, f"group {name!r}", allow_empty=True, error=MeshError)
    return out


def _check_arrays(vertices, triangles) -> tuple[np.ndarray, np.ndarray]:
    try:
        V = np.array(vertices, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise MeshError(f"vertices are not a numeric (n, 3) array: {exc}") from None
    try:
        T_raw = np.asarray(triangles)
    except (TypeError, ValueError) as exc:
        raise MeshError(f"triangles are not an integer (m, 3) array: {exc}") from None
    if V.size == 0 or T_raw.size == 0:
        raise MeshError(
            f"empty mesh ({V.shape[0] if V.ndim else 0} vertices, {T_raw.shape[0] if T_raw.ndim else 0} "
            "triangles): a shell model needs at least one triangle"
        )
    if V.ndim != 2 or V.shape[1] not in (2, 3):
        raise MeshError(f"vertices must be an (n, 3) array, got shape {V.shape}")
    if V.shape[1] == 2:
        V = np.column_stack([V, np.zeros(V.shape[0])])
    if T_raw.ndim != 2 or T_raw.shape[1] != 3:
        raise MeshError(
            f"triangles must be an (m, 3) array of vertex indices, got shape {T_raw.shape}"
            + ("; split quads or polygons first (load_mesh does)" if T_raw.ndim == 2 else "")
        )
    T = _integer_cells(T_raw, "triangle indices")
    _check_finite_and_in_range(V, T, ("vertex", "vertices"), "triangle")
    return V, T


def _integer_cells(T_raw: np.ndarray, what: str) -> np.ndarray:
    """Cell indices as C-ordered int64: integers, or floats holding whole numbers."""
    if not np.issubdtype(T_raw.dtype, np.integer):
        if not np.issubdtype(T_raw.dtype, np.floating) or np.any(T_raw != np.round(T_raw)):
            raise MeshError(f"{what} must be integers, got dtype {T_raw.dtype}")
    return np.ascontiguousarray(T_raw, dtype=np.int64)


def _check_finite_and_in_range(V: np.ndarray, T: np.ndarray, node: tuple[str, str], cell: str) -> None:
    """MeshError naming the first non-finite point and the first cell with an index out of range
    (``node``: the word for a point, singular and plural; ``cell``: for a cell)."""
    bad_v = np.flatnonzero(~np.isfinite(V).all(axis=1))
    if bad_v.size:
        raise MeshError(
            f"non-finite (NaN or infinite) coordinates at {node[0]} {_listing(bad_v)}: "
            f"first one is {V[bad_v[0]].tolist()}; fix or remove these {node[1]}"
        )
    bad_t = np.flatnonzero(((T < 0) | (T >= V.shape[0])).any(axis=1))
    if bad_t.size:
        raise MeshError(
            f"{cell} {_listing(bad_t)} refers to a {node[0]} index outside 0..{V.shape[0] - 1} "
            f"(first one: {T[bad_t[0]].tolist()})"
        )


def unique_rows(a: np.ndarray, *, return_index: bool = False, return_inverse: bool = False,
                return_counts: bool = False):
    """``np.unique(a, axis=0, ...)`` for rows of non-negative integers (node numbers), with the same
    results in the same order: each row packed into one int64 (lexicographic order kept) where the
    numbers allow, so that numpy sorts one key per row instead of a row of keys (the 23k-tet liver's
    checks on loading 0.17 -> 0.07 s); ``np.unique(axis=0)`` itself otherwise."""
    a = np.asarray(a)
    flags = dict(return_index=return_index, return_inverse=return_inverse, return_counts=return_counts)
    base = int(a.max()) + 1 if a.size else 1
    if a.ndim != 2 or a.dtype.kind not in "iu" or (a.size and a.min() < 0) or base ** a.shape[1] >= 2**62:
        return np.unique(a, axis=0, **flags)
    key = np.zeros(a.shape[0], np.int64)
    for col in a.T:
        key = key * base + col
    _, first, *rest = np.unique(key, return_index=True, return_inverse=return_inverse, return_counts=return_counts)
    out = [a[first]] + ([first] if return_index else []) + rest
    return out[0] if len(out) == 1 else tuple(out)


def _edge_index(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unique sorted edges and, for each triangle side (0-1, 1-2, 2-0), its edge number."""
    e = np.stack([T[:, [0, 1]], T[:, [1, 2]], T[:, [2, 0]]], axis=1).reshape(-1, 2)
    e = np.sort(e, axis=1)
    edges, inverse = unique_rows(e, return_inverse=True)
    return edges, inverse.ravel()


def _unique_edges(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    edges, inverse = _edge_index(T)
    return edges, np.bincount(inverse, minlength=edges.shape[0])


def _twice_areas(V: np.ndarray, T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    c = V[T]
    n = np.linalg.norm(np.cross(c[:, 1] - c[:, 0], c[:, 2] - c[:, 0]), axis=1)
    lmax = np.max(np.linalg.norm(c - np.roll(c, 1, axis=1), axis=2), axis=1)
    return n, lmax


def _degenerate(V: np.ndarray, T: np.ndarray) -> np.ndarray:
    """Triangles with a repeated vertex or (numerically) zero area."""
    rep = (T[:, 0] == T[:, 1]) | (T[:, 1] == T[:, 2]) | (T[:, 2] == T[:, 0])
    a2, lmax = _twice_areas(V, T)
    return rep | (a2 <= 1e-12 * lmax**2)


def _refuse_unrepaired(V: np.ndarray, T: np.ndarray) -> None:
    deg = np.flatnonzero(_degenerate(V, T))
    if deg.size:
        raise MeshError(
            f"degenerate (zero-area) triangle {_listing(deg)}: vertices {T[deg[0]].tolist()}; "
            "pass repair=True to remove them"
        )


def _merge_classes(V: np.ndarray, tol: float) -> np.ndarray:
    """For each vertex, the lowest index of the vertices it merges with (within ``tol``).

    O(n log n) time and O(n) memory however the points cluster: vertices are first binned
    into cells of size ``tol`` (one cell = one class), then only the cells' representatives
    are paired within ``tol`` -- at most a few dozen neighbours each, where pairing all points
    directly would list n^2 / 2 pairs for n coincident vertices.
    """
    n = V.shape[0]
    if tol > 0:
        key = np.floor((V - V.min(axis=0)) / tol).astype(np.int64)
    else:
        key = V
    _, first, cell = np.unique(key, axis=0, return_index=True, return_inverse=True)
    cell = cell.ravel()
    reps = V[first]
    if tol > 0 and first.size > 1:
        pairs = close_pairs(reps, tol)
    else:
        pairs = np.zeros((0, 2), dtype=np.int64)
    k = first.size
    if pairs.shape[0]:
        _, label = components(k, pairs[:, 0], pairs[:, 1])
    else:
        label = np.arange(k)
    label = label[cell]
    # representative of each class: its lowest index
    rep = np.full(int(label.max()) + 1, n, dtype=np.int64)
    np.minimum.at(rep, label, np.arange(n))
    return rep[label]


# ------------------------------------------------------------ graphs in numpy
# (issue 54: scipy.sparse.csgraph and scipy.spatial, with scipy.sparse.linalg, scipy.linalg and scipy.special
# that they import, were 0.07-0.14 s of CPU of every fresh process that loads a mesh)
def components(n: int, i: np.ndarray, j: np.ndarray) -> tuple[int, np.ndarray]:
    """Connected components of the undirected graph on ``n`` nodes with edges (i[e], j[e]): their number
    and each node's label, numbered in the order of each component's lowest node (as
    ``scipy.sparse.csgraph.connected_components`` numbers them). Each round hooks every root to the
    smallest root an edge joins it to, then halves the paths to the roots until each points at one."""
    parent, _ = _hook(n, np.asarray(i, np.int64).ravel(), np.asarray(j, np.int64).ravel(), None)
    roots, label = np.unique(parent, return_inverse=True)
    return int(roots.size), label.ravel()


def _hook(n: int, i: np.ndarray, j: np.ndarray, odd: np.ndarray | None):
    """Union by smallest root over the edges (i, j): the root of each node (its component's lowest
    node) and, with ``odd`` (a bool per edge: whether its ends differ), each node's parity to its root."""
    parent = np.arange(n)
    par = np.zeros(n, bool)
    while True:
        ri, rj = parent[i], parent[j]
        cross = ri != rj
        if not cross.any():
            return parent, par
        lo, hi = np.minimum(ri, rj)[cross], np.maximum(ri, rj)[cross]
        rel = (par[i] ^ par[j] ^ odd)[cross] if odd is not None else np.zeros(lo.size, bool)
        order = np.lexsort((lo, hi))  # for each root, the smallest root it is joined to
        hi, lo, rel = hi[order], lo[order], rel[order]
        keep = np.r_[True, hi[1:] != hi[:-1]]
        parent[hi[keep]], par[hi[keep]] = lo[keep], rel[keep]
        while True:  # pointer jumping: every node to its root, the parities composed on the way
            up = parent[parent]
            if np.array_equal(up, parent):
                break
            par ^= par[parent]
            parent = up


def close_pairs(P: np.ndarray, tol: float) -> np.ndarray:
    """(k, 2) index pairs (i < j) of the points P (n, 3) within ``tol`` of each other, as
    ``scipy.spatial.cKDTree(P).query_pairs(tol)`` finds them: the points binned into cells at least
    ``tol`` wide whose numbers pack in one int64, each cell paired with itself and its 13 forward
    neighbours (a pair within ``tol`` lies in one cell or two adjacent ones)."""
    P = np.asarray(P, dtype=float)
    lo = P.min(axis=0)
    size = max(float(tol), float((P.max(axis=0) - lo).max()) / (2**20 - 4))
    g = np.floor((P - lo) / size).astype(np.int64) + 1  # 1 .. 2**20 - 3 on each axis: no carry below
    B = np.int64(2**21)
    key = (g[:, 0] * B + g[:, 1]) * B + g[:, 2]
    order = np.argsort(key, kind="stable")
    cells, start, count = np.unique(key[order], return_index=True, return_counts=True)
    found = [np.zeros((0, 2), np.int64)]
    for c in np.flatnonzero(count > 1):  # a cell with several points: every pair in it
        idx = order[start[c]:start[c] + count[c]]
        a, b = np.triu_indices(idx.size, 1)
        found.append(np.column_stack([idx[a], idx[b]]))
    for dx, dy, dz in [(x, y, z) for x in (-1, 0, 1) for y in (-1, 0, 1) for z in (-1, 0, 1) if (x, y, z) > (0, 0, 0)]:
        target = cells + (dx * B + dy) * B + dz
        pos = np.minimum(np.searchsorted(cells, target), cells.size - 1)
        hit = np.flatnonzero(cells[pos] == target)
        for a, b in zip(hit.tolist(), pos[hit].tolist()):  # neighbouring occupied cells: few
            ia, ib = order[start[a]:start[a] + count[a]], order[start[b]:start[b] + count[b]]
            found.append(np.column_stack([np.repeat(ia, ib.size), np.tile(ib, ia.size)]))
    pairs = np.concatenate(found)
    pairs = pairs[np.linalg.norm(P[pairs[:, 0]] - P[pairs[:, 1]], axis=1) <= tol]
    return np.sort(pairs, axis=1)


def _repair(V: np.ndarray, T: np.ndarray, merge_tol: float, report: MeshReport):
    n_in = V.shape[0]
    # 1. merge duplicate vertices within a tolerance relative to the model size
    diag = float(np.linalg.norm(V.max(axis=0) - V.min(axis=0)))
    tol = merge_tol * (diag if diag > 0 else 1.0)
    merge = _merge_classes(V, tol)
    report.merged_vertices = int(np.sum(merge != np.arange(n_in)))
    if report.merged_vertices:
        T = merge[T]
    # 2. degenerate triangles
    deg = _degenerate(V, T)
    report.removed_degenerate = int(deg.sum())
    T = T[~deg]
    if T.shape[0] == 0:
        raise MeshError("every triangle is degenerate (zero area): the mesh has no usable surface")
    # 3. duplicate triangles (same three vertices, either orientation)
    _, first = unique_rows(np.sort(T, axis=1), return_index=True)
    report.removed_duplicate_triangles = int(T.shape[0] - first.size)
    T = T[np.sort(first)]
    # 4. unreferenced vertices
    used = np.zeros(n_in, bool)
    used[T.ravel()] = True
    new_index = np.full(n_in, -1, dtype=np.int64)
    new_index[used] = np.arange(int(used.sum()))
    report.dropped_unreferenced = int(n_in - report.merged_vertices - used.sum())
    vmap = new_index[merge]
    return V[used], new_index[T], vmap


def _check_manifold_edges(V: np.ndarray, T: np.ndarray) -> None:
    edges, count = _unique_edges(T)
    bad = np.flatnonzero(count > 2)
    if bad.size:
        a, b = edges[bad[0]]
        tri = np.flatnonzero(np.isin(T, [a, b]).sum(axis=1) == 2)
        raise MeshError(
            f"non-manifold mesh: {bad.size} edges are shared by more than two triangles; the first, "
            f"between vertices {a} {V[a].tolist()} and {b} {V[b].tolist()}, belongs to triangles "
            f"{_listing(tri)}. A shell surface must have at most two triangles per edge: "
            "separate the sheets or remove the extra faces"
        )


@dataclass
class _HalfEdges:
    """Directed edges (3 per triangle, half-edge h of triangle h // 3), the undirected edges and
    the two half-edges (h1, h2) of each interior edge, with their triangles (t1, t2)."""

    e_dir: np.ndarray
    edges: np.ndarray
    inv: np.ndarray  # half-edge -> undirected edge
    count: np.ndarray  # triangles per undirected edge
    h1: np.ndarray
    h2: np.ndarray

    @classmethod
    def of(cls, T: np.ndarray) -> "_HalfEdges":
        e_dir = np.stack([T[:, [0, 1]], T[:, [1, 2]], T[:, [2, 0]]], axis=1).reshape(-1, 2)
        edges, inv = unique_rows(np.sort(e_dir, axis=1), return_inverse=True)
        inv = inv.ravel()
        count = np.bincount(inv, minlength=edges.shape[0])
        order = np.argsort(inv, kind="stable")
        sorted_inv = inv[order]
        starts = np.flatnonzero(np.r_[True, sorted_inv[1:] != sorted_inv[:-1]])
        pair_edges = starts[count[sorted_inv[starts]] == 2]
        return cls(e_dir, edges, inv, count, order[pair_edges], order[pair_edges + 1])

    @property
    def t1(self) -> np.ndarray:
        return self.h1 // 3

    @property
    def t2(self) -> np.ndarray:
        return self.h2 // 3


def _orientation_flips(m: int, he: _HalfEdges) -> tuple[np.ndarray, np.ndarray, int, bool]:
    """Which triangles to flip for one orientation per component: (flip, component label,
    number of components, orientable). Each component's lowest triangle keeps its orientation; the
    others' flips follow from the relation flip[t2] = flip[t1] xor same across each shared edge,
    composed by the union of :func:`_hook` (parities to the root)."""
    t1, t2 = he.t1, he.t2
    same = he.e_dir[he.h1, 0] == he.e_dir[he.h2, 0]  # same direction -> inconsistent orientation
    parent, flip = _hook(m, t1.astype(np.int64), t2.astype(np.int64), same)
    roots, label = np.unique(parent, return_inverse=True)
    orientable = bool(((flip[t1] ^ flip[t2]) == same).all())
    return flip, label.ravel(), int(roots.size), orientable


def _outward_turns(V: np.ndarray, T: np.ndarray, label: np.ndarray, n_comp: int, he: _HalfEdges) -> np.ndarray:
    """Triangles of closed components with negative enclosed volume (to be turned outward)."""
    c = V[T]
    vol6 = np.einsum("ij,ij->i", c[:, 0], np.cross(c[:, 1], c[:, 2]))
    comp_closed = np.ones(n_comp, bool)
    open_tris = np.zeros(T.shape[0], bool)
    open_tris[np.flatnonzero(he.count[he.inv] == 1) // 3] = True
    comp_closed[np.unique(label[open_tris])] = False
    comp_vol = np.bincount(label, weights=vol6, minlength=n_comp)
    return (comp_closed & (comp_vol < 0))[label]


def _nonmanifold_vertices(T: np.ndarray, he: _HalfEdges, n_vertices: int) -> np.ndarray:
    """Vertices whose corners do not share one fan of edge-adjacent triangles (bow ties)."""
    m = T.shape[0]
    t1, t2 = he.t1, he.t2
    corner_of = lambda t, v: 3 * t + np.argmax(T[t] == v[:, None], axis=1)  # noqa: E731
    a, b = he.edges[he.inv[he.h1]][:, 0], he.edges[he.inv[he.h1]][:, 1]
    ca = np.r_[corner_of(t1, a), corner_of(t1, b)]
    cb = np.r_[corner_of(t2, a), corner_of(t2, b)]
    _, fan = components(3 * m, ca, cb)
    pairs = unique_rows(np.stack([T.ravel(), fan], axis=1))
    return np.flatnonzero(np.bincount(pairs[:, 0], minlength=n_vertices) > 1)


def _orient(V: np.ndarray, T: np.ndarray, report: MeshReport, repair: bool) -> np.ndarray:
    """Consistent orientation by a breadth-first walk over edge-adjacent triangles; closed
    components outward; boundary, components and non-manifold vertices into the report."""
    he = _HalfEdges.of(T)
    report.n_boundary_edges = int(np.sum(he.count == 1))
    report.closed = report.n_boundary_edges == 0
    flip, label, n_comp, orientable = _orientation_flips(T.shape[0], he)
    report.n_components = n_comp
    if not orientable:
        report.orientable = False
        report.notes.append(
            "note: the surface is not orientable (a Moebius-like band); normals cannot be made "
            "consistent, which does not affect the stiffness but makes 'pressure' ambiguous"
        )
        flip[:] = False
    T = T.copy()
    if repair and report.orientable:
        T[flip] = T[flip][:, ::-1]
        turn = _outward_turns(V, T, label, n_comp, he)
        T[turn] = T[turn][:, ::-1]
        report.flipped_triangles = int(np.sum(flip ^ turn))
    elif not repair and report.orientable and flip.any() and not np.all(flip[label == label[0]]):
        report.notes.append("note: orientation is inconsistent (repair=False left it as given)")
    report.nonmanifold_vertices = _nonmanifold_vertices(T, he, V.shape[0])
    return T
