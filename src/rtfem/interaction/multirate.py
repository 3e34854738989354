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

import sys
import threading
import time

import numpy as np

from .. import validate
from ..drivers.base import as_driver, displacements_at, predictions
from ..errors import ModelError
from .haptics import Probe

__all__ = ["MultiRateProbe"]

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
        self.force = np.zeros(3)

    def publish(self, U, free: dict, W: dict) -> None:
        """Swap in a new state (one assignment each: a tick reads either the old or the new arrays)."""
        self.U, self.free = U, free
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
            self.force = np.asarray(next(iter(forces.values())), dtype=float)
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


class MultiRateProbe:
    """A probe whose force loop runs at the haptic rate while the organ steps on its own thread at
    the rate its driver manages (a full-order nonlinear :class:`~rtfem.DirectSimulator` at 50-200
    steps/s): see the module. Use it where a :class:`~rtfem.Probe` goes, in a
    :class:`~rtfem.HapticLoop` (Python ticks) or calling :meth:`update` yourself at the haptic rate.

    Parameters
    ----------
    mesh, driver, radius, coupling, stiffness, candidates : as for :class:`~rtfem.Probe` (the
        driver is stepped by the physics thread only).
    rate : the haptic ticks per second the caller runs (Hz): the snapshot driver's dt.
    pace : the physics never runs ahead of the wall clock (simulated time <= wall time since the
        first tick); False steps as fast as it can.
    thread : False: no physics thread; the caller advances the organ with :meth:`physics_step`
        (a deterministic run: tests, offline replays, a scheduler of one's own).

    Raises
    ------
    ModelError
        What :class:`~rtfem.Probe` refuses; a rate that is not positive; in :meth:`update`, what the
        physics thread raised (the probe is stopped; the force is zero from then on).
    """

    def __init__(self, mesh, driver, *, radius: float = 0.0, coupling: str = "spring", stiffness: float = 200.0,
                 candidates: int = 8, rate: float = 1000.0, pace: bool = True, thread: bool = True) -> None:
        driver = as_driver(driver, "probe")
        rate = validate.positive(rate, "rate", "haptic ticks per second, in Hz")
        self.pace = validate.flag(pace, "pace")
        self.threaded = validate.flag(thread, "thread")
        self.physics = Probe(mesh, driver, radius=radius, coupling=coupling, stiffness=stiffness, candidates=candidates)
        self.snapshot = _Snapshot(driver.n_nodes, 1.0 / rate, getattr(driver, "fingerprint", None))
        self.haptic = Probe(mesh, self.snapshot, radius=radius, coupling=coupling, stiffness=stiffness,
                            candidates=candidates)
        self.mesh, self.driver = mesh, driver
        self.force = np.zeros(3)
        self.error: BaseException | None = None
        self.stop_reason: str | None = None  # why the physics stopped (the force is zero from then on)
        self._hand = None
        self._last_tick = 0.0
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._t0 = None  # wall clock of the first tick (pace)
        self._sim0 = 0.0
        self.physics_steps = 0
        self.physics_seconds = 0.0  # wall time spent in physics steps
        self.step_times: list[float] = []
        self._switch = None
        self._publish(np.asarray(driver.displacements(), dtype=float).copy())
        # a compliance before the first physics step: a vertex touched before its own is published
        # uses the last one computed (a constraint coupling would divide by a zero W)
        self.prepare(nodes=[int(self.physics._touchable[0])])

    # ------------------------------------------------------------------ the haptic side
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
        W = {int(v): np.asarray(self.driver.step_compliance(int(v)), dtype=float) for v in nodes.tolist()}
        self.snapshot.publish(self.snapshot.U, self.snapshot.free, W)
        return int(nodes.size)

    def update(self, position) -> np.ndarray:
        """One haptic tick with the hand at ``position``: the force on the hand (N), from the latest
        snapshot; the physics thread takes the position for its next step (started at the first
        tick)."""
        if self.error is not None or self.stop_reason is not None:
            self.force = np.zeros(3)
            err, self.error = self.error, None
            if err is not None:
                self.close()
                self.stop_reason = f"the probe's physics step failed, so its force is zero: {err}"
            raise ModelError(self.stop_reason) from err
        c = validate.point(position, "probe position")
        self._hand, self._last_tick = c, time.perf_counter()
        if self.threaded:
            if self._thread is None:
                self.start()
            self._wake.set()
        self.force = self.haptic.update(c)
        return self.force

    def displacements(self) -> np.ndarray:
        """The organ's (n, 3) displacements at the last physics step (for drawing)."""
        return self.snapshot.U.copy()

    # ------------------------------------------------------------------ the physics side
    def start(self) -> "MultiRateProbe":
        """Start the physics thread (the first :meth:`update` does)."""
        if self._thread is not None and self._thread.is_alive():
            return self
        from ..threads import background

        self._stop.clear()
        self._t0, self._sim0 = time.perf_counter(), float(self.driver.time)
        self._switch = sys.getswitchinterval()
        sys.setswitchinterval(SWITCH_INTERVAL)
        self._thread = threading.Thread(target=self._run, name="rtfem-multirate-physics", daemon=True)
        background(self._thread, self._stop.set)
        self._thread.start()
        return self

    def close(self, timeout: float = 10.0) -> None:
        """Stop the physics thread (after the step it is in) and restore the switch interval."""
        self._stop.set()
        self._wake.set()
        th = self._thread
        if th is not None and th is not threading.current_thread():
            th.join(timeout)
        self._thread = None
        if self._switch is not None:
            sys.setswitchinterval(self._switch)
            self._switch = None

    def __enter__(self) -> "MultiRateProbe":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _run(self) -> None:
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
        except BaseException as exc:  # noqa: BLE001 - surfaced by the next tick
            self.error = exc

    def physics_step(self) -> None:
        """One step of the organ with the contact at the hand's latest position (the physics
        thread's work; call it yourself with ``thread=False``), then a new snapshot."""
        if self._hand is None:
            raise ModelError("no hand position yet: call update(position) first")
        t = time.perf_counter()
        self.physics.update(self._hand)
        self._publish(None)
        dt = time.perf_counter() - t
        self.physics_steps += 1
        self.physics_seconds += dt
        if len(self.step_times) < 100_000:
            self.step_times.append(dt)

    def _publish(self, U) -> None:
        """After a physics step: the displacements, the free step of the vertices near the hand and
        the contact vertex's compliance (and of any vertex a tick touched without one)."""
        d, p = self.driver, self.physics
        if U is None:
            U = np.asarray(displacements_at(d, np.arange(d.n_nodes)), dtype=float)
        near = np.zeros(0, dtype=np.int64)
        if self._hand is not None:
            _, cand = p._tree.query(self._hand, k=p._k)
            near = p._touchable[np.atleast_1d(cand)]
        contact = p.contact_node
        if contact is not None:
            near = np.union1d(near, [contact])
        free = {}
        if near.size:
            u_free = predictions(d, near)
            free = {int(i): u_free[j].copy() for j, i in enumerate(near.tolist())}
        want = set(self.snapshot.wanted)
        self.snapshot.wanted.clear()
        if contact is not None:
            want.add(int(contact))
        elif near.size:
            X = p.X[near] + U[near]
            want.add(int(near[np.argmin(np.linalg.norm(X - self._hand, axis=1))]))
        W = {i: np.asarray(d.step_compliance(i), dtype=float) for i in sorted(want)[:4]}
        self.snapshot.publish(U, free, W)

    def stats(self) -> dict:
        """The physics thread's record: steps, steps per wall second (while stepping), the median
        and 99th-percentile step time (s) and the simulated seconds per wall second since the first
        tick."""
        st = np.asarray(self.step_times) if self.step_times else np.zeros(1)
        wall = time.perf_counter() - self._t0 if self._t0 is not None else 0.0
        return {"steps": self.physics_steps,
                "steps_per_second": self.physics_steps / self.physics_seconds if self.physics_seconds else 0.0,
                "step_median": float(np.median(st)), "step_p99": float(np.percentile(st, 99)),
                "time_ratio": (float(self.driver.time) - self._sim0) / wall if wall > 0 else 0.0}
