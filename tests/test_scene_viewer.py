"""The scene viewer (rtfem.viewer.scene_view, `rtfem view --example gallbladder`): the mouse as a
grasper and a probe of the scene, the bodies served as frames, the clock (waiting for the first
browser, pause, restart, the time slider's seek), what is drawn, the command's start and Ctrl-C."""

from __future__ import annotations

import time
import types
from importlib import resources

import numpy as np
import pytest
from conftest import serves_and_stops_on_ctrl_c

from rtfem.interaction.scene_file import load_scene
from rtfem.viewer.scene_view import SceneSession

EXAMPLE = resources.files("rtfem") / "scenes" / "gallbladder.toml"


@pytest.fixture(scope="module")
def example():
    return load_scene(EXAMPLE, dt=0.004)


def test_the_mouse_grasps_pulls_and_lets_go_and_presses_with_the_probe(example):
    scene = example
    session = SceneSession(scene)
    gb, liver = scene.body("gallbladder"), scene.body("liver")
    fundus = int(np.flatnonzero(gb.surface == gb.mesh.groups["fundus"][0])[0])
    for _ in range(5):
        session.step()
    x0 = gb.X[gb.surface[fundus]] + session.surface_displacements()[1][fundus]
    session.grab(x0)
    for k in range(100):  # pull 1 cm down over 0.2 s, hold 0.2 s
        session.drag(x0 - [0.0, 0.0, 0.01 * min(1.0, k / 50)])
        session.step()
    assert session.held == "gallbladder"
    pull = scene.contacts[("gallbladder", "mouse")]
    assert pull[2] < -0.05  # pulling it down
    moved = session.surface_displacements()[1][fundus] - (x0 - gb.X[gb.surface[fundus]])
    assert moved[2] < -0.003  # the fundus followed the hand down by millimetres
    assert np.allclose(session.hand.force, -scene.contacts[("gallbladder", "mouse")])  # the hand feels it
    session.release()
    session.step()
    assert session.held is None and np.abs(scene.contacts[("gallbladder", "mouse")]).max() == 0.0
    # the probe pressed 3 mm into the liver's right lobe from above
    top = int(np.argmax(liver.X[liver.surface][:, 2] - 10 * np.abs(liver.X[liver.surface][:, 0] + 0.05)))
    x = liver.X[liver.surface[top]] + session.surface_displacements()[0][top]
    n = liver.normals[top]
    for k in range(60):
        session.press(x + (session.probe.radius + 5e-4 - 0.003 * min(1.0, k / 30)) * n)
        session.step()
    push = scene.contacts[("liver", "mouse probe")]
    assert push @ n < -0.05  # into the liver
    session.unpress()
    session.step()
    assert np.abs(scene.contacts[("liver", "mouse probe")]).max() == 0.0


def test_the_viewer_serves_the_bodies_and_a_drag_grasps(example):
    pytest.importorskip("viser")
    from rtfem.viewer.scene_view import SceneViewer

    scene = load_scene(EXAMPLE, dt=0.004)
    viewer = SceneViewer(SceneSession(scene), port=_free_port(), wait_for_client=False).start()
    try:
        t0 = time.time()
        while viewer.frames < 5 and time.time() - t0 < 30:
            time.sleep(0.1)
        gb = scene.body("gallbladder")
        fundus = int(np.flatnonzero(gb.surface == gb.mesh.groups["fundus"][0])[0])
        x0 = gb.X[gb.surface[fundus]] + viewer._u[1][fundus]
        event = types.SimpleNamespace(phase="start", start_position=tuple(x0), end_position=tuple(x0))
        viewer._on_drag(event, 1, press=False)
        end = x0 - [0.0, 0.0, 0.01]
        viewer._on_drag(types.SimpleNamespace(phase="update", start_position=tuple(x0), end_position=tuple(end)), 1,
                        press=False)
        t0 = time.time()
        while viewer.state()["held"] is None and time.time() - t0 < 10:
            time.sleep(0.05)
        time.sleep(0.5)
        state = viewer.state()
        assert state["held"] == "gallbladder" and state["tool_forces"]["mouse"] > 0.01
        assert state["frames"] >= 5 and state["steps"] > 0 and state["error"] is None
        viewer._on_drag(types.SimpleNamespace(phase="end", start_position=tuple(x0), end_position=tuple(end)), 1,
                        press=False)
        time.sleep(0.2)
        assert viewer.state()["held"] is None
    finally:
        viewer.stop()


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_rtfem_view_example_serves_and_stops_on_ctrl_c():
    pytest.importorskip("viser")
    serves_and_stops_on_ctrl_c("--example", "gallbladder")


def _positions(scene) -> list[np.ndarray]:
    from rtfem.drivers.base import displacements_at

    return [displacements_at(b.driver, b.surface) for b in scene.bodies]


