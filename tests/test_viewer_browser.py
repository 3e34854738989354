"""The viewer in a real browser: headless Chromium (Debian's package) driven by Playwright.

A drag on the organ must grab a patch (the default 10 mm jaw), deform the organ (served state,
against the static response to the grasp's forces, and pixels) and move
the contact-force plot; after the release the organ must settle back. The example scene
(``rtfem view --example gallbladder``) must wait for the browser, draw its plane and its tools
(pixels that change when they are hidden) and go back to t = 0 when the page's restart is pressed. Screenshots are kept in
test-artifacts/browser/. Without a chromium binary the test is skipped, unless
RTFEM_REQUIRE_BROWSER=1 (set by .ci/run, which installs Debian's chromium when missing).
"""

from __future__ import annotations

import contextlib
import os
import shutil
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("viser", reason="the viewer extra (viser) is not installed")
playwright_api = pytest.importorskip("playwright.sync_api", reason="playwright is not installed")

from conftest import cut_state, cuts_settled, free_port, wait_until  # noqa: E402
from rtfem.viewer.benchmark import BROWSER_COUNTER  # noqa: E402

ARTIFACTS = Path(__file__).resolve().parents[1] / "test-artifacts" / "browser"
ARGS = ["--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run", "--disable-background-networking",
        "--disable-component-update", "--disable-sync", "--disable-dev-shm-usage",
        "--use-angle=swiftshader", "--enable-unsafe-swiftshader"]


def _chromium() -> str:
    for name in (os.environ.get("RTFEM_CHROMIUM"), "chromium", "chromium-browser"):
        if name and shutil.which(name):
            return shutil.which(name)
    if os.environ.get("RTFEM_REQUIRE_BROWSER") == "1":
        pytest.fail("no chromium binary on PATH: install Debian's chromium (apt-get install chromium); .ci/run does")
    pytest.skip("no chromium binary on PATH (apt-get install chromium)")


def _dismiss_notices(page) -> None:
    """Close viser's "Software WebGL rendering detected" notice (headless chromium draws in
    software), which would cover part of the screenshots (docs/img/viewer.png is one)."""
    try:
        page.get_by_text("Software WebGL rendering detected").wait_for(timeout=5000)
        page.locator("#webgl-software-rendering button.mantine-Notification-closeButton").click(timeout=2000)
        page.locator("#webgl-software-rendering").wait_for(state="detached", timeout=5000)
    except Exception:  # no notice (a GPU), or another layout: the screenshots keep it
        pass


@contextlib.contextmanager
def _open_page(viewer):
    """Headless chromium showing the viewer: the page once connected and drawing."""
    exe = _chromium()
    with playwright_api.sync_playwright() as p:
        browser = p.chromium.launch(executable_path=exe, headless=True, args=ARGS)
        try:
            page = browser.new_page(viewport={"width": 1280, "height": 800})
            page.add_init_script(BROWSER_COUNTER)  # window.__rtfem: frames drawn, shaders compiled
            page.goto(viewer.url)
            wait_until(lambda: viewer.state()["clients"] >= 1, 60, "the browser to connect")
            page.wait_for_selector("canvas", timeout=60_000)
            _dismiss_notices(page)
            # the viewer frames each browser's camera once the browser has said its canvas size, which
            # a loaded machine's browser said late (CI: the first camera, centred, was still in place)
            wait_until(lambda: _framed(viewer), 40, "the viewer to frame the browser's camera")
            # the browser's transition to the framed camera: a press where the organ will be drawn, made
            # while it still moved, missed it (and orbited the camera)
            wait_until(lambda: _camera_still(viewer), 60, lambda: f"the browser's camera to come to rest ({_camera(viewer)})")
            yield page
        finally:
            browser.close()


def _framed(viewer) -> bool:
    """Whether the first browser's camera looks elsewhere than the first camera every browser gets
    (frame_client shifts its look-at point to put the organ left of the panel)."""
    clients = list(viewer.server.get_clients().values())
    return bool(clients) and not np.allclose(clients[0].camera.look_at, viewer.server.initial_camera.look_at)


