"""Mesh files (rtfem.mesh.files): every reference organ loads, formats round-trip through
save_mesh/load_mesh, what meshio cannot read is read, broken files are refused in words."""

import numpy as np
import pytest

import rtfem as rt
from conftest import organ

ORGAN_FILES = {
    # name: (vertices, triangles) as listed in shared/data/organs/README.md
    "sofa_liver2.obj": (1170, 2336),
    "sofa_liver-smooth.obj": (2194, 4384),
    "sofa_env_Liver.stl": (15365, 30726),
    "sofa_env_gallbladder_collision.stl": (252, 500),
    "sofa_env_gallbladder_visual.stl": (7352, 14700),
    "GCA-Models_small_intestine_20k.vtk": (10002, 20000),
}


@pytest.mark.parametrize("name", sorted(ORGAN_FILES))
def test_every_reference_organ_loads_closed(name):
    mesh = rt.load_mesh(organ(name), scale=1e-3)
    nv, nt = ORGAN_FILES[name]
    assert (mesh.n_vertices, mesh.n_triangles) == (nv, nt)
    assert mesh.is_closed() and mesh.report.closed
    assert mesh.report.n_components == 1
    assert mesh.volume() > 0  # outward orientation
    assert np.isfinite(mesh.report.min_angle_deg)
    assert "scaled by 0.001" in str(mesh.report)


def test_legacy_vtk_that_meshio_refuses():
    import meshio

    path = organ("GCA-Models_small_intestine_20k.vtk")
    with pytest.raises((Exception, SystemExit)):  # meshio 5.3 even calls sys.exit here
        meshio.read(str(path))
    mesh = rt.load_mesh(path)
    assert mesh.n_triangles == 20000
    # its coordinates are in millimetres: about 26 x 15 x 30 cm
    assert 200 < mesh.bounds()[1][0] - mesh.bounds()[0][0] < 300


@pytest.mark.parametrize("suffix", [".obj", ".stl", ".ply", ".off", ".vtk", ".vtu", ".msh"])
def test_formats_round_trip(tmp_path, suffix):
    import meshio

    src = rt.meshes.liver(2)
    path = tmp_path / f"liver{suffix}"
    kw = {"file_format": "gmsh22", "binary": False} if suffix == ".msh" else {}
    meshio.write_points_cells(str(path), np.asarray(src.vertices), [("triangle", np.asarray(src.triangles))], **kw)
    mesh = rt.load_mesh(path)
    assert (mesh.n_vertices, mesh.n_triangles) == (src.n_vertices, src.n_triangles)
    assert mesh.areas().sum() == pytest.approx(src.areas().sum(), rel=1e-6)
    assert mesh.volume() == pytest.approx(src.volume(), rel=1e-6)


def test_save_mesh_and_quads_split(tmp_path):
    path = tmp_path / "quads.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 2 0 0\nv 2 1 0\nf 1 2 3 4\nf 2 5 6 3\n")
    mesh = rt.load_mesh(path)
    assert mesh.n_triangles == 4 and mesh.areas().sum() == pytest.approx(2.0)
    out = tmp_path / "out.vtu"
    rt.save_mesh(mesh, out, point_data={"u": np.ones((mesh.n_vertices, 3))})
    assert rt.load_mesh(out).n_triangles == 4


def test_tet_volume_mesh_loads_as_a_volume_with_its_surface(tmp_path):
    import meshio

    pts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]], float)
    tets = np.array([[0, 1, 2, 3], [1, 2, 3, 4]])
    path = tmp_path / "tets.vtu"
    meshio.write_points_cells(str(path), pts, [("tetra", tets)])
    mesh = rt.load_mesh(path)
    assert isinstance(mesh, rt.TetMesh) and mesh.n_tets == 2
    surface = mesh.surface
    assert surface.n_triangles == 6 and surface.is_closed() and surface.volume() == pytest.approx(mesh.volume())


def test_broken_files_raise_mesh_error(tmp_path):
    with pytest.raises(rt.MeshError, match="does not exist"):
        rt.load_mesh(tmp_path / "missing.obj")
    junk = tmp_path / "junk.stl"
    junk.write_bytes(b"\x00\x01garbage" * 3)
    with pytest.raises(rt.MeshError, match="could not read"):
        rt.load_mesh(junk)
    trunc = tmp_path / "trunc.vtk"
    trunc.write_text("# vtk DataFile Version 2.0\nx\nASCII\nDATASET POLYDATA\nPOINTS 3 float\n0 0 0 1 0 0\n")
    with pytest.raises(rt.MeshError, match="truncated"):
        rt.load_mesh(trunc)
    lines = tmp_path / "lines.vtu"
    import meshio

    meshio.write_points_cells(str(lines), np.eye(3), [("line", np.array([[0, 1], [1, 2]]))])
    with pytest.raises(rt.MeshError, match="no surface cells"):
        rt.load_mesh(lines)
    nan = tmp_path / "nan.obj"
    nan.write_text("v 0 0 0\nv 1 0 nan\nv 0 1 0\nf 1 2 3\n")
    with pytest.raises(rt.MeshError, match="vertex 1"):
        rt.load_mesh(nan)
    with pytest.raises(rt.MeshError, match="scale"):
        rt.load_mesh(nan, scale=-1)


