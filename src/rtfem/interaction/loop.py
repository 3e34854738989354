"""The haptic loop: a device read, a tool's force computed and sent at a fixed rate (1-10 kHz), in
Python or compiled ticks, with its timing statistics (:class:`LoopStats`)."""

from __future__ import annotations

import contextlib
import threading
import time
from dataclasses import dataclass, field

import numpy as np

from .. import validate
from ..errors import ModelError, SolverError

from .devices.base import ScriptedDevice, SharedDevice
from .haptics import Grasp, Probe, _CompiledGrasp, _CompiledProbe, _foreign_loads
from .ticks import _OWNERS, _OWNERS_LOCK, _compiled_driver, _compiled_loop

__all__ = ["HapticLoop", "LoopStats"]

MAX_PRESAMPLED = 2_000_000  # ticks of a ScriptedDevice a compiled loop samples in advance (48 MB)


@dataclass
class LoopStats:
    """What a HapticLoop achieved."""

    steps: int = 0
    seconds: float = 0.0
    compute: list[float] = field(default_factory=list)  # per-step compute time (s)
    lateness: list[float] = field(default_factory=list)  # start time minus scheduled time (s)
    peak_force: float = 0.0
    missed: int = 0  # ticks skipped because the loop was more than a period behind its schedule
    slots: list[int] = field(default_factory=list)  # the schedule slot of each step (k: due at start + k / rate)
    compiled: bool = False  # True when the ticks ran in compiled code without the GIL
    priority: str = ""  # the loop thread's scheduling priority (rtfem.threads.raise_priority)
    monitor: object = field(default=None, repr=False)  # the loop's ErrorMonitor (HapticLoop(monitor=...)), or None

    @property
    def error_estimate(self):
        """The latest :class:`~rtfem.reduction.indicator.ErrorEstimate` of the loop's monitor (the
        organ's full-order error, estimated beside the loop), or None."""
        return None if self.monitor is None else self.monitor.latest

    def period_errors(self) -> np.ndarray:
        """|interval between consecutive ticks - period| (s), over pairs of adjacent slots: the
        jitter a device sees (the lateness difference of neighbouring ticks)."""
        late, slot = np.asarray(self.lateness), np.asarray(self.slots)
        if late.size < 2 or slot.size != late.size:
            return np.zeros(0)
        adjacent = np.diff(slot) == 1
        return np.abs(np.diff(late))[adjacent]

    def period_error(self, q: float) -> float:
        """The q-th percentile of :meth:`period_errors` (s)."""
        e = self.period_errors()
        return float(np.percentile(e, q)) if e.size else float("nan")

    @property
    def behind(self) -> bool:
        """True when the loop could not keep its rate (some ticks were skipped)."""
        return self.missed > 0

    @property
    def rate(self) -> float:
        return self.steps / self.seconds if self.seconds > 0 else 0.0

    def percentile(self, q: float) -> float:
        return float(np.percentile(self.compute, q)) if self.compute else float("nan")

    @property
    def jitter(self) -> float:
        """Standard deviation of the step start times around the schedule (s)."""
        return float(np.std(self.lateness)) if self.lateness else float("nan")

    def __str__(self) -> str:
        text = (f"{self.steps} steps in {self.seconds:.2f} s: {self.rate:.0f} Hz achieved; compute median "
                f"{self.percentile(50) * 1e6:.1f} us, 99th percentile {self.percentile(99) * 1e6:.1f} us; "
                f"jitter {self.jitter * 1e6:.1f} us; period error 99th percentile {self.period_error(99) * 1e6:.1f} us; "
                f"peak force {self.peak_force:.3f} N" + (" (compiled loop)" if self.compiled else ""))
        if self.missed:
            share = 100.0 * self.missed / (self.missed + self.steps)
            text += f"; FELL BEHIND: {self.missed} ticks skipped ({share:.1f} % of the schedule)"
        est = self.error_estimate
        if est is not None:
            text += f"; error estimate {est.max_error * 1e3:.3g} mm at node {est.worst_node}"
        return text


