import numpy as np
import pytest

import rtfem as rt

def test_stl_triangle_soup_is_welded(tmp_path):
    src = rt.meshes.icosphere(0.05, 2)
    soup = np.asarray(src.vertices)[np.asarray(src.triangles)].reshape(-1, 3)
    mesh = rt.TriMesh(soup, np.arange(soup.shape[0]).reshape(-1, 3))
    assert mesh.n_vertices == src.n_vertices
    assert mesh.report.merged_vertices == soup.shape[0] - src.n_vertices
    assert mesh.is_closed()
    assert np.all(mesh.vertex_map >= 0)


def test_repairs_are_reported():
    V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [1, 0, 0], [5, 5, 5], [2, 0, 0]], float)
    T = np.array([
        [0, 1, 2],
        [2, 3, 4],  # uses the duplicate of vertex 1 (index 4) with flipped orientation
        [0, 0, 2],  # repeated vertex: degenerate
        [0, 1, 6],  # collinear: zero area
        [2, 1, 0],  # duplicate of the first triangle
    ])
    mesh = rt.TriMesh(V, T)
    r = mesh.report
    assert r.merged_vertices == 1
    assert r.removed_degenerate == 2
    assert r.removed_duplicate_triangles == 1
    assert r.dropped_unreferenced == 2  # vertex 5 and vertex 6
    assert r.flipped_triangles == 1
    assert r.repaired
    assert mesh.n_vertices == 4 and mesh.n_triangles == 2
    assert mesh.vertex_map.tolist() == [0, 1, 2, 3, 1, -1, -1]
    n = mesh.face_normals()
    assert np.allclose(n[0], n[1])
    text = str(r)
    for words in ("1 duplicate vertices merged", "2 degenerate", "1 duplicate triangles", "flipped"):
        assert words in text


def test_closed_surface_oriented_outward():
    s = rt.meshes.icosphere(1.0, 2)
    inside_out = rt.TriMesh(s.vertices, np.asarray(s.triangles)[:, ::-1])
    assert inside_out.report.flipped_triangles == s.n_triangles
    assert inside_out.volume() == pytest.approx(s.volume())
    assert s.volume() == pytest.approx(4 / 3 * np.pi, rel=0.05)


def test_non_manifold_edge_raises_with_location():
    V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1]], float)
    T = np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4]])
    with pytest.raises(rt.MeshError, match=r"non-manifold.*vertices 0 .* and 1 .*triangles 0, 1, 2"):
        rt.TriMesh(V, T)


def test_bad_arrays_raise():
    V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], float)
    with pytest.raises(rt.MeshError, match="empty"):
        rt.TriMesh(np.zeros((0, 3)), np.zeros((0, 3), int))
    bad = V.copy()
    bad[1, 2] = np.nan
    with pytest.raises(rt.MeshError, match="non-finite .* vertex 1"):
        rt.TriMesh(bad, [[0, 1, 2]])
    with pytest.raises(rt.MeshError, match="triangle 1 refers to a vertex index outside 0..2"):
        rt.TriMesh(V, [[0, 1, 2], [0, 1, 7]])
    with pytest.raises(rt.MeshError, match="triangle 0 refers"):
        rt.TriMesh(V, [[-1, 1, 2]])
    with pytest.raises(rt.MeshError, match=r"\(m, 3\)"):
        rt.TriMesh(V, [[0, 1, 2, 0]])
    with pytest.raises(rt.MeshError, match="integers"):
        rt.TriMesh(V, [[0, 1, 2.5]])
    with pytest.raises(rt.MeshError, match="every triangle is degenerate"):
        rt.TriMesh(V, [[0, 1, 1]])
    with pytest.raises(rt.MeshError, match="repair=True"):
        rt.TriMesh(V, [[0, 1, 1], [0, 1, 2]], repair=False)


def test_moebius_strip_reported_not_orientable():
    n = 12
    th = 2 * np.pi * np.arange(n) / n
    V = []
    for t in th:
        c = np.array([np.cos(t), np.sin(t), 0.0])
        d = np.array([np.cos(t / 2) * np.cos(t), np.cos(t / 2) * np.sin(t), np.sin(t / 2)]) * 0.3
        V += [c - d, c + d]
    V = np.array(V)
    T = []
    for i in range(n):
        a, b = 2 * i, 2 * i + 1
        c, d = (2 * (i + 1), 2 * (i + 1) + 1) if i < n - 1 else (1, 0)  # the half twist
        T += [[a, c, b], [b, c, d]]
    mesh = rt.TriMesh(V, np.array(T))
    assert not mesh.report.orientable
    assert "not orientable" in str(mesh.report)