def _camera(viewer) -> tuple:
    """(position, look-at, the time the browser last said them) of the first browser's camera."""
    cam = list(viewer.server.get_clients().values())[0].camera
    return np.array(cam.position, dtype=float), np.array(cam.look_at, dtype=float), cam.update_timestamp


def _camera_still(viewer, span: float = 1.0) -> bool:
    """Whether the first browser's camera, framed, is where it was ``span`` s ago, to a micrometre (the
    browser says its camera while it moves; a transition's steps move it by far more)."""
    p0, a0, _ = _camera(viewer)
    time.sleep(span)
    p1, a1, _ = _camera(viewer)
    return _framed(viewer) and np.abs(p1 - p0).max() < 1e-6 and np.abs(a1 - a0).max() < 1e-6


def _settled(viewer, span: float = 0.5) -> bool:
    """Whether the grasp's force changed by under 2 % over ``span`` s of the organ's own (simulated)
    time: the organ follows the mouse's spring, and a loaded machine's physics lags real time, so a
    span of wall time saw too little of the motion (CI's MKL_CBWR run snapshotted an organ 16.6 % from
    its equilibrium, against the 6-7 % a settled one shows)."""
    before = viewer.state()
    steps = span / viewer.session.settings.dt
    deadline = time.monotonic() + 30.0
    while viewer.state()["steps"] - before["steps"] < steps and time.monotonic() < deadline:
        time.sleep(0.05)
    f0, f1 = before["force"], viewer.state()["force"]
    return f1 > 0 and abs(f1 - f0) <= 0.02 * f1


def _pixels(png: bytes) -> np.ndarray:
    from io import BytesIO

    from PIL import Image

    return np.asarray(Image.open(BytesIO(png)).convert("RGB"), dtype=float)


def _drawn_at(page, x: float, y: float, timeout: float = 30_000) -> bool:
    """Whether the browser draws something at (x, y) of the page (the 5 x 5 pixels about it): not the white
    background: the press lands on the block, not on an empty canvas still loading its scene."""
    box = page.screenshot(clip={"x": x - 2, "y": y - 2, "width": 5, "height": 5}, timeout=timeout)
    return bool((_pixels(box) < 235).any(axis=2).all())


# the page's pointer events, counted before any of its own handlers (a failed press says whether the page saw it)
POINTER_COUNTER = """
window.__rtfem_ptr = {down: 0, move: 0, up: 0, ctrl_down: 0};
for (const kind of ["down", "move", "up"]) {
  window.addEventListener("pointer" + kind, (e) => {
    window.__rtfem_ptr[kind]++;
    if (kind === "down" && e.ctrlKey) window.__rtfem_ptr.ctrl_down++;
  }, true);
}
"""


def _page_frames(page, n: int = 2, timeout: float = 30.0) -> None:
    """Wait for the page to run ``n`` more animation frames (window.__rtfem.frame, BROWSER_COUNTER): the
    input sent before is handled and its pointer's place seen by the scene's next frame."""
    f0 = page.evaluate("window.__rtfem.frame")
    wait_until(lambda: page.evaluate("window.__rtfem.frame") >= f0 + n, timeout, f"the page to run {n} frames")


def _page_state(page, x: float, y: float) -> str:
    """What the page says of itself, for a failed press: its pointer events (POINTER_COUNTER), its animation
    frames (BROWSER_COUNTER) and whether the block is drawn at (x, y), each read within 10 s."""
    out = []
    for what, read in (("pointer events", lambda: page.evaluate("({...window.__rtfem_ptr})")),
                       ("frames", lambda: page.evaluate("({...window.__rtfem})")),
                       ("drawn at the press", lambda: _drawn_at(page, x, y, 10_000))):
        t0 = time.monotonic()
        try:
            out.append(f"the page's {what}: {read()} ({time.monotonic() - t0:.1f} s to read)")
        except Exception as exc:  # noqa: BLE001 - said, with the others
            out.append(f"the page's {what}: not read ({type(exc).__name__} after {time.monotonic() - t0:.1f} s)")
    return "; ".join(out)


