"""A cut searches and changes only the tets about its surface (rtfem.mesh.cut._zone), and builds the cut
model's nonlinear pattern by arithmetic on the node pattern (rtfem.fe.nonlinear_system.free_pattern):
both against the slower algorithms they replaced, run here as the reference.

- The zone against the whole mesh: strips like a scalpel's (a quad from the outside into the embedded
  liver, ending inside it; a bent one; one across its whole width), tet4 and tet10, split and snapped:
  cutting the zone alone gives the same mesh, node for node and tet for tet, the same interpolation and
  the same refusals as cutting with every tet searched.
- A scalpel's strips one after another, each cut on the mesh the strips before it cut: the same again.
  (The zone's own outside is pinched where an earlier slit's front leaves it; before that was told
  apart, 7 of 336 such strips on the liver were refused in the zone and cut in the whole mesh.)
- A scalpel's swept surface recorded in the viewer (a blade drawn through a block hanging under gravity:
  its strips meet at kinks of 0.1-0.2 mm, beyond the surface's 0.1 mm thickness) is cut through: a node
  placed on the surface is on it, not moved to and fro between the planes of the triangles about it
  (before: 41 nudges in 8 rounds, a node carried 0.5 mm along the surface, and the cut refused).
- The pattern against the sort of every element entry's (row, column) key (what the system did before),
  on tet4, tet10 and shell cells with whole nodes and single dofs fixed: the compiled loops and numpy's.
"""

from __future__ import annotations

import numpy as np
import pytest

import rtfem as rt
import rtfem.mesh.cut as C
import rtfem.fe.nonlinear_system as ns
from rtfem.fe.nonlinear_system import free_pattern

MAT = rt.Material(E=3e4, nu=0.45, density=1060.0)


@pytest.fixture(scope="module")
def liver():
    mesh = rt.meshes.liver(solid=True)
    X = np.asarray(mesh.vertices)
    lo, hi = X.min(axis=0), X.max(axis=0)
    return mesh, lo, hi


def _strips(lo, hi):
    """Scalpel-like surfaces (vertices, triangles) through the liver's bounding box."""
    x = lo[0] + 0.6 * (hi[0] - lo[0])
    zt = hi[2] + 0.01
    out = []
    for reach in (0.25, 0.45, 1.1):  # from beyond the side at low y to a share of the width (1.1: all of it, above 0.4 height)
        y1 = lo[1] + reach * (hi[1] - lo[1])
        V = np.array([[x, lo[1] - 0.01, lo[2] + 0.4 * (hi[2] - lo[2])], [x, y1, lo[2] + 0.4 * (hi[2] - lo[2])],
                      [x, y1, zt], [x, lo[1] - 0.01, zt]])
        out.append((V, np.array([[0, 1, 2], [0, 2, 3]])))
    # bent: two quads meeting at 20 degrees along a line in the liver
    y1, z0 = lo[1] + 0.5 * (hi[1] - lo[1]), lo[2] + 0.5 * (hi[2] - lo[2])
    d = (y1 - lo[1] + 0.01) * np.tan(np.radians(20.0))
    V = np.array([[x, lo[1] - 0.01, z0], [x, y1, z0], [x, y1, zt], [x, lo[1] - 0.01, zt],
                  [x + d, hi[1] + 0.01, z0], [x + d, hi[1] + 0.01, zt]])
    out.append((V, np.array([[0, 1, 2], [0, 2, 3], [1, 4, 5], [1, 5, 2]])))
    return out


def _whole(V, T, tri, reach):
    return np.ones(T.shape[0], dtype=bool), np.arange(V.shape[0])


def _cut(mesh, V, T, snap):
    try:
        new, info = C.cut_mesh(mesh, V, T, snap=snap)
    except rt.ModelError as exc:
        return type(exc).__name__ + ": " + str(exc)
    return new, info


