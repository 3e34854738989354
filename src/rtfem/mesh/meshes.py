"""Mesh generators: plate, cylinder, hemisphere, icosphere and the embedded default liver.

All generators return :class:`~rtfem.mesh.surface.TriMesh` in metres with named vertex groups
(``mesh.groups``) for the natural places to fix or load a model.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from .. import validate
from ..errors import MeshError
from .surface import TriMesh
from .tetmesh import TetMesh

__all__ = ["plate", "cylinder", "hemisphere", "icosphere", "liver", "gallbladder", "box", "hollow_sphere", "PROBE_POINT"]

#: where the default liver is pressed: its vertex group "probe" is the vertex nearest this point (m)
PROBE_POINT = (0.055, 0.05, 0.0)


_MAX_TRIANGLES = 20_000_000  # a generated mesh larger than this is a typo, not a request


def _count(name: str, value, minimum: int, maximum: int = 10**6) -> int:
    return validate.count(value, name, minimum, maximum, error=MeshError)


def _length(name: str, value) -> float:
    return validate.positive(value, name, "a length in metres", error=MeshError)


def _size_check(n_triangles: int, what: str) -> None:
    if n_triangles > _MAX_TRIANGLES:
        raise MeshError(f"{what} would have {n_triangles:,} triangles (the limit is {_MAX_TRIANGLES:,}); "
                        "ask for fewer cells")


def plate(a: float = 1.0, b: float | None = None, nx: int = 8, ny: int | None = None, pattern: str = "alternate") -> TriMesh:
    """Rectangular plate [0, a] x [0, b] in the z = 0 plane, nx x ny cells, two triangles each.

    ``pattern``: "alternate" (diagonals alternate in a checkerboard, symmetric), "right"
    (all diagonals from lower-left to upper-right) or "left". Groups: ``x0``, ``x1``, ``y0``,
    ``y1`` (the four edges), ``boundary`` and ``center`` (the vertex nearest the centre).
    """
    a = _length("a", a)
    b = a if b is None else _length("b", b)
    nx = _count("nx", nx, 1)
    ny = nx if ny is None else _count("ny", ny, 1)
    validate.choice(pattern, "pattern", ("alternate", "right", "left"), error=MeshError)
    _size_check(2 * nx * ny, "the plate")
    xs = np.linspace(0.0, a, nx + 1)
    ys = np.linspace(0.0, b, ny + 1)
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    V = np.column_stack([X.ravel(), Y.ravel(), np.zeros(X.size)])
    idx = np.arange(V.shape[0]).reshape(nx + 1, ny + 1)
    i, j = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
    i, j = i.ravel(), j.ravel()
    v00, v10, v01, v11 = idx[i, j], idx[i + 1, j], idx[i, j + 1], idx[i + 1, j + 1]
    if pattern == "right":
        flip = np.zeros(i.size, bool)
    elif pattern == "left":
        flip = np.ones(i.size, bool)
    else:
        flip = (i + j) % 2 == 1
    t1 = np.where(flip[:, None], np.stack([v00, v10, v01], 1), np.stack([v00, v10, v11], 1))
    t2 = np.where(flip[:, None], np.stack([v10, v11, v01], 1), np.stack([v00, v11, v01], 1))
    T = np.concatenate([t1, t2])
    groups = {
        "x0": idx[0, :],
        "x1": idx[-1, :],
        "y0": idx[:, 0],
        "y1": idx[:, -1],
        "boundary": np.unique(np.r_[idx[0, :], idx[-1, :], idx[:, 0], idx[:, -1]]),
        "center": np.array([int(np.argmin(np.linalg.norm(V - [a / 2, b / 2, 0], axis=1)))]),
    }
    return TriMesh(V, T, repair=False, groups=groups)


def cylinder(radius: float = 0.05, length: float = 0.2, n_around: int = 24, n_along: int = 16) -> TriMesh:
    """Open circular cylinder along z from 0 to ``length``. Groups ``bottom`` and ``top``."""
    radius, length = _length("radius", radius), _length("length", length)
    na, nl = _count("n_around", n_around, 3), _count("n_along", n_along, 1)
    _size_check(2 * na * nl, "the cylinder")
    th = 2 * np.pi * np.arange(na) / na
    z = np.linspace(0, length, nl + 1)
    # rotate every other ring by half a step: near-equilateral triangles
    TH = th[None, :] + (np.arange(nl + 1)[:, None] % 2) * (np.pi / na)
    V = np.column_stack([radius * np.cos(TH).ravel(), radius * np.sin(TH).ravel(), np.repeat(z, na)])
    idx = np.arange(V.shape[0]).reshape(nl + 1, na)
    tris = []
    for k in range(nl):
        a, b = idx[k], idx[k + 1]
        an, bn = np.roll(a, -1), np.roll(b, -1)
        if k % 2 == 0:
            tris += [np.stack([a, an, b], 1), np.stack([an, bn, b], 1)]
        else:
            tris += [np.stack([a, bn, b], 1), np.stack([a, an, bn], 1)]
    return TriMesh(V, np.concatenate(tris), repair=False, groups={"bottom": idx[0], "top": idx[-1]})


def hemisphere(radius: float = 0.05, n_rings: int = 12) -> TriMesh:
    """Hemisphere z >= 0 of the given radius: ring k (k = 0 at the pole) holds 6k vertices.

    Groups ``rim`` (the equator) and ``pole``.
    """
    radius = _length("radius", radius)
    nr = _count("n_rings", n_rings, 1, 1000)
    pts = [np.array([[0.0, 0.0, radius]])]
    rings = [np.array([0])]
    count = 1
    for k in range(1, nr + 1):
        phi = 0.5 * np.pi * k / nr
        th = 2 * np.pi * (np.arange(6 * k) + 0.5 * (k % 2)) / (6 * k)
        pts.append(radius * np.column_stack([np.sin(phi) * np.cos(th), np.sin(phi) * np.sin(th), np.full(6 * k, np.cos(phi))]))
        rings.append(np.arange(count, count + 6 * k))
        count += 6 * k
    V = np.vstack(pts)
    V[rings[-1], 2] = 0.0
    tris = []
    ang = lambda r: np.mod(np.arctan2(V[r, 1], V[r, 0]), 2 * np.pi)  # noqa: E731
    for k in range(nr):
        inner, outer = rings[k], rings[k + 1]
        if k == 0:
            tris.append(np.stack([np.zeros(6, int), outer, np.roll(outer, -1)], 1))
            continue
        # merge the two rings by angle (advancing front around the annulus)
        ai, ao = ang(inner), ang(outer)
        oi, oo = np.argsort(ai), np.argsort(ao)
        inner, outer, ai, ao = inner[oi], outer[oo], ai[oi], ao[oo]
        i = o = 0
        ni, no = inner.size, outer.size
        while i < ni or o < no:
            ci, co = inner[i % ni], outer[o % no]
            next_i = ai[(i + 1) % ni] + (2 * np.pi if i + 1 >= ni else 0)
            next_o = ao[(o + 1) % no] + (2 * np.pi if o + 1 >= no else 0)
            if o >= no or (i < ni and next_i < next_o):
                tris.append(np.array([[ci, outer[o % no], inner[(i + 1) % ni]]]))
                i += 1
            else:
                tris.append(np.array([[ci, co, outer[(o + 1) % no]]]))
                o += 1
    T = np.concatenate(tris)
    mesh = TriMesh(V, T, repair=True, groups={"rim": rings[-1], "pole": rings[0]})
    return mesh


def icosphere(radius: float = 1.0, level: int = 3) -> TriMesh:
    """Sphere from a subdivided icosahedron: 10 * 4**level + 2 vertices, well-shaped triangles."""
    radius = _length("radius", radius)
    level = _count("level", level, 0, 9)
    t = (1 + 5**0.5) / 2
    V = np.array(
        [[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t],
         [0, -1, -t], [0, 1, -t], [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]], dtype=float
    )
    T = np.array(
        [[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4], [11, 10, 2],
         [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5],
         [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]]
    )
    m = TriMesh(V, T, repair=False)
    if level:
        m = m.subdivided(level)
    P = np.asarray(m.vertices)
    P = P / np.linalg.norm(P, axis=1)[:, None] * radius
    return TriMesh(P, m.triangles, repair=False)


def _liver_map(p: np.ndarray) -> np.ndarray:
    """Smooth map of the unit sphere onto a liver-like surface (metres).

    A wedge: the thick, domed right lobe (x < 0) tapers into the thin left lobe (x > 0);
    the diaphragmatic (upper) face is convex, the visceral (lower) face is flatter and
    slightly concave, and the anterior edge has an interlobar notch.
    """
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    X = 0.100 * x
    Y = 0.075 * y * (1.0 - 0.18 * x) - 0.012 * (1 - x**2)
    # anterior notch between the lobes
    Y -= 0.018 * np.exp(-(((x - 0.15) / 0.12) ** 2)) * np.clip(y, 0, None) ** 3
    thick = 0.040 * (0.62 - 0.38 * np.tanh(1.6 * x)) / 0.62 * (1.0 - 0.25 * y**2)
    up = np.where(z > 0, 1.0, 0.55)
    Z = thick * z * up - 0.010 * (1 - x**2) * (1 - y**2) * (z < 0) * (-z)
    Z += 0.012 * (1 - y) * 0.5 * (1 - x**2)  # posterior rise toward the diaphragm
    return np.column_stack([X, Y, Z])


def liver(level: int = 4, *, solid: bool = False, spacing: float | None = None):
    """The embedded default organ: a smooth, closed, liver-like surface in metres.

    About 0.2 x 0.15 x 0.08 m. ``level`` 4 gives 2,562 vertices (the default), 5 gives
    10,242 and 6 gives 40,962 (refinements of the same surface, for benchmarks).
    ``mesh.groups["attachment"]`` is the default fixed region: the posterior-superior
    "bare area" where the liver is held by the coronary ligament and the vena cava;
    ``mesh.groups["probe"]`` is one vertex on the free anterior edge of the right lobe (nearest
    :data:`PROBE_POINT`), where the examples, demo and benchmarks press.
    Generated from an icosphere by a smooth map; no data files are involved.

    ``solid=True`` gives the volume as a :class:`TetMesh`: the level-3 surface (or ``level`` if
    lower) filled by :func:`rtfem.tetrahedralize` with target edge ``spacing`` (m; default 5 % of
    the diagonal), groups carried over to the nearest surface nodes. The default, 1,152 nodes and
    4,903 tets, is shipped with rtfem (meshed once by tools/embed_liver.py): the mesher's output
    differs from run to run, and the default organ is the same on every machine, with no mesher
    needed. Another ``spacing`` (``0.0075`` gives about 4,300 nodes and 21,000 tets, the size of
    SOFA's liver scene) or a lower ``level`` is meshed here (the ``mesh`` extra) and kept on disk
    (:func:`rtfem.cache.cache_dir`): the same call then gives the same mesh on this machine.
    """
    level = _count("level", level, 1, 8)
    solid = validate.flag(solid, "solid", error=MeshError)
    # relax on a coarse sphere, then refine in parameter space and relax a little more:
    # subdivision keeps the shapes, so each level needs only a few smoothing sweeps
    sph = icosphere(1.0, min(level, 3))
    P = _relax_on_map(np.asarray(sph.vertices), sph, _liver_map, iterations=60)
    for _ in range(level - 3):
        sph = TriMesh(P, sph.triangles, repair=False).subdivided(1)
        P = np.asarray(sph.vertices) / np.linalg.norm(sph.vertices, axis=1)[:, None]
        P = _relax_on_map(P, sph, _liver_map, iterations=12)
    V = _liver_map(P)
    x, y, z = P[:, 0], P[:, 1], P[:, 2]
    attach = np.flatnonzero((y < -0.55) & (z > 0.05) & (x > -0.55) & (x < 0.25))
    probe = np.argmin(np.linalg.norm(V - PROBE_POINT, axis=1))
    groups = {"attachment": attach, "probe": [probe]}
    surface = TriMesh(V, sph.triangles, repair=False, groups=groups)
    if not solid:
        return surface
    return _solid_liver(min(level, 3), None if spacing is None else _length("spacing", spacing))


def gallbladder(level: int = 2) -> TriMesh:
    """A gallbladder in the default liver's frame: a closed pear-shaped sac about 8 cm long and 3 cm
    across, its long axis along +y (the wide fundus anterior, the neck posterior), lying 1.5 mm below
    the visceral face of :func:`liver`'s right lobe (its fossa). ``level`` 2 gives 162 vertices, 3
    gives 642. Groups: ``"bed"``, the upper face that the cystic plate joins to the liver (where a
    scene attaches it), and ``"fundus"``, the vertex at its anterior tip (where a grasper takes it).
    A hollow organ: model it as a shell."""
    level = _count("level", level, 0, 6)
    P = np.asarray(icosphere(1.0, level).vertices)
    x, y, z = P[:, 0], P[:, 1], P[:, 2]
    widen = 1.0 + 0.3 * y  # the fundus wider than the neck
    V = np.column_stack([0.015 * x * widen, 0.04 * y, 0.013 * z * widen]) + [-0.03, 0.005, -0.0445]
    bed = np.flatnonzero((z > 0.45) & (np.abs(y) < 0.8))
    return TriMesh(V, icosphere(1.0, level).triangles, repair=False,
                   groups={"bed": bed, "fundus": [int(np.argmax(y))]})


@lru_cache(maxsize=4)
def _solid_liver(level: int, spacing: float | None) -> TetMesh:
    from .meshing import cached_tetrahedralize

    if level == 3 and spacing is None:
        return _embedded_liver()
    return cached_tetrahedralize(liver(level), spacing)


def _embedded_liver() -> TetMesh:
    """The default solid liver: fTetWild's tets of ``liver(3)`` at the default edge, made once
    (tools/embed_liver.py) and shipped, so that every machine has the same organ; the groups are
    carried from the surface as :func:`rtfem.tetrahedralize` carries them."""
    import zipfile
    from importlib import resources

    from .meshing import _carry_groups

    try:
        with resources.files("rtfem").joinpath("data", "liver_tets.npz").open("rb") as f, \
                np.load(f, allow_pickle=False) as z:
            X, T = np.array(z["vertices"], dtype=np.float64), np.array(z["tets"], dtype=np.int64)
    except (OSError, KeyError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise MeshError(f"the embedded liver's tets (rtfem/data/liver_tets.npz) cannot be read ({exc}); "
                        "reinstall rtfem") from None
    return _carry_groups(liver(3), TetMesh(X, T))


def box(lx: float = 1.0, ly: float = 0.1, lz: float = 0.1, nx: int = 20, ny: int = 2, nz: int = 2) -> TetMesh:
    """A solid box [0, lx] x [0, ly] x [0, lz] of nx x ny x nz hexahedra, six tets each (the
    Kuhn split along each hex's main diagonal, conforming across hexes). Groups: the faces
    "x0" and "x1" (nodes at x = 0 and x = lx), for clamping and loading a cantilever."""
    lx, ly, lz = (_length(n, v) for n, v in (("lx", lx), ("ly", ly), ("lz", lz)))
    nx, ny, nz = (_count(n, v, 1, 400) for n, v in (("nx", nx), ("ny", ny), ("nz", nz)))
    if 6 * nx * ny * nz > 5_000_000:
        raise MeshError(f"{6 * nx * ny * nz} tets is too many for a box; use fewer divisions")
    X = np.array(np.meshgrid(np.linspace(0, lx, nx + 1), np.linspace(0, ly, ny + 1), np.linspace(0, lz, nz + 1),
                             indexing="ij")).reshape(3, -1).T
    idx = np.arange(X.shape[0]).reshape(nx + 1, ny + 1, nz + 1)
    i, j, k = (a.ravel() for a in np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij"))
    corner = np.stack([idx[i + a, j + b, k + c] for a, b, c in
                       [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (0, 0, 1), (1, 0, 1), (1, 1, 1), (0, 1, 1)]], axis=1)
    kuhn = np.array([[0, 1, 2, 6], [0, 2, 3, 6], [0, 3, 7, 6], [0, 7, 4, 6], [0, 4, 5, 6], [0, 5, 1, 6]])
    T = corner[:, kuhn].reshape(-1, 4)
    groups = {"x0": np.flatnonzero(X[:, 0] == 0.0), "x1": np.flatnonzero(X[:, 0] == lx)}
    return TetMesh(X, T, groups=groups)


def hollow_sphere(inner_radius: float = 0.05, outer_radius: float = 0.1, level: int = 3, layers: int = 4) -> TetMesh:
    """A thick-walled hollow sphere of tets: ``layers`` + 1 concentric icospheres of ``level``
    (radii spaced evenly) joined by prisms, three tets each (the diagonal of every side quad
    runs from the lower-numbered vertex's inner node to the higher one's outer node, so
    neighbouring prisms conform). Groups: "inner" and "outer" surface nodes (Lame's problem)."""
    r0, r1 = _length("inner_radius", inner_radius), _length("outer_radius", outer_radius)
    if r0 >= r1:
        raise MeshError(f"inner_radius={inner_radius} must be below outer_radius={outer_radius}")
    layers = _count("layers", layers, 1, 200)
    sph = icosphere(1.0, level)
    P, F = np.asarray(sph.vertices), np.sort(np.asarray(sph.triangles), axis=1)
    n = P.shape[0]
    X = np.concatenate([P * r for r in np.linspace(r0, r1, layers + 1)])
    a, b, c = F[:, 0], F[:, 1], F[:, 2]
    tets = []
    for k in range(layers):
        lo, hi = k * n, (k + 1) * n
        tets += [np.stack(t, axis=1) for t in ((a + lo, b + lo, c + lo, c + hi), (a + lo, b + lo, b + hi, c + hi),
                                               (a + lo, a + hi, b + hi, c + hi))]
    T = np.concatenate(tets)
    q = X[T]
    neg = np.einsum("ij,ij->i", np.cross(q[:, 1] - q[:, 0], q[:, 2] - q[:, 0]), q[:, 3] - q[:, 0]) < 0
    T[neg] = T[neg][:, [0, 2, 1, 3]]
    return TetMesh(X, T, groups={"inner": np.arange(n), "outer": layers * n + np.arange(n)})


def _relax_on_map(P: np.ndarray, sph: TriMesh, fmap, iterations: int = 40, step: float = 0.5) -> np.ndarray:
    """Move sphere points so the mapped mesh has near-uniform edges (parametric smoothing).

    Each iteration moves every mapped vertex toward the centroid of its neighbours, pulls the
    move back to the sphere's tangent plane through the map's Jacobian (least squares) and
    re-normalises: the vertices stay exactly on the mapped surface while the anisotropy of
    the map is undone.
    """
    A = sph.adjacency().copy()
    A.data[:] = 1.0
    deg = np.asarray(A.sum(axis=1)).ravel()
    h = 1e-6
    for _ in range(iterations):
        V = fmap(P)
        d = (A @ V) / deg[:, None] - V
        # tangent basis of the sphere at P
        ref = np.where(np.abs(P[:, [0]]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])
        t1 = np.cross(P, ref)
        t1 /= np.linalg.norm(t1, axis=1)[:, None]
        t2 = np.cross(P, t1)
        J = np.stack([(fmap(P + h * t) - V) / h for t in (t1, t2)], axis=2)  # (n, 3, 2)
        JtJ = np.einsum("nki,nkj->nij", J, J)
        ab = np.linalg.solve(JtJ, np.einsum("nki,nk->ni", J, d)[..., None])[..., 0]
        P = P + step * (ab[:, :1] * t1 + ab[:, 1:] * t2)
        P /= np.linalg.norm(P, axis=1)[:, None]
    return P