def _drag_messages(viewer) -> list:
    """The scene-node drag messages the viewer's server receives from now on, as (phase, modifier, node)."""
    from viser import _messages

    heard: list = []

    async def hear(client_id, message) -> None:
        heard.append((message.phase, message.modifier, message.name))

    viewer.server.scene._websock_interface.register_handler(_messages.SceneNodeDragMessage, hear)
    return heard


@pytest.fixture(autouse=True)
def _no_viewer_running():
    """Each test's browser shares the machine with its own viewer only: the ``viewer`` fixture, module-scoped
    before, kept the liver's viewer serving (its organ stepped, its frames encoded) through the later tests,
    the ctrl+drag test among them, whose page then ignored 3 presses in CI (its viewer at 5 frames/s)."""
    import threading

    from rtfem.viewer.app import FRAMES_THREAD

    def running() -> list:
        return [t for t in threading.enumerate() if t.name == FRAMES_THREAD and t.is_alive()]

    for t in running():  # (a viewer stopped waits 2 s for its frame in progress: the last may still end)
        t.join(10.0)
    assert not running(), f"{len(running())} viewer(s) left serving by an earlier test"


@pytest.fixture(params=["default", "shell"])
def viewer(request):
    """The scene of ``rtfem view`` and ``make demo`` (the liver as a solid of tet10 with the
    reduced nonlinear model: drawn and touched on its boundary), and the liver as a linear modal
    shell (``--shell --method modal``, a hollow organ's model); stopped when the test ends."""
    import rtfem as rt
    from rtfem.viewer.app import Viewer
    from rtfem.viewer.session import Session, default_session

    if request.param == "default":
        session = default_session()
        assert session.kind == "solid (tet10)" and session.settings.method == "nonlinear"
    else:
        session = Session(rt.meshes.liver(), fixed="attachment")
    v = Viewer(session, port=free_port()).start()
    v.kind = request.param
    yield v
    v.stop()


