"""The scene viewer: ``rtfem view scene.toml`` and ``rtfem view --example gallbladder``.

Each body is drawn in its own colour, lighter where it has moved further; the scene file's
scripted tools run their paths, and the mouse is two more tools of the scene: a left-drag on a body
closes a grasper on it (the surface nodes within its radius of the picked point, held by springs
to the cursor in the plane facing the camera), a shift-drag presses a probe into it along the
surface's inward normal by the drag distance. Both act through the scene's one contact problem,
with the organs, the obstacles and the attachments. The physics runs on its own thread against
the wall clock (:class:`SceneSession`); a frame thread sends the bodies at up to 30 frames a second
and the panel says how close to real time the scene steps.
"""

from __future__ import annotations

import sys
import threading
import time

import numpy as np

from ..drivers.base import displacements_at
from ..interaction.devices.base import SharedDevice
from ..threads import background, raise_priority, runtime
from .app import Served, serve_until_interrupted
from .gltf import SurfaceGlb
from .session import PhysicsThread

__all__ = ["SceneSession", "SceneViewer", "serve_scene", "COLOURS"]

#: the bodies' colours (sRGB), in the file's order: liver, gallbladder, then others
COLOURS = ((168, 74, 62), (92, 150, 70), (214, 170, 96), (110, 120, 200), (180, 120, 170), (90, 170, 170))

HELP = ("**Drag a body** with the left mouse button to grasp and pull it; **shift+drag** presses a probe "
        "into it. The scene's own tools follow their paths. Drag empty space to orbit, scroll to zoom.")


class SceneSession(PhysicsThread):
    """A :class:`~rtfem.Scene` stepped in real time on its own thread, with the mouse as a grasper
    and a probe (tools "mouse" and "mouse probe", parked far above the scene while unused).

    Parameters
    ----------
    scene : the scene (its bodies, obstacles, attachments and tools).
    grasp_radius, grasp_stiffness : the mouse grasper's reach (m) and hold (N/m).
    probe_radius, probe_stiffness : the mouse probe's sphere (m) and coupling (N/m).

    Raises
    ------
    ModelError
        A scene without bodies, or one that already has tools named "mouse" or "mouse probe".
    """

    def __init__(self, scene, *, grasp_radius: float = 0.008, grasp_stiffness: float = 300.0,
                 probe_radius: float = 0.004, probe_stiffness: float = 300.0) -> None:
        from ..errors import ModelError

        if not scene.bodies:
            raise ModelError("the scene has no body to show")
        self.scene = scene
        X = np.concatenate([b.X[b.surface] for b in scene.bodies])
        lo, hi = X.min(axis=0), X.max(axis=0)
        self.centre, self.size = (lo + hi) / 2, float(np.linalg.norm(hi - lo))
        self.park = self.centre + np.array([0.0, 0.0, 20.0 * self.size])
        self.hand, self.pointer = SharedDevice(self.park), SharedDevice(self.park)
        self.grasper = scene.add_tool("mouse", self.hand, kind="grasper", radius=grasp_radius, stiffness=grasp_stiffness)
        self.probe = scene.add_tool("mouse probe", self.pointer, kind="probe", radius=probe_radius,
                                    stiffness=probe_stiffness)
        self._thread_name = "rtfem-scene-physics"
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.error: str | None = None
        self.sim_rate = self.realtime = self.step_us = 0.0
        self.priority = ""  # the stepping thread's scheduling priority (rtfem.threads.raise_priority)

    # ---------------------------------------------------------------- the mouse
    def grab(self, point) -> None:
        """Close the mouse grasper at ``point`` (it takes the nearest body's surface within its radius)."""
        self.hand.move_to(point)
        self.hand.mailbox[7] = 1.0

    def drag(self, target) -> None:
        self.hand.move_to(target)

    def release(self) -> None:
        self.hand.mailbox[7] = 0.0
        self.hand.move_to(self.park)

    def press(self, centre) -> None:
        """Put the mouse probe's centre at ``centre``."""
        self.pointer.move_to(centre)

    def unpress(self) -> None:
        self.pointer.move_to(self.park)

    @property
    def held(self) -> str | None:
        """The body the mouse grasper holds, or None."""
        held = self.grasper.held
        return None if held is None else held.a.name

    def tool_forces(self) -> dict[str, float]:
        """|force| (N) of each tool on the bodies in the last step."""
        return {t.name: float(np.linalg.norm(t.force)) for t in self.scene.tools}

    def surface_displacements(self) -> list[np.ndarray]:
        """Each body's surface displacements (k, 3), read between steps."""
        with self._lock:
            return [displacements_at(b.driver, b.surface) for b in self.scene.bodies]

    # ---------------------------------------------------------------- the clock
    def step(self) -> None:
        with self._lock:
            self.scene.step()

    def _run(self) -> None:
        self.priority = raise_priority()
        with runtime():  # one BLAS thread while the scene is stepped (see rtfem.threads)
            self._clock()

    def _clock(self) -> None:
        dt = self.scene.dt
        wall0, steps0 = time.perf_counter(), self.scene.steps
        window_start, window_steps, computes = wall0, 0, []
        try:
            while not self._stop.is_set():
                target = wall0 + (self.scene.steps - steps0) * dt
                now = time.perf_counter()
                if target - now > 3e-4:
                    time.sleep(target - now - 3e-4)
                    continue
                if now - target > 0.1:  # cannot keep up: stop owing steps (the panel says the rate)
                    wall0, steps0 = now, self.scene.steps
                c0 = time.perf_counter()
                self.step()
                c1 = time.perf_counter()
                computes.append(c1 - c0)
                window_steps += 1
                if c1 - window_start >= 1.0:
                    self.sim_rate = window_steps / (c1 - window_start)
                    self.realtime, self.step_us = self.sim_rate * dt, float(np.median(computes)) * 1e6
                    window_start, window_steps, computes = c1, 0, []
        except Exception as exc:  # shown in the panel; the viewer keeps serving
            self.error = f"{type(exc).__name__}: {exc}"



