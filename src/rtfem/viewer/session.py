"""The simulation behind the viewer: a grabbed organ stepped in real time on its own thread.

Nothing here needs a browser: the viser front end (:mod:`rtfem.viewer.app`) only reads
snapshots and forwards the mouse. Tests drive a :class:`Session` directly as well.

Methods
-------
``modal``      the modal simulator (r modes, exact integrator, static correction): 1 kHz.
``impedance``  the impedance map (:class:`~rtfem.ImpedanceDriver`, dynamic): the precomputed
               responses of the grabbed vertex to unit loads, superposed over the history of
               the grasp force (the paper's run-time route); the force is the quasi-static one.
               A vertex's map is built when it is first grabbed and kept until a rebuild.
``direct``     direct Newmark integration of the full model, the paper's baseline: it cannot
               keep up with the clock on a real mesh, and the panel shows by how much.
``nonlinear``  the reduced nonlinear model (the r modes and their modal derivatives, cubature
               forces): large deformation without the warped model's error; its precompute
               takes ~20 s on the level-4 liver, and a step ~1 ms there (the panel shows the
               rate it keeps).
"""

from __future__ import annotations

import threading
import time
from collections import deque
from dataclasses import dataclass, field, fields, replace

import numpy as np

from .. import validate
from ..errors import ModelError
from ..interaction.haptics import Grasp
from ..drivers.fullorder import DirectSimulator
from ..drivers.impedance_driver import ImpedanceDriver
from ..fe.hyperelastic import Hyperelastic
from ..fe.material import Damping, Material
from .gltf import region_colours
from ..mesh.surface import TriMesh
from ..mesh.tetmesh import TetMesh
from ..reduction.modal import ModalBasis
from ..reduction.precompute import cached_modes
from ..drivers.reduced_nonlinear import reduced_nonlinear_driver
from ..fe.build import make_model
from ..drivers import gpu
from ..drivers.base import as_driver, displacements_at, prepare
from ..drivers.modal import ModalSimulator
from ..threads import background, raise_priority, runtime

from .cutting import Cutting
from .settings import MAP_TIMES, METHODS, Settings, describe_material  # noqa: F401 (re-exported)


class PhysicsThread:
    """``start()`` runs ``self._run`` (the clock) on a daemon thread until ``stop()`` sets ``self._stop``
    and joins it; a Ctrl-C in the main thread stops it too (:func:`rtfem.threads.background`)."""

    _thread_name = "rtfem-physics"

    def start(self):
        if self._thread is None or not self._thread.is_alive():
            self._stop.clear()
            self._thread = threading.Thread(target=self._run, name=self._thread_name, daemon=True)
            background(self._thread, self._stop.set)
            self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()


@dataclass
class Stats:
    steps: int = 0
    sim_time: float = 0.0
    sim_rate: float = 0.0  # steps per wall-clock second, last second
    realtime: float = 0.0  # simulated seconds per wall-clock second, last second
    step_us: float = 0.0  # median compute per step, last second
    priority: str = ""  # the stepping thread's scheduling priority (rtfem.threads.raise_priority)
    forces: deque = field(default_factory=lambda: deque(maxlen=600))  # (t, |f|) at ~60 Hz
    computes: deque = field(default_factory=lambda: deque(maxlen=1_000_000))  # every step's compute (s)


