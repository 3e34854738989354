"""TetMesh: validation, repair, orientation, boundary surface, quality, files; the solid generators."""

from __future__ import annotations

import numpy as np
import pytest

import rtfem as rt

REGULAR = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], float)


def _two_tets():
    X = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]], float)
    return X, np.array([[0, 1, 2, 3], [1, 2, 3, 4]])


def test_regular_tet_quality_is_the_textbook_one():
    m = rt.TetMesh(REGULAR, [[0, 1, 2, 3]])
    q = m.quality()
    # regular tet: dihedral angle arccos(1/3) = 70.53 deg, radius ratio 1, volume a^3 / (6 sqrt 2)
    assert q.min_dihedral[0] == pytest.approx(np.degrees(np.arccos(1 / 3)), abs=1e-9)
    assert q.max_dihedral[0] == pytest.approx(np.degrees(np.arccos(1 / 3)), abs=1e-9)
    assert q.radius_ratio[0] == pytest.approx(1.0, abs=1e-12)
    a = np.sqrt(8.0)
    assert m.volume() == pytest.approx(a**3 / (6 * np.sqrt(2)), rel=1e-12)


def test_inverted_tets_are_reoriented_and_the_surface_points_outward():
    X, T = _two_tets()
    T = T.copy()
    T[1] = T[1][[0, 2, 1, 3]]  # inverted
    m = rt.TetMesh(X, T)
    assert m.report.flipped_tets == 1 and np.all(m.volumes() > 0)
    s = m.surface
    assert s.n_triangles == 6 and s.is_closed()
    # divergence theorem on the outward boundary gives the tets' volume
    assert s.volume() == pytest.approx(m.volume(), rel=1e-12)
    with pytest.raises(rt.MeshError, match="inverted tet 1"):
        rt.TetMesh(X, T, repair=False)


def test_repairs_are_reported_and_refused_without_repair():
    X, T = _two_tets()
    X2 = np.vstack([X, X[4] + 1e-14, [5.0, 5.0, 5.0]])  # a duplicate of node 4 and an unreferenced node
    T2 = np.vstack([T, T[0], [0, 1, 2, 2], [1, 2, 3, 5]])  # duplicate tet, repeated node, tet on the duplicate
    T2[-1] = [1, 2, 3, 5]
    m = rt.TetMesh(X2, T2, groups={"tip": [4, 5]})
    r = m.report
    assert (r.merged_nodes, r.removed_duplicate_tets, r.removed_degenerate, r.dropped_unreferenced) == (1, 2, 1, 1)
    assert m.n_vertices == 5 and m.n_tets == 2 and list(m.groups["tip"]) == [4]
    assert "duplicate nodes merged" in str(r)
    with pytest.raises(rt.MeshError, match="degenerate"):
        rt.TetMesh(X, np.vstack([T, [[0, 1, 2, 2]]]), repair=False)
    flat = np.vstack([X, [0.5, 0.5, 0.0]])
    with pytest.raises(rt.MeshError, match="zero-volume"):
        rt.TetMesh(flat, [[0, 1, 2, 5]], repair=False)


@pytest.mark.parametrize("vertices,tets,match", [
    (np.zeros((0, 3)), np.zeros((0, 4), int), "empty"),
    ([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, np.nan]], [[0, 1, 2, 3]], "non-finite .* node 3"),
    ([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], [[0, 1, 2, 4]], "outside 0..3"),
    ([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], [[0, 1, 2]], r"\(m, 4\) or \(m, 10\)"),
    ([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], [[0, 1, 2, 3.5]], "integers"),
])
def test_broken_input_names_the_place(vertices, tets, match):
    with pytest.raises(rt.MeshError, match=match):
        rt.TetMesh(vertices, tets)


def test_overlapping_tets_are_refused():
    X, T = _two_tets()
    X = np.vstack([X, [0.2, 0.2, -1.0]])
    T = np.vstack([T, [0, 1, 2, 5], [0, 2, 1, 4]])  # three tets on face (0, 1, 2)
    with pytest.raises(rt.MeshError, match="shared by more than two tets"):
        rt.TetMesh(X, T)