def test_bow_tie_vertex_reported():
    V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [-1, 0, 0], [0, -1, 0]], float)
    mesh = rt.TriMesh(V, [[0, 1, 2], [0, 3, 4]])
    assert mesh.report.nonmanifold_vertices.tolist() == [0]
    assert "non-manifold vertices" in str(mesh.report)


def test_groups_follow_repairs_and_subdivision():
    p = rt.meshes.plate(1.0, 1.0, 2)
    assert set(p.groups) >= {"x0", "x1", "boundary", "center"}
    q = p.subdivided(1)
    assert q.n_vertices == 25
    assert len(q.groups["x0"]) == 5  # mid-points of the edge are in the group
    assert np.allclose(np.asarray(q.vertices)[q.groups["x0"], 0], 0.0)


def test_topology_queries():
    s = rt.meshes.icosphere(1.0, 2)
    assert s.n_vertices - s.edges().shape[0] + s.n_triangles == 2  # genus 0
    assert s.is_closed() and s.boundary_vertices().size == 0
    h = rt.meshes.hemisphere(1.0, 6)
    assert np.array_equal(np.sort(h.boundary_vertices()), np.sort(h.groups["rim"]))
    assert s.nearest_vertex([0, 0, 2.0]) == int(np.argmax(np.asarray(s.vertices)[:, 2]))
    assert np.allclose(np.linalg.norm(s.vertex_normals(), axis=1), 1.0)
    assert s.vertex_areas().sum() == pytest.approx(s.areas().sum())


def test_unique_rows_is_numpys_unique_of_rows():
    """The packed-key unique of integer rows (issue 54: a mesh's checks on loading) gives np.unique(axis=0)'s
    answer, row order, first indices, inverse and counts, and falls back to it where rows cannot be packed."""
    from rtfem.mesh.repair import unique_rows

    rng = np.random.default_rng(0)
    cases = [rng.integers(0, n, (m, k)) for n, m, k in [(1, 5, 2), (7, 200, 2), (40, 300, 3), (1000, 50, 4), (5, 0, 3)]]
    cases += [np.array([[2**40, 1], [0, 2**40]]), np.array([[-1, 2], [-1, 2]]), rng.random((20, 2))]
    for a in cases:
        for flags in ({}, {"return_index": True, "return_inverse": True, "return_counts": True}, {"return_inverse": True}):
            got, want = unique_rows(a, **flags), np.unique(a, axis=0, **flags)
            got, want = (got, want) if flags else ((got,), (want,))
            assert all(np.array_equal(g.ravel(), w.ravel()) and g.dtype == w.dtype for g, w in zip(got, want))


def test_components_and_close_pairs_are_scipys():
    """The numpy graph helpers that spare loading a mesh scipy.sparse.csgraph and scipy.spatial (issue 54)
    give csgraph's component labels and cKDTree's pairs within a distance."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    from rtfem.mesh.repair import close_pairs, components

    rng = np.random.default_rng(1)
    for _ in range(100):
        n, e = int(rng.integers(1, 60)), int(rng.integers(0, 80))
        i, j = rng.integers(0, n, e), rng.integers(0, n, e)
        k, label = connected_components(coo_matrix((np.ones(e), (i, j)), shape=(n, n)), directed=False)
        got = components(n, i, j)
        assert got[0] == k and np.array_equal(got[1], label)
    for _ in range(50):
        n = int(rng.integers(2, 300))
        P = rng.random((n, 3)) * rng.choice([1e-3, 1.0, 100.0])
        P[rng.integers(0, n, n // 5)] = P[rng.integers(0, n, n // 5)] + rng.normal(0, 1e-4, (n // 5, 3))
        tol = float(rng.choice([1e-5, 1e-3, 0.05, 0.2]))
        want = {tuple(p) for p in np.sort(cKDTree(P).query_pairs(tol, output_type="ndarray"), axis=1).tolist()}
        got = close_pairs(P, tol)
        assert {tuple(p) for p in got.tolist()} == want and len(got) == len(want)