def tint(base, amount: np.ndarray) -> np.ndarray:
    """(k, 4) sRGB colours: ``base`` lightened toward white by ``amount`` (0..1) of the way."""
    a = np.clip(amount, 0.0, 1.0)[:, None] * 0.75
    out = np.full((amount.size, 4), 255, dtype=np.uint8)
    out[:, :3] = np.round((1 - a) * np.asarray(base, float) + a * 255.0).astype(np.uint8)
    return out


class SceneViewer(Served):
    """A viser server showing a :class:`SceneSession`: one mesh per body, the mouse's tools, a panel."""

    def __init__(self, session: SceneSession, *, host: str = "127.0.0.1", port: int = 8080, fps: float = 30.0) -> None:
        from .app import _is_loopback, _need_viser, open_server

        viser = _need_viser()
        self.session, self.fps = session, float(fps)
        self.server, self.host, self.port = open_server(viser, host, port)
        if not _is_loopback(host):
            print(f"rtfem viewer: WARNING: serving on {host}:{self.port} makes the scene and its controls reachable "
                  "from other machines on the network, and the viewer has no authentication.", file=sys.stderr,
                  flush=True)
        self.url = f"http://{host}:{self.port}"
        self.frames, self.frame_rate, self.drags = 0, 0.0, 0
        self.vmax = 1e-3
        self._drag: dict | None = None
        self._stop = threading.Event()
        self._build()
        self._thread = background(threading.Thread(target=self._frames, name="rtfem-scene-frames", daemon=True),
                                  self._stop.set)

    def _build(self) -> None:
        from .app import light_scene

        s, sc = self.session, self.server.scene
        view = getattr(s.scene, "view", None)
        light_scene(self.server, s.centre, s.size, *(() if view is None else (0.8 * view / np.linalg.norm(view),)))
        self._glbs, self.meshes, self.picks = [], [], []
        for k, body in enumerate(s.scene.bodies):
            faces = body.local[np.asarray(body.mesh.triangles)]
            glb = SurfaceGlb(faces, body.surface.size)
            colour = COLOURS[k % len(COLOURS)]
            X = body.X[body.surface]
            self._glbs.append((glb, colour, X))
            self.meshes.append(sc.add_glb(f"/bodies/{k}", glb(X, tint(colour, np.zeros(X.shape[0])))))
            pick = sc.add_mesh_simple(f"/picks/{k}", X.astype(np.float32), faces.astype(np.uint32),
                                      color=(255, 255, 255), opacity=0.0, side="double")
            pick.on_drag("left")(lambda event, k=k: self._on_drag(event, k, press=False))
            pick.on_drag("left", modifier="shift")(lambda event, k=k: self._on_drag(event, k, press=True))
            self.picks.append(pick)
        # a speck with the bodies' material keeps its shader program while their frames are replaced
        # (see Viewer._build_scene: without it every frame compiled the shaders again)
        speck = s.centre + 1e-6 * np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
        self._speck = sc.add_glb("/speck", SurfaceGlb(np.array([[0, 1, 2]]), 3)(speck, tint(COLOURS[0], np.zeros(3))))
        self.hand = sc.add_icosphere("/hand", radius=0.006 * s.size, color=(255, 255, 255), visible=False)
        self.probe = sc.add_icosphere("/probe", radius=s.probe.radius, color=(230, 230, 240), visible=False)
        self.tools = [(t, sc.add_icosphere(f"/tools/{i}", radius=t.radius if t.kind == "probe" else 0.004 * s.size,
                                           color=(200, 200, 215) if t.kind == "probe" else (240, 200, 60), visible=False))
                      for i, t in enumerate(s.scene.tools) if t not in (s.grasper, s.probe)]  # the file's tools
        self._u = [np.zeros((b.surface.size, 3)) for b in s.scene.bodies]
        gui = self.server.gui
        gui.configure_theme(control_width="large")
        names = ", ".join(f"{b.name} ({'#%02x%02x%02x' % COLOURS[k % len(COLOURS)]})" for k, b in enumerate(s.scene.bodies))
        gui.add_markdown(f"### rtfem scene\n{HELP}\n\nBodies: {names}")
        self.stats_md = gui.add_markdown("starting ...")

    # ---------------------------------------------------------------- the mouse
    def _on_drag(self, event, k: int, *, press: bool) -> None:
        s = self.session
        if event.phase == "start":
            self.drags += 1
            start = np.asarray(event.start_position, dtype=float)
            body = s.scene.bodies[k]
            x = body.X[body.surface] + self._u[k]
            i = int(np.argmin(np.linalg.norm(x - start, axis=1)))
            self._drag = {"press": press, "start": start, "x0": x[i], "n": body.normals[i]}
            if press:
                s.press(x[i] + (s.probe.radius + 5e-4) * body.normals[i])
            else:
                s.grab(start)
            return
        if self._drag is None:
            return
        end = np.asarray(event.end_position, dtype=float)
        if event.phase == "update":
            d = self._drag
            if d["press"]:
                depth = float(np.linalg.norm(end - d["start"]))
                s.press(d["x0"] + (s.probe.radius + 5e-4 - depth) * d["n"])
            else:
                s.drag(end)
            return
        s.unpress() if self._drag["press"] else s.release()
        self._drag = None

    # ---------------------------------------------------------------- frames
    def _frames(self) -> None:
        s = self.session
        count, t_window, next_panel = 0, time.perf_counter(), 0.0
        while not self._stop.is_set():
            t0 = time.perf_counter()
            try:
                self._u = us = s.surface_displacements()
                peak = max(float(np.linalg.norm(u, axis=1).max()) for u in us)
                self.vmax = max(peak, 0.97 * self.vmax, 1e-4)
                for mesh, (glb, colour, X), u in zip(self.meshes, self._glbs, us):
                    mesh.glb_data = glb(X + u, tint(colour, np.linalg.norm(u, axis=1) / self.vmax))
                if self._drag is None:  # the grabbable copies follow the bodies between drags
                    for pick, (_, _, X), u in zip(self.picks, self._glbs, us):
                        pick.vertices = (X + u).astype(np.float32)
                self._draw_tools()
                self.frames += 1
                count += 1
                now = time.perf_counter()
                if now - t_window >= 1.0:
                    self.frame_rate, count, t_window = count / (now - t_window), 0, now
                if now >= next_panel:
                    self._panel(peak)
                    next_panel = now + 0.25
            except Exception as exc:  # keep serving; say what went wrong
                s.error = f"{type(exc).__name__}: {exc}"
            time.sleep(max(0.0, 1.0 / self.fps - (time.perf_counter() - t0)))

    def _draw_tools(self) -> None:
        s = self.session
        self.hand.visible = s.hand.buttons == 1
        if self.hand.visible:
            self.hand.position = tuple(s.hand.position(0.0))
        self.probe.visible = self._drag is not None and self._drag["press"]
        if self.probe.visible and s.probe.proxy is not None:
            self.probe.position = tuple(s.probe.proxy)
        for tool, sphere in self.tools:  # a probe where it is, a grasper's tip while it is closed
            shown = tool.proxy is not None and (tool.kind == "probe" or tool.closed)
            if shown:
                sphere.position = tuple(tool.proxy)
            sphere.visible = shown

    def _panel(self, peak: float) -> None:
        s = self.session
        sc = s.scene
        forces = ", ".join(f"{name} {f:.2f} N" for name, f in s.tool_forces().items())
        lines = [f"{len(sc.bodies)} bodies, {len(sc.obstacles)} obstacles, {len(sc.attachments)} attachments; "
                 f"dt = {sc.dt * 1e3:g} ms",
                 f"simulation **{s.sim_rate:,.0f} steps/s** ({s.realtime * 100:.0f} % of real time), "
                 f"{s.step_us / 1e3:.2f} ms per step",
                 f"frames **{self.frame_rate:.0f} /s**; peak displacement {peak * 1e3:.1f} mm",
                 f"tools: {forces}" + (f"; the mouse holds **{s.held}**" if s.held else "")]
        if s.error:
            lines.append(f"**error:** {s.error}")
        self.stats_md.content = "  \n".join(lines)

    def state(self) -> dict:
        """What the browser is being served, for tests and scripts."""
        s = self.session
        return {"url": self.url, "frames": self.frames, "frame_rate": self.frame_rate, "sim_rate": s.sim_rate,
                "realtime": s.realtime, "steps": s.scene.steps, "drags": self.drags, "held": s.held,
                "tool_forces": s.tool_forces(), "error": s.error}


def serve_scene(session: SceneSession, *, host: str = "127.0.0.1", port: int = 8080, block: bool = True) -> SceneViewer:
    """Serve the scene viewer and (``block``) run until Ctrl-C (the command then exits 130)."""
    viewer = SceneViewer(session, host=host, port=port).start()
    if block:
        serve_until_interrupted(viewer)
    return viewer