@pytest.mark.parametrize("cells, types, what", [
    ("CELLS 2 9\n4 0 1 2 3\n3 0 1 2", "10\n10", "cell 1 is VTK type 10 .tetra. with 3 node indices, not 4"),
    ("CELLS 2 8\n3 0 1 2\n3 0 1 3", "5\n10", "cell 1 is VTK type 10 .tetra. with 3 node indices, not 4"),
    ("CELLS 2 9\n3 0 1 2\n4 0 1 3 2", "5\n5", "cell 1 is VTK type 5 .triangle. with 4 node indices, not 3"),
    ("CELLS 1 3\n2 0 1", "7", "cell 0 is VTK type 7 .polygon. with 2 node indices, not at least 3"),
])
def test_a_ragged_legacy_vtk_cell_list_is_a_mesh_error(tmp_path, cells, types, what):
    """Cells whose index count does not match their VTK type (issue 53): a ValueError traceback from
    numpy's stacking before; one MeshError naming the cell, and the CLI's exit 2."""
    f = tmp_path / "ragged.vtk"
    f.write_text("# vtk DataFile Version 3.0\nr\nASCII\nDATASET UNSTRUCTURED_GRID\nPOINTS 4 float\n"
                 f"0 0 0 1 0 0 0 1 0 0 0 1\n{cells}\nCELL_TYPES {types.count(chr(10)) + 1}\n{types}\n")
    with pytest.raises(rt.MeshError, match=what):
        rt.load_mesh(f)
    import subprocess
    import sys

    r = subprocess.run([sys.executable, "-m", "rtfem.cli.main", "info", str(f)], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 2 and "Traceback" not in r.stderr and "node indices" in r.stderr




def test_obj_reader_takes_negative_and_slashed_indices(tmp_path):
    """OBJ faces may use relative (negative) indices and v/vt/vn triplets: the same square."""
    a = tmp_path / "a.obj"
    a.write_text("v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3\nf 1 3 4\n")
    b = tmp_path / "b.obj"
    b.write_text("v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvt 0 0\nvn 0 0 1\nf -4/1/1 -3/1/1 -2/1/1\nf 1//1 3//1 4//1\n")
    ma, mb = rt.load_mesh(a), rt.load_mesh(b)
    assert np.array_equal(ma.triangles, mb.triangles) and np.array_equal(ma.vertices, mb.vertices)
    bad = tmp_path / "bad.obj"
    bad.write_text("v 0 0 0\nv 1 0 0\nv 1 1 0\nf 1 2 7\n")
    with pytest.raises(rt.MeshError, match="line 4"):
        rt.load_mesh(bad)


@pytest.mark.parametrize("suffix", [".obj", ".stl", ".ply", ".vtu", ".off"])
def test_save_mesh_then_load_mesh_gives_the_same_surface(tmp_path, suffix):
    src = rt.meshes.liver(2)
    path = tmp_path / f"out{suffix}"
    rt.save_mesh(src, path)
    back = rt.load_mesh(path)
    assert (back.n_vertices, back.n_triangles) == (src.n_vertices, src.n_triangles)
    # same geometry, vertex for vertex (STL is single precision)
    tol = 1e-6 if suffix == ".stl" else 1e-12
    d, idx = __import__("scipy.spatial", fromlist=["cKDTree"]).cKDTree(src.vertices).query(back.vertices)
    assert d.max() <= tol * np.abs(src.vertices).max() and np.unique(idx).size == src.n_vertices
    assert back.volume() == pytest.approx(src.volume(), rel=1e-6)


def test_save_mesh_refuses_an_unknown_suffix_and_keeps_the_old_file(tmp_path):
    src = rt.meshes.liver(2)
    path = tmp_path / "keep.obj"
    rt.save_mesh(src, path)
    before = path.read_bytes()
    with pytest.raises(rt.MeshError, match="suffix"):
        rt.save_mesh(src, tmp_path / "x.nope")
    with pytest.raises(rt.RtfemError, match="162 rows"):
        rt.save_mesh(src, path, point_data={"u": np.ones((3, 3))})  # wrong length: refused before writing
    assert path.read_bytes() == before
