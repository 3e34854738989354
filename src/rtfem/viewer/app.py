"""The web viewer: viser serves the organ, the mouse pushes and pulls it.

Left-drag on the organ grabs the vertex under the cursor and pulls it through a virtual
spring within the plane facing the camera; shift+left-drag presses it along its inward
normal by the drag distance; ctrl+left-drag cuts a solid with a blade along the line of sight
(:mod:`rtfem.viewer.cut_view`). Dragging empty space orbits the camera. The physics runs on
its own thread (:class:`~rtfem.viewer.session.Session`); a frame thread sends the deformed,
colour-coded surface at up to 30 frames per second, the contact-force plot and the rates.
"""

from __future__ import annotations

import threading
import sys
import time
from types import SimpleNamespace

import numpy as np

from ..errors import RtfemError
from ..fe.material import Material
from ..threads import background
from .camera import VIEW, frame_client, light_scene, project
from .cut_view import CutView
from .gltf import SurfaceGlb, colormap, surface_faces
from .session import METHODS, Session, Settings, default_session, describe_material

#: the name of each viewer's frame thread (one per viewer serving)
FRAMES_THREAD = "rtfem-viewer-frames"

HELP = (
    "**Drag the organ** with the left mouse button to pull it; **shift+drag** presses along the surface "
    "normal; **ctrl+drag** cuts a solid (it hangs under gravity while cut; Reset to grasp again). Drag empty "
    "space to orbit, scroll to zoom. Grey dots: fixed nodes."
)


def surface_glb(session, glb: SurfaceGlb, u: np.ndarray, vmax: float) -> bytes:
    """One frame: the drawn surface (``session.drawn``, encoded by ``glb``: :func:`surface_encoder`)
    displaced by ``u`` (k, 3), coloured by the displacement magnitude on 0..vmax; a solid of regions
    in its regions' colours (``session.region_colours``), lightened where it moves."""
    base = getattr(session, "region_colours", None)
    if base is None:
        return glb(session.X[session.drawn] + u, colormap(np.linalg.norm(u, axis=1), vmax))
    t = np.clip(np.linalg.norm(u, axis=1) / vmax, 0.0, 1.0)[:, None] if vmax > 0 else 0.0
    colours = base.copy()
    colours[:, :3] = np.round(base[:, :3] + (255.0 - base[:, :3]) * 0.7 * t).astype(np.uint8)
    return glb(session.X[session.drawn] + u, colours)


def surface_encoder(session) -> SurfaceGlb:
    """The frames' encoder of the session's drawn surface (:func:`surface_faces`)."""
    return SurfaceGlb(surface_faces(session), session.drawn.size)


def open_server(viser, host: str, port: int):
    """A viser server on host:port (the next free port when that one is taken, said on stderr):
    (server, host, the port served)."""
    try:
        server = viser.ViserServer(host=host, port=port, verbose=False)
    except OSError as exc:
        raise RtfemError(f"cannot serve on {host}:{port} ({exc.strerror or exc}); choose another --port") from None
    served = server.get_port()
    if port and served != port:
        print(f"rtfem viewer: port {port} is in use; serving on port {served} instead", file=sys.stderr, flush=True)
    return server, host, served


def _need_viser():
    try:
        import trimesh  # noqa: F401
        import viser
    except ImportError as exc:
        raise RtfemError(
            f"the viewer needs viser ({exc.name} is missing): pip install 'rtfem[viewer]' "
            "(make demo installs it into .venv)"
        ) from None
    return viser


class Served:
    """``start()``/``stop()`` of a viewer: its session's physics thread, its frame thread and its server."""

    def start(self):
        self.session.start()
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
        self.session.stop()
        self.server.stop()


def serve_until_interrupted(viewer) -> None:
    """Say where the viewer is served and keep serving until Ctrl-C, then stop it (the KeyboardInterrupt
    goes on: the command exits 130, as every interrupted command does)."""
    print(f"rtfem viewer: open {viewer.url} in a browser (Ctrl-C stops it)", flush=True)
    try:
        while True:
            time.sleep(0.5)
    except KeyboardInterrupt:
        print("\nrtfem viewer: stopped", flush=True)
        raise
    finally:
        viewer.stop()