def test_quadratic_and_back():
    box = rt.meshes.box(1.0, 0.5, 0.5, 2, 1, 1)
    q = box.quadratic()
    assert q.order == 2 and q.tets.shape == (box.n_tets, 10)
    # mid-edge nodes at the midpoints of their corner edges, VTK order
    X = q.vertices
    for k, (i, j) in enumerate(rt.mesh.tetmesh.TET10_EDGES):
        np.testing.assert_allclose(X[q.tets[:, 4 + k]], 0.5 * (X[q.tets[:, i]] + X[q.tets[:, j]]), atol=1e-15)
    assert q.n_vertices == box.n_vertices + box.edges().shape[0]
    assert q.surface.n_triangles == box.surface.n_triangles  # the corner surface
    lin = q.linear()
    assert lin.n_vertices == box.n_vertices and lin.volume() == pytest.approx(box.volume())


@pytest.mark.parametrize("suffix", [".vtu", ".vtk", ".msh", ".mesh", ".inp"])
@pytest.mark.parametrize("order", [1, 2])
def test_volume_files_load_as_tet_meshes(tmp_path, suffix, order):
    box = rt.meshes.box(1.0, 0.4, 0.3, 3, 2, 1)
    mesh = box if order == 1 else box.quadratic()
    if suffix == ".mesh" and order == 2:  # MEDIT has no 10-node tets: refused, not an empty file (meshio's)
        with pytest.raises(rt.MeshError, match="no 10-node tets"):
            rt.save_mesh(mesh, tmp_path / "organ.mesh")
        assert not (tmp_path / "organ.mesh").exists()
        return
    path = tmp_path / f"organ{suffix}"
    rt.save_mesh(mesh, path)
    back = rt.load_mesh(path)
    assert isinstance(back, rt.TetMesh) and back.order == order
    assert back.n_tets == mesh.n_tets and back.volume() == pytest.approx(mesh.volume(), rel=1e-9)
    np.testing.assert_allclose(back.vertices, mesh.vertices, atol=1e-9)
    assert back.report.flipped_tets == 0


def test_legacy_ascii_unstructured_grid_with_tets(tmp_path):
    X, T = _two_tets()
    lines = ["# vtk DataFile Version 2.0", "tets", "ASCII", "DATASET UNSTRUCTURED_GRID", f"POINTS {len(X)} float"]
    lines += [" ".join(map(str, p)) for p in X]
    lines += [f"CELLS {len(T)} {5 * len(T)}"] + [f"4 {' '.join(map(str, t))}" for t in T]
    lines += [f"CELL_TYPES {len(T)}"] + ["10"] * len(T)
    path = tmp_path / "tets.vtk"
    path.write_text("\n".join(lines) + "\n")
    m = rt.load_mesh(path)
    assert isinstance(m, rt.TetMesh) and m.n_tets == 2 and m.volume() == pytest.approx(0.5)


def test_box_and_hollow_sphere_generators():
    b = rt.meshes.box(2.0, 1.0, 0.5, 4, 2, 1)  # cubic cells: Kuhn tets have dihedral angles 45, 60 and 90 deg
    assert b.n_tets == 6 * 8 and b.volume() == pytest.approx(1.0, rel=1e-12)
    assert b.quality().min_dihedral.min() == pytest.approx(45.0) and set(b.groups) == {"x0", "x1"}
    s = rt.meshes.hollow_sphere(0.05, 0.1, level=2, layers=3)
    assert s.surface.is_closed() and s.surface.n_triangles == 2 * 320
    # the volume between the two polyhedral spheres, by the divergence theorem on their surfaces
    shell = rt.meshes.icosphere(0.1, 2).volume() - rt.meshes.icosphere(0.05, 2).volume()
    assert s.volume() == pytest.approx(shell, rel=1e-12)
    r = np.linalg.norm(s.vertices, axis=1)
    np.testing.assert_allclose(r[s.groups["inner"]], 0.05)
    np.testing.assert_allclose(r[s.groups["outer"]], 0.1)


@pytest.mark.parametrize("call,match", [
    (lambda: rt.meshes.box(-1.0), "lx"),
    (lambda: rt.meshes.box(nx=0), "nx"),
    (lambda: rt.meshes.hollow_sphere(0.1, 0.05), "inner_radius"),
    (lambda: rt.meshes.hollow_sphere(layers=0), "layers"),
    (lambda: rt.meshes.liver(solid=True, spacing=-0.01), "spacing"),
    (lambda: rt.meshes.liver(solid="yes"), "solid"),
    (lambda: rt.meshes.box().scaled(0.0), "scale"),
    (lambda: rt.TetMesh(*_two_tets(), merge_tol=2.0), "merge_tol"),
    (lambda: rt.tetrahedralize(rt.meshes.box()), "TriMesh"),
])
def test_generators_and_meshing_refuse_nonsense(call, match):
    with pytest.raises(rt.RtfemError, match=match):
        call()


