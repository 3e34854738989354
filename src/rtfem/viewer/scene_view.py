"""The scene viewer: ``rtfem view scene.toml`` and ``rtfem view --example gallbladder``.

Each body is drawn in its own colour, lighter where it has moved further; the obstacles, the
supports and attachments and every tool of the scene are drawn as what they are
(:mod:`rtfem.viewer.scene_glyphs`). The scene file's scripted tools run their paths from the moment
the first browser connects (before, the scene waits at its start), and the panel's transport plays,
pauses and restarts the scene and moves it to any time (:mod:`rtfem.viewer.controls`). The mouse is
two more tools of the scene: a left-drag on a body closes a grasper on it (the surface nodes within
its radius of the picked point, held by springs to the cursor in the plane facing the camera), a
shift-drag presses a probe into it along the surface's inward normal by the drag distance. Both act
through the scene's one contact problem, with the organs, the obstacles and the attachments. The
physics runs on its own thread against the wall clock (:class:`SceneSession`); a frame thread sends
the bodies at up to 30 frames a second and the panel says how close to real time the scene steps.
"""

from __future__ import annotations

import sys
import threading
import time

import numpy as np

from ..threads import background
from .app import Served, serve_until_interrupted
from .controls import Transport
from .gltf import SurfaceGlb
from .scene_glyphs import Glyphs
from .scene_session import SceneSession, rewind, snapshot
from .session import describe_material

__all__ = ["SceneSession", "SceneViewer", "serve_scene", "COLOURS", "snapshot", "rewind", "describe_body"]

#: the bodies' colours (sRGB), in the file's order: liver, gallbladder, then others
COLOURS = ((168, 74, 62), (92, 150, 70), (214, 170, 96), (110, 120, 200), (180, 120, 170), (90, 170, 170))

HELP = ("**Drag a body** with the left mouse button to grasp and pull it; **shift+drag** presses a probe "
        "into it. The scene's own tools follow their paths from when this page opened: **play / pause / "
        "restart** and the time slider below. Drag empty space to orbit, scroll to zoom.")


def describe_body(body) -> str:
    """A body in words: its model (shell or solid, the element, the nodes), its material law and its
    driver (the modes in use, the static correction)."""
    d = body.driver
    r = getattr(getattr(d, "modes", None), "n_modes", None) or getattr(getattr(d, "reduced", None), "size", None)
    driver = type(d).__name__ + (f", r = {r}" if r else "") + (
        ", static correction" if getattr(d, "static_correction", False) else "")
    model = getattr(body, "model", None)
    if model is None:
        return f"**{body.name}**: {driver}"
    kind = f"solid ({model.element})" if getattr(model, "element", None) else "shell"
    return f"**{body.name}**: {kind}, {model.n_nodes:,} nodes; {describe_material(model)}; {driver}"


def _count(n: int, what: str) -> str:
    return f"{n} {what}" + ("" if n == 1 else "s")


def tint(base, amount: np.ndarray) -> np.ndarray:
    """(k, 4) sRGB colours: ``base`` lightened toward white by ``amount`` (0..1) of the way."""
    a = np.clip(amount, 0.0, 1.0)[:, None] * 0.75
    out = np.full((amount.size, 4), 255, dtype=np.uint8)
    out[:, :3] = np.round((1 - a) * np.asarray(base, float) + a * 255.0).astype(np.uint8)
    return out