class Viewer(Served, CutView):
    """A viser server showing one :class:`Session`."""

    def __init__(self, session: Session, *, host: str = "127.0.0.1", port: int = 8080, fps: float = 30.0) -> None:
        viser = _need_viser()
        self.session = session
        self.fps = float(fps)
        self.server, self.host, self.port = open_server(viser, host, port)
        if not _is_loopback(host):
            print(f"rtfem viewer: WARNING: serving on {host}:{self.port} makes the organ and its controls reachable "
                  "from other machines on the network, and the viewer has no authentication: anyone who can "
                  "reach this port can use it. Serve on 127.0.0.1 unless that is what you want.", file=sys.stderr,
                  flush=True)
        self.url = f"http://{host}:{self.port}"
        self.frames = 0
        self.frame_rate = 0.0
        self.vmax = 1e-3  # colour scale (m), follows the largest displacement
        self.drags = 0
        self.mode_index: int | None = None  # mode browser: the mode shown, or None
        self._drag_lock = threading.Lock()
        self._dragging = False
        self._press: tuple[np.ndarray, float] | None = None  # shift-drag: (vertex position, inward normal)
        self._last_u = np.zeros((session.mesh.n_vertices, 3))
        self._stop = threading.Event()
        self._init_cut()
        self._build_scene()
        self._build_panel()
        self._thread = background(threading.Thread(target=self._frames, name=FRAMES_THREAD, daemon=True),
                                  self._stop.set)

    # ---------------------------------------------------------------- scene
    def _build_scene(self) -> None:
        s, mesh = self.session, self.session.mesh
        sc = self.server.scene
        lo, hi = mesh.bounds()
        centre, size = (lo + hi) / 2, float(np.linalg.norm(hi - lo))
        self.centre, self.size = centre, size
        light_scene(self.server, centre, size)
        self.server.on_client_connect(lambda client: frame_client(client, centre, 0.5 * size, VIEW))
        self._use_surface()  # the frames' encoder and the grabbable copy (see below)
        self.organ = sc.add_glb("/organ", surface_glb(s, self._glb, np.zeros((s.drawn.size, 3)), 1.0))
        # The client disposes each replaced frame's material and with it the shader program, unless
        # another object uses one alike: every frame then compiled its shaders again, and a browser
        # without a GPU drew 2-3 of the 28 frames/s sent. A speck drawn with the same material (a
        # triangle of 1 um at the centre: below a pixel) keeps the program.
        speck = centre + 1e-6 * np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
        self._speck = sc.add_glb("/organ_speck", SurfaceGlb(np.array([[0, 1, 2]]), 3)(speck, colormap(np.zeros(3), 1.0)))
        # the mouse grabs a transparent copy of the surface, not the drawn organ: the drawn one is
        # replaced every frame, and a press that came while the client swapped it in (often, at a low
        # frame rate) missed it and orbited the camera. The copy moves only when the organ has moved
        # by PICK_TOLERANCE, at most twice a second, and never during a drag.
        self._pick_time = 0.0
        fixed = np.flatnonzero(s.model.held_nodes)
        if fixed.size:
            sc.add_point_cloud("/fixed", s.X[fixed], colors=(150, 150, 150), point_size=0.0012 * size / 0.25,
                               point_shape="circle")
        self.marker = sc.add_icosphere("/grab", radius=0.012 * size, color=(230, 60, 40), visible=False)
        self.hand = sc.add_icosphere("/hand", radius=0.008 * size, color=(255, 255, 255), visible=False)

    def _add_pick(self):
        """The grabbable copy of the drawn surface, its drags bound: drawn (transparent) like any mesh, its
        front faces only where the surface is closed (on a browser without a GPU, 17.5 frames/s drawn
        against 13.5 with both sides)."""
        s = self.session
        organ = self.server.scene.add_mesh_simple("/organ_pick", s.X[s.drawn].astype(np.float32), self._faces,
                                                  color=(255, 255, 255), opacity=0.0,
                                                  side="front" if s.mesh.is_closed() else "double")

        @organ.on_drag("left")
        async def _pull(event) -> None:
            self._on_drag(event, press=False)

        @organ.on_drag("left", modifier="shift")
        async def _press(event) -> None:
            self._on_drag(event, press=True)

        @organ.on_drag("left", modifier="cmd/ctrl")
        async def _cut(event) -> None:
            self._on_cut(event)

        return organ

    def _on_drag(self, event, *, press: bool) -> None:
        s = self.session
        if event.phase == "start":
            self.mode_index = None
            self._mode_dropdown.value = "off"
            with self._drag_lock:
                self._dragging = True
                self.drags += 1
                drag_id = self.drags
            self._target = np.asarray(event.end_position, dtype=float)
            self._grab_at = np.asarray(event.start_position, dtype=float)
            self._press_mode = press
            threading.Thread(target=self._grab, args=(drag_id, self._grab_at), daemon=True).start()
            return
        if event.phase == "update":
            self._target = np.asarray(event.end_position, dtype=float)
            self._apply_target()
            return
        with self._drag_lock:  # end
            self._dragging = False
        s.release()
        self._press = None

    def _grab(self, drag_id: int, point: np.ndarray) -> None:
        s = self.session
        # the surface moved: grab the vertex nearest the picked point on the *deformed* surface
        u = self._last_u
        try:
            node = s.grab(point, u)
        except RtfemError as exc:
            s.error = str(exc)
            return
        with self._drag_lock:
            if not self._dragging or drag_id != self.drags:
                s.release()
                return
            n = s.mesh.vertex_normals()[node]
            self._press = (s.X[node] + u[node], n) if self._press_mode else None
            self._grab_point = point
        self._apply_target()

    def _apply_target(self) -> None:
        s = self.session
        if s.node is None or not self._dragging:
            return
        if self._press is not None:
            x0, n = self._press
            depth = float(np.linalg.norm(self._target - self._grab_point))
            s.drag(x0 - depth * n)
        else:
            s.drag(self._target)

    # ---------------------------------------------------------------- panel
    def _build_panel(self) -> None:
        import viser.uplot as uplot

        gui, s = self.server.gui, self.session
        gui.configure_theme(control_width="large")
        gui.add_markdown(f"### rtfem\n{HELP}")
        self.stats_md = gui.add_markdown("starting ...")
        t = np.zeros(2)
        self.plot = gui.add_uplot(
            data=(t, t.copy()),
            series=(uplot.Series(label="t (s)"), uplot.Series(label="|F| (N)", stroke="#d62728", width=2)),
            title="contact force",
            scales={"x": uplot.Scale(time=False, auto=True), "y": uplot.Scale(auto=True)},
            legend=uplot.Legend(show=True),
            aspect=1.8,
        )
        with gui.add_folder("Dynamics"):
            self.method = gui.add_dropdown("method", METHODS, initial_value=s.settings.method,
                                           hint="modal: r modes, 1 kHz; impedance: precomputed responses superposed; "
                                                "direct: Newmark on the full model (the baseline)")
            self.large = gui.add_checkbox("large deformation", initial_value=s.settings.large,
                                          hint="modal: modal warping (rotation-aware); direct: the corotational "
                                               "full order (Newton per step)")
            self.modes_slider = gui.add_slider("modes r", min=5, max=200, step=5, initial_value=s.settings.n_modes)
            self.dt_ms = gui.add_number("time step (ms)", initial_value=s.settings.dt * 1e3, min=0.05, max=20.0, step=0.05)
            self.alpha = gui.add_slider("damping alpha (1/s)", min=0.0, max=60.0, step=0.5, initial_value=s.settings.alpha)
            self.E_kpa = gui.add_number("Young's modulus (kPa)", initial_value=s.settings.E / 1e3, min=1.0, max=1e6, step=1.0)
            self.k_grasp = gui.add_slider("grasp spring (N/m)", min=10.0, max=2000.0, step=10.0,
                                          initial_value=s.settings.grasp_stiffness)
            self.max_force = gui.add_slider("force limit (N)", min=0.5, max=50.0, step=0.5,
                                            initial_value=min(50.0, s.settings.max_force),
                                            hint="the grasp force is capped here (a desktop haptic device renders "
                                                 "~10 N); the panel says when it clips")
            self.grab_mm = gui.add_slider("grab radius (mm)", min=0.0, max=40.0, step=1.0,
                                          initial_value=s.settings.grab_radius * 1e3,
                                          hint="the jaw holds the surface within this radius of the picked point "
                                               "(0: one vertex, a point pull)")
            apply = gui.add_button("apply")
            reset = gui.add_button("reset (let go, zero state)")
        with gui.add_folder("Mode browser"):
            self._mode_dropdown = gui.add_dropdown("mode", self._mode_labels(), initial_value="off")
            self.mode_amp = gui.add_slider("amplitude (% of size)", min=1.0, max=20.0, step=1.0, initial_value=6.0)
            self.mode_md = gui.add_markdown("")

        @apply.on_click
        def _(_) -> None:
            self._reconfigure()

        @self.method.on_update
        def _(_) -> None:
            self._reconfigure()

        @self.max_force.on_update
        def _(_) -> None:
            try:
                s.set_force_limit(float(self.max_force.value))
            except RtfemError as exc:
                s.error = str(exc)

        @self.large.on_update
        def _(_) -> None:
            self._reconfigure()

        @reset.on_click
        def _(_) -> None:
            self._reconfigure(force=True)

        @self._mode_dropdown.on_update
        def _(_) -> None:
            v = self._mode_dropdown.value
            self.mode_index = None if v == "off" else int(v.split(":")[0]) - 1

    def _reconfigure(self, force: bool = False) -> None:
        s = self.session
        changes = dict(method=self.method.value, n_modes=int(self.modes_slider.value), dt=float(self.dt_ms.value) * 1e-3,
                       alpha=float(self.alpha.value), E=float(self.E_kpa.value) * 1e3,
                       grasp_stiffness=float(self.k_grasp.value), grab_radius=float(self.grab_mm.value) * 1e-3,
                       max_force=float(self.max_force.value), large=bool(self.large.value))
        if not force and all(getattr(s.settings, k) == v for k, v in changes.items()):
            return
        self.stats_md.content = "rebuilding ..."
        try:
            s.configure(**changes)
        except RtfemError as exc:
            s.error = str(exc)
        self._mode_dropdown.options = self._mode_labels()

    def _mode_labels(self) -> tuple[str, ...]:
        """The mode browser's choices: the r modes in use, with their frequencies."""
        return ("off",) + tuple(f"{i + 1}: {f:.2f} Hz" for i, f in enumerate(self.session.reduced.frequencies))

    # ---------------------------------------------------------------- frames
    def _field(self) -> np.ndarray:
        s = self.session
        modes = s.reduced
        if self.mode_index is not None and self.mode_index < modes.n_modes and getattr(modes, "model", s.model) is s.model:
            i = self.mode_index
            phi = modes.shapes[s.drawn, :, i]
            scale = self.mode_amp.value / 100 * self.size / max(float(np.abs(phi).max()), 1e-30)
            f_vis = min(1.0, 0.5 + 0.1 * i)  # slowed down to be seen; the true frequency is in the panel
            self.mode_md.content = (f"mode {i + 1}: **{modes.frequencies[i]:.3f} Hz** "
                                    f"(omega = {modes.omega[i]:.2f} rad/s), shown at {f_vis:.1f} Hz")
            return scale * np.sin(2 * np.pi * f_vis * time.perf_counter()) * phi
        return s.surface_displacements()

    def _frames(self) -> None:
        s = self.session
        period = 1.0 / self.fps
        count, t_window, next_stats = 0, time.perf_counter(), 0.0
        while not self._stop.is_set():
            t0 = time.perf_counter()
            try:
                self._apply_cut()  # a blade the mouse moved; a cut organ's new surface
                with s._lock:  # (a cut swaps these together)
                    shown = SimpleNamespace(X=s.X, drawn=s.drawn, region_colours=s.region_colours)
                u = self._field()  # on the drawn vertices
                if u.shape[0] != shown.drawn.size or shown.drawn is not self._drawn_sent:  # a cut swapped it meanwhile
                    time.sleep(period)
                    continue
                full = np.zeros((shown.X.shape[0], 3))
                full[shown.drawn] = u
                self._last_u = full  # the field a grab looks for the nearest vertex on
                peak = float(np.linalg.norm(u, axis=1).max())
                self.vmax = max(peak, 0.97 * self.vmax, 1e-4)
                self.organ.glb_data = surface_glb(shown, self._glb, u, self.vmax)
                self._move_pick(u)
                s.record_force()
                self._draw_hand(full)
                self.frames += 1
                count += 1
                now = time.perf_counter()
                if now - t_window >= 1.0:
                    self.frame_rate = count / (now - t_window)
                    count, t_window = 0, now
                if now >= next_stats:
                    self._update_panel(peak)
                    next_stats = now + 0.25
            except Exception as exc:  # keep serving; say what went wrong
                s.error = f"{type(exc).__name__}: {exc}"
            time.sleep(max(0.0, period - (time.perf_counter() - t0)))

    PICK_TOLERANCE = 5e-4  # m: how far the drawn organ may move from its grabbable copy

    def _move_pick(self, u: np.ndarray) -> None:
        """Bring the grabbable copy to the drawn surface (see _build_scene) when they differ."""
        now = time.perf_counter()
        if self._dragging or now - self._pick_time < 0.5:
            return
        if u.shape != self._pick_u.shape or np.abs(u - self._pick_u).max() < self.PICK_TOLERANCE:
            return  # (the shapes differ for the frame a cut swapped the surface in)
        self._pick_u, self._pick_time = u.copy(), now
        self.pick.vertices = (self.session.X[self.session.drawn] + u).astype(np.float32)

    def _draw_hand(self, u: np.ndarray) -> None:
        s = self.session
        node = s.node
        hand = s.target if s.target is not None else s.device_hand  # a device's hand is drawn ungrabbed too
        if hand is None:
            self.marker.visible = self.hand.visible = False
            return
        self.hand.position = tuple(hand)
        self.hand.visible = True
        self.marker.visible = node is not None
        if node is not None:
            self.marker.position = tuple(s.X[node] + u[node])

    def _update_panel(self, peak: float) -> None:
        s = self.session
        st = s.stats
        hist = np.array(st.forces) if st.forces else np.zeros((2, 2))
        if hist.shape[0] < 2:
            hist = np.vstack([hist, hist])
        self.plot.data = (hist[:, 0].copy(), hist[:, 1].copy())
        f = float(np.linalg.norm(s.force))
        lines = [
            f"**{s.settings.label}** on a {s.kind}: {s.model.n_nodes:,} nodes, r = {s.settings.n_modes} modes, "
            f"dt = {s.settings.dt * 1e3:g} ms",
            f"material: {describe_material(s.model)}",
            f"simulation **{st.sim_rate:,.0f} steps/s** ({st.realtime * 100:.0f} % of real time), "
            f"{st.step_us:,.1f} us per step; thread priority {st.priority.split(':')[0] or '-'}",
            f"frames **{self.frame_rate:.0f} /s**; force {f:.3f} N; peak displacement {peak * 1e3:.2f} mm "
            f"(colour scale 0 .. {self.vmax * 1e3:.2f} mm); field drawn on the {s.field_on.upper()}",
        ]
        g = s.grasp
        if s.node is not None and getattr(g, "clipped", False):
            lines.append(f"**force clipped at {g.max_force:g} N**: the hand asks {g.demand:.1f} N; raise the force "
                         "limit to follow it")
        mon = getattr(s, "monitor", None)
        if mon is not None and mon.latest is not None:
            est = mon.latest
            lines.append(f"error estimate **{est.max_error * 1e3:.2f} mm** at node {est.worst_node} (the full order's "
                         f"residual of this state, every {mon.period:g} s, {mon.cost[-1]:.2f} s each)")
            if est.regions:
                lines.append("per region: " + ", ".join(f"{k} {v * 1e3:.2f} mm" for k, v in est.regions.items()))
        elif mon is not None and mon.error:
            lines.append(f"error estimate: {mon.error}")
        if s.building:
            lines.append(f"precomputing: {s.building}")
        if s.local_status:
            lines.append(s.local_status)
        if s.cut_status:
            lines.append(s.cut_status)
        if s.device is not None:
            reason = getattr(s.device, "stop_reason", None)
            lines.append(f"device: {type(s.device).__name__}, " + (f"**stopped: {reason}**" if reason else
                         "rendering (its first button grabs)"))
        if s.error:
            lines.append(f"**error:** {s.error}")
        self.stats_md.content = "  \n".join(lines)

    # ---------------------------------------------------------------- control
    def project(self, points) -> np.ndarray:
        """Where ``points`` (k, 3) are drawn on the first connected browser's canvas (pixels)."""
        clients = list(self.server.get_clients().values())
        if not clients:
            raise RtfemError("no browser is connected to the viewer")
        return project(clients[0], points)

    def state(self) -> dict:
        """What the browser is being served, for tests and scripts."""
        s = self.session
        forces = np.array(s.stats.forces) if s.stats.forces else np.zeros((0, 2))
        return {
            "url": self.url,
            "method": s.settings.method,
            "frames": self.frames,
            "frame_rate": self.frame_rate,
            "sim_rate": s.stats.sim_rate,
            "steps": s.stats.steps,
            "drags": self.drags,
            "cut_drags": self.cut_drags,
            "grabbed": s.node,
            "max_displacement": float(np.linalg.norm(self._last_u, axis=1).max()),
            "force": float(np.linalg.norm(s.force)),
            "peak_force_plotted": float(forces[:, 1].max()) if forces.size else 0.0,
            "clients": len(self.server.get_clients()),
            "error": s.error,
            "field_on": s.field_on,
        }


