"""Two rates for one probe: the haptic tick (1 kHz or more) against the organ's latest linearization,
the organ's own step (a full-order nonlinear step, at whatever rate it manages) on a physics thread.

The coupling is the constraint-based one of SOFA's haptic rendering (Saupin, Duriez, Cotin 2008;
Courtecuisse, Allard et al. 2010/2014): the contact's compliance comes from the simulation's own
factor, and the fast loop solves the contact against it between the simulation's steps. Here:

* the physics thread runs an ordinary :class:`~rtfem.Probe` on the driver (the contact solved
  implicitly with the step's compliance, as in a synchronous loop) at the hand's latest position,
  and after each step publishes a snapshot: the displacements, the one-step predictions
  u_free (:meth:`Driver.predict`, the free step the next physics step reuses) of the vertices
  near the hand, and the step compliance W of the vertex in contact (or the nearest one);
* every haptic tick runs the same Probe formulas against that snapshot: the contact force for the
  hand where it is now, lam = (n . u_free - g) / (n^T W n + 1/k). Between two physics steps the
  force follows the hand through the compliance (a stiff, stable surface: W is the implicit step's
  own), and at each physics step it is the force the organ was stepped with.

A tick does O(candidates) work on arrays and no solve, so it holds to 1 kHz whatever the physics
step costs; the tissue moves at the physics thread's rate (``stats()``: its steps per second and
simulated time per wall second). With ``pace`` the simulated time never runs ahead of the wall
clock; a step slower than its dt runs the tissue in slow motion (say so: choose dt near the
measured step time for real time). While the loop runs, Python's thread switch interval is
lowered to 0.1 ms (a physics thread in Python code otherwise held the tick for up to 5 ms).
"""

from __future__ import annotations

import contextlib
import sys
import threading
import time

import numpy as np

from .. import validate
from ..drivers.base import as_driver, displacements_at, predictions, step_compliances
from ..errors import ModelError
from .haptics import Grasp, Probe

__all__ = ["MultiRateProbe", "MultiRateGrasp"]

#: the physics thread waits once no haptic tick has come for this long (s): the loop was stopped
IDLE_AFTER = 0.25
#: Python's thread switch interval while a multi-rate probe runs (s; the default is 5 ms)
SWITCH_INTERVAL = 1e-4


class _Snapshot:
    """The haptic side's driver: the physics thread's last published state, read by the haptic
    Probe's formulas; ``step`` records the force and moves nothing (the physics thread steps)."""

    compliance_changes = True  # a new snapshot brings a new W: the probe must not keep an old one

    def __init__(self, n_nodes: int, dt: float, fingerprint) -> None:
        self.n_nodes, self.dt, self.time, self.steps = int(n_nodes), float(dt), 0.0, 0
        if fingerprint is not None:
            self.fingerprint = fingerprint
        self.U = np.zeros((self.n_nodes, 3))
        self.free: dict[int, np.ndarray] = {}
        self.W: dict[int, np.ndarray] = {}
        self.W_any = None  # the last compliance computed: for a vertex touched before its own is published
        self.wanted: set[int] = set()
        self.block = (np.zeros(0, dtype=np.int64), np.zeros((0, 0)))  # a held patch's nodes and cross compliances
        self.force = np.zeros(3)

    def publish(self, U, free: dict, W: dict, block=None) -> None:
        """Swap in a new state (one assignment each: a tick reads either the old or the new arrays)."""
        self.U, self.free = U, free
        if block is not None:
            self.block = block
        if W:
            self.W = {**self.W, **W} if len(self.W) < 64 else dict(W)
            self.W_any = next(iter(W.values()))

    # the Driver protocol, against the snapshot
    def predict(self, node: int) -> np.ndarray:
        u = self.free.get(int(node))
        return self.U[int(node)].copy() if u is None else u.copy()

    def step_compliance(self, node: int) -> np.ndarray:
        W = self.W.get(int(node))
        if W is None:
            self.wanted.add(int(node))
            W = self.W_any if self.W_any is not None else np.zeros((3, 3))
        return W

    def predict_at(self, nodes) -> np.ndarray:
        free, U = self.free, self.U
        return np.array([free[i] if i in free else U[i] for i in np.asarray(nodes).tolist()]).reshape(-1, 3)

    def step_compliances(self, nodes, loaded=None) -> np.ndarray:
        """The published patch's block where ``nodes`` are its nodes; else the published 3x3 blocks on
        the diagonal (the cross terms of a set nobody published are not known here)."""
        nodes = np.asarray(nodes)
        held, W = self.block
        if (loaded is None or np.array_equal(loaded, nodes)) and np.array_equal(nodes, held):
            return W
        loaded = nodes if loaded is None else np.asarray(loaded)
        out = np.zeros((3 * nodes.size, 3 * loaded.size))
        for a, i in enumerate(nodes.tolist()):
            for b, j in enumerate(loaded.tolist()):
                if i == j:
                    out[3 * a:3 * a + 3, 3 * b:3 * b + 3] = self.step_compliance(i)
        return out

    def prepare(self, nodes) -> None:
        self.wanted.update(int(i) for i in np.atleast_1d(nodes).tolist())

    def displacement(self, node: int) -> np.ndarray:
        return self.U[int(node)].copy()

    def displacements_at(self, nodes) -> np.ndarray:
        return self.U[nodes]

    def displacements(self) -> np.ndarray:
        return self.U.copy()

    def step(self, forces=None) -> None:
        if forces:
            self.force = np.sum([np.asarray(f, dtype=float) for f in forces.values()], axis=0)
        else:
            self.force = np.zeros(3)
        self.steps += 1
        self.time = self.steps * self.dt

    def reset(self) -> None:
        self.steps, self.time, self.force = 0, 0.0, np.zeros(3)

    def get_state(self) -> dict:
        return {"steps": self.steps}

    def set_state(self, state) -> None:
        self.steps = int(state["steps"])
        self.time = self.steps * self.dt


