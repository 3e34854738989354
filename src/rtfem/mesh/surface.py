"""Triangle surface meshes: validated arrays, repair with a report, topology queries.

File input and output live in :mod:`rtfem.mesh.files` (``load_mesh``, ``save_mesh``); this module holds the
in-memory mesh and its checks.
"""

from __future__ import annotations

from typing import Mapping

import numpy as np
import scipy.sparse as sp

from .. import validate
from ..errors import MeshError
from .repair import (MeshReport, _check_arrays, _check_groups, _check_manifold_edges, _edge_index, _orient,
                     _refuse_unrepaired, _repair, _unique_edges, components)

__all__ = ["TriMesh"]

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
        A = self.adjacency().tocoo()
        return components(self.n_vertices, A.row, A.col)

    def nearest_vertex(self, point: np.ndarray) -> int:
        """Index of the vertex closest to ``point`` among those a triangle uses (:meth:`used_vertices`)."""
        if "kdtree" not in self._cache:
            from scipy.spatial import cKDTree  # here: importing scipy.spatial is 40 ms that loading a mesh need not pay

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