def serve(mesh=None, *, material: Material | None = None, fixed="attachment",
          settings: Settings | None = None, host: str = "127.0.0.1", port: int = 8080,
          block: bool = True, model_options: dict | None = None, session: Session | None = None) -> Viewer:
    """Precompute, serve the viewer and (``block``) run until Ctrl-C. ``mesh``: a TriMesh (a shell)
    or a TetMesh (a solid, drawn and touched on its boundary); ``model_options`` go to the model
    (``element``, ``mass`` of a solid). No mesh: the scene of ``rtfem view``, the embedded liver
    (its shipped tets) as a solid of tet10 with the reduced nonlinear model.
    ``session``: serve this one instead (built by the caller)."""
    from ..mesh import meshes

    _need_viser()
    if session is None:
        if mesh is None:
            session = default_session(settings=settings)
        else:
            session = Session(meshes.liver() if mesh is None else mesh, material, fixed, settings, model_options)
    viewer = Viewer(session, host=host, port=port).start()
    if block:
        serve_until_interrupted(viewer)
    return viewer


def _is_loopback(host: str) -> bool:
    import ipaddress
    import socket

    try:
        addrs = {info[4][0] for info in socket.getaddrinfo(host, None)}
    except (socket.gaierror, UnicodeError):
        return False
    try:
        return all(ipaddress.ip_address(a.split("%")[0]).is_loopback for a in addrs)
    except ValueError:
        return False
