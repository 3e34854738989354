"""Load schedules, the scripted press and the run writer (rtfem.io.scenario, ScriptedDevice.press)."""

from __future__ import annotations

import csv

import numpy as np
import pytest

import rtfem as rt
from rtfem.io.scenario import LoadSchedule, RunWriter


def test_a_schedule_holds_each_nodes_force_until_its_next_row():
    s = LoadSchedule([(0.0, 3, (0, 0, 1)), (0.5, 7, (1, 0, 0)), (1.0, 3, (0, 0, 0)), (0.5, 3, (0, 0, 2))], 10)
    assert s.nodes == [3, 7] and s.switches == [0.0, 0.5, 1.0]
    assert s.forces_at(-0.1) == {}
    assert s.forces_at(0.2)[3].tolist() == [0, 0, 1] and 7 not in s.forces_at(0.2)
    assert s.forces_at(0.7)[3].tolist() == [0, 0, 2] and s.forces_at(0.7)[7].tolist() == [1, 0, 0]
    assert set(s.forces_at(2.0)) == {7}  # node 3's zero row ended its load
    pw = s.piecewise()
    assert [t for t, _ in pw] == [0.0, 0.5, 1.0] and pw[1][1][3].tolist() == [0, 0, 2]


def test_schedule_rows_are_checked(tmp_path):
    with pytest.raises(rt.RtfemError, match="node"):
        LoadSchedule([(0.0, 12, (0, 0, 1))], 10)
    with pytest.raises(rt.RtfemError, match="time"):
        LoadSchedule([(-1.0, 1, (0, 0, 1))], 10)
    f = tmp_path / "loads.csv"
    f.write_text("t,node,fx,fy,fz\n0,1,0,0,1\n0.1,1,x,0,0\n")
    with pytest.raises(rt.RtfemError, match="line 3"):
        LoadSchedule.from_csv(f, 10)


def test_sldm_answers_a_schedule_as_it_answers_its_piecewise_list():
    model = rt.ShellModel(rt.meshes.liver(2), rt.Material()).fix("attachment")
    node = int(model.mesh.groups["probe"][0])
    s = LoadSchedule([(0.0, node, (0, 0, -0.1)), (0.02, node, (0, 0, 0))], model.n_nodes)
    times = np.linspace(0.005, 0.05, 10)
    sldm = rt.SLDM(model, rt.Damping(alpha=8.0))
    np.testing.assert_array_equal(sldm.response(s, times), sldm.response(s.piecewise(), times))


def test_the_scripted_press_follows_its_depth_profile():
    X, n = np.array([0.1, 0.0, 0.0]), np.array([0.0, 0.0, 2.0])
    dev = rt.ScriptedDevice.press(X, n, depth=0.004, duration=1.0, approach=0.002, ramp=0.2, release=0.6)
    depth = lambda t: float((X - dev.position(t)) @ np.array([0, 0, 1.0]))  # noqa: E731
    assert depth(0.0) == pytest.approx(-0.002)
    assert depth(0.1) == pytest.approx(0.001)  # half way down the ramp
    assert depth(0.2) == pytest.approx(0.004) and depth(0.5) == pytest.approx(0.004)
    assert depth(0.7) == pytest.approx(0.001) and depth(0.9) == pytest.approx(-0.002)
    rep = rt.ScriptedDevice.press(X, n, 0.004, 1.0, repeat=True)
    np.testing.assert_allclose(rep.position(1.3), rep.position(0.3))
    with pytest.raises(rt.RtfemError, match="normal"):
        rt.ScriptedDevice.press(X, (0, 0, 0), 0.004, 1.0)


def test_the_run_writer_writes_rows_and_frames_at_its_rate(tmp_path):
    mesh = rt.meshes.liver(2)
    w = RunWriter(tmp_path / "run", mesh, ["t", "x"], frame_every=3)
    for k in range(1, 10):
        w.row([k * 0.1, 2.0 * k])
        w.frame(k, k * 0.1, lambda: np.zeros((mesh.n_vertices, 3)))
    csv_path, pvd = w.close()
    rows = list(csv.reader(open(csv_path)))
    assert rows[0] == ["t", "x"] and len(rows) == 10 and float(rows[-1][1]) == 18.0
    assert [t for t, _ in w.frames] == pytest.approx([0.3, 0.6, 0.9]) and pvd.exists()
