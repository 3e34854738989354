"""Exports and saved files (rtfem.io, rtfem.storage): VTU/PVD contents read back by meshio, versioned .npz
round trips with their types, atomic replacement."""

from __future__ import annotations

import xml.etree.ElementTree as ET

import numpy as np
import pytest

import rtfem as rt
from rtfem.io import write_pvd, write_vtu
from rtfem.storage import atomic_target, load_versioned, save_versioned


def test_vtu_holds_the_reference_points_and_the_displacement_field(tmp_path):
    """ParaView's convention: the points at rest and the field beside them, so that Warp By Vector
    (points + displacement) is the deformed organ, counted once; the field data says which."""
    import meshio

    mesh = rt.meshes.liver(2)
    X = np.asarray(mesh.vertices)
    U = np.random.default_rng(0).normal(scale=1e-3, size=(mesh.n_vertices, 3))
    m = meshio.read(write_vtu(tmp_path / "a.vtu", mesh, U))
    np.testing.assert_array_equal(m.points, X)
    np.testing.assert_array_equal(m.points + m.point_data["displacement"], X + U)
    np.testing.assert_allclose(m.point_data["displacement_magnitude"], np.linalg.norm(U, axis=1), rtol=1e-12)
    assert np.array_equal(m.cells_dict["triangle"], mesh.triangles)
    assert m.field_data["rtfem_reference_points"].tolist() == [1]
    moved = meshio.read(write_vtu(tmp_path / "b.vtu", mesh, U, deformed=True))  # asked for: the points displaced
    np.testing.assert_allclose(moved.points, X + U, rtol=1e-12)
    assert moved.field_data["rtfem_reference_points"].tolist() == [0]
    with pytest.raises(rt.ModelError, match="deformed"):
        write_vtu(tmp_path / "c.vtu", mesh, U, deformed="yes")


def test_a_runs_frames_are_the_reference_points_with_the_displacement(tmp_path):
    """RunWriter (rtfem simulate, scenes) writes its frames through write_vtu: reference + field."""
    import meshio

    from rtfem.io.scenario import RunWriter

    tets = rt.meshes.box(0.1, 0.1, 0.05, nx=2, ny=2, nz=1)
    U = np.random.default_rng(1).normal(scale=1e-3, size=(tets.n_vertices, 3))
    writer = RunWriter(tmp_path, tets, ["t"], 1)
    writer.frame(0, 0.0, U)
    writer.close()
    m = meshio.read(tmp_path / "frame_00000.vtu")
    assert m.cells[0].type == "tetra"
    np.testing.assert_array_equal(m.points, tets.vertices)
    np.testing.assert_array_equal(m.points + m.point_data["displacement"], np.asarray(tets.vertices) + U)


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


def test_a_save_killed_while_it_writes_leaves_no_file_behind(tmp_path):
    """SIGKILL in the middle of a versioned save (issue 53: its temporary file stayed until the next save
    of that name): the file being written has no name until it is complete (O_TMPFILE), so nothing is
    left, and the old file is untouched."""
    import os
    import signal
    import subprocess
    import sys
    import textwrap

    if not hasattr(os, "O_TMPFILE"):
        pytest.skip("no O_TMPFILE on this system: the named temporary file is swept at the next save instead")
    target = tmp_path / "basis.npz"
    save_versioned(target, "rtfem.Test", 1, {"a": np.arange(3.0)}, {})
    before = target.read_bytes()
    code = textwrap.dedent(f"""
        import time
        import numpy as np
        from rtfem import storage

        def hung(fh, **arrays):  # a save that writes a megabyte, then hangs until it is killed
            fh.write(b"x" * 1000000)
            fh.flush()
            print("writing", flush=True)
            time.sleep(120)

        np.savez = hung
        storage.save_versioned({str(target)!r}, "rtfem.Test", 1, {{"a": np.zeros(10)}}, {{}})
    """)
    p = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    try:
        assert p.stdout.readline().strip() == "writing"
        os.kill(p.pid, signal.SIGKILL)
        p.wait(timeout=30)
    finally:
        if p.poll() is None:
            p.kill()
    assert sorted(f.name for f in tmp_path.iterdir()) == ["basis.npz"] and target.read_bytes() == before


def test_a_save_sweeps_the_temporary_files_of_killed_saves_from_its_folder(tmp_path):
    """A named temporary file a killed writer left (``atomic_target``'s, for writers that need a path)
    goes at the next save into the folder, whatever that save's name; a live process's stays."""
    import os

    dead = 2**22 + 12345  # above Linux's default pid_max (4,194,304): no such process
    stale = tmp_path / f".mesh.vtu.{dead}.abc123.tmp.vtu"
    live = tmp_path / f".mesh.vtu.{os.getpid()}.def456.tmp.vtu"
    for f in (stale, live):
        f.write_text("half")
    save_versioned(tmp_path / "other.npz", "rtfem.Test", 1, {"a": np.zeros(2)}, {})
    assert not stale.exists() and live.exists()
    with atomic_target(tmp_path / "notes.txt") as tmp:
        tmp.write_text("x")
    assert live.exists() and sorted(f.name for f in tmp_path.iterdir() if not f.name.startswith(".")) == \
        ["notes.txt", "other.npz"]


@pytest.mark.parametrize("without", ["linkat", "O_TMPFILE"])
def test_a_versioned_save_without_anonymous_files_still_replaces_in_one_step(tmp_path, monkeypatch, without):
    """Where the system has no linkat through /proc or no O_TMPFILE, the save falls back on a named
    temporary file renamed over the target: the same file, and no temporary left."""
    import os

    from rtfem import storage

    if without == "linkat":
        monkeypatch.setattr(storage, "_link", lambda fd, name: False)
    else:
        monkeypatch.delattr(os, "O_TMPFILE", raising=False)
    target = tmp_path / "x.npz"
    for value in (1.0, 2.0):
        save_versioned(target, "rtfem.Test", 1, {"a": np.full(4, value)}, {"v": value})
        arrays, info = load_versioned(target, "rtfem.Test", 1, ["a"], "test")
        assert np.array_equal(arrays["a"], np.full(4, value)) and info["v"] == value
    assert sorted(f.name for f in tmp_path.iterdir()) == ["x.npz"]