class _MultiRate:
    """The physics thread, its pacing, the snapshot and the record, shared by the multi-rate tools:
    a subclass builds ``physics`` (the tool on the driver) and ``haptic`` (the same tool on the
    snapshot) and says what a step publishes (:meth:`_published`)."""

    #: a tick is a few array reads (the physics on its own thread): rt.HapticLoop runs these ticks under
    #: real-time scheduling where permitted (rtfem.threads.raise_to_realtime)
    light_ticks = True

    def _setup(self, driver, rate, pace, thread) -> None:
        rate = validate.positive(rate, "rate", "haptic ticks per second, in Hz")
        self.pace = validate.flag(pace, "pace")
        self.threaded = validate.flag(thread, "thread")
        self.snapshot = _Snapshot(driver.n_nodes, 1.0 / rate, getattr(driver, "fingerprint", None))
        self.driver = driver
        self.force = np.zeros(3)
        self.error: BaseException | None = None
        self.stop_reason: str | None = None  # why the physics stopped (the force is zero from then on)
        self._hand = None
        self._last_tick = 0.0
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._lock = threading.RLock()  # held by a physics step; a grab or release waits for it (_between_steps)
        # calls into _between_steps begun and ended: after its step the physics thread pauses until those begun by
        # then have ended (not for those begun while it pauses: calls back to back would stop it)
        self._asked, self._served = 0, 0
        self._waiting_lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._t0 = None  # wall clock of the first tick (pace)
        self._sim0 = 0.0
        self.physics_steps = 0
        self.physics_seconds = 0.0  # wall time spent in physics steps
        self.step_times: list[float] = []
        self._switch = None
        self.priority = ""  # the physics thread's scheduling, in words (rtfem.threads.below_ticks)

    def _tick(self, position, allow_none: bool = False):
        """The checks of every tick: a stopped physics raises (zero force), the hand kept for the
        physics, the thread started at the first tick."""
        if self.error is not None or self.stop_reason is not None:
            self.force = np.zeros(3)
            err, self.error = self.error, None
            if err is not None:
                self.close()
                self.stop_reason = f"the {self.WHAT}'s physics step failed, so its force is zero: {err}"
            raise ModelError(self.stop_reason) from err
        c = None if (position is None and allow_none) else validate.point(position, f"{self.WHAT} position")
        self._hand, self._last_tick = c, time.perf_counter()
        if self.threaded:
            if self._thread is None:
                self.start()
            self._wake.set()
        return c

    def displacements(self) -> np.ndarray:
        """The organ's (n, 3) displacements at the last physics step (for drawing)."""
        return self.snapshot.U.copy()

    @contextlib.contextmanager
    def _between_steps(self):
        """The physics' lock for a grab, a release, a prepare, between two physics steps: the physics thread
        pauses after its step until the waiting threads have had it. Without that pause the thread, stepping
        flat out, took the lock again first, step after step: on the 9k-tet liver of benchmarks/fullorder.py a
        grasp's grab() returned after 316-366 ms by the median, now 87-112 ms (beside a busy core no sooner:
        83-152 against 96-189 ms; benchmarks/grab_wait.py)."""
        with self._waiting_lock:
            self._asked += 1
        try:
            with self._lock:
                yield
        finally:
            with self._waiting_lock:
                self._served += 1

    def start(self):
        """Start the physics thread (the first :meth:`update` does)."""
        if self._thread is not None and self._thread.is_alive():
            return self
        from ..fe.jit import reserve_core
        from ..threads import background

        self._stop.clear()
        self._t0, self._sim0 = time.perf_counter(), float(self.driver.time)
        self._switch = sys.getswitchinterval()
        sys.setswitchinterval(SWITCH_INTERVAL)
        reserve_core(True)
        self._thread = threading.Thread(target=self._run, name="rtfem-multirate-physics", daemon=True)
        background(self._thread, self._stop.set)
        self._thread.start()
        return self

    def close(self, timeout: float = 10.0) -> None:
        """Stop the physics thread (after the step it is in) and restore the switch interval."""
        from ..fe.jit import reserve_core

        self._stop.set()
        self._wake.set()
        th = self._thread
        if th is not None and th is not threading.current_thread():
            th.join(timeout)
        self._thread = None
        if self._switch is not None:
            sys.setswitchinterval(self._switch)
            self._switch = None
            reserve_core(False)

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _run(self) -> None:
        from ..threads import below_ticks

        self.priority = below_ticks()  # (started by the loop's first tick, it had the ticks' own scheduling)
        try:
            while not self._stop.is_set():
                if time.perf_counter() - self._last_tick > IDLE_AFTER:  # no ticks: the loop stopped
                    self._wake.clear()
                    self._wake.wait(0.05)
                    continue
                if self.pace:
                    ahead = (self.driver.time + self.driver.dt - self._sim0) - (time.perf_counter() - self._t0)
                    if ahead > 0:
                        self._stop.wait(min(ahead, 0.05))
                        continue
                self.physics_step()
                asked = self._asked
                while self._served < asked and not self._stop.is_set():  # a grab waits: it goes first
                    time.sleep(1e-4)
        except BaseException as exc:  # noqa: BLE001 - surfaced by the next tick
            self.error = exc

    def physics_step(self) -> None:
        """One step of the organ with the tool at the hand's latest position (the physics thread's
        work; call it yourself with ``thread=False``), then a new snapshot."""
        t = time.perf_counter()
        with self._lock:
            self._advance()
        dt = time.perf_counter() - t
        self.physics_steps += 1
        self.physics_seconds += dt
        if len(self.step_times) < 100_000:
            self.step_times.append(dt)

    def _advance(self) -> None:
        """The physics step's work, under the lock: the tool on the driver, then a new snapshot."""
        self.physics.update(self._hand)
        self._publish()

    def _publish(self) -> None:
        d = self.driver
        U = np.asarray(displacements_at(d, np.arange(d.n_nodes)), dtype=float)
        near, want, block = self._published(U)
        free = {}
        if near.size:
            u_free = predictions(d, near)
            free = {int(i): u_free[j].copy() for j, i in enumerate(near.tolist())}
        want = set(want) | self.snapshot.wanted
        self.snapshot.wanted = set()
        W = {i: np.asarray(d.step_compliance(i), dtype=float) for i in sorted(want)[:4]}
        self.snapshot.publish(U, free, W, block)

    def stats(self) -> dict:
        """The physics thread's record: steps, steps per wall second (while stepping), the median
        and 99th-percentile step time (s) and the simulated seconds per wall second since the first
        tick."""
        st = np.asarray(self.step_times) if self.step_times else np.zeros(1)
        wall = time.perf_counter() - self._t0 if self._t0 is not None else 0.0
        return {"steps": self.physics_steps,
                "steps_per_second": self.physics_steps / self.physics_seconds if self.physics_seconds else 0.0,
                "step_median": float(np.median(st)), "step_p99": float(np.percentile(st, 99)),
                "time_ratio": (float(self.driver.time) - self._sim0) / wall if wall > 0 else 0.0, "priority": self.priority}