def test_restart_and_seek_go_back_through_the_drivers_states():
    """The session keeps the scene's state every 0.1 s: a seek back to t = 0.4 s gives the bodies and
    the tools what the run had there (stepping on from the state kept at 0.4 s: the same steps), a
    restart the rest state at t = 0 with the scripted tools at their paths' starts and their force
    records cleared; a seek forward steps there."""
    from rtfem.viewer.scene_session import scripted_end

    scene = load_scene(EXAMPLE, dt=0.004)
    session = SceneSession(scene, playing=False)
    assert session.path_end == 1.0 == scripted_end(scene)  # the grasper's closed = [[0.2, 100]] is a hold
    grasper, probe = scene.tools[0], scene.tools[1]
    for _ in range(100):  # 0.4 s: the grasper holds the fundus
        session.step()
    at = _positions(scene)
    held = grasper.held.nodes_a.copy()
    proxy = probe.proxy.copy()
    for _ in range(150):  # 1.0 s
        session.step()
    assert scene.time == pytest.approx(1.0) and len(probe.device.times) == 250
    session.seek(0.4)
    assert scene.steps == 100 and scene.time == pytest.approx(0.4)
    for u, v in zip(_positions(scene), at):
        np.testing.assert_allclose(u, v, rtol=0, atol=1e-12)
    assert np.array_equal(grasper.held.nodes_a, held) and np.allclose(probe.proxy, proxy)
    assert len(probe.device.times) == 100 and probe.device.times[-1] == pytest.approx(0.4)  # the record cut there
    session.restart()
    assert scene.steps == 0 and scene.time == 0.0 and not session.playing
    assert all(np.abs(u).max() == 0.0 for u in _positions(scene))  # at rest, no correction left over
    assert grasper.held is None and not grasper.closed and probe.device.times == []
    assert grasper.proxy is None and probe.proxy is None  # drawn at their paths' starts (scene_glyphs.tool_start)
    session.seek(0.6)
    assert scene.steps == 150 and grasper.held is not None


def test_the_viewer_waits_for_a_browser_and_draws_the_planes_tools_and_attachments():
    """Until a browser connects the example scene stays at t = 0 (its scripted paths start in front of
    the user); the served state lists the abdominal wall (a plane), the liver's supports, the cystic
    plate's springs and both scripted tools, each at its path's start: the grasper open, the probe's
    sphere of the file's radius."""
    pytest.importorskip("viser")
    from rtfem.viewer.scene_view import SceneViewer

    scene = load_scene(EXAMPLE, dt=0.004)
    viewer = SceneViewer(SceneSession(scene), port=_free_port()).start()
    try:
        t0 = time.time()
        while viewer.frames < 5 and time.time() - t0 < 30:
            time.sleep(0.1)
        time.sleep(0.3)
        state = viewer.state()
    finally:
        viewer.stop()
    assert state["steps"] == 0 and state["time"] == 0.0 and not state["playing"] and state["clients"] == 0
    drawn = state["drawn"]
    assert drawn["planes"] == ["abdominal wall"] and drawn["supports"] == ["liver"]
    assert drawn["attachments"] == ["cystic plate"]
    grasper, probe = drawn["tools"]["grasper"], drawn["tools"]["probe"]
    assert grasper["shape"] == "grasper" and grasper["visible"] and not grasper["closed"]
    assert grasper["position"] == pytest.approx([-0.03, 0.045, -0.0445])
    assert probe["shape"] == "sphere" and probe["position"] == pytest.approx([-0.05, 0.0, 0.065])
    assert viewer.glyphs.tools[1][1].parts[0].radius == 0.005  # the probe's sphere is the file's radius
    assert "mouse" not in drawn["tools"]  # the mouse's tools are drawn as the hand and the pressing probe


def test_every_kind_of_tool_obstacle_and_attachment_is_drawn_as_what_it_is():
    """A plate clamped at one edge, a capsule and a jaw-plate probe, a grasper on a scripted grip, a
    mesh obstacle and a plane, a spring to the world: each drawn (the served state names each glyph's
    shape), the grasper open until its grip closes and then tied to the nodes it holds."""
    pytest.importorskip("viser")
    import rtfem as rt
    from rtfem.interaction.scene_tools import Keyframes
    from rtfem.viewer.scene_view import SceneViewer

    mesh = rt.meshes.plate(0.1, nx=6)
    model = rt.ShellModel(mesh, rt.Material(E=1e5, thickness=0.003))
    model.fix("x0")
    scene = rt.Scene()
    scene.add_body("plate", rt.ModalSimulator(rt.modal_analysis(model, 8), 2e-3, rt.Damping(alpha=10.0)), mesh)
    scene.bodies[0].model = model
    scene.add_plane("floor", (0.0, 0.0, -0.05), (0.0, 0.0, 1.0))
    ball = rt.meshes.icosphere(0.01, 1)
    scene.add_obstacle("block", rt.TriMesh(np.asarray(ball.vertices) + [0.05, 0.05, -0.03], ball.triangles))
    scene.attach("spring", "plate", "x1", stiffness=50.0)
    far = [[0.0, 0.05, 0.05, 0.2]]
    scene.add_tool("rod", rt.ScriptedDevice(Keyframes(far)), shape=rt.Tool.capsule(0.003, 0.02))
    scene.add_tool("paddle", rt.ScriptedDevice(Keyframes([[0.0, 0.02, 0.05, 0.2]])), shape=rt.Tool.jaw(0.01, 0.02, 0.002))
    grip = Keyframes([[0.0, 0.1, 0.05, 0.0]], closed=[[0.01, 1.0]])
    scene.add_tool("forceps", grip.device(), kind="grasper", radius=0.012)
    viewer = SceneViewer(SceneSession(scene, playing=False), port=_free_port())
    try:
        viewer._draw_tools(viewer._u)
        before = viewer.state()["drawn"]
        for _ in range(10):
            viewer.session.step()
        viewer._draw_tools(viewer.session.surface_displacements())
        after = viewer.state()["drawn"]
    finally:
        viewer.server.stop()
    assert before["planes"] == ["floor"] and before["obstacles"] == ["block"] and before["supports"] == ["plate"]
    assert before["attachments"] == ["spring"]
    tools = before["tools"]
    assert tools["rod"]["shape"] == "capsule" and tools["paddle"]["shape"] == "jaw"
    assert tools["forceps"]["shape"] == "grasper" and not tools["forceps"]["closed"]
    assert tools["rod"]["position"] == pytest.approx([0.05, 0.05, 0.2])
    grasper = after["tools"]["forceps"]
    assert grasper["closed"] and grasper["holds"] == "plate" and grasper["held_nodes"] >= 1

