"""Bad arguments to the entry points added by the protocols issue (11) and the speed issue (12):
an RtfemError with a message, and the state of the object as it was."""

from __future__ import annotations

import numpy as np
import pytest

import rtfem as rt
from rtfem.io.scenario import LoadSchedule, RunWriter


@pytest.fixture(scope="module")
def world():
    mesh = rt.meshes.liver(2)
    model = rt.ShellModel(mesh, rt.Material()).fix("attachment")
    node = int(mesh.groups["probe"][0])
    imap = rt.ImpedanceMap.build(model, rt.Damping(alpha=8.0), nodes=[node], n_modes=8)
    return mesh, model, node, imap


@pytest.mark.parametrize("spec", ["nope", "z<abc", "bottom:2", "nodes:1,x", "nodes:99999", [1.5], np.ones(3, bool),
                                  object(), -1])
def test_select_nodes_refuses_what_it_cannot_read(world, spec):
    mesh = world[0]
    with pytest.raises(rt.RtfemError):
        rt.select_nodes(mesh, spec)


@pytest.mark.parametrize("bad", [None, "liver.stl", np.eye(3), object()])
def test_make_model_and_check_model_refuse_non_models(bad):
    with pytest.raises(rt.RtfemError):
        rt.make_model(bad, rt.Material())
    with pytest.raises(rt.RtfemError, match="not a model"):
        rt.modal_analysis(bad, 4)


@pytest.mark.parametrize("kw", [dict(normal=(0, 0, 0)), dict(depth=float("nan")), dict(duration=0.0),
                                dict(approach=-1.0), dict(ramp=0.7), dict(release=0.05), dict(point="here"),
                                dict(repeat="yes")])
def test_the_scripted_press_refuses_bad_arguments(kw):
    args = dict(point=(0.0, 0.0, 0.0), normal=(0, 0, 1), depth=0.004, duration=1.0) | kw
    with pytest.raises(rt.RtfemError):
        rt.ScriptedDevice.press(args.pop("point"), args.pop("normal"), args.pop("depth"), args.pop("duration"), **args)


def test_a_run_writer_refuses_a_file_for_a_folder(world, tmp_path):
    f = tmp_path / "file"
    f.write_text("x")
    with pytest.raises(rt.RtfemError, match="folder"):
        RunWriter(f, world[0], ["t"])
    assert f.read_text() == "x"
    with pytest.raises(rt.RtfemError):
        LoadSchedule("0,1,0,0,1", 10)


def test_the_map_driver_refuses_foreign_maps_and_bad_loads_and_keeps_its_state(world):
    mesh, model, node, imap = world
    other = rt.ImpedanceMap.build(rt.ShellModel(rt.meshes.liver(3), rt.Material()).fix("attachment"), nodes=[5],
                                  n_modes=6)
    d = rt.ImpedanceDriver(imap, 1e-3, dynamic=True)
    d.step({node: (0.0, 0.0, 0.1)})
    before = d.get_state()
    for bad in ({node + 1: (0.0, 0.0, 1.0)}, {node: (np.nan, 0.0, 0.0)}, {node: (1.0, 2.0)}, {"a": (0, 0, 1)},
                np.ones((3, 3))):
        with pytest.raises(rt.RtfemError):
            d.step(bad)
    with pytest.raises(rt.RtfemError, match="another mesh"):
        d.add(other)
    with pytest.raises(rt.RtfemError):
        d.add("map.npz")
    with pytest.raises(rt.RtfemError, match="prepare|build"):
        d.prepare([node + 1])
    after = d.get_state()
    assert after["steps"] == before["steps"] and len(d.maps) == 1
    np.testing.assert_array_equal(after["loads"][node], before["loads"][node])
    with pytest.raises(rt.RtfemError):
        rt.ImpedanceDriver([], 1e-3)
    with pytest.raises(rt.RtfemError):
        rt.ImpedanceDriver(imap, -1.0)
    with pytest.raises(rt.RtfemError):
        rt.ImpedanceDriver.on_demand("model")


def test_the_session_refuses_a_non_driver_and_keeps_its_own(world):
    from rtfem.viewer.session import Session, Settings

    mesh = world[0]
    s = Session(mesh, settings=Settings(n_modes=4))
    driver = s.driver
    for bad in (None, "driver", object(), world[3].as_driver().__dict__):
        with pytest.raises(rt.RtfemError):
            s.use_driver(bad)
    assert s.driver is driver
    other = rt.ModalSimulator(rt.modal_analysis(rt.ShellModel(rt.meshes.liver(3), rt.Material()).fix("attachment"), 4),
                              1e-3)
    with pytest.raises(rt.RtfemError):
        s.use_driver(other)  # a driver of another mesh
    assert s.driver is driver


def test_bad_backend_names_and_progress_callbacks_are_refused(world, monkeypatch):
    model = world[1]
    monkeypatch.setenv("RTFEM_BACKEND", "magic")
    with pytest.raises(rt.SolverError, match="RTFEM_BACKEND"):
        rt.linalg.default_backend()
    monkeypatch.delenv("RTFEM_BACKEND")
    for call in (lambda: rt.SLDM(model, progress="bar"), lambda: rt.modal_analysis(model, 4, progress=5)):
        with pytest.raises(rt.RtfemError, match="progress"):
            call()