def test_drag_in_chromium_deforms_the_organ_and_moves_the_force_plot(viewer):
    import rtfem as rt

    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    with _open_page(viewer) as page:
        start = viewer.frames
        wait_until(lambda: viewer.frames > start + 30, 60, "frames to be served")
        time.sleep(3.0)  # the client renders what it was sent
        plot = page.locator(".uplot").first
        plot_before = _pixels(plot.screenshot())
        before_png = page.screenshot(path=str(ARTIFACTS / f"1_before_{viewer.kind}.png"))
        before = viewer.state()
        assert before["max_displacement"] < 1e-12 and before["force"] == 0.0  # m: at rest, to roundoff

        # the camera frames the organ left of the panel: press where its centre is drawn
        canvas = page.locator("canvas").first.bounding_box()
        px = viewer.project(viewer.centre)[0]
        assert 0.2 * canvas["width"] < px[0] < 0.45 * canvas["width"], px  # beside the panel (right 400 px)
        x0, y0 = canvas["x"] + px[0], canvas["y"] + px[1]
        page.mouse.move(x0, y0)
        page.mouse.down()
        # ~80 px: the full order's equilibrium (the reference below) under the jaw's four forces of a
        # 5.5 N pull (90 px) exists, and is gone at 1.3 times them (elements turned inside out), which
        # 120 px reached, and so did 90 px on a loaded machine before the organ had settled
        for i in range(1, 21):
            page.mouse.move(x0 + 2.1 * i, y0 - 3.5 * i)
            time.sleep(0.05)
        wait_until(lambda: viewer.state()["grabbed"] is not None, 20, "the drag to grab a vertex")
        wait_until(lambda: _settled(viewer), 30, "the held organ to settle")
        time.sleep(0.8)
        counts0 = page.evaluate("({...window.__rtfem})")
        time.sleep(1.2)
        counts = page.evaluate("({...window.__rtfem})")
        during = viewer.state()
        held, held_forces = viewer.session.grasp.nodes.copy(), viewer.session.grasp.forces.copy()
        during_png = page.screenshot(path=str(ARTIFACTS / f"2_dragging_{viewer.kind}.png"))
        plot_during = _pixels(plot.screenshot(path=str(ARTIFACTS / f"2_force_plot_{viewer.kind}.png")))
        page.mouse.up()
        wait_until(lambda: viewer.state()["grabbed"] is None, 20, "the release")
        time.sleep(2.5)
        after = viewer.state()
        page.screenshot(path=str(ARTIFACTS / f"3_released_{viewer.kind}.png"))

    # served state: one drag, a vertex held by a real force, the organ deformed, the plot fed
    assert during["drags"] == 1 and during["error"] is None
    assert during["grabbed"] in set(viewer.session.mesh.used_vertices().tolist())  # a surface node
    assert during["force"] > 0.05, during  # N; ~90 px of drag stretches the 200 N/m grasp spring
    # the jaw holds a patch (default grab radius 10 mm) of vertices the supports leave free, and the
    # organ, settled with the mouse still for 2 s, shows the static response to the forces on them
    model = viewer.session.model
    assert held.size > 1 and not model.held_nodes[held].any(), held
    loads = {int(v): f for v, f in zip(held, held_forces)}
    linear = float(np.linalg.norm(model.solve_static(loads), axis=1).max())
    assert during["max_displacement"] > 1e-3, during  # m: visible
    if viewer.kind == "default":
        # the reduced nonlinear model (40 modes + derivatives of 10) against the full order's nonlinear
        # equilibrium under the same held forces: settled 3 cm pulls of the probe vertex measured 5.9-6.9 %
        # (derivatives of 20 / 10); here after a 2 s hold, so 15 %; and nearer it than the linear model is.
        # On the shipped liver 3.0 % in 3 of 4 runs (MKL_CBWR=COMPATIBLE), 13.5 % in one; on livers meshed
        # afresh, as each machine did before the mesh was shipped, 4.2-13.6 % in 8 runs, and 16 % in CI
        reference = float(np.linalg.norm(rt.nonlinear.solve_static(model, loads, steps=8).displacements, axis=1).max())
        assert abs(during["max_displacement"] - reference) < 0.15 * reference, (during, reference, linear)
        assert abs(during["max_displacement"] - reference) < abs(linear - reference), (during, reference, linear)
    else:
        assert abs(during["max_displacement"] - linear) < 0.05 * linear, (during, linear)
    assert during["peak_force_plotted"] > 0.05
    assert during["sim_rate"] > 0 and during["frame_rate"] > 0
    # the browser draws the frames it is sent without compiling a shader for each (it did: the
    # replaced frame's material took its program along, and software WebGL drew 2-3 frames/s)
    assert counts["compiled"] == counts0["compiled"], (counts0, counts)
    assert counts["drawn"] - counts0["drawn"] >= 2, (counts0, counts)
    # the released organ settles (B = 8 M: amplitudes fall as exp(-4 t))
    assert after["force"] == 0.0
    assert after["max_displacement"] < 0.2 * during["max_displacement"], (during, after)
    # pixels: the organ's picture changed where it was pulled, and so did the force plot
    a, b = _pixels(before_png), _pixels(during_png)
    h, w = a.shape[:2]
    region = (slice(int(0.2 * h), int(0.8 * h)), slice(int(px[0] - 0.2 * w), int(px[0] + 0.2 * w)))
    changed = np.mean(np.abs(a[region] - b[region]).sum(axis=2) > 30)
    assert changed > 0.01, f"only {changed:.2%} of the organ's pixels changed"
    # the plot's box is laid out to a fractional height, and its screenshot is 244 or 245 px high
    # from one moment to the next (seen in 2 of 5 fresh clones): compare the rows and columns both have
    rows, cols = min(plot_before.shape[0], plot_during.shape[0]), min(plot_before.shape[1], plot_during.shape[1])
    assert rows > 100 and cols > 100, (plot_before.shape, plot_during.shape)
    plot_changed = np.mean(np.abs(plot_before[:rows, :cols] - plot_during[:rows, :cols]).sum(axis=2) > 30)
    assert plot_changed > 0.005, f"only {plot_changed:.2%} of the force plot's pixels changed"