@pytest.mark.parametrize("element", ["tet4", "tet10"])
@pytest.mark.parametrize("snap", ["split", True])
def test_cutting_the_zone_alone_is_cutting_the_whole_mesh(liver, element, snap, monkeypatch):
    mesh, lo, hi = liver
    if element == "tet10":
        mesh = mesh.quadratic()
    n, E = mesh.n_vertices, mesh.n_tets
    for V, T in _strips(lo, hi):
        zone, _ = C._zone(np.asarray(mesh.vertices), np.asarray(mesh.tets), V[T], 1e-3)
        assert 0 < zone.sum() < E  # a strip's zone is part of the mesh
        local = _cut(mesh, V, T, snap)
        with monkeypatch.context() as m:
            m.setattr(C, "_zone", _whole)
            whole = _cut(mesh, V, T, snap)
        _same(local, whole)
        if isinstance(whole, str):
            continue
        (a, ia), (b, ib) = local, whole
        np.testing.assert_array_equal(a.labels, b.labels)
        assert (ia.faces, ia.nodes_added, ia.pieces, ia.moved, ia.max_move, ia.uncut) == \
            (ib.faces, ib.nodes_added, ib.pieces, ib.moved, ib.max_move, n)
        assert ia.nodes_added > 0
        assert abs(ia.transfer() - ib.transfer()).max() == 0.0


def _same(local, whole) -> None:
    if isinstance(whole, str) or isinstance(local, str):
        assert local == whole
        return
    (a, ia), (b, ib) = local, whole
    np.testing.assert_array_equal(np.asarray(a.vertices), np.asarray(b.vertices))
    np.testing.assert_array_equal(np.asarray(a.tets), np.asarray(b.tets))
    for key in ("parent", "piece", "split", "split_at"):
        np.testing.assert_array_equal(ia[key], ib[key])


