"""TetMesh: a validated tetrahedral volume mesh (linear or quadratic) and its boundary surface.

Node order of a tetrahedron follows VTK (and meshio): corners 0-3 with a positive volume
det[x1 - x0, x2 - x0, x3 - x0] / 6, then for a 10-node tet the mid-edge nodes of the edges
(0,1), (1,2), (0,2), (0,3), (1,3), (2,3). The boundary surface is a :class:`TriMesh` over the
same node numbering (interior nodes are vertices no triangle uses), so a displacement field
of the solid draws and is touched on the surface without any index map.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Mapping

import numpy as np
import scipy.sparse as sp

from .. import validate
from ..errors import MeshError
from .repair import _check_finite_and_in_range, _check_groups, _integer_cells, _listing, _merge_classes, components, unique_rows
from .surface import TriMesh

__all__ = ["TetMesh", "TetReport", "TetQuality", "TET10_EDGES", "TET_FACES"]

# the mid-edge nodes of a 10-node tet, in VTK order: the corners each one sits between
TET10_EDGES = np.array([[0, 1], [1, 2], [0, 2], [0, 3], [1, 3], [2, 3]])
# the faces of a positively oriented tet, each with its normal pointing out of the tet
TET_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])
# swapping corners 1 and 2 turns a tet inside out; for 10 nodes the mid-edge nodes follow
_FLIP = np.array([0, 2, 1, 3, 6, 5, 4, 7, 9, 8])


@dataclass
class TetReport:
    """What validation found and what it repaired."""

    n_nodes_in: int = 0
    n_tets_in: int = 0
    merged_nodes: int = 0
    removed_degenerate: int = 0
    removed_duplicate_tets: int = 0
    dropped_unreferenced: int = 0
    flipped_tets: int = 0
    n_components: int = 1
    n_boundary_faces: int = 0
    notes: list[str] = field(default_factory=list)

    @property
    def repaired(self) -> bool:
        return bool(self.merged_nodes or self.removed_degenerate or self.removed_duplicate_tets
                    or self.dropped_unreferenced or self.flipped_tets)

    def __str__(self) -> str:
        lines = [f"tet mesh: {self.n_nodes_in} nodes, {self.n_tets_in} tets read"]
        for count, what in ((self.merged_nodes, "duplicate nodes merged"),
                            (self.removed_degenerate, "zero-volume tets removed"),
                            (self.removed_duplicate_tets, "duplicate tets removed"),
                            (self.dropped_unreferenced, "unreferenced nodes dropped"),
                            (self.flipped_tets, "inverted tets re-oriented")):
            if count:
                lines.append(f"  repaired: {count} {what}")
        lines.append(f"  {self.n_components} connected piece(s), {self.n_boundary_faces} boundary faces")
        lines += [f"  {n}" for n in self.notes]
        return "\n".join(lines)


@dataclass(frozen=True)
class TetQuality:
    """Element quality: volumes, dihedral angles (degrees) and the radius ratio
    3 r_in / r_circ (1 for the regular tet, 0 for a flat one) of every corner tet."""

    volumes: np.ndarray
    min_dihedral: np.ndarray
    max_dihedral: np.ndarray
    radius_ratio: np.ndarray

    def __str__(self) -> str:
        v, rr = self.volumes, self.radius_ratio
        return (f"volume {v.sum():.4g} (tets {v.min():.3g} .. {v.max():.3g}); dihedral angles "
                f"{self.min_dihedral.min():.1f} .. {self.max_dihedral.max():.1f} deg; radius ratio min "
                f"{rr.min():.3f}, median {np.median(rr):.3f}, {int(np.sum(rr < 0.1))} tets below 0.1")


class TetMesh:
    """A validated tetrahedral volume mesh in 3D (4-node or 10-node tets).

    Parameters
    ----------
    vertices : (n, 3) node coordinates.
    tets : (m, 4) or (m, 10) node indices (VTK order, see the module docstring).
    repair : merge duplicate nodes (within ``merge_tol`` of the bounding-box diagonal), remove
        zero-volume and duplicate tets, drop unreferenced nodes and re-orient inverted tets;
        the changes are listed in :attr:`report` and :attr:`vertex_map` maps input node indices
        to the repaired ones (-1 for dropped nodes). With ``repair=False`` a mesh that needs
        any of it is refused with the place named.
    groups : optional named node sets (indices into the input nodes).
    labels : optional (m,) integer region label of each tet (a segmentation's label, a Gmsh physical
        group, a MEDIT reference): a :class:`~rtfem.SolidModel` takes a material per label. Default:
        every tet in region 0. Repair keeps each kept tet's label.
    region_names : optional {name: label}, the regions' names (e.g. ``{"liver": 1, "tumor": 2}``), by
        which a model's materials may be given.

    Raises
    ------
    MeshError : empty mesh, non-finite coordinates, out-of-range or non-integer indices,
        faces shared by more than two tets (overlapping elements), labels that are not one
        integer per tet, names that name no label.
    """

    def __init__(self, vertices, tets, *, repair: bool = True, merge_tol: float = 1e-10,
                 groups: Mapping[str, np.ndarray] | None = None, labels=None,
                 region_names: Mapping[str, int] | None = None, _changed=None) -> None:
        repair = validate.flag(repair, "repair", error=MeshError)
        merge_tol = validate.in_range(merge_tol, "merge_tol", 0.0, 1.0, hi_open=True,
                                      what="a fraction of the bounding-box diagonal", error=MeshError)
        V, T = _check_arrays(vertices, tets)
        labels = _check_labels(labels, T.shape[0])
        groups = _check_groups(groups, V.shape[0])
        report = TetReport(n_nodes_in=V.shape[0], n_tets_in=T.shape[0])
        if _changed is not None:  # a cut's mesh (rtfem.mesh.cut): checked where it changed, see _check_near
            _check_near(V, T, _changed[0])
            vmap, kept = np.arange(V.shape[0]), np.arange(T.shape[0])
        else:
            V, T, vmap, kept = _repair(V, T, merge_tol, report, repair)
            T = _orient(V, T, report, repair)
        self._vertices, self._tets, self._labels = V, T, np.ascontiguousarray(labels[kept])
        for a in (V, T, self._labels):
            a.flags.writeable = False
        self.region_names = _check_names(region_names, self._labels)
        self.vertex_map = vmap
        self.report = report
        self.groups: dict[str, np.ndarray] = {}
        for name, idx in (groups or {}).items():
            mapped = vmap[idx]
            self.groups[name] = np.unique(mapped[mapped >= 0])
        self._cache: dict[str, object] = {}
        if _changed is not None:
            report.n_boundary_faces = int(np.sum(self._faces()[2] == 1))
            report.n_components = int(_changed[1])
            return
        self._check_faces()
        report.n_components = self.components()[0]

    # ------------------------------------------------------------------ arrays
    @property
    def vertices(self) -> np.ndarray:
        """(n, 3) node coordinates (read-only)."""
        return self._vertices

    @property
    def tets(self) -> np.ndarray:
        """(m, 4) or (m, 10) node indices (read-only)."""
        return self._tets

    @property
    def labels(self) -> np.ndarray:
        """(m,) the region label of each tet (read-only; all 0 unless given)."""
        return self._labels

    @property
    def regions(self) -> np.ndarray:
        """The distinct region labels, ascending."""
        return np.unique(self._labels)

    def _same(self, vertices, tets, **options) -> "TetMesh":
        """A mesh of these regions (labels and names) over other nodes or node numbering."""
        return TetMesh(vertices, tets, labels=self._labels, region_names=self.region_names, **options)

    @property
    def corner_tets(self) -> np.ndarray:
        """(m, 4) the corner nodes of each tet."""
        return self._tets[:, :4]

    @property
    def order(self) -> int:
        """1 for 4-node tets, 2 for 10-node tets."""
        return 1 if self._tets.shape[1] == 4 else 2

    @property
    def n_vertices(self) -> int:
        return self._vertices.shape[0]

    n_nodes = n_vertices

    @property
    def n_tets(self) -> int:
        return self._tets.shape[0]

    def __repr__(self) -> str:
        return (f"TetMesh({self.n_vertices} nodes, {self.n_tets} tets of {self._tets.shape[1]} nodes, "
                f"{self.surface.n_triangles} boundary triangles, volume {self.volume():.4g})")

    # ------------------------------------------------------------------ geometry
    def volumes(self) -> np.ndarray:
        """(m,) signed volumes of the corner tets (positive after validation)."""
        return _signed_volumes(self._vertices, self.corner_tets)

    def volume(self) -> float:
        return float(self.volumes().sum())

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        return self._vertices.min(axis=0), self._vertices.max(axis=0)

    def diagonal(self) -> float:
        lo, hi = self.bounds()
        return float(np.linalg.norm(hi - lo))

    def quality(self) -> TetQuality:
        """Volumes, dihedral angles and radius ratios of the corner tets."""
        c = self._vertices[self.corner_tets]
        vol = _signed_volumes(self._vertices, self.corner_tets)
        # outward face normals with |n| = face area
        normals = np.stack([0.5 * np.cross(c[:, f[1]] - c[:, f[0]], c[:, f[2]] - c[:, f[0]]) for f in TET_FACES], axis=1)
        areas = np.linalg.norm(normals, axis=2)
        unit = normals / np.maximum(areas, 1e-300)[:, :, None]
        pairs = [(i, j) for i in range(4) for j in range(i + 1, 4)]
        dihedral = np.degrees(np.pi - np.arccos(np.clip(np.stack(
            [np.einsum("ij,ij->i", unit[:, i], unit[:, j]) for i, j in pairs], axis=1), -1, 1)))
        r_in = 3.0 * vol / np.maximum(areas.sum(axis=1), 1e-300)
        r_circ = _circumradius(c)
        return TetQuality(vol, dihedral.min(axis=1), dihedral.max(axis=1), 3.0 * r_in / np.maximum(r_circ, 1e-300))

    # ------------------------------------------------------------------ topology
    def _faces(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """All (4m, 3) outward corner faces, the unique sorted faces' index per face, and the counts."""
        if "faces" not in self._cache:
            F = self.corner_tets[:, TET_FACES].reshape(-1, 3)
            _, inverse, count = unique_rows(np.sort(F, axis=1), return_inverse=True, return_counts=True)
            self._cache["faces"] = (F, inverse.ravel(), count)
        return self._cache["faces"]  # type: ignore[return-value]

    def _check_faces(self) -> None:
        F, inverse, count = self._faces()
        over = np.flatnonzero(count > 2)
        if over.size:
            k = int(np.flatnonzero(inverse == over[0])[0])
            tets = np.flatnonzero(np.isin(inverse, over[0]).reshape(-1, 4).any(axis=1))
            raise MeshError(
                f"{over.size} faces are shared by more than two tets (overlapping elements); the first, nodes "
                f"{sorted(F[k].tolist())}, belongs to tets {_listing(tets)}. Re-mesh the volume "
                "(rt.tetrahedralize) or remove the overlapping tets")
        self.report.n_boundary_faces = int(np.sum(count == 1))
        self._check_folds(F, inverse, count)
        if self.order == 2:
            self._check_conforming()

    def _check_folds(self, F: np.ndarray, inverse: np.ndarray, count: np.ndarray) -> None:
        """Refuse a tangled mesh: two tets on the same side of the face they share (a fold, which
        re-orienting the inverted tets cannot undo: they then overlap). Each face's outward
        normal from one tet must be opposite to the one from the other."""
        inner = np.flatnonzero(count[inverse] == 2)
        if not inner.size:
            return
        order = inner[np.argsort(inverse[inner], kind="stable")]
        a, b = order[0::2], order[1::2]  # the two sides of each interior face
        V = self._vertices

        def normal(k):
            P = V[F[k]]
            return np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0])

        na, nb = normal(a), normal(b)
        size = np.linalg.norm(na, axis=1) * np.linalg.norm(nb, axis=1)
        same = np.einsum("ij,ij->i", na, nb) > 1e-9 * size
        if same.any():
            k = int(np.flatnonzero(same)[0])
            raise MeshError(f"the mesh is tangled: at {int(same.sum())} interior faces both tets lie on the same side "
                            f"(a fold), e.g. tets {int(a[k] // 4)} and {int(b[k] // 4)} at the face of nodes "
                            f"{sorted(F[a[k]].tolist())}. Re-orienting cannot undo a fold (the tets would overlap): "
                            "re-mesh the volume (rt.tetrahedralize) or untangle it in the mesher")

    def _check_conforming(self) -> None:
        """Refuse 10-node tets that share a corner edge but not its mid-edge node."""
        e = np.sort(self._tets[:, TET10_EDGES].reshape(-1, 2), axis=1)
        mids = self._tets[:, 4:].reshape(-1)
        keys = e[:, 0] * self.n_vertices + e[:, 1]
        order = np.lexsort((mids, keys))
        k, m = keys[order], mids[order]
        bad = np.flatnonzero((k[1:] == k[:-1]) & (m[1:] != m[:-1]))
        if bad.size:
            i, j = order[bad[0]], order[bad[0] + 1]
            raise MeshError(f"the 10-node tets are not conforming: tets {int(i // 6)} and {int(j // 6)} share the corner "
                            f"edge {e[i].tolist()} but not its mid-edge node ({int(mids[i])} and {int(mids[j])}), so the "
                            "mesh would tear there. Export the mesh again, or rebuild it: mesh.linear().quadratic()")

    @property
    def boundary_faces(self) -> np.ndarray:
        """(f, 3) the corner faces that belong to one tet only, oriented outward."""
        F, inverse, count = self._faces()
        return F[count[inverse] == 1]

    @property
    def surface(self) -> TriMesh:
        """The boundary surface as a TriMesh over this mesh's node numbering (interior nodes and, for
        10-node tets, mid-edge nodes are vertices no triangle uses). What is drawn and touched."""
        if "surface" not in self._cache:
            try:
                S = TriMesh(self._vertices, self.boundary_faces, repair=False, groups=self.groups)
            except MeshError as exc:
                raise MeshError(f"the boundary of the tet mesh is not a usable surface: {exc}") from None
            if self.order == 2:  # each triangle's mid-edge nodes (edges 01, 12, 20): its 6-node face
                e = np.sort(self._tets[:, TET10_EDGES].reshape(-1, 2), axis=1)
                n = self.n_vertices
                keys, first = np.unique(e[:, 0] * n + e[:, 1], return_index=True)
                mids = self._tets[:, 4:].ravel()[first]
                T = S.triangles
                a, b = T, np.roll(T, -1, axis=1)
                S.mid_nodes = mids[np.searchsorted(keys, np.minimum(a, b) * n + np.maximum(a, b))]
            self._cache["surface"] = S
        return self._cache["surface"]  # type: ignore[return-value]

    def surface_nodes(self) -> np.ndarray:
        """Indices of the nodes on the boundary surface."""
        return np.unique(self.boundary_faces)

    def edges(self) -> np.ndarray:
        """(e, 2) unique corner edges."""
        if "edges" not in self._cache:
            c = self.corner_tets
            e = np.sort(c[:, TET10_EDGES].reshape(-1, 2), axis=1)
            self._cache["edges"] = unique_rows(e)
        return self._cache["edges"]  # type: ignore[return-value]

    def adjacency(self) -> sp.csr_matrix:
        """Node adjacency (n, n): nodes that share a tet, weighted by distance."""
        if "adjacency" not in self._cache:
            k = self._tets.shape[1]
            i, j = np.triu_indices(k, 1)
            e = unique_rows(np.sort(np.stack([self._tets[:, i].ravel(), self._tets[:, j].ravel()], axis=1), axis=1))
            w = np.linalg.norm(self._vertices[e[:, 0]] - self._vertices[e[:, 1]], axis=1)
            n = self.n_vertices
            A = sp.coo_matrix((np.r_[w, w], (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])), shape=(n, n))
            self._cache["adjacency"] = A.tocsr()
        return self._cache["adjacency"]  # type: ignore[return-value]

    def components(self) -> tuple[int, np.ndarray]:
        """Number of connected pieces and the piece label of each node (kept: a cut model's are asked by its
        system's check in the cut worker and again by the driver built on it)."""
        if "components" not in self._cache:
            A = self.adjacency().tocoo()
            self._cache["components"] = components(self.n_vertices, A.row, A.col)
        n, label = self._cache["components"]  # type: ignore[misc]
        return n, label.copy()

    # ------------------------------------------------------------------ derived
    def scaled(self, factor: float) -> "TetMesh":
        """A copy with coordinates multiplied by ``factor`` (e.g. 1e-3 for mm -> m)."""
        factor = validate.positive(factor, "scale", "a length factor, e.g. 1e-3 for mm", error=MeshError)
        return self._same(self._vertices * factor, self._tets, repair=False, groups=self.groups)

    def quadratic(self) -> "TetMesh":
        """The 10-node version: a node added at the middle of each corner edge (straight edges).
        A group gains the mid-edge nodes of the edges whose both ends are in it (a clamped face
        stays clamped). A 10-node mesh is returned as it is."""
        if self.order == 2:
            return self
        c = self.corner_tets
        e = np.sort(c[:, TET10_EDGES].reshape(-1, 2), axis=1)
        edges, inverse = unique_rows(e, return_inverse=True)
        mid = 0.5 * (self._vertices[edges[:, 0]] + self._vertices[edges[:, 1]])
        T = np.column_stack([c, self.n_vertices + inverse.reshape(-1, 6)])
        groups = {}
        for name, idx in self.groups.items():
            inside = np.zeros(self.n_vertices, bool)
            inside[idx] = True
            both = np.flatnonzero(inside[edges[:, 0]] & inside[edges[:, 1]])
            groups[name] = np.concatenate([np.asarray(idx, dtype=np.int64), self.n_vertices + both])
        # merge_tol 0: a cut mesh's twin nodes stay apart
        return self._same(np.vstack([self._vertices, mid]), T, repair=False, merge_tol=0.0, groups=groups)

    def linear(self) -> "TetMesh":
        """The 4-node mesh of the corners (mid-edge nodes dropped and the nodes renumbered;
        :attr:`vertex_map` of the result maps this mesh's nodes to it)."""
        if self.order == 1:
            return self
        return self._same(self._vertices, self.corner_tets, repair=True, merge_tol=0.0, groups=self.groups)

    def fingerprint(self) -> str:
        """A short hash of the node coordinates and the tets (what saved results are checked against)."""
        import hashlib

        h = hashlib.sha1()
        h.update(np.ascontiguousarray(self._vertices).tobytes())
        h.update(np.ascontiguousarray(self._tets, dtype=np.int64).tobytes())
        if self._labels.any():  # a mesh of one region 0 keeps the fingerprint it had before labels
            h.update(np.ascontiguousarray(self._labels, dtype=np.int64).tobytes())
        return h.hexdigest()[:16]