def test_presses_grab_the_organ_at_a_low_frame_rate():
    """At 2 frames/s the drawn organ is replaced while the browser is still swapping in the last
    one; the mouse grabs a transparent copy that moves only when the organ has moved, so each of
    three presses on the organ grabs it (none orbits the camera instead)."""
    import rtfem as rt
    from rtfem.viewer.app import Viewer
    from rtfem.viewer.session import Session

    v = Viewer(Session(rt.meshes.liver(), fixed="attachment"), port=free_port(), fps=2.0).start()
    try:
        with _open_page(v) as page:
            time.sleep(3.0)
            canvas = page.locator("canvas").first.bounding_box()
            px = v.project(v.centre)[0]
            x0, y0 = canvas["x"] + px[0], canvas["y"] + px[1]
            grabbed = []
            for k in range(3):
                page.mouse.move(x0, y0)
                page.mouse.down()
                for i in range(1, 11):
                    page.mouse.move(x0 + 3 * i, y0 - 4 * i)
                    time.sleep(0.05)
                wait_until(lambda: v.state()["grabbed"] is not None, 20, f"press {k + 1} to grab the organ")
                grabbed.append(v.state()["grabbed"])
                time.sleep(0.7)  # mid-pull: frames (and the organ) change under the mouse
                page.mouse.up()
                wait_until(lambda: v.state()["grabbed"] is None, 20, "the release")
                time.sleep(0.8)  # the next press lands while the organ still settles
    finally:
        v.stop()
    assert v.drags == 3 and len(grabbed) == 3 and v.state()["error"] is None


def _canvas_changed(a: np.ndarray, b: np.ndarray, x: float, y: float, half: int) -> float:
    """The share of pixels within ``half`` px of (x, y) that differ between two screenshots."""
    h, w = a.shape[:2]
    box = (slice(max(0, int(y) - half), min(h, int(y) + half)), slice(max(0, int(x) - half), min(w, int(x) + half)))
    return float(np.mean(np.abs(a[box] - b[box]).sum(axis=2) > 30))