_PARAMETERS = """    rate : the haptic ticks per second the caller runs (Hz): the snapshot driver's dt.
    pace : the physics never runs ahead of the wall clock (simulated time <= wall time since the
        first tick); False steps as fast as it can.
    thread : False: no physics thread; the caller advances the organ with :meth:`physics_step`
        (a deterministic run: tests, offline replays, a scheduler of one's own)."""


class MultiRateProbe(_MultiRate):
    __doc__ = f"""A probe whose force loop runs at the haptic rate while the organ steps on its own thread at
    the rate its driver manages (a full-order nonlinear :class:`~rtfem.DirectSimulator` at 40-200
    steps/s): see the module. Use it where a :class:`~rtfem.Probe` goes, in a
    :class:`~rtfem.HapticLoop` (Python ticks) or calling :meth:`update` yourself at the haptic rate.

    Parameters
    ----------
    mesh, driver, radius, coupling, stiffness, candidates : as for :class:`~rtfem.Probe` (the
        driver is stepped by the physics thread only).
{_PARAMETERS}

    Raises
    ------
    ModelError
        What :class:`~rtfem.Probe` refuses; a rate that is not positive; in :meth:`update`, what the
        physics thread raised (the probe is stopped; the force is zero from then on).
    """

    WHAT = "probe"

    def __init__(self, mesh, driver, *, radius: float = 0.0, coupling: str = "spring", stiffness: float = 200.0,
                 candidates: int = 8, rate: float = 1000.0, pace: bool = True, thread: bool = True) -> None:
        driver = as_driver(driver, "probe")
        self.physics = Probe(mesh, driver, radius=radius, coupling=coupling, stiffness=stiffness, candidates=candidates)
        self._setup(driver, rate, pace, thread)
        self.haptic = Probe(mesh, self.snapshot, radius=radius, coupling=coupling, stiffness=stiffness,
                            candidates=candidates)
        self.mesh = mesh
        self._publish()
        # a compliance before the first physics step: a vertex touched before its own is published
        # uses the last one computed (a constraint coupling would divide by a zero W)
        self.prepare(nodes=[int(self.physics._touchable[0])])

    @property
    def contact_node(self):
        return self.haptic.contact_node

    @property
    def penetration(self) -> float:
        return self.haptic.penetration

    def prepare(self, nodes=None, *, around=None, radius: float = 0.01) -> int:
        """Compute the step compliances of the vertices the probe may touch (on the caller's
        thread, before the loop: see :meth:`Probe.prepare`)."""
        from .contact import nodes_to_prepare

        p = self.physics
        nodes = nodes_to_prepare(p._touchable, p._tree, p.mesh.n_vertices, nodes, around, radius)
        with self._between_steps():
            W = {int(v): np.asarray(self.driver.step_compliance(int(v)), dtype=float) for v in nodes.tolist()}
        self.snapshot.publish(self.snapshot.U, self.snapshot.free, W)
        return int(nodes.size)

    def update(self, position) -> np.ndarray:
        """One haptic tick with the hand at ``position``: the force on the hand (N), from the latest
        snapshot; the physics thread takes the position for its next step (started at the first
        tick)."""
        c = self._tick(position)
        self.force = self.haptic.update(c)
        return self.force

    def physics_step(self) -> None:
        if self._hand is None:
            raise ModelError("no hand position yet: call update(position) first")
        super().physics_step()

    def _published(self, U):
        """The free step of the vertices near the hand and of the contact vertex; the compliance of
        the contact vertex, or of the nearest vertex to the hand."""
        p = self.physics
        near = np.zeros(0, dtype=np.int64)
        if self._hand is not None:
            _, cand = p._tree.query(self._hand, k=p._k)
            near = p._touchable[np.atleast_1d(cand)]
        contact = p.contact_node
        if contact is not None:
            near = np.union1d(near, [contact])
        want = set()
        if contact is not None:
            want.add(int(contact))
        elif near.size:
            X = p.X[near] + U[near]
            want.add(int(near[np.argmin(np.linalg.norm(X - self._hand, axis=1))]))
        return near, want, None


