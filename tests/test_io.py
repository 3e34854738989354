"""Exports and saved files (rtfem.io, rtfem.storage): VTU/PVD contents read back by meshio, versioned .npz
round trips with their types, atomic replacement."""

from __future__ import annotations

import xml.etree.ElementTree as ET

import numpy as np
import pytest

import rtfem as rt
from rtfem.io import write_pvd, write_vtu
from rtfem.storage import atomic_target, load_versioned, save_versioned


def test_vtu_holds_the_deformed_points_and_the_displacement_field(tmp_path):
    import meshio

    mesh = rt.meshes.liver(2)
    U = np.random.default_rng(0).normal(scale=1e-3, size=(mesh.n_vertices, 3))
    m = meshio.read(write_vtu(tmp_path / "a.vtu", mesh, U))
    np.testing.assert_allclose(m.points, np.asarray(mesh.vertices) + U, rtol=1e-12)
    np.testing.assert_allclose(m.point_data["displacement"], U, rtol=1e-12)
    np.testing.assert_allclose(m.point_data["displacement_magnitude"], np.linalg.norm(U, axis=1), rtol=1e-12)
    assert np.array_equal(m.cells_dict["triangle"], mesh.triangles)
    und = meshio.read(write_vtu(tmp_path / "b.vtu", mesh, U, deformed=False))
    np.testing.assert_allclose(und.points, mesh.vertices, rtol=1e-12)


def test_pvd_lists_the_frames_in_time_order(tmp_path):
    mesh = rt.meshes.liver(2)
    frames = [(k * 0.01, write_vtu(tmp_path / f"f{k}.vtu", mesh, np.zeros((mesh.n_vertices, 3)))) for k in range(3)]
    root = ET.parse(write_pvd(tmp_path / "run.pvd", frames)).getroot()
    ds = root.findall(".//DataSet")
    assert [float(d.get("timestep")) for d in ds] == [0.0, 0.01, 0.02]
    assert all((tmp_path / d.get("file")).exists() for d in ds)


def test_versioned_npz_round_trips_arrays_and_typed_metadata(tmp_path):
    arrays = {"a": np.arange(6.0).reshape(2, 3), "i": np.array([3, 1, 2]), "s": np.array("text")}
    info = {"flag": False, "n": 7, "x": 0.5, "name": "liver", "lst": [1, 2.5, "z"]}
    path = save_versioned(tmp_path / "x", "rtfem.Test", 2, arrays, info)
    assert path.suffix == ".npz"
    z, back = load_versioned(path, "rtfem.Test", 2, ["a", "i", "s"], "test file")
    for k, v in arrays.items():
        assert np.array_equal(z[k], v) and z[k].dtype == v.dtype
    assert back == info and back["flag"] is False and isinstance(back["n"], int)
    newer = save_versioned(tmp_path / "y", "rtfem.Test", 3, arrays, info)  # a file from a later rtfem
    with pytest.raises(rt.RtfemError, match="version 3; this rtfem reads up to 2"):
        load_versioned(newer, "rtfem.Test", 2, ["a"], "test file")
    with pytest.raises(rt.RtfemError):
        load_versioned(path, "rtfem.Other", 2, ["a"], "test file")


def test_an_atomic_write_that_fails_leaves_the_old_file_and_no_temporary(tmp_path):
    target = tmp_path / "keep.txt"
    target.write_text("old")
    with pytest.raises(RuntimeError):
        with atomic_target(target) as tmp:
            tmp.write_text("half")
            raise RuntimeError("disk full")
    assert target.read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["keep.txt"]
    with atomic_target(target) as tmp:
        tmp.write_text("new")
    assert target.read_text() == "new" and sorted(p.name for p in tmp_path.iterdir()) == ["keep.txt"]