def test_the_example_scene_in_chromium_draws_its_tools_and_plane_and_restarts():
    """`rtfem view --example gallbladder` (its scene as the command prepares it): the scene waits at
    t = 0 until the page connects, then its scripted tools run; the browser draws the abdominal wall
    and the tools (the pixels where they are projected change when each is hidden); the page's pause
    stops the clock, its restart brings t back to 0 and the tools to their paths' starts (the grasper
    open again), its play runs on, and the slider's box sends the scene to the time typed there."""
    from rtfem.cli.scene import scene_for_viewer
    from rtfem.viewer.scene_view import SceneSession, SceneViewer

    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    scene = scene_for_viewer(resources_example())
    v = SceneViewer(SceneSession(scene), port=free_port()).start()
    try:
        time.sleep(0.5)
        assert v.state()["time"] == 0.0 and not v.state()["playing"]  # nobody watches yet
        with _open_page(v) as page:
            wait_until(lambda: v.state()["playing"] and v.state()["time"] > 0.5, 60, "the scripted paths to run")
            st = v.state()
            assert st["error"] is None and st["drawn"]["planes"] == ["abdominal wall"]
            grasper = st["drawn"]["tools"]["grasper"]
            assert grasper["closed"] and grasper["holds"] == "gallbladder" and st["tool_forces"]["grasper"] > 0.1
            button = page.get_by_role("button", name="pause", exact=True)
            button.click()
            wait_until(lambda: not v.state()["playing"], 10, "pause")
            t_paused = v.state()["time"]
            time.sleep(2.0)  # the client draws what it was sent
            assert v.state()["time"] == t_paused  # the clock stopped
            shown = _pixels(page.screenshot(path=str(ARTIFACTS / "scene_1_paused.png")))
            v.glyphs.set_visible("planes", False)
            time.sleep(1.5)
            no_plane = _pixels(page.screenshot(path=str(ARTIFACTS / "scene_2_no_plane.png")))
            v.glyphs.set_visible("planes", True)
            v.glyphs.set_visible("tools", False)
            time.sleep(1.5)
            no_tools = _pixels(page.screenshot(path=str(ARTIFACTS / "scene_3_no_tools.png")))
            v.glyphs.set_visible("tools", True)
            tip = v.project(grasper["position"])[0]
            wall = v.project(scene.obstacles[0].point + np.array([0.06, 0.0, 0.0]))[0]  # on the wall, beside the liver
            page.get_by_role("button", name="restart", exact=True).click()
            wait_until(lambda: v.state()["time"] == 0.0, 20, "the restart")
            time.sleep(1.5)
            restarted = v.state()
            back = _pixels(page.screenshot(path=str(ARTIFACTS / "scene_4_restarted.png")))
            page.get_by_role("button", name="play", exact=True).click()
            wait_until(lambda: v.state()["time"] > 0.2, 20, "play after the restart")
            page.get_by_role("button", name="pause", exact=True).click()
            wait_until(lambda: not v.state()["playing"], 10, "pause")
            slider_box = page.locator("input.mantine-NumberInput-input").last  # the time slider's box
            # a loaded browser draws the slider's values late (its box showed 0.234 s with the clock
            # paused at 0.66 s): typing the value the box shows at that moment changes nothing and
            # sends nothing, so wait until it shows where the clock stopped, then type another time
            paused_at = v.transport.slider.value
            wait_until(lambda: abs(float(slider_box.input_value() or "nan") - paused_at) < 1e-9, 30,
                       f"the slider's box to show the paused time {paused_at} s")
            target = 0.6 if abs(paused_at - 0.6) > 0.05 else 0.7  # the grasper is closed at both
            for _ in range(3):  # a loaded browser can drop the typed value (the page then sends nothing; seen once
                sent = v.transport.seeks  # in a full suite, the box showing the paused time): type it again
                slider_box.fill(f"{target}")
                slider_box.press("Enter")
                t0 = time.time()
                while v.transport.seeks == sent and time.time() - t0 < 10:
                    time.sleep(0.05)
                if v.transport.seeks > sent:
                    break
            wait_until(lambda: not v.state()["seeking"] and abs(v.state()["time"] - target) < 1e-9, 30,
                       f"the slider's seek to {target} s (the page sent {v.transport.seeks} values; its box "
                       f"shows {slider_box.input_value()}, the clock is at {v.state()['time']} s)")
            sought = v.state()
    finally:
        v.stop()
    h, w = shown.shape[:2]
    # the wall is drawn: where it is projected, left of the panel, hiding it changes the picture
    assert 0 < wall[0] < w - 400 and 0 < wall[1] < h, wall
    assert _canvas_changed(shown, no_plane, *wall, 60) > 0.3
    # the grasper is drawn where it is: hiding the tools changes the pixels about its tip
    assert _canvas_changed(shown, no_tools, *tip, 25) > 0.1
    # the restart: t = 0, the tools at their paths' starts, the grasper open and holding nothing
    tools = restarted["drawn"]["tools"]
    assert restarted["steps"] == 0 and not restarted["playing"]
    assert tools["grasper"]["position"] == pytest.approx([-0.03, 0.045, -0.0445]) and not tools["grasper"]["closed"]
    assert tools["grasper"]["holds"] is None and tools["probe"]["position"] == pytest.approx([-0.05, 0.0, 0.065])
    assert _canvas_changed(shown, back, *tip, 25) > 0.1  # the jaws left where they had been
    assert sought["time"] == pytest.approx(target) and not sought["playing"] and sought["drawn"]["tools"]["grasper"]["closed"]


def resources_example():
    from importlib import resources

    return resources.files("rtfem") / "scenes" / "gallbladder.toml"