class MultiRateGrasp(_MultiRate):
    __doc__ = f"""A grasp whose force loop runs at the haptic rate while the organ steps on its own thread
    (see the module): the jaw's implicit formula of :class:`~rtfem.Grasp` each tick against the held
    vertices' free step and cross compliances of the last physics step. :meth:`grab` waits for the
    physics step in progress (one step: the physics thread then pauses for it), then both sides hold the
    same grip; :meth:`release` waits for nothing: the hand's force is zero from the next tick, and the
    physics lets the organ go at its next step.

    Parameters
    ----------
    mesh, driver, stiffness, max_force, radius, grip : as for :class:`~rtfem.Grasp`.
{_PARAMETERS}

    Raises
    ------
    ModelError
        What :class:`~rtfem.Grasp` refuses; in :meth:`update`, what the physics thread raised (zero
        force from then on).
    """

    WHAT = "grasp"

    def __init__(self, mesh, driver, *, stiffness: float = 200.0, max_force: float | None = None,
                 radius: float = 0.0, grip: float | None = None, rate: float = 1000.0, pace: bool = True,
                 thread: bool = True) -> None:
        driver = as_driver(driver, "grasp")
        options = dict(stiffness=stiffness, max_force=max_force, radius=radius, grip=grip)
        self.physics = Grasp(mesh, driver, **options)
        self._setup(driver, rate, pace, thread)
        self.haptic = Grasp(mesh, self.snapshot, **options)
        self.mesh = mesh
        self._let_go = False  # a release the physics side has not taken yet (its next step does)
        self._grip = threading.Lock()  # a grab and a release, one at a time (a release waits for nothing else)
        self._grip_changes = 0  # odd while a grab or release changes the hand's side; a tick it overlapped feels nothing
        self._publish()

    @property
    def node(self):
        return self.haptic.node

    @property
    def nodes(self) -> np.ndarray:
        return self.haptic.nodes

    def grab(self, node: int, radius: float | None = None) -> np.ndarray:
        """Close the jaw (:meth:`Grasp.grab`) on both sides, between two physics steps."""
        with self._between_steps(), self._grip:
            self._take_release()
            nodes = self.physics.grab(node, radius)
            h, p = self.haptic, self.physics
            self._publish()
            self._grip_changes += 1
            h.node, h.nodes, h._hold, h._jaw = p.node, p.nodes.copy(), p._hold.copy(), p._jaw.copy()
            h._block, h._patch_inv = None, None
            self._grip_changes += 1
        return nodes

    def release(self) -> None:
        """Open the jaw on both sides: the hand's side at once, the physics' at its next step (with its
        thread running; at once otherwise). Waiting for the physics' lock, a release on the 9k-tet liver of
        benchmarks/fullorder.py returned after 19-267 ms by the median (up to 440 ms), the jaw pulling the hand
        meanwhile; now 0.03-0.04 ms (benchmarks/grab_wait.py)."""
        with self._grip:  # (a grab in progress ends first: both sides then let go)
            self._grip_changes += 1
            self.haptic.release()
            self._let_go = True
            self._grip_changes += 1
        if self._thread is None:
            with self._between_steps():
                self._take_release()

    def _take_release(self) -> None:
        if self._let_go:
            self._let_go = False
            self.physics.release()

    def _advance(self) -> None:
        self._take_release()
        super()._advance()

    def update(self, target=None) -> np.ndarray:
        """One haptic tick with the hand at ``target`` (None: no hand): the total force on the organ
        (N; the hand feels its opposite), from the latest snapshot."""
        c = self._tick(target, allow_none=True)
        seen = self._grip_changes
        try:
            force = self.haptic.update(c) if seen % 2 == 0 else np.zeros(3)
        except Exception:
            if self._grip_changes == seen:
                raise
            force = np.zeros(3)
        if self._grip_changes != seen:  # a grab or release on another thread changed the grip under this tick (it read
            force = np.zeros(3)  # part of each: 'nodes is empty' was raised): zero, the next tick has the new grip
        self.force = force
        return self.force

    def _published(self, U):
        """The held vertices' free step and their cross compliances (the block the physics grasp
        iterates with: the lagged factor's, which changes at its refreshes)."""
        g = self.physics
        if g.node is None:
            return np.zeros(0, dtype=np.int64), set(), None
        nodes = np.asarray(g.nodes, dtype=np.int64)
        if nodes.size == 1:
            return nodes, {int(nodes[0])}, None
        W = np.asarray(step_compliances(self.driver, nodes), dtype=float)
        return nodes, set(), (nodes.copy(), W)