class Session(PhysicsThread, Cutting):
    """The organ, its precomputed dynamics and a thread stepping it in real time; a blade drawn through a
    solid cuts it (:meth:`cut`, :meth:`lift`: :mod:`rtfem.viewer.cutting`)."""

    _thread_name = "rtfem-viewer-physics"

    def __init__(self, mesh: TriMesh | TetMesh, material: Material | Hyperelastic | None = None, fixed="attachment",
                 settings: Settings | None = None, model_options: dict | None = None, progress=None) -> None:
        if not isinstance(mesh, (TriMesh, TetMesh)):
            raise ModelError(f"mesh={validate.show(mesh)} must be an rtfem TriMesh (a shell) or TetMesh (a solid)")
        if isinstance(material, dict) and isinstance(mesh, TetMesh):  # a material per region (issue 58)
            from ..fe.regions import region_materials

            material = region_materials(material, mesh)
        elif material is not None and not isinstance(material, (Material, Hyperelastic)):
            raise ModelError(f"material={validate.show(material)} must be an rt.Material, a hyperelastic law "
                             "(rt.NeoHookean, ...; solids), a solid's {region: material} or None")
        if settings is not None and not isinstance(settings, Settings):
            raise ModelError(f"settings={validate.show(settings)} must be a viewer Settings (or None)")
        # a solid is drawn and touched on its boundary, over the same node numbering
        self._model_options = dict(model_options or {})
        if isinstance(mesh, TetMesh) and self._model_options.get("element") == "tet10":
            mesh = mesh.quadratic()  # the model's own nodes: its corner surface is drawn
        self.volume = mesh if isinstance(mesh, TetMesh) else None
        self.mesh = mesh.surface if isinstance(mesh, TetMesh) else mesh
        self.material = material if material is not None else Material()
        self.settings = (settings or Settings()).check()
        if self.settings.E is None:
            self.settings.E = self._linear.E
        self._fixed = fixed
        self.X = np.asarray(self.mesh.vertices)
        self.drawn = self.mesh.used_vertices()  # the surface's vertices (a solid's interior is not drawn)
        self.region_colours = region_colours(self.volume, self.drawn)  # a labelled solid's regions, else None
        self._lock = threading.RLock()
        self.field_device = "gpu" if gpu.module() is not None else "cpu"  # where a modal field is drawn from
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.stats = Stats()
        self.target: np.ndarray | None = None
        self.device = None  # a haptic device driving the hand (attach_device), or None: the mouse
        self.device_hand: np.ndarray | None = None  # where the device's hand is (organ frame, m)
        self._grabbing: threading.Thread | None = None  # a device's grab being prepared
        self.error: str | None = None
        self.local_status = ""  # what the per-grab localization is doing (settings.local > 0)
        self.localizing: threading.Thread | None = None
        self._local_gen = 0
        # grabs so far; the grab the error estimate last localized; the grab the estimate under way is of (issue 56)
        self._grabs, self._adapted, self._estimated_grab = 0, -1, None
        self.building = ""  # what a (re)build is doing now, for the panel ("" when none runs)
        self._progress = progress  # progress(done, total, message) of the precompute (the CLI's bars)
        self._blade = None  # scalpel mode: the blade (tip, heel) in the tissue, or None (lifted)
        self._entry = threading.Lock()  # entering scalpel mode: one at a time
        self._build(self.settings)

    # ---------------------------------------------------------------- building
    @property
    def _linear(self) -> Material:
        """The linear material (a law's linearization at rest; of regions, the first region's: the
        panel's E is its, the others scaled alike)."""
        m = self.material
        m = next(iter(m.values())) if isinstance(m, dict) else m
        return m.linearized() if isinstance(m, Hyperelastic) else m

    def _model(self, E: float):
        factor = E / self._linear.E  # the panel's E: every modulus (a law's, each region's) scaled alike

        def scaled(m):  # (one linear material gets the panel's E itself, not E / E0 * E0)
            return m.scaled(factor) if isinstance(m, Hyperelastic) else replace(m, E=E if m is self._linear else m.E * factor)

        m = {k: scaled(v) for k, v in self.material.items()} if isinstance(self.material, dict) else scaled(self.material)
        model = make_model(self.volume or self.mesh, m, **self._model_options)
        model._viewer_E = E
        model.fix(self._fixed)
        model.check_restrained()
        return model

    def _report(self, stage: str):
        """A progress(done, total, message) callback for one precompute stage: it keeps the
        panel's line and feeds the caller's progress (the CLI's bar)."""
        t0 = time.perf_counter()

        def progress(done: int, total: int, message: str = "") -> None:
            self.building = (f"{stage}: {done}/{total} {message} ({time.perf_counter() - t0:.0f} s)" if total
                             else f"{stage} ...")
            if self._progress is not None:
                self._progress(stage, done, total, message)

        return progress

    def _driver(self, s: Settings, model, modes, damping):
        """The Driver of a method: the one place the methods differ."""
        if s.method == "direct":
            return DirectSimulator(model, s.dt, damping, large_deformation=s.large)
        if s.method == "modal":
            return ModalSimulator(modes, s.dt, damping, static_correction=True, warping=s.large)
        if s.method == "nonlinear":  # static correction, single precision; spread 1 (benchmarks/viewer_settings.py)
            return reduced_nonlinear_driver(model, modes, s.dt, damping, derivatives=s.derivatives, spread=s.spread,
                                            precision="single", background=True,
                                            progress=self._report("modal derivatives"), cache=True)
        return ImpedanceDriver.on_demand(model, damping, s.dt, dynamic=True, modes=modes, times=MAP_TIMES)

    def _build(self, s: Settings) -> None:
        """Model, modes and driver for the settings ``s`` (the heavy part runs outside the lock; a scalpel
        mode is left first, the cut mesh kept)."""
        with self._lock:
            self._leave_scalpel_mode()
        try:
            self.building = "assembling the model ..."
            old = getattr(self, "model", None)
            model = old if old is not None and getattr(old, "_viewer_E", None) == s.E else self._model(s.E)
            basis: ModalBasis | None = getattr(self, "modes", None)
            if basis is None or basis.model is not model or basis.n_modes < s.n_modes:
                r = max(s.n_modes, 40)
                basis = cached_modes(model, r, progress=self._report(f"modes (r = {r})"))
            modes = basis.truncated(s.n_modes) if basis.n_modes > s.n_modes else basis  # the r in use
            damping = Damping(alpha=s.alpha)
            self.building = f"building the {s.method} driver ..."
            driver = self._driver(s, model, modes, damping)
        finally:
            self.building = ""
        with self._lock:
            self.model, self.modes, self.damping, self.settings = model, basis, damping, s
            self.reduced = modes
            self.driver = driver
            self._monitor_for(s)
            self.local_status = ""  # a patch of the driver replaced, or one still training (discarded)
            self.grasp = self._grasp_on(driver, s)
            self.node: int | None = None
            self.target = None
            self._t0_sim = 0.0
            self.stats.steps, self.stats.sim_time = 0, 0.0
            self.stats.forces.clear()

    #: seconds between two error estimates of a reduced nonlinear model (0: none)
    indicator_period = 2.0

    def _monitor_for(self, s: Settings) -> None:
        """The error indicator of a reduced nonlinear model (rt.error_estimate on a low-priority
        thread, every :attr:`indicator_period` s): the full-order residual of the state shown."""
        old = getattr(self, "monitor", None)
        if old is not None:
            old.stop(timeout=0.0)
        self.monitor = None
        if s.method == "nonlinear" and self.indicator_period > 0:
            from ..reduction.indicator import ErrorMonitor

            self.monitor = ErrorMonitor(self.model, self._error_state, period=self.indicator_period, on_estimate=self._adapt,
                                        regions=_region_nodes(self.volume))
            if self._thread is not None and self._thread.is_alive():
                self.monitor.start()

    def _error_state(self):
        """(displacements, the grasp's forces on the organ, the inertial forces) now, under the lock."""
        from ..reduction.indicator import driver_inertia

        with self._lock:
            self._estimated_grab = self._grabs if self.node is not None else None  # the grab the estimate is of
            U = np.array(self.driver.displacements(), dtype=float)
            g = self.grasp
            loads = {int(v): tuple(map(float, f)) for v, f in zip(np.asarray(g.nodes).tolist(), g.forces)}
            inertia = driver_inertia(self.driver, self.model)
        return U, (loads or None), inertia

    def _grasp_on(self, driver, s: Settings | None = None) -> Grasp:
        """The jaw on the drawn surface of the organ ``driver`` steps, as the settings ``s`` (default the
        session's) make it."""
        s = s or self.settings
        return Grasp(self.mesh, driver, stiffness=s.grasp_stiffness, max_force=s.max_force, radius=s.grab_radius)

    def use_driver(self, driver) -> None:
        """Drive the organ with any Driver of this mesh (a user's own class) until the next
        :meth:`configure`; the grasp, the clock and the panel work through the protocol only."""
        driver = as_driver(driver, "viewer")
        if self.scalpel is not None:
            raise ModelError("the organ is in scalpel mode: press Reset first (the cut is kept), then use_driver")
        grasp = self._grasp_on(driver)
        with self._lock:
            self.driver, self.grasp = driver, grasp
            self.local_status = ""
            self.node, self.target = None, None
            self.stats.steps, self.stats.sim_time = 0, 0.0
            self.stats.forces.clear()

    def configure(self, **changes) -> None:
        """Change settings (method, n_modes, dt, alpha, E, grasp_stiffness, grab_radius, max_force, large) and
        rebuild."""
        known = {f.name for f in fields(Settings)}
        unknown = sorted(set(changes) - known)
        if unknown:
            raise ModelError(f"unknown setting {unknown[0]!r}; the settings are {', '.join(sorted(known))}")
        s = replace(self._pre_scalpel or self.settings, **changes).check()  # (scalpel mode's method is not the user's)
        if s.n_modes > self.model.n_dofs // self.model.dofs_per_node * 3 - 1:
            raise ModelError(f"n_modes={s.n_modes} is more than this mesh can give")
        changed = {f.name for f in fields(Settings) if getattr(s, f.name) != getattr(self.settings, f.name)}
        if changed and changed <= {"adapt", "adapt_radius"}:  # when the model adapts: read by the next estimate
            with self._lock:
                self.settings = s
            return
        if changed and changed <= {"grasp_stiffness", "grab_radius", "max_force"}:  # the hand only: no precompute
            grasp = self._grasp_on(self.driver, s)
            with self._lock:
                self.settings, self.grasp = s, grasp
                self.node, self.target = None, None
                self._local_gen += 1  # a patch training for the grasp dropped here is not wanted
            return
        self._build(s)

    def set_force_limit(self, newtons: float) -> None:
        """Change the grasp's force limit (N) now, mid-pull included (the panel's slider)."""
        f = validate.positive(newtons, "max_force", "the force limit in N")
        with self._lock:
            self.settings = replace(self.settings, max_force=f)
            self.grasp.max_force = f

    # ---------------------------------------------------------------- the hand
    def grab(self, point, displacements: np.ndarray | None = None) -> int:
        """Grab the free vertex nearest ``point`` on the surface displaced by ``displacements``
        (default undeformed); returns it. What the driver needs there (a map, compliance
        columns) is prepared here, outside the lock the stepping thread takes."""
        if self.scalpel is not None:
            raise ModelError("the organ is in scalpel mode (hanging, stepped by the scalpel): press Reset to grasp it "
                             "again (the cut is kept)")
        node = self.model.nearest_free_node(point, displacements)
        with self._lock:
            grasp = self.grasp
        prepare(grasp.driver, grasp.patch(node))  # the driver prepares the held vertices here
        with self._lock:
            if grasp is not self.grasp:  # rebuilt meanwhile
                return node
            self.grasp.grab(node)
            self.node = node
            self._grabs += 1
            self._local_gen += 1  # a patch still training for an earlier grab is dropped when it arrives
            self.target = self.X[node] + self.driver.displacement(node)
        if self.settings.method == "nonlinear" and self.settings.local > 0:
            self._localize(node)
        return node

    def _adapt(self, est) -> None:
        """The model adapts where it is wrong (issue 56; the monitor's ``on_estimate``, on its thread):
        while a grasp is held and the error estimate of the state exceeds ``settings.adapt``, the basis
        is localized around the held vertices (``adapt_radius``), once per grab, in the background."""
        s = self.settings
        running = self._thread is None or self._thread.is_alive()  # (a failed step ended it: nothing to adapt)
        with self._lock:
            node, grab = self.node, self._grabs
            wanted = (s.method == "nonlinear" and s.adapt > 0 and s.local == 0 and node is not None and running
                      and not self.error and grab != self._adapted and grab == self._estimated_grab
                      and est.max_error > s.adapt)
            if wanted:
                self._adapted = grab
        if wanted:
            self._localize(node, s.adapt_radius, f"the error estimate {est.max_error * 1e3:.2f} mm is above "
                                                 f"{s.adapt * 1e3:g} mm: ")

    def _localize(self, node: int, radius: float | None = None, why: str = "") -> None:
        """Localize the reduced nonlinear basis around the held vertices in a background thread
        (:meth:`ReducedNonlinearSimulator.localized`: the dofs within ``radius`` (default
        ``settings.local``) added, a new cubature: seconds), while the running basis goes on; then
        swap it in, in the state the running one has reached, with the grasp carried over
        (:meth:`Grasp.transferred`). A later grab, a rebuild or another driver meanwhile discards it."""
        with self._lock:
            self._local_gen += 1
            gen, driver, nodes = self._local_gen, self.driver, self.grasp.nodes.copy()
            radius = self.settings.local if radius is None else radius
        if not hasattr(driver, "localized") or nodes.size == 0:
            return
        self.local_status = f"{why}localizing: the dofs within {radius * 1e3:g} mm of vertex {node} ..."

        def work() -> None:
            # at the priority of the thread that grabbed (not nice 19: a starved thread that holds the
            # GIL holds the raised stepping thread back with it; see drivers.tangent.TangentWorker)
            try:
                new = driver.localized(nodes, radius)
                prepare(new, nodes)  # the held vertices' columns, outside the lock
                cost = _step_cost(new)
                new.continue_from(driver)  # linearized at the running state, outside the lock
                if gen != self._local_gen:  # released or grabbed elsewhere meanwhile: not wanted any more
                    return
                if cost > 0.9 * new.dt:  # it could not keep real time: the running basis goes on
                    self.local_status = (f"the patch within {radius * 1e3:g} mm of vertex {node} would take "
                                         f"{cost * 1e3:.2f} ms a step, more than the {new.dt * 1e3:g} ms step: "
                                         "kept the running basis")
                    return
                with self._lock:
                    if gen != self._local_gen or self.driver is not driver:  # a later grab says its own
                        if gen == self._local_gen:
                            self.local_status = ""
                        return
                    new.continue_from(driver, tangent="kept")  # the state now, the tangent from just before
                    self.grasp = self.grasp.transferred(new)
                    self.driver = new
                info = new.reduced.info["local"]
                self.local_status = (f"{why}localized: {info['nodes']} nodes within {radius * 1e3:g} mm of vertex {node}, "
                                     f"+{info['coordinates']} coordinates")
            except Exception as exc:  # shown in the panel; the running basis goes on
                self.local_status = ""
                self.error = self.error or f"localizing failed ({type(exc).__name__}: {exc}); the running basis goes on"

        self.localizing = background(threading.Thread(target=work, name="rtfem-viewer-localize", daemon=True))
        self.localizing.start()

    def drag(self, target) -> None:
        t = validate.point(target, "drag target")
        with self._lock:
            if self.node is not None:
                self.target = t

    def release(self) -> None:
        with self._lock:
            self.node, self.target = None, None
            self.grasp.release()
            self._local_gen += 1  # a patch still training (or about to) is for this grab: dropped when it arrives
            if self.localizing is not None and self.localizing.is_alive():
                self.local_status = "released before the patch was ready: it is dropped, the running basis goes on"

    def attach_device(self, device) -> None:
        """Drive the hand from a haptic device (``rt.devices``) instead of the mouse: each step its
        position is the hand, its first button closes the jaw on the free surface vertex nearest the
        hand (and opens it when let go), and the force the hand feels goes back to it. A device with
        a workspace to fit is fitted to this organ. None detaches it.

        Raises
        ------
        ModelError
            An object without ``position(t)`` and ``set_force(t, f)``.
        """
        if device is not None:
            if self.scalpel is not None:
                raise ModelError("the organ is in scalpel mode (the mouse's blade): press Reset first (the cut is kept), "
                                 "then attach the device")
            if not (callable(getattr(device, "position", None)) and callable(getattr(device, "set_force", None))):
                raise ModelError(f"device={validate.show(device)} must have position(t) and set_force(t, f) "
                                 "(an rt.devices adapter)")
            attach = getattr(device, "attach", None)
            if attach is not None:
                attach(self.mesh.bounds())
        with self._lock:
            self.device, self.device_hand = device, None

    def _device_hand(self, t: float) -> None:
        """Before a step: the device's hand as the grasp's target, its first button as the jaw. A
        grab prepares the held vertices' columns (sparse solves, tens of ms) on a thread of its own,
        as the mouse's does, so that the steps, and the forces the device's watchdog waits for, go on."""
        p = validate.point(self.device.position(t), "the device's position")
        self.device_hand = p
        pressed = bool(int(getattr(self.device, "buttons", 0)) & 1)
        grabbing = self._grabbing is not None and self._grabbing.is_alive()
        if pressed and self.node is None and not grabbing:
            self._grabbing = background(threading.Thread(target=self._device_grab, args=(p,), daemon=True,
                                                         name="rtfem-viewer-device-grab"))
            self._grabbing.start()
        elif not pressed and self.node is not None and not grabbing:
            self.release()
        if self.node is not None:
            self.target = p

    def _device_grab(self, p: np.ndarray) -> None:
        try:
            self.grab(p)
        except Exception as exc:  # shown in the panel; the device goes on
            self.error = f"the device's grab failed ({type(exc).__name__}: {exc})"

    # ---------------------------------------------------------------- stepping
    def step(self) -> None:
        """One time step of the driver under the current grasp (and the device's hand, when one is
        attached: it gets the force the hand feels)."""
        with self._lock:
            t = self._t0_sim + self.stats.steps * self.driver.dt
            if self.scalpel is not None:  # (no device there)
                self._scalpel_step()
            else:
                if self.device is not None:
                    self._device_hand(t)
                self.grasp.update(self.target)
            self.stats.steps += 1
            self.stats.sim_time = self._t0_sim + self.stats.steps * self.driver.dt
            if self.device is not None:
                self.device.set_force(t, -self.grasp.force)

    @property
    def kind(self) -> str:
        """The model in words: "solid (tet10)" or "shell"."""
        return f"solid ({self.model.element})" if self.volume is not None else "shell"

    @property
    def force(self) -> np.ndarray:
        """Force on the organ at the grabbed vertex (N); the hand feels the opposite."""
        return self.grasp.force.copy()

    @property
    def field_on(self) -> str:
        """Where the drawn field is computed: "gpu" (a linear modal driver, CuPy present) or "cpu"."""
        return self.field_device if type(self.driver) is ModalSimulator else "cpu"

    def displacements(self) -> np.ndarray:
        """The (n, 3) displacement field now (called at the frame rate; reads only)."""
        with self._lock:
            if type(self.driver) is ModalSimulator:  # single precision for drawing: half the memory read
                if self.field_device == "gpu":
                    try:
                        return self.driver.displacements(dtype=np.float32, device="gpu")
                    except Exception as exc:  # e.g. out of device memory: draw from the CPU from now on
                        self.field_device = "cpu"
                        self.error = f"the GPU field failed ({type(exc).__name__}: {exc}); drawing from the CPU"
                return self.driver.displacements(dtype=np.float32)
            return self.driver.displacements()

    def surface_displacements(self) -> np.ndarray:
        """The (k, 3) displacements of the drawn vertices (:attr:`drawn`) now: what a frame shows.
        A solid's field is evaluated on its surface only (566 of the 7,398 nodes of the default
        tet10 liver)."""
        with self._lock:
            driver, drawn = self.driver, self.drawn  # (a cut swaps both)
            if type(driver) is ModalSimulator or drawn.size == self.X.shape[0]:
                return self.displacements()[drawn]
            if not getattr(driver, "concurrent_reads", False):
                return displacements_at(driver, drawn)
        # outside the lock: the stepping thread does not wait for the frame's field (2 ms on a
        # 15,000-node liver with a 114-node grasp: a frame thread pre-empted while holding the lock
        # held the steps back with it; benchmarks/viewer_step.py)
        return displacements_at(driver, drawn)

    def record_force(self) -> None:
        with self._lock:
            self.stats.forces.append((self.stats.sim_time, float(np.linalg.norm(self.force))))

    # ---------------------------------------------------------------- the clock
    def start(self):
        super().start()
        if getattr(self, "monitor", None) is not None:
            self.monitor.start()
        return self

    def stop(self) -> None:
        if getattr(self, "monitor", None) is not None:
            self.monitor.stop()
        with self._lock:
            self._local_gen += 1  # a patch still training is not swapped into a stopped session
        super().stop()
        if self.scalpel is not None:  # its cut worker process ends (a restarted session cuts in this one)
            self.scalpel.close()

    def _run(self) -> None:
        self.stats.priority = raise_priority()
        with runtime():  # one BLAS thread while the organ is stepped (see rtfem.threads)
            self._clock()

    def _clock(self) -> None:
        st = self.stats
        wall0, steps0 = time.perf_counter(), st.steps
        window_steps, window_start, computes = 0, time.perf_counter(), []
        try:
            while not self._stop.is_set():
                dt = self.driver.dt
                if st.steps < steps0:  # rebuilt: restart the schedule
                    wall0, steps0 = time.perf_counter(), st.steps
                target = wall0 + (st.steps - steps0) * dt
                now = time.perf_counter()
                if target - now > 3e-4:
                    time.sleep(target - now - 3e-4)
                    continue
                if now - target > 0.1:  # cannot keep up (direct route): stop owing steps
                    wall0, steps0 = now, st.steps
                c0 = time.perf_counter()
                self.step()
                c1 = time.perf_counter()
                computes.append(c1 - c0)
                st.computes.append(c1 - c0)
                window_steps += 1
                if c1 - window_start >= 1.0:
                    st.sim_rate = window_steps / (c1 - window_start)
                    st.realtime = st.sim_rate * dt
                    st.step_us = float(np.median(computes)) * 1e6
                    window_steps, window_start, computes = 0, c1, []
        except Exception as exc:  # shown in the panel; the viewer keeps serving
            self.error = f"{type(exc).__name__}: {exc}"