def test_a_ctrl_drag_in_chromium_cuts_a_tet4_organ_and_the_cut_is_drawn():
    """Ctrl held, a drag across a tet4 block clamped at both ends (the modifier as the browser sends it,
    viser's "cmd/ctrl"): the viewer enters scalpel mode, the blade sweeps, the block is cut (nodes
    added), the new surface is drawn (the grabbable copy is the session's drawn vertices) and the
    picture shows the cut organ hanging; a plain drag afterwards grabs nothing (refused in scalpel mode)."""
    import rtfem as rt
    from rtfem.viewer.app import Viewer
    from rtfem.viewer.session import Session, Settings

    mesh = rt.meshes.box(0.1, 0.02, 0.02, nx=20, ny=4, nz=4)
    ends = np.concatenate([mesh.groups["x0"], mesh.groups["x1"]])
    s = Session(mesh, rt.Material(E=3e5, nu=0.45, density=1060.0), fixed=ends,
                settings=Settings(method="direct", large=True, dt=2e-3))
    n0 = s.model.n_nodes
    v = Viewer(s, port=free_port()).start()
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    try:
        with _open_page(v) as page:
            canvas = page.locator("canvas").first.bounding_box()
            px, camera = v.project(v.centre)[0], _camera(v)
            x0, y0 = canvas["x"] + px[0], canvas["y"] + px[1]
            wait_until(lambda: _drawn_at(page, x0, y0), 60, "the browser to draw the block where it is pressed")
            page.evaluate(POINTER_COUNTER)
            heard = _drag_messages(v)
            for attempt in (1, 2, 3):  # (a loaded browser, 4 % of real time, ignored a press on the drawn block
                # with its camera at rest, 2 rounds in 5 of the viewer tests beside 2 spinners: pressed again;
                # in CI 3 presses were ignored while the block at rest took a Newton step each (45-72 ms, a
                # core taken: fixed) and the liver's viewer of an earlier test still served (fixed, see below):
                # a page that answered no screenshot for 30 s, seen once here)
                page.keyboard.down("Control")
                page.mouse.move(x0, y0)  # pressed on the block's middle, once the page has seen the pointer there
                _page_frames(page)
                page.mouse.down()
                _page_frames(page)
                for i in range(1, 6):
                    page.mouse.move(x0, y0 - 4 * i)
                    time.sleep(0.05)
                try:
                    wait_until(lambda: v.cut_drags >= 1, 20, "the browser to begin a ctrl+drag on the block")
                    break
                except AssertionError:
                    with contextlib.suppress(Exception):  # (a page that does not answer: said below)
                        page.screenshot(path=str(ARTIFACTS / f"4_no_ctrl_drag_{attempt}.png"), timeout=10_000)
                    keys = ("drags", "cut_drags", "frames", "frame_rate", "error")
                    state = {k: val for k, val in v.state().items() if k in keys}
                    if attempt == 3:
                        raise AssertionError(f"no ctrl+drag began in 3 presses: {state}; {_page_state(page, x0, y0)}; the "
                                             f"drag messages the server heard {heard}; the press at {px} of the canvas; "
                                             f"the camera then {camera}, now {_camera(v)}; the grabbable copy last moved "
                                             f"{time.perf_counter() - v._pick_time:.1f} s ago") from None
                    page.mouse.up()
                    page.keyboard.up("Control")
                    time.sleep(1.0)
            wait_until(lambda: s.scalpel is not None, 180, lambda: f"scalpel mode ({s.cut_status!r}, {s.error})")
            for i in range(1, 41):  # down across the block's height on the screen
                page.mouse.move(x0, y0 - 20 + 3 * i)
                time.sleep(0.1)
            page.mouse.up()
            page.keyboard.up("Control")
            # (generous: in a fresh clone beside the suite, the worker process's first cut compiles its kernels)
            wait_until(lambda: v.cuts_drawn >= 1, 240, lambda: f"a cut drawn ({cut_state(s, v)})")
            wait_until(lambda: cuts_settled(s, v), 240, "the cuts to settle")  # (the strips still waiting: cut)
            frames = v.frames
            wait_until(lambda: v.frames > frames + 5, 30, "frames after the cut")
            page.screenshot(path=str(ARTIFACTS / "4_cut_block.png"))
            assert s.model.n_nodes > n0 and s.generation >= 1 and v.state()["error"] is None
            assert v._drawn_sent is s.drawn and np.asarray(v.pick.vertices).shape == (s.drawn.size, 3)
            page.mouse.move(x0 + 40, y0)  # a plain drag: refused in scalpel mode, said, nothing held
            page.mouse.down()
            page.mouse.move(x0 + 60, y0 - 20)
            time.sleep(1.0)
            page.mouse.up()
            assert s.grasp.nodes.size == 0 or not np.any(s.grasp.forces), "a grasp in scalpel mode"
    finally:
        v.stop()