def test_a_file_mixing_linear_and_quadratic_tets_is_refused(tmp_path):
    import meshio

    q = rt.meshes.box(1.0, 1.0, 1.0, 1, 1, 1).quadratic()
    path = tmp_path / "mixed.vtu"
    meshio.write_points_cells(str(path), q.vertices, [("tetra", q.tets[:2, :4]), ("tetra10", q.tets[2:])])
    with pytest.raises(rt.MeshError, match="mixes 4-node and 10-node"):
        rt.load_mesh(path)


def _corrupted(kind: str, quadratic: bool):
    """A box mesh with one tet made bad as ``kind`` says, and the mask of the tets changed."""
    mesh = rt.meshes.box(0.05, 0.02, 0.02, nx=5, ny=2, nz=2)
    mesh = mesh.quadratic() if quadratic else mesh
    V, T = np.asarray(mesh.vertices).copy(), np.asarray(mesh.tets).copy()
    k = 17
    if kind in ("inverted", "inverted with all about it"):
        ring = np.flatnonzero(np.isin(T[:, :4], T[k, :4]).any(axis=1)) if kind != "inverted" else [k]
        T[np.ix_(ring, [1, 2])] = T[np.ix_(ring, [2, 1])]
        if quadratic:  # the mid-edge nodes follow: (0,1) <-> (0,2), (1,3) <-> (2,3)
            T[np.ix_(ring, [4, 6, 8, 9])] = T[np.ix_(ring, [6, 4, 9, 8])]
    elif kind == "degenerate":
        T[k, 3] = T[k, 0]
    elif kind == "duplicate":
        T = np.vstack([T, T[k]])
    elif kind == "three on a face":  # a tet on an inner face of tet k, on the side of its own opposite corner
        F = rt.TetMesh(V, T)._faces()
        inner = np.flatnonzero(F[2][F[1][4 * k:4 * k + 4]] == 2)[0]
        face = F[0][4 * k + inner]
        apex = 0.5 * (V[T[k, inner]] + V[face].mean(axis=0))
        V = np.vstack([V, apex])
        new = np.r_[face, V.shape[0] - 1]  # (tet4 only, see the parametrization)
        T = np.vstack([T, new if rt.TetMesh(V, new[None]).tets[0].tolist() == new.tolist() else new[[1, 0, 2, 3]]])
    elif kind == "unshared mid-edge node":
        V = np.vstack([V, V[T[k, 4]]])
        T[k, 4] = V.shape[0] - 1
    changed = np.zeros(T.shape[0], dtype=bool)
    changed[k if kind not in ("duplicate", "three on a face") else -1] = True
    return V, T, changed


@pytest.mark.parametrize("kind, quadratic", [("inverted", False), ("inverted", True), ("inverted with all about it", False),
                                             ("degenerate", False),
                                             ("duplicate", False), ("three on a face", False),
                                             ("unshared mid-edge node", True)])
def test_a_mesh_checked_about_its_changed_tets_refuses_what_the_whole_check_refuses(kind, quadratic):
    """A cut's mesh is checked on the tets it changed and those sharing a node with them (rtfem.mesh.cut
    passes them): each refusal of the whole mesh's construction (repair=False, merge_tol=0) is made, with
    the whole check's message; and a mesh that passes reports what the whole check reports."""
    V, T, changed = _corrupted(kind, quadratic)
    with pytest.raises(rt.MeshError) as whole:
        rt.TetMesh(V, T, repair=False, merge_tol=0.0)
    with pytest.raises(rt.MeshError) as near:
        rt.TetMesh(V, T, repair=False, merge_tol=0.0, _changed=(changed, 1))
    assert str(near.value) == str(whole.value)


def test_a_mesh_checked_about_its_changed_tets_reports_what_the_whole_check_reports():
    mesh = rt.meshes.box(0.05, 0.02, 0.02, nx=5, ny=2, nz=2).quadratic()
    V, T = np.asarray(mesh.vertices), np.asarray(mesh.tets)
    changed = np.zeros(T.shape[0], dtype=bool)
    changed[[3, 40]] = True
    a = rt.TetMesh(V, T, repair=False, merge_tol=0.0)
    b = rt.TetMesh(V, T, repair=False, merge_tol=0.0, _changed=(changed, a.report.n_components))
    assert str(a.report) == str(b.report) and a.report.n_boundary_faces == 2 * (5 * 2 + 5 * 2 + 2 * 2) * 2
    assert np.array_equal(a.tets, b.tets) and np.array_equal(a.vertices, b.vertices)