@pytest.mark.parametrize("fx", [0.3, 0.6])
def test_strips_cut_one_after_another_in_the_zone_are_those_cut_in_the_whole_mesh(liver, fx, monkeypatch):
    mesh, lo, hi = liver
    x, zb, zt = lo[0] + fx * (hi[0] - lo[0]), lo[2] + 0.3 * (hi[2] - lo[2]), hi[2] + 0.01
    ys = np.arange(lo[1] - 0.01, hi[1] + 0.012, 0.006)  # strips 6 mm wide, the last four each time (a scalpel's job)
    cuts = 0
    for k in range(2, ys.size):
        V = np.array([[[x, ys[i], zb], [x, ys[i + 1], zb], [x, ys[i + 1], zt], [x, ys[i], zt]]
                      for i in range(max(0, k - 4), k)]).reshape(-1, 3)
        T = (4 * np.arange(V.shape[0] // 4)[:, None, None] + np.array([[0, 1, 2], [0, 2, 3]])).reshape(-1, 3)
        local = _cut(mesh, V, T, "split")
        with monkeypatch.context() as m:
            m.setattr(C, "_zone", _whole)
            whole = _cut(mesh, V, T, "split")
        _same(local, whole)
        if not isinstance(whole, str):
            mesh, cuts = whole[0], cuts + 1
    assert cuts >= 15  # most strips open the liver further


def test_a_scalpels_kinked_strips_cut_through_the_block_they_were_swept_across():
    from pathlib import Path

    data = np.load(Path(__file__).with_name("scalpel_strips.npz"))
    V, T = data["vertices"], data["triangles"]
    mesh = rt.meshes.box(0.1, 0.02, 0.02, nx=20, ny=4, nz=4)
    new, info = C.cut_mesh(mesh, V, T, snap="split")
    assert info.pieces == 2 and info.nodes_added == 25  # through: the 5 x 5 nodes of the plane at x = L / 2, twice
    assert info.max_move <= 0.2 * 0.005 and (new.volumes() > 0).all()
    X = np.asarray(new.vertices)
    left = X[np.asarray(new.tets)].mean(axis=1)[:, 0] < 0.05
    assert (X[np.asarray(new.tets)[left]][..., 0] <= 0.05 + info.max_move).all()


def test_a_refusal_names_the_tets_the_surface_passes_through_in_the_meshs_numbering():
    """A slanted plane through mid-length with snap=False: the tets named lie where it passes (their
    centres within an element of x = 0.052), not where the zone's own numbering would put them."""
    import re

    mesh = rt.meshes.box(0.1, 0.02, 0.02, nx=20, ny=4, nz=4)
    V = np.array([[0.0512, -0.001, -0.001], [0.0512, 0.021, -0.001], [0.0532, 0.021, 0.021], [0.0532, -0.001, 0.021]])
    with pytest.raises(rt.ModelError, match="passes through the inside") as err:
        rt.cut(rt.SolidModel(mesh, MAT, element="tet4"), V, [[0, 1, 2], [0, 2, 3]], snap=False)
    named = [int(t) for t in re.search(r"tets \[([0-9, ]+)\]", str(err.value)).group(1).split(",")]
    centres = np.asarray(mesh.vertices)[np.asarray(mesh.tets)[named]].mean(axis=1)
    assert np.abs(centres[:, 0] - 0.0522).max() < 0.005


def _pattern_by_sort(cells, dpn, free, n_dofs):
    """The pattern as the system built it before: every kept element entry's (row, column) key sorted."""
    ne, k = cells.shape
    nd = k * dpn
    dofs = (dpn * cells[:, :, None] + np.arange(dpn)).reshape(ne, nd)
    pos = np.full(n_dofs, -1)
    pos[free] = np.arange(free.size)
    pe = pos[dofs]
    rows, cols = np.repeat(pe, nd, axis=1).ravel(), np.tile(pe, (1, nd)).ravel()
    keep = np.flatnonzero((rows >= 0) & (cols >= 0))
    keys = rows[keep].astype(np.int64) * free.size + cols[keep]
    uniq, slot = np.unique(keys, return_inverse=True)
    indptr = np.searchsorted(uniq // free.size, np.arange(free.size + 1))
    return uniq % free.size, indptr, keep, slot


@pytest.mark.parametrize("compiled", [True, False], ids=["compiled", "numpy"])
@pytest.mark.parametrize("k, dpn", [(4, 3), (10, 3), (3, 6)])
def test_the_nonlinear_pattern_is_the_sorted_entries_pattern(k, dpn, compiled, monkeypatch):
    from rtfem.fe import jit
    from rtfem.fe.assembly_kernels import _slot

    if compiled and jit.compiled("free-slots", ns._free_slots, _slot) is None:
        pytest.skip("numba cannot compile here: the numpy path is the one run")
    if not compiled:  # numba's absence: the numpy path
        monkeypatch.setitem(jit._COMPILED, "free-slots", None)
    rng = np.random.default_rng(k)
    n = 400
    cells = np.array([rng.choice(n, k, replace=False) for _ in range(3 * n)])
    fixed = rng.random(n * dpn) < 0.1  # single dofs ...
    fixed[:5 * dpn] = True  # ... and whole nodes
    fixed[dpn * (n - 1):] = False
    free = np.flatnonzero(~fixed)
    mine, ref = free_pattern(cells, dpn, free, n), _pattern_by_sort(cells, dpn, free, n * dpn)
    for a, b in zip(mine, ref):
        np.testing.assert_array_equal(a, b)


def test_the_tangent_at_rest_of_a_partly_fixed_model_is_its_stiffness():
    """Through the system: a tet4 block with a face clamped and a line held in z alone; its tangent at
    rest (assembled on the new pattern) equals the linear stiffness on the free dofs to round-off."""
    mesh = rt.meshes.box(0.05, 0.02, 0.02, nx=5, ny=2, nz=2)
    X = np.asarray(mesh.vertices)
    model = rt.SolidModel(mesh, MAT, element="tet4").fix(np.flatnonzero(X[:, 0] < 1e-9))
    model.fix(np.flatnonzero((X[:, 0] > 0.05 - 1e-9) & (X[:, 1] < 1e-9)), dofs=[2])
    system = model.nonlinear()
    from rtfem.fe.nonlinear_system import Configuration

    _, K, _ = system.evaluate(Configuration.rest(model.n_nodes, False))
    free = model.free_dofs
    ref = model.K[free][:, free]
    assert abs(K - ref).max() <= 1e-9 * abs(ref).max()