class HapticLoop:
    """Runs ``probe.update`` on its own thread at a fixed rate (default 1 kHz).

    Each tick reads the device position, computes the contact force and hands it back. The
    schedule is absolute (tick k at start + k/rate): a late tick does not shift later ones.
    Waiting sleeps until shortly before the tick and spins for the rest (sleep alone is
    too coarse for 1 ms periods). A tick that starts more than a period late does not burst
    through the ticks it owes: they are skipped, counted in ``stats.missed`` (``stats.behind``,
    and said by ``str(stats)``), and the loop resumes on the current slot of the schedule, so
    ``stats.rate`` is the rate actually achieved and the device's time stays the wall time.

    With numba, a Probe or a Grasp on a linear ModalSimulator or on a quasi-static
    ImpedanceDriver, read from a ScriptedDevice (with ``seconds``) or a SharedDevice, ticks in
    compiled code without the GIL (``compiled``: None = when it can, True = insist, False = the
    Python ticks); ``loop.compiled`` and ``stats.compiled`` say which ran.

    Parameters
    ----------
    probe : an :class:`~rtfem.Probe` or :class:`~rtfem.Grasp` (anything with ``update(position)``
        and a ``driver``).
    device : a device: ``position(t)`` and ``set_force(t, f)`` (:class:`~rtfem.ScriptedDevice`,
        :class:`~rtfem.CallbackDevice`, :class:`~rtfem.SharedDevice`).
    rate : ticks per second (Hz), up to 1e5.
    spin : seconds of busy-waiting before each tick (sleep alone is too coarse for 1 ms), 0 .. 0.1.
    compiled : None (compiled ticks where they can run), True (insist), False (Python ticks).
    monitor : an :class:`~rtfem.reduction.indicator.ErrorMonitor` of the organ
        (:func:`~rtfem.reduction.indicator.probe_monitor`) run on its own low-priority thread from
        :meth:`start` to :meth:`stop`: ``stats.error_estimate`` is its latest estimate (issue 56). With a
        monitor the ticks run in Python (compiled ticks do not keep the tool's loads where it reads them).

    Raises
    ------
    ModelError
        A probe or device without those methods, a rate or spin out of range, ``compiled=True``
        where the compiled loop cannot run (the message says why); in :meth:`run`/:meth:`start`,
        a second loop on the same simulator.
    """

    MAX_RATE = 1e5  # Hz: beyond this a Python-level tick cannot be scheduled (the OS clock alone jitters ~us)

    def __init__(self, probe: Probe, device, rate: float = 1000.0, spin: float = 3e-4, *,
                 compiled: bool | None = None, monitor=None) -> None:
        if not callable(getattr(probe, "update", None)) or not hasattr(probe, "driver"):
            raise ModelError(f"probe={validate.show(probe)} must be an rt.Probe (or an rt.Grasp): an object with "
                             "update(position) and a driver")
        if not (callable(getattr(device, "position", None)) and callable(getattr(device, "set_force", None))):
            raise ModelError(f"device={validate.show(device)} must have position(t) and set_force(t, f) methods "
                             "(rt.ScriptedDevice, rt.CallbackDevice)")
        rate = validate.positive(rate, "rate", "ticks per second, in Hz")
        if rate > self.MAX_RATE:
            raise ModelError(f"rate={rate:g} Hz is above the {self.MAX_RATE:g} Hz a loop can be scheduled at; "
                             "haptic devices run at 1 .. 10 kHz")
        spin = validate.in_range(spin, "spin", 0.0, 0.1, what="seconds of busy-waiting before each tick")
        if monitor is not None and not (callable(getattr(monitor, "start", None)) and hasattr(monitor, "latest")):
            raise ModelError(f"monitor={validate.show(monitor)} must be an ErrorMonitor (rtfem.reduction.indicator."
                             "probe_monitor(probe)) or None")
        if monitor is not None and compiled:  # the compiled ticks leave the tool's loads where the monitor reads them stale
            raise ModelError("monitor= reads the tool's loads, which compiled ticks do not keep in Python: pass "
                             "compiled=False (or None) with a monitor")
        self.probe, self.device, self.monitor = probe, device, monitor
        self.rate = rate
        self.period = 1.0 / rate
        self.spin = spin
        self.stats = LoopStats()
        self._stop = threading.Event()
        self._owned: list[int] = []  # ids of the probe and its driver while this loop runs them
        self._ctl = np.zeros(1, dtype=np.int64)  # the compiled loop's flag: 1 stop, 2 pause
        self._paused, self._resume = threading.Event(), threading.Event()
        self._pause_lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self.error: BaseException | None = None
        self._kernels = None
        why = self._compiled_refusal()
        self._required = compiled is not None and validate.flag(compiled, "compiled")
        if compiled is None:
            compiled = why is None and monitor is None
        elif self._required and why is not None:
            raise ModelError(f"compiled=True: {why}")
        self.compiled = bool(compiled)  # ticks in compiled code where the run allows it (see start)
        if self.compiled:
            self._kernels = _compiled_loop()

    def _compiled_refusal(self) -> str | None:
        """Why the ticks cannot run in compiled code here (None: they can)."""
        if _compiled_loop() is None:
            return "the compiled loop needs numba (rtfem[fast]) and a monotonic clock (Linux, macOS)"
        if type(self.probe) not in (Probe, Grasp):
            return "only an rt.Probe or an rt.Grasp runs in the compiled loop (another object runs in Python)"
        if not _compiled_driver(self.probe.driver):
            return ("only a (linear) ModalSimulator with its compiled step, or a quasi-static ImpedanceDriver "
                    "(dynamic=False: a dynamic one keeps its force history in Python), drives the compiled loop")
        if type(self.device) is not ScriptedDevice and not isinstance(self.device, SharedDevice):
            return ("the compiled loop reads an rt.ScriptedDevice (sampled in advance) or an rt.SharedDevice (the "
                    "hardware adapters of rt.devices are)")
        return None

    def _run(self, stats: LoopStats, max_steps: int | None, seconds: float | None) -> None:
        with _spare_core():
            self._ticks(stats, max_steps, seconds)

    def _ticks(self, stats: LoopStats, max_steps: int | None, seconds: float | None) -> None:
        st = stats
        t0 = time.perf_counter()
        deadline = None if seconds is None else t0 + seconds
        k = 0
        try:
            while not self._stop.is_set() and (max_steps is None or k - st.missed < max_steps):
                target = t0 + k * self.period
                if deadline is not None and target >= deadline:
                    break
                while True:
                    now = time.perf_counter()
                    wait = target - now
                    if wait <= 0:
                        break
                    if wait > self.spin:
                        time.sleep(wait - self.spin)
                start = time.perf_counter()
                if deadline is not None and start >= deadline:  # a loop that cannot keep the rate stops on
                    while t0 + k * self.period < deadline:  # time; the slots still due are skipped, and counted
                        k += 1
                        st.missed += 1
                    break
                if start - target > self.period:  # behind by whole ticks: skip them, do not burst
                    skip = int((start - target) / self.period)
                    k += skip
                    st.missed += skip
                    target = t0 + k * self.period
                t = k * self.period
                f = self.probe.update(self.device.position(t))
                self.device.set_force(t, f)
                st.lateness.append(start - target)
                st.slots.append(k)
                st.compute.append(time.perf_counter() - start)
                st.peak_force = max(st.peak_force, float(np.linalg.norm(f)))
                k += 1
                st.steps = k - st.missed
                st.seconds = time.perf_counter() - t0
        except BaseException as exc:  # surfaced by stop()/join()
            self.error = exc
        finally:
            st.seconds = time.perf_counter() - t0
            self._disown()

    def _run_compiled(self, stats: LoopStats, max_steps: int | None, seconds: float | None) -> None:
        """The loop with every tick in compiled code (kernels.loop_kernels): the GIL is released
        for whole runs of ticks, taken back only to prepare a newly touched vertex (its static
        correction: sparse solves), to empty a full record, and at the end."""
        dev = self.device
        t0 = time.perf_counter()
        try:
            scripted = type(dev) is ScriptedDevice
            n_slots = int(np.ceil(seconds * self.rate)) if seconds is not None else 0
            if scripted:
                positions = np.array([dev.position(k * self.period) for k in range(n_slots)], dtype=float).reshape(-1, 3)
                if not np.all(np.isfinite(positions)):
                    raise ModelError("the scripted device's trajectory gave NaN or infinite positions")
                mailbox = np.zeros(6)
            else:
                positions, mailbox = np.zeros((0, 3)), dev.mailbox
            capacity = n_slots if seconds is not None else int(10 * self.rate)
            if max_steps is not None:
                capacity = min(capacity, max_steps) if capacity else max_steps
            if type(self.probe) is Grasp:
                run = _CompiledGrasp(self.probe, self._kernels[2])
            else:
                run = _CompiledProbe(self.probe, self._kernels[0])
            run.pause = self._pause_point
            with _spare_core():
                t0 = time.perf_counter()
                deadline = t0 + seconds if seconds is not None else np.inf
                run.ticks(np.array([t0, self.period, deadline, self.spin]), positions, mailbox, self._ctl, capacity,
                          max_steps, lambda *rec: self._keep(stats, *rec, dev if scripted else None))
            stats.missed = run.missed
            stats.steps = len(stats.compute)
            stats.seconds = run.ended - t0
        except BaseException as exc:  # surfaced by stop()/join()
            self.error = exc
        finally:
            stats.seconds = stats.seconds or time.perf_counter() - t0
            self._disown()

    def _disown(self) -> None:
        """Let go of the probe and its driver (see :meth:`start`)."""
        with _OWNERS_LOCK:
            for key in self._owned:
                if _OWNERS.get(key) is self:
                    del _OWNERS[key]

    def _keep(self, stats: LoopStats, late, comp, forces, slots, scripted) -> None:
        """Move compiled-loop records into the statistics (and a scripted device's force log)."""
        stats.lateness.extend(late.tolist())
        stats.compute.extend(comp.tolist())
        stats.slots.extend(slots.tolist())
        if len(forces):
            stats.peak_force = max(stats.peak_force, float(np.linalg.norm(forces, axis=1).max()))
        if scripted is not None:
            scripted.times.extend((slots * self.period).tolist())
            scripted.forces.extend(forces.copy())

    def start(self, max_steps: int | None = None, *, seconds: float | None = None) -> "HapticLoop":
        """Start the loop on its own thread (fresh statistics); stop with :meth:`stop`.

        One loop per probe and per simulator: a second loop on a probe, or on another probe or tool
        of the same simulator, that is already driven is refused (two loops would step the same
        simulator twice per tick).
        """
        if max_steps is not None:
            max_steps = validate.count(max_steps, "max_steps", 1)
        if seconds is not None:
            seconds = validate.positive(seconds, "seconds", "a duration in seconds")
        if self._thread is not None and self._thread.is_alive():
            raise ModelError("this haptic loop is already running; stop() it first")
        compiled = self.compiled
        if compiled and type(self.device) is ScriptedDevice and seconds is None:
            if self._required:
                raise ModelError("a compiled loop samples a ScriptedDevice in advance: give seconds= (or compiled=False)")
            compiled = False  # an open-ended scripted run: the Python ticks (stats.compiled says so)
        if compiled and type(self.device) is ScriptedDevice and seconds * self.rate > MAX_PRESAMPLED:
            if self._required:  # (an hour at 10 kHz would be 36 million positions sampled before the first tick)
                raise ModelError(f"a compiled loop samples a ScriptedDevice in advance: {seconds * self.rate:.3g} ticks is "
                                 f"more than {MAX_PRESAMPLED:,}; run it in parts, or pass compiled=False")
            compiled = False
        attach = getattr(self.device, "attach", None)  # a hardware adapter fits its workspace to the organ
        if attach is not None and hasattr(self.probe, "mesh"):
            attach(self.probe.mesh.bounds())
        try:  # the device's first answer, here: a device giving text or NaN fails now, not at stop()
            validate.point(self.device.position(0.0), "the device's position")
        except ModelError as exc:
            raise ModelError(f"{exc} (from {type(self.device).__name__}.position(0.0)); the loop was not started") \
                from None
        if compiled and _foreign_loads(self.probe):
            if self._required:
                raise ModelError(f"compiled=True: {_foreign_loads(self.probe)}")
            compiled = False
        driver = getattr(self.probe, "driver", None)
        owned = [(id(self.probe), "probe")] + ([] if driver is None else [(id(driver), "probe's simulator")])
        with _OWNERS_LOCK:
            for key, what in owned:
                owner = _OWNERS.get(key)
                if owner is not None and owner is not self:
                    raise ModelError(f"this {what} is already driven by another running HapticLoop (it would step twice "
                                     "per tick); stop that one first")
            for key, _ in owned:
                _OWNERS[key] = self
        self._owned = [key for key, _ in owned]
        self._stop.clear()
        self._ctl[0] = 0
        self._paused.clear()
        self._resume.clear()
        self.error = None
        self.stats = LoopStats(compiled=compiled, monitor=self.monitor)
        if self.monitor is not None:
            self.monitor.latest = None  # (not the last run's)
            self.monitor.start()
        run = self._run_compiled if compiled else self._run
        from ..threads import background, raise_priority, raise_to_realtime

        light = getattr(self.probe, "light_ticks", False)  # a multi-rate tool: its physics on its own thread

        def prioritized(stats, max_steps, seconds):
            stats.priority = raise_to_realtime() if light else raise_priority()
            run(stats, max_steps, seconds)

        self._thread = threading.Thread(target=prioritized, args=(self.stats, max_steps, seconds),
                                        name="rtfem-haptic-loop", daemon=True)

        background(self._thread, self._signal_stop)
        self._thread.start()
        return self

    def _signal_stop(self) -> None:
        """Tell the ticks to end (Python and compiled), without waiting."""
        self._stop.set()
        self._ctl[0] = 1
        self._resume.set()  # a loop waiting for a grab or release goes on to stop

    def _pause_point(self) -> None:
        """The loop thread, its ticks stopped for a waiting grab or release: wait until it is done."""
        self._paused.set()
        self._resume.wait()
        self._resume.clear()

    @contextlib.contextmanager
    def _held(self):
        """For a grab or a release from another thread while the compiled ticks run: the ticks
        stop (the slots meanwhile are skipped and counted), the grasp's state is handed back to
        it, and the ticks go on with the new grip when the block ends."""
        with self._pause_lock:
            self._paused.clear()
            self._ctl[0] = 2
            paused = False
            while not paused:
                paused = self._paused.wait(0.002)
                if not paused and (self._thread is None or not self._thread.is_alive() or self._ctl[0] == 1):
                    break  # the loop ended meanwhile: nothing to pause
            try:
                yield
            finally:
                if paused:
                    self._paused.clear()
                    self._resume.set()
                elif self._ctl[0] == 2:
                    self._ctl[0] = 0

    def stop(self, timeout: float = 5.0) -> LoopStats:
        """Stop the loop and return its statistics (raising what stopped it, if anything). A loop
        that does not end within ``timeout`` s (a device whose position() never returns) is left
        to end by itself and a SolverError says so, instead of waiting forever."""
        timeout = validate.positive(timeout, "timeout", "seconds to wait for the loop's thread")
        self._signal_stop()
        if self.monitor is not None:
            self.monitor.stop(timeout)
        if self._thread is not None:
            self._thread.join(timeout)
            if self._thread.is_alive():
                raise SolverError(f"the haptic loop did not stop within {timeout:g} s: its tick is blocked, most likely "
                                  f"in {type(self.device).__name__}.position() (a device read that never returns); it "
                                  "stops at its next tick. Make the device's read return (or time out)")
        if self.error is not None:
            err, self.error = self.error, None
            raise err
        return self.stats

    def run(self, seconds: float) -> LoopStats:
        """Run for ``seconds`` of wall-clock time (blocking) and return the statistics.

        A loop that cannot keep its rate still stops on time; its statistics show how many
        ticks it managed and how late they were.
        """
        seconds = validate.positive(seconds, "seconds", "a duration in seconds")
        if seconds > 1e6:
            raise ModelError(f"seconds={seconds:g} is more than 11 days; use start() and stop() for an open-ended loop")
        self.start(seconds=seconds)
        self._thread.join()  # type: ignore[union-attr]
        return self.stop()


def _spare_core():
    """While a loop runs, BLAS (numpy's and MKL's thread pools) is held to one thread
    (:func:`rtfem.threads.runtime`), so that a drawing thread's field product cannot take the
    loop's core: on 2 cores a two-thread product pre-empted the loop for 5 ms at a time
    (benchmarks/haptic_loop.py, "busy viewer"). Needs threadpoolctl (rtfem[fast]); without it,
    nothing is limited."""
    from ..threads import runtime

    return runtime()