# ---------------------------------------------------------------------- helpers
def _signed_volumes(V: np.ndarray, T: np.ndarray) -> np.ndarray:
    c = V[T[:, :4]]
    return np.einsum("ij,ij->i", np.cross(c[:, 1] - c[:, 0], c[:, 2] - c[:, 0]), c[:, 3] - c[:, 0]) / 6.0


def _circumradius(c: np.ndarray) -> np.ndarray:
    a, b, d = c[:, 1] - c[:, 0], c[:, 2] - c[:, 0], c[:, 3] - c[:, 0]
    num = (np.einsum("ij,ij->i", a, a)[:, None] * np.cross(b, d) + np.einsum("ij,ij->i", b, b)[:, None] * np.cross(d, a)
           + np.einsum("ij,ij->i", d, d)[:, None] * np.cross(a, b))
    den = 2.0 * np.einsum("ij,ij->i", a, np.cross(b, d))
    return np.linalg.norm(num, axis=1) / np.maximum(np.abs(den), 1e-300)


def _check_near(V: np.ndarray, T: np.ndarray, changed: np.ndarray) -> None:
    """A mesh derived from a valid one by changing the tets ``changed`` (a mask; the others kept, node for
    node: a cut's) checked as ``TetMesh(V, T, repair=False, merge_tol=0)`` checks it, on the changed tets and
    those sharing a node with them: every refusal (a degenerate, inverted or duplicate tet, a face of three
    tets, a fold, a tet10 edge not shared) involves a changed tet and all the tets on its nodes. A scalpel's
    strip cut from the 9k-tet liver so checks a few hundred tets, not all: its construction 36-50 -> 21-22 ms,
    most of it the element faces, which its surface takes next. A refusal is made again on the whole mesh, for
    its message's numbers."""
    touched = np.zeros(V.shape[0], dtype=bool)
    touched[T[changed].ravel()] = True
    near = touched[T].any(axis=1)
    if not near.any():
        return
    nodes, local = np.unique(T[near], return_inverse=True)
    try:
        if (_signed_volumes(V, T[near]) < 0).any():  # (the part alone, all inverted, would be re-oriented whole)
            raise MeshError("an inverted tet about the change")
        TetMesh(V[nodes], local.reshape(-1, T.shape[1]), repair=False, merge_tol=0.0)
    except MeshError:
        TetMesh(V, T, repair=False, merge_tol=0.0)
        raise