class SceneViewer(Served):
    """A viser server showing a :class:`SceneSession`: one mesh per body, the obstacles, attachments
    and tools, the mouse's tools, a panel with the transport.

    ``wait_for_client``: hold the scene at its start until the first browser connects (the
    scripted paths then play from t = 0 in front of the user); False: as the session is."""

    def __init__(self, session: SceneSession, *, host: str = "127.0.0.1", port: int = 8080, fps: float = 30.0,
                 wait_for_client: bool = True) -> None:
        from .app import _is_loopback, _need_viser, open_server

        viser = _need_viser()
        self.session, self.fps = session, float(fps)
        self.server, self.host, self.port = open_server(viser, host, port)
        if not _is_loopback(host):
            print(f"rtfem viewer: WARNING: serving on {host}:{self.port} makes the scene and its controls reachable "
                  "from other machines on the network, and the viewer has no authentication.", file=sys.stderr,
                  flush=True)
        self.url = f"http://{host}:{self.port}"
        self.frames, self.frame_rate, self.drags, self.connections = 0, 0.0, 0, 0
        self.vmax = 1e-3
        self._drag: dict | None = None
        self._stop = threading.Event()
        self._wait = bool(wait_for_client)
        if self._wait:
            session.pause()
        self._build()
        self.server.on_client_connect(self._on_connect)
        self._thread = background(threading.Thread(target=self._frames, name="rtfem-scene-frames", daemon=True),
                                  self._stop.set)

    def _on_connect(self, client) -> None:
        """Frame the browser's camera on the bodies beside the panel; the first one starts the scene."""
        from .camera import frame_client

        s = self.session
        self.connections += 1
        first = self.connections == 1
        frame_client(client, s.centre, 0.5 * s.size, self._view)
        if first and self._wait:
            s.play()

    def _build(self) -> None:
        from .camera import VIEW, light_scene

        s, sc = self.session, self.server.scene
        view = getattr(s.scene, "view", None)
        self._view = np.asarray(VIEW if view is None else view, dtype=float)
        light_scene(self.server, s.centre, s.size, 0.8 * self._view / np.linalg.norm(self._view))
        self._glbs, self.meshes, self.picks, self._bodies = [], [], [], []
        for k, body in enumerate(s.scene.bodies):
            self._body(k, body)
        # a speck with the bodies' material keeps its shader program while their frames are replaced
        # (see Viewer._build_scene: without it every frame compiled the shaders again)
        speck = s.centre + 1e-6 * np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
        self._speck = sc.add_glb("/speck", SurfaceGlb(np.array([[0, 1, 2]]), 3)(speck, tint(COLOURS[0], np.zeros(3))))
        self.glyphs = Glyphs(self.server, s.scene, s.centre, s.size, skip=(s.grasper, s.probe))
        self.hand = sc.add_icosphere("/hand", radius=0.006 * s.size, color=(255, 255, 255), visible=False)
        self.probe = sc.add_icosphere("/probe", radius=s.probe.radius, color=(230, 230, 240), visible=False)
        self._u = [np.zeros((b.surface.size, 3)) for b in s.scene.bodies]
        self.glyphs.update(self._u, self._bodies)
        gui = self.server.gui
        gui.configure_theme(control_width="large")
        sc_ = s.scene
        bodies = "  \n".join(f"{describe_body(b)} ({'#%02x%02x%02x' % COLOURS[k % len(COLOURS)]})"
                             for k, b in enumerate(sc_.bodies))
        gui.add_markdown(f"### rtfem scene\n{HELP}\n\n{bodies}  \nstep dt = {sc_.dt * 1e3:g} ms; "
                         f"{_count(len(sc_.obstacles), 'obstacle')}, {_count(len(sc_.attachments), 'attachment')}")
        self.transport = Transport(gui, s, step=sc_.dt)
        self.stats_md = gui.add_markdown("waiting for the first browser ..." if self._wait else "starting ...")

    def _body(self, k: int, body) -> None:
        """Body k's drawn mesh and its grabbable copy (again after a scalpel's cut: its surface is new)."""
        sc = self.server.scene
        faces = body.local[np.asarray(body.mesh.triangles)]
        glb = SurfaceGlb(faces, body.surface.size)
        colour = COLOURS[k % len(COLOURS)]
        X = body.X[body.surface]
        mesh = sc.add_glb(f"/bodies/{k}", glb(X, tint(colour, np.zeros(X.shape[0]))))
        pick = sc.add_mesh_simple(f"/picks/{k}", X.astype(np.float32), faces.astype(np.uint32),
                                  color=(255, 255, 255), opacity=0.0, side="double")
        pick.on_drag("left")(lambda event, k=k: self._on_drag(event, k, press=False))
        pick.on_drag("left", modifier="shift")(lambda event, k=k: self._on_drag(event, k, press=True))
        if k < len(self._bodies):
            self._glbs[k], self.meshes[k], self.picks[k], self._bodies[k] = (glb, colour, X), mesh, pick, body
        else:
            self._glbs.append((glb, colour, X))
            self.meshes.append(mesh)
            self.picks.append(pick)
            self._bodies.append(body)
        if hasattr(self, "_u"):
            self._u[k] = np.zeros((body.surface.size, 3))

    # ---------------------------------------------------------------- the mouse
    def _on_drag(self, event, k: int, *, press: bool) -> None:
        s = self.session
        if event.phase == "start":
            self.drags += 1
            start = np.asarray(event.start_position, dtype=float)
            body, u = self._bodies[k], self._u[k]  # (as last drawn)
            x = body.X[body.surface] + u
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
                us, bodies = s.surfaces()
                for k, body in enumerate(bodies):
                    if body is not self._bodies[k]:  # cut by a scalpel (or put back by a restart)
                        self._body(k, body)
                self._u = us
                peak = max(float(np.linalg.norm(u, axis=1).max()) for u in us)
                self.vmax = max(peak, 0.97 * self.vmax, 1e-4)
                for mesh, (glb, colour, X), u in zip(self.meshes, self._glbs, us):
                    mesh.glb_data = glb(X + u, tint(colour, np.linalg.norm(u, axis=1) / self.vmax))
                if self._drag is None:  # the grabbable copies follow the bodies between drags
                    for pick, (_, _, X), u in zip(self.picks, self._glbs, us):
                        pick.vertices = (X + u).astype(np.float32)
                self._draw_tools(us, bodies)
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

    def _draw_tools(self, us, bodies=None) -> None:
        s = self.session
        self.hand.visible = s.hand.buttons == 1
        if self.hand.visible:
            self.hand.position = tuple(s.hand.position(0.0))
        self.probe.visible = self._drag is not None and self._drag["press"]
        if self.probe.visible and s.probe.proxy is not None:
            self.probe.position = tuple(s.probe.proxy)
        self.glyphs.update(us, bodies)

    def _panel(self, peak: float) -> None:
        s = self.session
        forces = ", ".join(f"{name} {f:.2f} N" for name, f in s.tool_forces().items())
        if s.seeking:
            clock = "moving to the chosen time ..."
        elif not s.playing:
            clock = "paused" if self.connections or not self._wait else "waiting for the first browser"
        else:
            clock = (f"simulation **{s.sim_rate:,.0f} steps/s** ({s.realtime * 100:.0f} % of real time), "
                     f"{s.step_us / 1e3:.2f} ms per step")
        lines = [f"t = **{s.time:.3f} s** (the scripted paths end at {s.path_end:.2f} s); {clock}",
                 f"frames **{self.frame_rate:.0f} /s**; peak displacement {peak * 1e3:.1f} mm",
                 f"tools: {forces}" + (f"; the mouse holds **{s.held}**" if s.held else "")]
        if s.error:
            lines.append(f"**error:** {s.error}")
        self.stats_md.content = "  \n".join(lines)
        self.transport.refresh()

    def project(self, points) -> np.ndarray:
        """Where ``points`` (k, 3) are drawn on the first connected browser's canvas (pixels)."""
        from .camera import project

        clients = list(self.server.get_clients().values())
        if not clients:
            from ..errors import RtfemError

            raise RtfemError("no browser is connected to the viewer")
        return project(clients[0], points)

    def state(self) -> dict:
        """What the browser is being served, for tests and scripts: the clock, the rates, the tools'
        forces, and what is drawn (``drawn``: the planes, obstacles, supports, attachments, and each
        scripted tool's shape, position and state as the last frame drew it)."""
        s = self.session
        return {"url": self.url, "frames": self.frames, "frame_rate": self.frame_rate, "sim_rate": s.sim_rate,
                "realtime": s.realtime, "steps": s.scene.steps, "time": s.time, "playing": s.playing,
                "seeking": s.seeking, "drags": self.drags, "held": s.held, "tool_forces": s.tool_forces(),
                "clients": len(self.server.get_clients()), "drawn": self.glyphs.drawn, "error": s.error}


def serve_scene(session: SceneSession, *, host: str = "127.0.0.1", port: int = 8080, block: bool = True,
                wait_for_client: bool = True) -> SceneViewer:
    """Serve the scene viewer and (``block``) run until Ctrl-C (the command then exits 130);
    ``wait_for_client``: the scene starts when the first browser connects."""
    viewer = SceneViewer(session, host=host, port=port, wait_for_client=wait_for_client).start()
    if block:
        serve_until_interrupted(viewer)
    return viewer