def _region_nodes(volume) -> dict | None:
    """{region name (or label): its elements' nodes} of a solid of two regions or more, else None."""
    if volume is None or volume.regions.size < 2:
        return None
    names = {v: k for k, v in (volume.region_names or {}).items()}
    T, labels = np.asarray(volume.tets), np.asarray(volume.labels)
    return {names.get(int(k), int(k)): np.unique(T[labels == k]) for k in volume.regions.tolist()}


def _step_cost(driver, steps: int = 30) -> float:
    """Median seconds of a free step of ``driver`` (then reset): whether a new basis keeps real time.
    The CPU time of this thread, not the wall clock: measured beside the running step and a busy
    core, the wall clock read 0.95-0.98 ms for the block's and the liver's patches, whose steps then
    kept 1 kHz at 0.4-0.5 ms (benchmarks/model_errors.py --realtime --busy)."""
    times = []
    for _ in range(steps):
        t0 = time.thread_time()
        driver.step(None)
        times.append(time.thread_time() - t0)
    driver.reset()
    return float(np.median(times))


def default_session(progress=None, settings: Settings | None = None) -> Session:
    """The scene of ``rtfem view`` and ``make demo``: the embedded liver meshed into tets
    (:func:`rtfem.mesh.meshes.liver`, ``solid=True``: the mesh extra) as a solid of tet10 (no locking
    at nu = 0.45), held at its attachment, with the reduced nonlinear model (40 modes and the
    derivatives of the lowest 10, cubature forces, the static correction) and the 10 mm jaw."""
    from ..mesh import meshes

    return Session(meshes.liver(solid=True), Material(), "attachment", settings or Settings(method="nonlinear"),
                   {"element": "tet10"}, progress=progress)