def _check_arrays(vertices, tets) -> tuple[np.ndarray, np.ndarray]:
    try:
        V = np.array(vertices, dtype=np.float64, order="C")
    except (TypeError, ValueError) as exc:
        raise MeshError(f"vertices are not a numeric (n, 3) array: {exc}") from None
    try:
        T_raw = np.asarray(tets)
    except (TypeError, ValueError) as exc:
        raise MeshError(f"tets are not an integer (m, 4) array: {exc}") from None
    if V.size == 0 or T_raw.size == 0:
        raise MeshError(f"empty tet mesh ({V.shape[0] if V.ndim else 0} nodes, {T_raw.shape[0] if T_raw.ndim else 0} "
                        "tets): a solid model needs at least one tetrahedron")
    if V.ndim != 2 or V.shape[1] != 3:
        raise MeshError(f"vertices must be an (n, 3) array, got shape {V.shape}")
    if T_raw.ndim != 2 or T_raw.shape[1] not in (4, 10):
        raise MeshError(f"tets must be an (m, 4) or (m, 10) array of node indices, got shape {T_raw.shape}")
    T = _integer_cells(T_raw, "tet node indices")
    _check_finite_and_in_range(V, T, ("node", "nodes"), "tet")
    return V, T


def _degenerate(V: np.ndarray, T: np.ndarray) -> np.ndarray:
    """Tets with a repeated node or a (numerically) zero volume."""
    rep = np.zeros(T.shape[0], bool)
    for i in range(T.shape[1]):
        for j in range(i + 1, T.shape[1]):
            rep |= T[:, i] == T[:, j]
    c = V[T[:, :4]]
    lmax = np.max(np.linalg.norm(c[:, [1, 2, 3, 2, 3, 3]] - c[:, [0, 0, 0, 1, 1, 2]], axis=2), axis=1)
    return rep | (np.abs(_signed_volumes(V, T)) <= 1e-12 * lmax**3)


