"""Cutting a solid along a triangulated surface (issue 57): the tets on the two sides of every element face that lies
in the surface are separated there, by giving each node as many copies as there are groups of its tets still joined
through uncut faces around it (the cut's front, where the surface ends inside the solid, keeps its nodes shared, so
the slit closes there as a crack's does).

The cut follows element faces. Where the surface passes through elements, the nearer end of each edge it crosses is
first moved onto it (node snapping, :func:`_snap`; no tet keeps under :data:`MIN_VOLUME` of its volume, else the
surface is refused with the elements named). Nothing is removed: the mass and the volume stay, and the new faces are
surface (contact, drawing and export see them). With ``snap="split"`` (tet4, tet10) the crossed elements are split
instead and no node moves by more than :data:`MIN_SPLIT` of an edge (what a solid cut while it runs needs). Splitting
by virtual nodes (Molino, Bao and Fedkiw 2004), which leaves no slivers, is a later step.

A model is cut by :func:`rtfem.fe.cut.cut` (``rt.cut``). The tests: a slit cantilever's frequencies against
CalculiX's on a mesh built slit (tests/verification/test_cut.py); a bent surface (test_cut_curved.py).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from .. import validate
from ..errors import ModelError
from .repair import components, unique_rows
from .tetmesh import TET10_EDGES, TET_FACES, TetMesh, _signed_volumes

__all__ = ["cut_mesh", "CutInfo", "NothingToCut", "extend", "on_surface"]

# a tet10's mid-edge nodes (VTK order) on each face of TET_FACES (the face opposite corner i)
_FACE_MIDS = np.array([[5, 9, 8], [6, 9, 7], [4, 8, 7], [4, 5, 6]])
_TOL = 1e-7  # of the mesh's bounding-box diagonal: a point this near the surface is on it ...
#: ... or this share of the median element edge, if more: the cut surface's thickness (a surface
#: drawn in pieces, a scalpel's strips, is not exactly flat where they meet)
ON_SURFACE = 0.02
#: a face with its corners on the surface is in it if its midpoints are within this share of the median edge: it may bend
#: in an element (the scalpel's strips on the hanging tet10 liver, 2-7 % of an edge off such faces' midpoints: no cut)
BEND = 0.1
#: an edge is split no nearer its end than this share of it: nearer, that end moves onto the surface
MIN_SPLIT = 0.2


class NothingToCut(ModelError):
    """The surface cuts no element face inside the solid (a scalpel's strips not yet whole faces)."""


class CutInfo(dict):
    """What :func:`cut_mesh` did: ``faces`` (element faces cut), ``nodes_added`` (copies made),
    ``parent`` (for each node of the cut mesh, the node it copies), ``pieces`` (separate parts
    of the cut mesh), ``piece`` (each node's part), ``moved`` (nodes moved onto the surface),
    ``max_move`` (the longest move of a corner node, m), ``uncut`` (n, the node count before), ``rows``
    (where nodes moved or were added: their interpolation in the uncut tet each lies in) and ``split`` (the
    edges (s, 2) split by a node added on the surface, in order: node n + k of the mesh before the
    copies is on edge k) with ``split_at`` (where along each edge: 0 at its first end, 1 at its
    second); :meth:`transfer` is the interpolation from the old nodes to the new."""

    __getattr__ = dict.__getitem__

    def transfer(self) -> sp.csr_matrix:
        """The interpolation (n_cut, n) from the uncut mesh's nodes to the cut mesh's: a copy's row
        picks its node; a node added or moved (onto the surface) is the interpolation at its place in the
        uncut tet it lies in (``rows``; without them, a node on a split edge (a, b) at s is (1 - s) a + s b),
        so a field of the elements' order stays itself and the transfer lands the old nodes on the new.
        What a running driver's state goes through (DirectSimulator.carry_over)."""
        born, at, parent, n = self["split"], self["split_at"], self["parent"], self["uncut"]
        I = sp.identity(n, format="csr")
        rows: list = []  # the added nodes' rows, each from earlier ones
        for (a, b), s in zip(born.tolist(), at.tolist()):
            ra, rb = (I[a] if a < n else rows[a - n]), (I[b] if b < n else rows[b - n])
            rows.append((1.0 - s) * ra + s * rb)
        out = sp.vstack([I, *rows], format="csr")
        given = self.get("rows")  # the added and moved nodes' interpolation in their uncut tet
        if given is not None:
            keep = np.ones(out.shape[0])
            keep[np.unique(given.tocoo().row)] = 0.0
            out = (sp.diags(keep) @ out + given).tocsr()
        return out[parent]


def _surface(vertices, triangles) -> np.ndarray:
    """The cut surface's triangles (m, 3, 3), checked."""
    P = validate.real_array(vertices, "vertices", ndim=2, error=ModelError)
    if P.shape[1] != 3 or P.shape[0] < 3:
        raise ModelError(f"vertices of shape {P.shape}: give the cut surface's vertices as (k, 3) coordinates in metres")
    try:
        T = np.asarray(triangles)
    except Exception:
        raise ModelError(f"triangles={validate.show(triangles)}: give (m, 3) vertex indices") from None
    if T.ndim != 2 or T.shape[1] != 3 or T.shape[0] == 0 or not np.issubdtype(T.dtype, np.integer):
        raise ModelError(f"triangles of shape {T.shape} and type {T.dtype}: give the cut surface's triangles as (m, 3) "
                         "integer vertex indices")
    if T.min() < 0 or T.max() >= P.shape[0]:
        raise ModelError(f"triangles index vertices {int(T.min())}..{int(T.max())}, but there are {P.shape[0]}")
    tri = P[T]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    if not (area > 0).all():
        raise ModelError(f"cut triangle {int(np.flatnonzero(~(area > 0))[0])} has no area: remove degenerate triangles")
    return tri


def _frames(tri: np.ndarray) -> tuple:
    """Each triangle's corner a, edges ab and ac, unit normal and the Gram entries of (ab, ac)."""
    a, ab, ac = tri[:, 0], tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    n = np.cross(ab, ac)
    n /= np.linalg.norm(n, axis=1)[:, None]
    return a, ab, ac, n, (ab * ab).sum(1), (ab * ac).sum(1), (ac * ac).sum(1)


def _inside(e: np.ndarray, frames: tuple, tol: float) -> np.ndarray:
    """(p, m) whether the points e (p, m, 3) (taken from each triangle's corner a) project inside
    each triangle or onto its edges (within ``tol``)."""
    _, ab, ac, _, d00, d01, d11 = frames
    d20, d21 = (e * ab[None]).sum(-1), (e * ac[None]).sum(-1)
    den = d00 * d11 - d01 * d01
    v, w = (d11 * d20 - d01 * d21) / den, (d00 * d21 - d01 * d20) / den
    slack = tol / np.sqrt(np.maximum(d00, d11))  # on a triangle's edge counts: the cut's front
    return (v >= -slack) & (w >= -slack) & (v + w <= 1 + slack)


def on_surface(points: np.ndarray, tri: np.ndarray, tol: float, along: float | None = None) -> np.ndarray:
    """(p,) whether each point (p, 3) lies on one of the triangles (m, 3, 3): within ``tol`` (m) of its
    plane and projecting inside it or within ``along`` (m; default ``tol``) of its edges."""
    on = np.zeros(points.shape[0], dtype=bool)
    reach = max(tol, tol if along is None else along)
    lo, hi = tri.reshape(-1, 3).min(axis=0) - reach, tri.reshape(-1, 3).max(axis=0) + reach
    near_box = np.flatnonzero(((points >= lo) & (points <= hi)).all(axis=1))  # the rest cannot be on it
    frames = _frames(tri)
    a, n = frames[0], frames[3]
    for s in range(0, near_box.size, 512):  # (chunk, m) at a time
        rows = near_box[s:s + 512]
        p = points[rows, None, :] - a[None]
        near = np.abs((p * n[None]).sum(-1)) <= tol
        on[rows] = (near & _inside(p, frames, tol if along is None else along)).any(axis=1)
    return on


def _crossings(P: np.ndarray, Q: np.ndarray, tri: np.ndarray, tol: float) -> tuple[np.ndarray, np.ndarray]:
    """(s,) whether each segment P-Q passes through a triangle (its inside or its edges, within ``tol``), its ends off
    the triangle's plane on opposite sides (by more than ``tol``), and (s,) the first triangle it passes through (-1: none)."""
    out = np.zeros(P.shape[0], dtype=bool)
    first = np.full(P.shape[0], -1)
    frames = _frames(tri)
    a, n = frames[0], frames[3]
    for s in range(0, P.shape[0], 512):
        p, q = P[s:s + 512, None, :], Q[s:s + 512, None, :]
        dp, dq = ((p - a[None]) * n[None]).sum(-1), ((q - a[None]) * n[None]).sum(-1)
        cross = ((dp > tol) & (dq < -tol)) | ((dp < -tol) & (dq > tol))
        t = np.where(cross, dp / np.where(cross, dp - dq, 1.0), 0.0)
        hit = cross & _inside(p + t[..., None] * (q - p) - a[None], frames, tol)
        out[s:s + 512] = hit.any(axis=1)
        first[s:s + 512] = np.where(out[s:s + 512], hit.argmax(axis=1), -1)
    return out, first


def _faces(T: np.ndarray):
    """Every element face: (4E, 3) sorted corners, (4E, j) its node slots in its element (3 corners,
    and a tet10's 3 mid-edge nodes), and the unique faces' index and count."""
    E = T.shape[0]
    corners = T[:, TET_FACES].reshape(-1, 3)
    slots = TET_FACES if T.shape[1] == 4 else np.concatenate([TET_FACES, _FACE_MIDS], axis=1)
    keys = np.sort(corners, axis=1)
    _, index, count = unique_rows(keys, return_inverse=True, return_counts=True)
    return keys, np.tile(slots, (E, 1)), index.ravel(), count


def cut_mesh(mesh, vertices, triangles, *, snap: bool | str = True):
    """The tet mesh ``mesh`` separated along the element faces that lie in the triangulated surface
    (``vertices`` (k, 3) in metres, ``triangles`` (m, 3)): each node of those faces gets one copy per
    group of its tets still joined through uncut faces (see the module).

    Parameters
    ----------
    mesh : an rt.TetMesh (tet4 or tet10).
    vertices, triangles : the cut surface.
    snap : where the surface passes through elements, move nodes onto it first (:func:`_snap`: the
        nearer end of each crossing edge, straight onto the crossed triangle's plane, no tet left
        with under :data:`MIN_VOLUME` of its volume), so that the cut follows their faces; "split"
        (tet4 and tet10): move no node by more than :data:`MIN_SPLIT` of an edge, split the crossed
        elements instead (:func:`_split_edges`, :func:`_split_tet10`: the geometry unchanged, what a
        running simulation needs: a moved node of a deformed solid can turn its elements inside out);
        where snapping cannot move a node (True), the element is split too; False: refuse such a surface.

    Returns
    -------
    (TetMesh, CutInfo): the cut mesh (the old nodes first, in their order, then those split off, then
    the copies; the tets in their order, a split tet's parts in its place; the groups with the copies of their nodes)
    and what was done. Only the tets about the surface are searched and changed (:func:`_zone`).

    Raises
    ------
    ModelError
        A malformed surface; a surface still through the inside of elements after snapping (they are
        named: splitting could not follow it), or with ``snap=False``; one that lies along no element
        face inside the solid.
    """
    V, T = np.asarray(mesh.vertices, dtype=float), np.asarray(mesh.tets)
    tri = _surface(vertices, triangles)
    C = V[T[:, TET10_EDGES]]
    lengths = np.linalg.norm(C[:, :, 1] - C[:, :, 0], axis=2)
    edge = float(np.median(lengths))
    tol = max(_TOL * float(np.linalg.norm(V.max(axis=0) - V.min(axis=0))), ON_SURFACE * edge, 1e-300)
    n0 = mesh.n_vertices
    zone, zn = _zone(V, T, tri, tol + float(lengths.max()))
    if not zone.any():
        raise NothingToCut("the cut surface lies along no element face inside the solid: it misses the solid")
    Vz, moved, born, at, source, parent, T_new, cut, rows = _cut_zone(V[zn], _local(T[zone], zn, n0), tri,
                                                                      (tol, max(tol, BEND * edge)), snap, np.flatnonzero(zone))
    z = zn.size
    glob = np.concatenate([zn, n0 + np.arange(Vz.shape[0] - z)])  # the zone's nodes (and those split) -> the mesh's
    Vn = np.concatenate([V, Vz[z:]])
    Vn[zn] = Vz[:z]
    parent = np.concatenate([np.arange(Vn.shape[0]), glob[parent[Vz.shape[0]:]]])
    born = glob[born]
    outside = np.flatnonzero(~zone)
    T_new = np.concatenate([T[outside], np.concatenate([glob, np.arange(Vn.shape[0], parent.size)])[T_new]])
    source = np.concatenate([outside, np.flatnonzero(zone)[source]])
    order = np.argsort(source, kind="stable")  # the tets in their order (a split tet's parts in its place)
    T_new, source = T_new[order], source[order]
    groups = {name: np.flatnonzero(np.isin(parent, np.flatnonzero(extend(np.isin(np.arange(n0), nodes), born))))
              for name, nodes in mesh.groups.items()}
    pieces, piece = _pieces(T_new, parent.size)
    new = TetMesh(Vn[parent], T_new, repair=False, merge_tol=0.0, groups=groups, labels=mesh.labels[source],
                  region_names=mesh.region_names, _changed=(zone[source], pieces))  # checked about the zone
    corner = np.zeros(z, dtype=bool)
    corner[_local(T[zone][:, :4], zn, n0).ravel()] = True  # (a tet10's mid-edge node follows its corners)
    shift = np.where(corner, np.linalg.norm(Vz[:z] - V[zn], axis=1), 0.0)
    if rows is not None:
        R = rows.tocoo()
        rows = sp.csr_matrix((R.data, (glob[R.row], zn[R.col])), shape=(Vn.shape[0], n0))
    info = CutInfo(faces=int(cut.sum()), nodes_added=int(parent.size - n0), parent=parent, pieces=pieces,
                   piece=piece, moved=moved, max_move=float(shift.max(initial=0.0)),
                   split=born, split_at=at, uncut=n0)
    if rows is not None:
        info["rows"] = rows
    return new, info


def _zone(V: np.ndarray, T: np.ndarray, tri: np.ndarray, reach: float):
    """The tets a cut along ``tri`` can change (E,) and their nodes (sorted): the tets with a corner within
    ``reach`` (the tolerance and the longest edge) of the surface's box. Each node that can move, be split off
    or copied lies there with all its tets: the cut of the zone is the cut of the mesh, at the cost of the
    zone (a scalpel's strip: a few hundred tets of thousands). Its own outside may be pinched where the
    mesh's is not (an earlier slit's front leaving it): :func:`_manifold_split` leaves pinches no lip lies on."""
    lo, hi = tri.reshape(-1, 3).min(axis=0) - reach, tri.reshape(-1, 3).max(axis=0) + reach
    near = ((V >= lo) & (V <= hi)).all(axis=1)
    zone = near[T[:, :4]].any(axis=1)
    return zone, np.unique(T[zone])


def _local(T: np.ndarray, nodes: np.ndarray, n: int) -> np.ndarray:
    """Tets renumbered onto ``nodes`` (sorted, holding all theirs)."""
    index = np.full(n, -1, dtype=np.int64)
    index[nodes] = np.arange(nodes.size)
    return index[T]


def _cut_zone(V: np.ndarray, T: np.ndarray, tri: np.ndarray, tols: tuple, snap, ids: np.ndarray):
    """:func:`cut_mesh`'s work on the tets ``T`` about the surface (nodes ``V``, theirs alone; ``tols``: its thickness,
    and its bend in a face, for the faces' midpoints): returns the nodes moved and split (the given ones first), how many
    moved, the edges split and where, each tet's source tet, parent and the new tets (:func:`_split_nodes`), the faces
    cut and the rows of the nodes moved or added (:func:`_rows`; None: none). ``ids``: the tets' numbers in the mesh."""
    moved, born, at, source, rows = 0, np.zeros((0, 2), dtype=np.int64), np.zeros(0), np.arange(T.shape[0]), None
    (tol, bend), V0 = tols, V
    if snap:
        V, moved = _onto(V, T, tri, tol)
        if snap != "split":
            V, snapped = _snap(V, T, tri, tol)
            moved += snapped
        placed = (V != V0).any(axis=1)  # (moved onto the surface)
        if T.shape[1] == 4:
            T0 = T
            V, T, born, at, nudged, source, placed = _split_edges(V, T, tri, tol, placed)
            need = np.concatenate([np.flatnonzero((V[:V0.shape[0]] != V0).any(axis=1)), np.arange(V0.shape[0], V.shape[0])])
            rows = _rows(V, T, source, need, T0, V0) if need.size else None
        else:
            V, T, born, at, nudged, source, rows, placed = _split_tet10(V, T, tri, tol, V0, placed)
        moved += nudged
    else:
        placed = np.zeros(V.shape[0], dtype=bool)
    _refuse_crossed(V, T, tri, tol, snap, placed, ids[source])
    keys, slots, index, count = _faces(T)
    elem = np.repeat(np.arange(T.shape[0]), 4)
    inner = np.flatnonzero(count[index] == 2)
    order = inner[np.argsort(index[inner], kind="stable")]
    f1, f2 = order[0::2], order[1::2]  # the two sides of each interior face
    C = V[keys[f1]]
    cut = on_surface(np.concatenate([C[:, 0], C[:, 1], C[:, 2]]), tri, tol).reshape(3, -1).all(axis=0)
    C = C[cut]  # (the faces with their corners on the surface: their midpoints and centre)
    mids = np.concatenate([(C[:, 0] + C[:, 1]) / 2, (C[:, 1] + C[:, 2]) / 2, (C[:, 0] + C[:, 2]) / 2, C.mean(axis=1)])
    cut[cut] = on_surface(mids, tri, bend).reshape(4, -1).all(axis=0)
    if not cut.any():
        raise NothingToCut("the cut surface lies along no element face inside the solid: it misses the solid, runs "
                         "along its outside, or crosses elements without following their faces")
    parent, T_new, cut = _manifold_split(T, elem, slots, f1, f2, cut, V.shape[0])
    return V, moved, born, at, source, parent, T_new, cut, rows


def extend(values: np.ndarray, born: np.ndarray) -> np.ndarray:
    """Per-node ``values`` (n, ...) of booleans extended to the nodes :func:`_split_edges` added, in
    order: a node on the edge (a, b) takes values[a] & values[b] (a fixed edge's node is fixed)."""
    out = np.concatenate([values, np.zeros((born.shape[0],) + values.shape[1:], dtype=values.dtype)])
    n = values.shape[0]
    for k, (a, b) in enumerate(born):
        out[n + k] = out[a] & out[b]
    return out


def _split_edges(V: np.ndarray, T: np.ndarray, tri: np.ndarray, tol: float, placed: np.ndarray):
    """Where an edge passes through the surface (snap="split": every one; after node snapping: those left,
    where moving either end flattens a tet), a node is added where the edge crosses the surface and every
    tet on that edge is split in two there (conforming; the geometry, mass and volume unchanged; tet10:
    :func:`_split_tet10`); a crossing nearer an end than :data:`MIN_SPLIT` of the edge moves that end
    instead, where its tets keep :data:`MIN_VOLUME`.
    The crossing edges are found once a round and split in turn (a round's splits make new edges
    only from nodes on the surface; a curved surface may need a few rounds). A node placed on the
    surface (``placed``: moved onto it before, or here, or added here) is on it: its edges are not
    crossings, so a surface that is not flat where its triangles meet (a scalpel's strips) cannot move
    a node to and fro between their planes. Returns V, T, the edges split (s, 2), where along each the
    node is (s,: 0 at its first end, 1 at its second), how many ends moved, the tet of the input each tet
    came from and the nodes placed."""
    placed = placed.copy()
    source = np.arange(T.shape[0])
    born: list = []
    at: list = []
    nudged = 0
    frames = _frames(tri)
    corner, normal = frames[0], frames[3]
    for _ in range(8):
        E, first = _crossing_edges(V, T, tri, tol, placed)
        if not E.size:
            break
        for (a, b), f in zip(E.tolist(), first.tolist()):
            if placed[a] or placed[b]:
                continue  # an end placed on the surface since the round began
            pa, pb = V[a].copy(), V[b].copy()
            da, db = (pa - corner[f]) @ normal[f], (pb - corner[f]) @ normal[f]
            if not (da * db < 0 and min(abs(da), abs(db)) > tol):
                continue  # an end moved onto the surface since the round began
            on = (T[:, :4] == a).any(axis=1) & (T[:, :4] == b).any(axis=1)
            if not on.any():
                continue
            s = da / (da - db)
            if min(s, 1 - s) < MIN_SPLIT and _nudge(V, T, a if s < 0.5 else b, pa + s * (pb - pa)):
                nudged += 1  # the crossing is at an end: that end moved onto the surface (no sliver)
                placed[a if s < 0.5 else b] = True
                continue
            p = V.shape[0]
            V = np.vstack([V, pa + s * (pb - pa)])
            placed = np.append(placed, True)
            t1, t2 = T[on].copy(), T[on].copy()
            t1[t1 == b], t2[t2 == a] = p, p
            T = np.concatenate([T[~on], t1, t2])
            source = np.concatenate([source[~on], source[on], source[on]])
            born.append((a, b))
            at.append(s)
    return V, T, np.array(born, dtype=np.int64).reshape(-1, 2), np.array(at, dtype=float), nudged, source, placed


def _split_tet10(V: np.ndarray, T: np.ndarray, tri: np.ndarray, tol: float, V0: np.ndarray, placed: np.ndarray):
    """:func:`_split_edges` on a tet10 mesh (straight-sided: each mid-edge node midway): its corners'
    tets split as a tet4 mesh's, then the mid-edge nodes rebuilt. A split edge's mid-edge node becomes
    that of its first half, moved midway along it; every other new edge gets a new one midway; those of
    the edges at a nudged corner follow it. Returns what :func:`_split_edges` does, the new mid-edge
    nodes' edges appended to the split edges (at 0.5: a node's fixes and groups are its edge's), and
    the rows of the new, rebuilt and moved nodes (:func:`_rows`, ``V0`` the uncut nodes)."""
    n0 = V.shape[0]
    V, C, born, at, nudged, source, placed = _split_edges(V, T[:, :4], tri, tol, placed)
    n1 = V.shape[0]
    mids = {}  # (a, b) a < b -> its mid-edge node
    for t in T:
        for (i, j), m in zip(TET10_EDGES.tolist(), t[4:].tolist()):
            mids[(min(t[i], t[j]), max(t[i], t[j]))] = m
    rebuilt = []
    for k, (a, b) in enumerate(born.tolist()):  # the split edge's node goes to its first half
        m = mids.pop((min(a, b), max(a, b)), None)
        if m is not None:
            mids[(min(a, n0 + k), max(a, n0 + k))] = m
            rebuilt.append(m)
    edges = np.sort(C[:, TET10_EDGES].reshape(-1, 2), axis=1)
    new_edges = [e for e in unique_rows(edges).tolist() if tuple(e) not in mids]
    for k, e in enumerate(new_edges):
        mids[tuple(e)] = n1 + k
    M = np.array([mids[(a, b)] for a, b in edges.tolist()], dtype=np.int64).reshape(-1, 6)
    T10 = np.concatenate([C, M], axis=1)
    V = np.vstack([V, np.zeros((len(new_edges), 3))])
    V[T10[:, 4:]] = 0.5 * (V[C[:, TET10_EDGES[:, 0]]] + V[C[:, TET10_EDGES[:, 1]]])  # midway (a nudge moved some)
    born = np.concatenate([born, np.array(new_edges, dtype=np.int64).reshape(-1, 2)])
    at = np.concatenate([at, np.full(len(new_edges), 0.5)])
    moved = np.flatnonzero((V[:n0] != V0).any(axis=1))  # onto the surface, or a mid-edge node following its corner
    need = np.unique(np.concatenate([np.arange(n0, V.shape[0]), np.array(rebuilt, dtype=np.int64), moved]))
    return V, T10, born, at, nudged, source, _rows(V, T10, source, need, T, V0), placed


def _rows(V, Tn, source, need, T0, V0) -> sp.csr_matrix:
    """(nodes, uncut nodes) rows of the nodes ``need`` (added, or moved onto the surface): the shape
    functions (tet4's linear, tet10's quadratic) of the uncut tet each lies in, at its place there; of the
    uncut tets its new tets came from (``source``), the one it lies deepest in. So a field of the element's
    order carries over exactly, and a node moved keeps its place in the deformed solid (where its new
    reference point is carried), not its old point's: the elements about it are not strained by the move."""
    e, k = np.nonzero(np.isin(Tn, need))
    node, t = Tn[e, k], source[e]  # each (node, uncut tet a new tet holding it came from)
    X = V0[T0[t, :4]]  # (p, 4, 3) the uncut tets' corners
    A = np.transpose(X[:, 1:] - X[:, :1], (0, 2, 1))
    lam = np.linalg.solve(A, (V[node] - X[:, 0])[..., None])[..., 0]
    L = np.concatenate([1.0 - lam.sum(axis=1, keepdims=True), lam], axis=1)  # (p, 4) barycentric
    best = np.lexsort((-L.min(axis=1), node))  # by node, the deepest first
    first = np.r_[True, node[best][1:] != node[best][:-1]][:node.size]
    pick = best[first]
    node, t, L = node[pick], t[pick], L[pick]
    if T0.shape[1] == 4:
        N = L
    else:
        N = np.concatenate([L * (2.0 * L - 1.0), 4.0 * L[:, TET10_EDGES[:, 0]] * L[:, TET10_EDGES[:, 1]]], axis=1)
    return sp.csr_matrix((N.ravel(), (np.repeat(node, T0.shape[1]), T0[t].ravel())), shape=(V.shape[0], V0.shape[0]))


MIN_VOLUME = 0.25  # a node moves onto the surface only if each of its tets keeps this share of its volume


def _onto(V: np.ndarray, T: np.ndarray, tri: np.ndarray, tol: float) -> tuple[np.ndarray, int]:
    """Corner nodes within ``tol`` of the surface but not on it moved onto it (onto the plane of the
    first triangle they lie on), so that the faces cut lie in the surface; where a tet would keep less
    than :data:`MIN_VOLUME` of its volume the node stays (within ``tol``). Returns V and the count."""
    lo, hi = tri.reshape(-1, 3).min(axis=0) - tol, tri.reshape(-1, 3).max(axis=0) + tol
    corner = np.unique(T[:, :4])
    cand = corner[((V[corner] >= lo) & (V[corner] <= hi)).all(axis=1)]
    frames = _frames(tri)
    a, n = frames[0], frames[3]
    V = V.copy()
    count = 0
    for s in range(0, cand.size, 512):
        nodes = cand[s:s + 512]
        p = V[nodes][:, None, :] - a[None]
        dist = (p * n[None]).sum(-1)
        near = (np.abs(dist) <= tol) & _inside(p, frames, tol)
        first = np.argmax(near, axis=1)
        d = dist[np.arange(nodes.size), first]
        for k in np.flatnonzero(near.any(axis=1) & (np.abs(d) > 1e-6 * tol)).tolist():
            count += _nudge(V, T, int(nodes[k]), V[nodes[k]] - d[k] * n[first[k]])
    return V, count


def _nudge(V: np.ndarray, T: np.ndarray, v: int, to: np.ndarray) -> bool:
    """Move node ``v`` to ``to`` in place if each of its tets keeps :data:`MIN_VOLUME` of its volume."""
    tets = np.flatnonzero((T[:, :4] == v).any(axis=1))
    before = _signed_volumes(V, T[tets])
    old, V[v] = V[v].copy(), to
    if (_signed_volumes(V, T[tets]) >= MIN_VOLUME * before).all():
        return True
    V[v] = old
    return False


def _crossing_edges(V: np.ndarray, C: np.ndarray, tri: np.ndarray, tol: float, placed=None):
    """The corner edges (e, 2) that pass through a triangle's inside, and the triangle each crosses (not an
    edge with an end ``placed`` on the surface: see :func:`_split_edges`)."""
    lo, hi = tri.reshape(-1, 3).min(axis=0) - tol, tri.reshape(-1, 3).max(axis=0) + tol
    E = unique_rows(np.sort(C[:, TET10_EDGES].reshape(-1, 2), axis=1))
    if placed is not None:
        on = np.zeros(V.shape[0], dtype=bool)
        on[:placed.size] = placed[:V.shape[0]]
        E = E[~(on[E[:, 0]] | on[E[:, 1]])]
    E = E[((np.minimum(V[E[:, 0]], V[E[:, 1]]) <= hi) & (np.maximum(V[E[:, 0]], V[E[:, 1]]) >= lo)).all(axis=1)]
    if not E.size:
        return E, np.zeros(0, dtype=int)
    hit, first = _crossings(V[E[:, 0]], V[E[:, 1]], tri, tol)
    return E[hit], first[hit]


def _snap(V: np.ndarray, T: np.ndarray, tri: np.ndarray, tol: float) -> tuple[np.ndarray, int]:
    """Move nodes onto the surface where it passes through elements, so that it follows their faces
    (node snapping): of each crossing edge, its end nearer the crossed triangle's plane moves
    straight onto that plane, unless one of its tets would keep less than :data:`MIN_VOLUME` of its
    volume (then its other end is tried). A tet10's mid-edge nodes follow their corners. Returns the
    moved nodes' coordinates and how many moved."""
    C = T[:, :4]
    vol0 = _signed_volumes(V, C)
    n = V.shape[0]
    tets_of = sp.csr_matrix((np.ones(C.size), (C.ravel(), np.repeat(np.arange(C.shape[0]), 4))), shape=(n, C.shape[0]))
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    normal = np.cross(b - a, c - a)
    normal /= np.linalg.norm(normal, axis=1)[:, None]
    V = V.copy()
    moved = np.zeros(n, dtype=bool)
    for _ in range(8):
        E, first = _crossing_edges(V, C, tri, tol)
        if not E.size:
            break
        d = ((V[E] - a[first][:, None]) * normal[first][:, None]).sum(-1)  # (e, 2) signed distances
        order = np.argsort(np.abs(d), axis=1)
        any_moved = False
        for k in np.argsort(np.abs(d).min(axis=1), kind="stable"):  # the smallest moves first
            if moved[E[k]].any():  # an end moved onto the surface already (this sweep): it no longer crosses
                continue
            for m in (0, 1):
                v, f, dist = E[k, order[k, m]], first[k], d[k, order[k, m]]
                old = V[v].copy()
                V[v] = old - dist * normal[f]
                tets = tets_of[v].indices
                if (_signed_volumes(V, C[tets]) >= MIN_VOLUME * vol0[tets]).all():
                    any_moved = True
                    moved[v] = True
                    break
                V[v] = old
        if not any_moved:
            break
    if T.shape[1] == 10:
        V[T[:, 4:]] = 0.5 * (V[C[:, TET10_EDGES[:, 0]]] + V[C[:, TET10_EDGES[:, 1]]])
    return V, int(moved.sum())


def _refuse_crossed(V: np.ndarray, T: np.ndarray, tri: np.ndarray, tol: float, snapped: bool, placed, ids) -> None:
    """A surface still through an element's inside (an element edge through a triangle, neither end
    ``placed`` on it) is refused, the elements named (``ids``: each tet's number in the mesh cut)."""
    bad, _ = _crossing_edges(V, T[:, :4], tri, tol, placed)
    if bad.size:
        key = np.sort(T[:, :4][:, TET10_EDGES].reshape(-1, 2), axis=1)
        has = np.isin(key[:, 0] * V.shape[0] + key[:, 1], bad[:, 0] * V.shape[0] + bad[:, 1]).reshape(-1, 6).any(axis=1)
        which = np.unique(ids[has])
        if not snapped:
            why = "(snap=False): let rt.cut move nodes onto it, or split the elements (snap='split')"
        else:
            why = ("that splitting could not follow in 8 rounds (the surface folds back within elements): smooth the "
                   "surface there, or refine the mesh")
        raise ModelError(f"the cut surface passes through the inside of {which.size} element(s) (first: tets "
                         f"{which[:5].tolist()}) {why}")


def _split_nodes(T, elem, slots, f1, f2, cut, n: int):
    """(parent, new tets): each node of a cut face copied once per group of its tets joined through
    uncut faces that hold it; the other nodes untouched."""
    E, K = T.shape
    keep = ~cut
    a, b = f1[keep], f2[keep]
    na, nb = T[elem[a][:, None], slots[a]], T[elem[b][:, None], slots[b]]
    ia = elem[a][:, None] * K + np.take_along_axis(slots[a], np.argsort(na, axis=1), axis=1)
    ib = elem[b][:, None] * K + np.take_along_axis(slots[b], np.argsort(nb, axis=1), axis=1)
    _, label = components(E * K, ia.ravel(), ib.ravel())
    node = T.ravel()
    comp_node = np.empty(label.max() + 1, dtype=np.int64)
    comp_node[label] = node
    on_cut = np.zeros(n, dtype=bool)
    on_cut[T[elem[f1[cut]][:, None], slots[f1[cut]]].ravel()] = True
    comps = np.flatnonzero(on_cut[comp_node])
    comps = comps[np.lexsort((comps, comp_node[comps]))]  # by node, then label
    first = np.r_[True, comp_node[comps][1:] != comp_node[comps][:-1]]
    extra = comps[~first]
    new_id = comp_node.copy()
    new_id[extra] = n + np.arange(extra.size)
    parent = np.concatenate([np.arange(n), comp_node[extra]])
    return parent, new_id[label].reshape(E, K)


def _manifold_split(T, elem, slots, f1, f2, cut, n: int):
    """:func:`_split_nodes`, with the cut faces that would leave the boundary non-manifold left joined:
    where the cut's edge meets the outside or another cut along an edge alone (its nodes still joined
    through other faces), that edge would hold four boundary faces; the cut faces on it stay uncut
    until the cut goes on past them (a pinch is not a surface the solid can be drawn and touched by), and
    so do cut faces whose corners uncut faces elsewhere keep joined. A pinched edge no lip lies on is not
    the cut's making (the mesh's, or the outside of the tets given) and is left. Returns parent, the new
    tets and the faces cut."""
    cut = cut.copy()
    for _ in range(16):
        if not cut.any():
            raise NothingToCut("the faces along the cut surface stay joined at their corners through the faces around "
                               "them: the surface opens nothing; extend it, or cut along a smoother surface")
        parent, T_new = _split_nodes(T, elem, slots, f1, f2, cut, n)
        k = np.flatnonzero(cut)
        sides = [np.sort(T_new[elem[f][:, None], slots[f][:, :3]], axis=1) for f in (f1[k], f2[k])]
        joined = (sides[0] == sides[1]).all(axis=1)  # corners still shared through uncut faces: not opened
        if joined.any():  # (a tet10's mid-edge node alone would be copied: a non-conforming mesh)
            cut[k[joined]] = False
            continue
        keys, _, index, count = _faces(T_new[:, :4])
        outer = keys[count[index] == 1]
        edges = np.sort(outer[:, [[0, 1], [1, 2], [0, 2]]].reshape(-1, 2), axis=1)
        pairs, times = unique_rows(edges, return_counts=True)
        bad = pairs[times > 2]
        if not bad.size:
            return parent, T_new, cut
        k = np.flatnonzero(cut)
        code = bad[:, 0] * (parent.size + 1) + bad[:, 1]
        hits = []
        for f in (f1[k], f2[k]):  # each lip's face, in the new numbering
            side = np.sort(T_new[elem[f][:, None], slots[f][:, :3]][:, [[0, 1], [1, 2], [0, 2]]], axis=2)
            hits.append(np.isin(side[..., 0] * (parent.size + 1) + side[..., 1], code).any(axis=1))
        if not (hits[0] | hits[1]).any():  # pinched edges no lip lies on: not the cut's making
            return parent, T_new, cut
        cut[k[hits[0] | hits[1]]] = False
    raise ModelError("the cut leaves the solid's outside non-manifold however many of its faces are left joined: "
                     "cut along a smoother surface")


def _pieces(T: np.ndarray, n: int) -> tuple[int, np.ndarray]:
    """How many separate parts the tets make (joined through shared nodes), and each node's."""
    K = T.shape[1]
    _, label = components(n, np.repeat(T[:, 0], K - 1), T[:, 1:].ravel())
    used = np.unique(label[np.unique(T)])
    remap = np.full(label.max() + 1, -1)
    remap[used] = np.arange(used.size)
    return int(used.size), remap[label]
