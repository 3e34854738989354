"""`rtfem view out.pvd` / `rtfem view DIR` (rtfem.viewer.replay): a written run read back and replayed,
whichever way its VTUs place the points (the reference with the displacement field, or the displaced
points), a scene's folder of bodies on one clock, the clock's transport, and what a bad path says."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest
from conftest import serves_and_stops_on_ctrl_c

import rtfem as rt
from rtfem.viewer.replay import Replay, boundary, read_run

# one tet and a field that grows with time: u(t) = t * (node index + 1) * (1, 2, 3) mm
X = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.1, 0.0], [0.0, 0.0, 0.1]])
TET = [("tetra", np.array([[0, 1, 2, 3]]))]
TIMES = (0.0, 0.1, 0.2)


def _u(t: float) -> np.ndarray:
    return t * 1e-3 * np.outer(np.arange(1, 5), [1.0, 2.0, 3.0])


def _write(folder: Path, name: str, how: str, cells=TET, times=TIMES) -> Path:
    """A .pvd of frames written ``how``: "marked-reference" (rtfem's writer now: points at rest, the
    field, rtfem_reference_points = 1), "marked-displaced" (= 0), "reference" and "displaced" (no marker:
    another code's files, and rtfem's before the marker)."""
    import meshio

    folder.mkdir(parents=True, exist_ok=True)
    rows = []
    for k, t in enumerate(times):
        u = _u(t)
        points = X + u if how.endswith("displaced") else X
        path = folder / f"{name}_{k}.vtu"
        meshio.write_points_cells(str(path), points, cells, point_data={"displacement": u}, binary=True,
                                  file_format="vtu")
        if how.startswith("marked"):
            mark = b"1" if how == "marked-reference" else b"0"
            text = path.read_bytes()
            path.write_bytes(text.replace(b"<UnstructuredGrid>", b'<UnstructuredGrid>\n<FieldData>\n<DataArray type="Int8" '
                                          b'Name="rtfem_reference_points" NumberOfTuples="1" format="ascii">' + mark
                                          + b"</DataArray>\n</FieldData>", 1))
        rows.append(f'<DataSet timestep="{t}" group="" part="0" file="{path.name}"/>')
    pvd = folder / f"{name}.pvd"
    pvd.write_text('<?xml version="1.0"?>\n<VTKFile type="Collection" version="0.1"><Collection>\n'
                   + "\n".join(rows) + "\n</Collection></VTKFile>\n")
    return pvd


@pytest.mark.parametrize("how, convention", [("marked-reference", "reference + displacement"),
                                             ("marked-displaced", "displaced points"),
                                             ("reference", "reference + displacement"),
                                             ("displaced", "displaced points")])
def test_each_way_of_writing_the_points_is_drawn_where_the_body_was(tmp_path, how, convention):
    (track,) = read_run(_write(tmp_path, "run", how))
    assert track.convention == convention and track.times.tolist() == list(TIMES)
    assert track.positions.shape == (3, 4, 3) and len(track.triangles) == 4  # the tet's four faces
    for k, t in enumerate(TIMES):  # drawn at X + u(t) whichever way the file put it
        np.testing.assert_allclose(track.positions[k], X + _u(t), rtol=0, atol=1e-7)
        np.testing.assert_allclose(track.magnitudes[k], np.linalg.norm(_u(t), axis=1), rtol=1e-6)
    assert track.frame_at(0.15) == 1 and track.frame_at(-1.0) == 0 and track.frame_at(9.0) == 2


def test_a_scene_folder_replays_its_bodies_together_and_a_shell_draws_its_triangles(tmp_path):
    _write(tmp_path / "liver", "liver", "marked-reference")
    _write(tmp_path / "gallbladder", "gallbladder", "displaced", cells=[("triangle", np.array([[0, 1, 2], [0, 2, 3]]))],
           times=(0.0, 0.05, 0.1, 0.2))
    tracks = read_run(tmp_path)
    assert [t.name for t in tracks] == ["gallbladder", "liver"]  # one per body folder
    assert tracks[0].triangles.tolist() == [[0, 1, 2], [0, 2, 3]]
    clock = Replay(tracks)
    assert clock.begin == 0.0 and clock.end_time == pytest.approx(0.2)


def test_the_boundary_of_tets_is_their_unshared_faces_wound_outward():
    # two tets sharing the face (1, 2, 3): six outer faces
    V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]], dtype=float)
    T = np.array([[0, 1, 2, 3], [4, 1, 3, 2]])
    faces = boundary([("tetra", T)], 5)
    assert len(faces) == 6 and not any(set(f) == {1, 2, 3} for f in faces.tolist())
    centre = V.mean(axis=0)
    for f in faces:
        a, b, c = V[f]
        assert np.cross(b - a, c - a) @ (a - centre) > 0  # outward


def test_the_replay_clock_plays_pauses_restarts_and_stops_at_the_end(tmp_path):
    clock = Replay(read_run(_write(tmp_path, "run", "marked-reference", times=(0.0, 0.15, 0.3))))
    assert clock.time == 0.0 and not clock.playing
    clock.play()
    time.sleep(0.1)
    clock.pause()
    t = clock.time
    assert 0.05 < t < 0.3 and not clock.playing
    time.sleep(0.05)
    assert clock.time == t
    clock.request_seek(9.0)
    assert clock.time == 0.3  # clamped to the last frame
    clock.play()  # played at the end: from the start again
    time.sleep(0.35)
    assert clock.time == 0.3 and not clock.playing  # stopped at the end
    clock.restart()
    assert clock.time == 0.0


def test_a_bad_run_says_what_is_wrong(tmp_path):
    with pytest.raises(rt.ModelError, match="does not exist"):
        read_run(tmp_path / "nothing.pvd")
    with pytest.raises(rt.ModelError, match="holds no .pvd"):
        read_run(tmp_path)
    (tmp_path / "empty.pvd").write_text("<VTKFile><Collection></Collection></VTKFile>")
    with pytest.raises(rt.ModelError, match="lists no frames"):
        read_run(tmp_path / "empty.pvd")
    (tmp_path / "bad.pvd").write_text("<VTKFile><Collection>")
    with pytest.raises(rt.ModelError, match="not a ParaView collection"):
        read_run(tmp_path / "bad.pvd")
    (tmp_path / "gone.pvd").write_text('<VTKFile><Collection><DataSet timestep="0" file="f.vtu"/></Collection></VTKFile>')
    with pytest.raises(rt.ModelError, match="f.vtu"):
        read_run(tmp_path / "gone.pvd")
    pvd = _write(tmp_path / "two", "run", "reference")
    import meshio

    meshio.write_points_cells(str(pvd.parent / "run_2.vtu"), np.vstack([X, X[:1]]), TET, file_format="vtu")
    with pytest.raises(rt.ModelError, match="share one mesh"):
        read_run(pvd)


def test_rtfem_simulate_output_replays_and_rtfem_view_serves_it(tmp_path):
    """`rtfem simulate` writes a run; its replay draws each frame where the run left the organ (the
    written field added to the points where they are the reference); `rtfem view DIR` serves it and
    stops on Ctrl-C."""
    import meshio

    from rtfem.cli.main import main

    out = tmp_path / "sim"
    assert main(["simulate", "--duration", "0.05", "--fps", "100", "--out", str(out)]) == 0
    (track,) = read_run(out)
    assert track.times.size == 5 and track.name == "response"
    m = meshio.read(str(sorted(out.glob("*.vtu"))[-1]))
    reference = int(np.ravel(m.field_data.get("rtfem_reference_points", [0]))[0]) == 1
    deformed = np.asarray(m.points) + (np.asarray(m.point_data["displacement"]) if reference else 0.0)
    drawn = np.unique(boundary([(c.type, c.data) for c in m.cells], len(m.points)))
    np.testing.assert_allclose(track.positions[-1], deformed[drawn], rtol=0, atol=1e-7)
    assert track.magnitudes[-1].max() > 1e-4  # the probe's press is in the frames

    pytest.importorskip("viser")
    serves_and_stops_on_ctrl_c(out)


def test_the_replay_viewer_shows_the_frame_of_the_clock(tmp_path):
    pytest.importorskip("viser")
    from rtfem.viewer.replay import ReplayViewer

    v = ReplayViewer(read_run(_write(tmp_path, "run", "marked-reference")), port=_free_port()).start()
    try:
        time.sleep(0.3)
        assert v.state()["frames_shown"] == [0] and not v.state()["playing"]  # waits for a browser
        v.session.request_seek(0.12)
        time.sleep(0.3)
        assert v.state()["frames_shown"] == [1]
        v.session.restart()
        time.sleep(0.3)
        assert v.state()["frames_shown"] == [0] and v.state()["conventions"] == ["reference + displacement"]
    finally:
        v.stop()


def test_rtfem_view_refuses_a_run_with_live_options(tmp_path, capsys):
    from rtfem.cli.main import main

    pvd = _write(tmp_path, "run", "reference")
    assert main(["view", str(pvd), "--benchmark", "1"]) == 2
    assert "written run" in capsys.readouterr().err


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]
