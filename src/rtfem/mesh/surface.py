"""Triangle surface meshes: validated arrays, repair with a report, topology queries.

File input and output live in :mod:`rtfem.mesh.files` (``load_mesh``, ``save_mesh``); this module holds the
in-memory mesh and its checks.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Mapping

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import breadth_first_order, connected_components
from scipy.spatial import cKDTree

from .. import validate
from ..errors import MeshError

__all__ = ["TriMesh", "MeshReport"]

_MAX_LISTED = 5


def _listing(idx: np.ndarray) -> str:
    idx = np.asarray(idx).ravel()
    head = ", ".join(str(int(i)) for i in idx[:_MAX_LISTED])
    return head + (f", ... ({idx.size} in all)" if idx.size > _MAX_LISTED else "")


@dataclass
class MeshReport:
    """What validation found and what repair changed."""

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


class TriMesh:
    """A validated triangle surface mesh in 3D.

    Parameters
    ----------
    vertices : (n, 3) coordinates (an (n, 2) array is placed in the z = 0 plane).
    triangles : (m, 3) vertex indices.
    repair : merge duplicate vertices (within ``merge_tol`` times the bounding-box diagonal),
        drop unreferenced vertices, remove zero-area and duplicate triangles and make the
        orientation consistent (outward for closed components). The changes are listed in
        :attr:`report`, and :attr:`vertex_map` maps input vertex indices to the repaired ones
        (-1 for dropped vertices). With ``repair=False`` a mesh that needs repair is refused.
    groups : optional named vertex sets (indices into the input vertices), e.g. an attachment.

    Raises
    ------
    MeshError : empty mesh, non-finite coordinates, out-of-range indices, non-manifold edges.

    ``mid_nodes`` ((m, 3) or None): on the surface of a 10-node tet mesh, each triangle's mid-edge
    nodes (edges 01, 12, 20): its 6-node face, which contact touches (:meth:`contact_surface`).
    """

    mid_nodes: np.ndarray | None = None

    def __init__(
        self,
        vertices: np.ndarray,
        triangles: np.ndarray,
        *,
        repair: bool = True,
        merge_tol: float = 1e-10,
        groups: Mapping[str, np.ndarray] | None = None,
    ) -> None:
        repair = validate.flag(repair, "repair", error=MeshError)
        merge_tol = validate.in_range(merge_tol, "merge_tol", 0.0, 1.0, hi_open=True,
                                      what="a fraction of the bounding-box diagonal", error=MeshError)
        V, T = _check_arrays(vertices, triangles)
        groups = _check_groups(groups, V.shape[0])
        report = MeshReport(n_vertices_in=V.shape[0], n_triangles_in=T.shape[0])
        vmap = np.arange(V.shape[0])
        if repair:
            V, T, vmap = _repair(V, T, merge_tol, report)
        else:
            _refuse_unrepaired(V, T)
        _check_manifold_edges(V, T)
        T = _orient(V, T, report, repair)
        self._vertices = V
        self._triangles = T
        self._vertices.flags.writeable = False
        self._triangles.flags.writeable = False
        self.vertex_map = vmap
        self.report = report
        self.groups: dict[str, np.ndarray] = {}
        for name, idx in (groups or {}).items():
            mapped = vmap[idx]
            self.groups[name] = np.unique(mapped[mapped >= 0])
        self._cache: dict[str, object] = {}
        report.min_angle_deg = float(np.degrees(self.angles().min()))

    def contact_surface(self) -> "TriMesh":
        """The surface contact touches: this mesh, or where its triangles are 6-node faces
        (``mid_nodes``) each split into its 4 corner and mid-edge triangles, so that the mid-edge
        nodes are contact points and a point on a face moves and is loaded through the same
        weights (over the same node numbering)."""
        if self.mid_nodes is None:
            return self
        if "contact" not in self._cache:
            (c0, c1, c2), (m01, m12, m20) = self._triangles.T, self.mid_nodes.T
            sub = np.stack([np.column_stack(t) for t in ((c0, m01, m20), (m01, c1, m12), (m20, m12, c2),
                                                         (m01, m12, m20))], axis=1).reshape(-1, 3)
            self._cache["contact"] = TriMesh(self._vertices, sub, repair=False, groups=self.groups)
        return self._cache["contact"]  # type: ignore[return-value]

    # ------------------------------------------------------------------ arrays
    @property
    def vertices(self) -> np.ndarray:
        """(n, 3) vertex coordinates (read-only)."""
        return self._vertices

    @property
    def triangles(self) -> np.ndarray:
        """(m, 3) vertex indices of each triangle (read-only)."""
        return self._triangles

    @property
    def n_vertices(self) -> int:
        return self._vertices.shape[0]

    @property
    def n_triangles(self) -> int:
        return self._triangles.shape[0]

    def __repr__(self) -> str:
        lo, hi = self.bounds()
        return (
            f"TriMesh({self.n_vertices} vertices, {self.n_triangles} triangles, "
            f"extent {np.array2string(hi - lo, precision=4)})"
        )

    # --------------------------------------------------------------- geometry
    def corners(self) -> np.ndarray:
        """(m, 3, 3) corner coordinates of each triangle."""
        return self._vertices[self._triangles]

    def face_normals(self, unit: bool = True) -> np.ndarray:
        c = self.corners()
        n = np.cross(c[:, 1] - c[:, 0], c[:, 2] - c[:, 0])
        return n / np.linalg.norm(n, axis=1)[:, None] if unit else n

    def areas(self) -> np.ndarray:
        return 0.5 * np.linalg.norm(self.face_normals(unit=False), axis=1)

    def vertex_normals(self) -> np.ndarray:
        """Area-weighted unit vertex normals (n, 3)."""
        fn = self.face_normals(unit=False)
        vn = np.zeros_like(self._vertices)
        for k in range(3):
            np.add.at(vn, self._triangles[:, k], fn)
        norm = np.linalg.norm(vn, axis=1)
        norm[norm == 0] = 1.0
        return vn / norm[:, None]

    def vertex_areas(self) -> np.ndarray:
        """A third of the area of the triangles around each vertex (n,)."""
        out = np.zeros(self.n_vertices)
        a = self.areas() / 3.0
        for k in range(3):
            np.add.at(out, self._triangles[:, k], a)
        return out

    def angles(self) -> np.ndarray:
        """(m, 3) interior angles in radians."""
        c = self.corners()
        out = np.empty((self.n_triangles, 3))
        for k in range(3):
            a = c[:, (k + 1) % 3] - c[:, k]
            b = c[:, (k + 2) % 3] - c[:, k]
            cosang = np.einsum("ij,ij->i", a, b) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1))
            out[:, k] = np.arccos(np.clip(cosang, -1.0, 1.0))
        return out

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        return self._vertices.min(axis=0), self._vertices.max(axis=0)

    def diagonal(self) -> float:
        lo, hi = self.bounds()
        return float(np.linalg.norm(hi - lo))

    def volume(self) -> float:
        """Enclosed volume (meaningful for closed, outward-oriented surfaces)."""
        c = self.corners()
        return float(np.einsum("ij,ij->i", c[:, 0], np.cross(c[:, 1], c[:, 2])).sum() / 6.0)

    # --------------------------------------------------------------- topology
    def edges(self) -> np.ndarray:
        """(k, 2) unique undirected edges, sorted pairs."""
        if "edges" not in self._cache:
            self._cache["edges"], self._cache["edge_count"] = _unique_edges(self._triangles)
        return self._cache["edges"]  # type: ignore[return-value]

    def boundary_edges(self) -> np.ndarray:
        self.edges()
        return self._cache["edges"][self._cache["edge_count"] == 1]  # type: ignore[index]

    def used_vertices(self) -> np.ndarray:
        """Indices of the vertices some triangle uses: all of them for a surface mesh; for the
        boundary of a solid (:attr:`TetMesh.surface`), the surface nodes, not the interior ones."""
        if "used" not in self._cache:
            used = np.zeros(self.n_vertices, bool)
            used[self._triangles.ravel()] = True
            self._cache["used"] = np.flatnonzero(used)
        return self._cache["used"]  # type: ignore[return-value]

    def boundary_vertices(self) -> np.ndarray:
        return np.unique(self.boundary_edges())

    def is_closed(self) -> bool:
        return self.boundary_edges().shape[0] == 0

    def adjacency(self) -> sp.csr_matrix:
        """Vertex adjacency (n, n) with edge lengths as weights."""
        if "adjacency" not in self._cache:
            e = self.edges()
            w = np.linalg.norm(self._vertices[e[:, 0]] - self._vertices[e[:, 1]], axis=1)
            n = self.n_vertices
            A = sp.coo_matrix((np.r_[w, w], (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])), shape=(n, n))
            self._cache["adjacency"] = A.tocsr()
        return self._cache["adjacency"]  # type: ignore[return-value]

    def components(self) -> tuple[int, np.ndarray]:
        """Number of connected components and the component label of each vertex."""
        return connected_components(self.adjacency(), directed=False)

    def nearest_vertex(self, point: np.ndarray) -> int:
        """Index of the vertex closest to ``point`` among those a triangle uses (:meth:`used_vertices`)."""
        if "kdtree" not in self._cache:
            self._cache["kdtree"] = cKDTree(self._vertices[self.used_vertices()])
        local = int(self._cache["kdtree"].query(np.asarray(point, dtype=float))[1])  # type: ignore[union-attr]
        return int(self.used_vertices()[local])

    # -------------------------------------------------------------- derived
    def scaled(self, factor: float) -> "TriMesh":
        """A copy with coordinates multiplied by ``factor`` (e.g. 1e-3 for mm -> m)."""
        factor = validate.positive(factor, "factor", "a scale factor", error=MeshError)
        return TriMesh(self._vertices * factor, self._triangles, repair=False, groups=self.groups)

    def subdivided(self, levels: int = 1) -> "TriMesh":
        """Each triangle split into 4 by its edge mid-points, ``levels`` times (groups carried)."""
        levels = validate.count(levels, "levels", 0, 8, error=MeshError)
        if self.n_triangles * 4**levels > 20_000_000:
            raise MeshError(f"{levels} subdivisions of {self.n_triangles} triangles would exceed 20,000,000 triangles")
        V, T, groups = self._vertices, self._triangles, dict(self.groups)
        for _ in range(levels):
            edges, inverse = _edge_index(T)
            mids = 0.5 * (V[edges[:, 0]] + V[edges[:, 1]])
            n = V.shape[0]
            e = inverse.reshape(-1, 3) + n  # edges (0-1), (1-2), (2-0)
            a, b, c = T[:, 0], T[:, 1], T[:, 2]
            T = np.concatenate(
                [
                    np.stack([a, e[:, 0], e[:, 2]], 1),
                    np.stack([e[:, 0], b, e[:, 1]], 1),
                    np.stack([e[:, 2], e[:, 1], c], 1),
                    np.stack([e[:, 0], e[:, 1], e[:, 2]], 1),
                ]
            )
            for name, idx in groups.items():
                inside = np.zeros(n, bool)
                inside[idx] = True
                both = inside[edges[:, 0]] & inside[edges[:, 1]]
                groups[name] = np.r_[idx, n + np.flatnonzero(both)]
            V = np.vstack([V, mids])
        return TriMesh(V, T, repair=False, groups=groups)


# ---------------------------------------------------------------- helpers
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


def _edge_index(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unique sorted edges and, for each triangle side (0-1, 1-2, 2-0), its edge number."""
    e = np.stack([T[:, [0, 1]], T[:, [1, 2]], T[:, [2, 0]]], axis=1).reshape(-1, 2)
    e = np.sort(e, axis=1)
    edges, inverse = np.unique(e, axis=0, return_inverse=True)
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
        pairs = cKDTree(reps).query_pairs(tol, output_type="ndarray")
    else:
        pairs = np.zeros((0, 2), dtype=np.int64)
    k = first.size
    if pairs.shape[0]:
        G = sp.coo_matrix((np.ones(pairs.shape[0]), (pairs[:, 0], pairs[:, 1])), shape=(k, k))
        _, label = connected_components(G, directed=False)
    else:
        label = np.arange(k)
    label = label[cell]
    # representative of each class: its lowest index
    rep = np.full(int(label.max()) + 1, n, dtype=np.int64)
    np.minimum.at(rep, label, np.arange(n))
    return rep[label]


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
    _, first = np.unique(np.sort(T, axis=1), axis=0, return_index=True)
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
        edges, inv = np.unique(np.sort(e_dir, axis=1), axis=0, return_inverse=True)
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
    number of components, orientable). One breadth-first walk over every component at once."""
    t1, t2 = he.t1, he.t2
    same = he.e_dir[he.h1, 0] == he.e_dir[he.h2, 0]  # same direction -> inconsistent orientation
    G = sp.coo_matrix((np.ones(t1.size), (t1, t2)), shape=(m, m)).tocsr()
    G = G + G.T
    n_comp, label = connected_components(G, directed=False)
    # sign relation between adjacent triangles: flip[t2] = flip[t1] xor same
    rel = sp.coo_matrix((np.r_[same, same].astype(np.int8) + 1, (np.r_[t1, t2], np.r_[t2, t1])), shape=(m, m)).tocsr()
    # a virtual root (index m) joined to one triangle of each component: O(m) however many pieces
    _, roots = np.unique(label, return_index=True)
    Gc = G.tocoo()
    Gr = sp.coo_matrix((np.ones(Gc.nnz + roots.size), (np.r_[Gc.row, np.full(roots.size, m)], np.r_[Gc.col, roots])),
                       shape=(m + 1, m + 1)).tocsr()
    bfs, pred = breadth_first_order(Gr, m, directed=False, return_predecessors=True)
    child = bfs[1:]
    parent = pred[child]
    inner = parent != m
    child, parent = child[inner], parent[inner]
    s_rel = (np.asarray(rel[parent, child]).ravel() == 2) if child.size else np.zeros(0, bool)
    flip = np.zeros(m, bool)
    for c_, p_, si in zip(child.tolist(), parent.tolist(), s_rel.tolist()):  # in BFS order: parents first
        flip[c_] = flip[p_] ^ si
    orientable = bool(((flip[t1] ^ flip[t2]) == same).all())
    return flip, label, int(n_comp), orientable


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
    _, fan = connected_components(sp.coo_matrix((np.ones(ca.size), (ca, cb)), shape=(3 * m, 3 * m)), directed=False)
    pairs = np.unique(np.stack([T.ravel(), fan], axis=1), axis=0)
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