def _repair(V: np.ndarray, T: np.ndarray, merge_tol: float, report: TetReport, repair: bool):
    """The repaired nodes and tets, the input nodes' new indices and the input tets kept."""
    n_in = V.shape[0]
    kept = np.arange(T.shape[0])
    if repair:
        diag = float(np.linalg.norm(V.max(axis=0) - V.min(axis=0)))
        merge = _merge_classes(V, merge_tol * (diag if diag > 0 else 1.0)) if merge_tol > 0 else np.arange(n_in)
        report.merged_nodes = int(np.sum(merge != np.arange(n_in)))
        T = merge[T]
    else:
        merge = np.arange(n_in)
        diag = float(np.linalg.norm(V.max(axis=0) - V.min(axis=0)))
        same = _merge_classes(V, merge_tol * (diag if diag > 0 else 1.0)) if merge_tol > 0 else merge
        if np.any(same != merge):
            i = int(np.flatnonzero(same != merge)[0])
            raise MeshError(f"nodes {int(same[i])} and {i} coincide (within {merge_tol:g} of the mesh's size): the tets "
                            "on each would not be joined; pass repair=True to merge them")
    deg = _degenerate(V, T)
    if deg.any():
        if not repair:
            k = int(np.flatnonzero(deg)[0])
            raise MeshError(f"degenerate (zero-volume or repeated-node) tet {_listing(np.flatnonzero(deg))}: nodes "
                            f"{T[k].tolist()}; pass repair=True to remove them, or re-mesh")
        report.removed_degenerate = int(deg.sum())
        T, kept = T[~deg], kept[~deg]
        if T.shape[0] == 0:
            raise MeshError("every tet is degenerate (zero volume): the mesh has no usable volume")
    _, first = unique_rows(np.sort(T[:, :4], axis=1), return_index=True)
    if first.size < T.shape[0]:
        if not repair:
            dup = np.setdiff1d(np.arange(T.shape[0]), first)
            raise MeshError(f"duplicate tet {_listing(dup)} (same four corners as another); pass repair=True to remove them")
        report.removed_duplicate_tets = int(T.shape[0] - first.size)
        T, kept = T[np.sort(first)], kept[np.sort(first)]
    used = np.zeros(n_in, bool)
    used[T.ravel()] = True
    if not repair or used.all():
        return V, T, merge, kept
    new_index = np.full(n_in, -1, dtype=np.int64)
    new_index[used] = np.arange(int(used.sum()))
    report.dropped_unreferenced = int(n_in - report.merged_nodes - used.sum())
    return V[used], new_index[T], new_index[merge], kept


def _check_labels(labels, m: int) -> np.ndarray:
    """(m,) int64 region labels (zeros when None)."""
    if labels is None:
        return np.zeros(m, dtype=np.int64)
    try:
        raw = np.asarray(labels)
    except (TypeError, ValueError) as exc:
        raise MeshError(f"labels are not an integer array: {exc}") from None
    if raw.shape != (m,):
        raise MeshError(f"labels must be one integer per tet, shape ({m},), got shape {raw.shape}")
    if raw.dtype.kind == "f" and np.all(np.isfinite(raw)) and np.all(raw == np.round(raw)):
        raw = raw.astype(np.int64)
    if raw.dtype.kind not in "iu" or (raw.size and (raw.min() < -2**31 or raw.max() >= 2**31)):
        raise MeshError(f"labels must be integers (of 32 bits), got {raw.dtype} values "
                        f"{validate.show(raw[:3].tolist())}...: a label map's region numbers")
    return raw.astype(np.int64)


def _check_names(names, labels: np.ndarray) -> dict[str, int]:
    """{name: label} for labels the mesh has (names of labels no tet carries are dropped)."""
    import unicodedata

    if names is None:
        return {}
    if not isinstance(names, Mapping):
        raise MeshError(f"region_names={validate.show(names)} must be a mapping {{name: label}}")
    out, present = {}, set(np.unique(labels).tolist())
    for name, label in names.items():
        if not isinstance(name, str) or not name or isinstance(label, bool) or not isinstance(label, (int, np.integer)):
            raise MeshError(f"region_names: {validate.show(name)} = {validate.show(label)} must be a name (a string) "
                            "and an integer label")
        if len(name) > 200 or any(unicodedata.category(c) in ("Cc", "Cf", "Zl", "Zp") for c in name):
            raise MeshError(f"region_names: {ascii(name[:60])} is not a region name: give at most 200 characters with no "
                            "control, formatting (bidirectional, zero-width) or line-break character (rename the region "
                            "in the file)")
        if int(label) in present:
            out[name] = int(label)
    return out


def _orient(V: np.ndarray, T: np.ndarray, report: TetReport, repair: bool) -> np.ndarray:
    neg = _signed_volumes(V, T) < 0
    if not neg.any():
        return T
    if neg.all():
        # a mesher writing the other handedness: every tet inverted the same way
        report.notes.append("note: every tet came with the opposite orientation; all were re-oriented")
    elif not repair:
        raise MeshError(f"inverted tet {_listing(np.flatnonzero(neg))} (negative volume) among positive ones; "
                        "pass repair=True to re-orient them")
    T = T.copy()
    flip = _FLIP[:T.shape[1]]
    T[neg] = T[neg][:, flip]
    report.flipped_tets = int(neg.sum())
    return T
