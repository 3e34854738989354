"""The compiled haptic ticks' common machinery: the compiled loop kernels, the driver they step, the
cached compliances and the pause of a loop while a tool's state is replayed."""

from __future__ import annotations

import contextlib
import threading
import time

import numpy as np

from ..drivers.base import prepare

__all__ = []

_OWNERS: dict = {}  # id(probe or grasp) -> the HapticLoop driving it
_OWNERS_LOCK = threading.Lock()


def _cached_compliance(driver, cache: dict, node: int) -> np.ndarray:
    """The driver's 3x3 step compliance at ``node``, kept in ``cache``; the first time the driver
    prepares the node (static-correction or compliance columns, an impedance map)."""
    W = cache.get(node)
    if W is None:
        prepare(driver, [node])
        W = cache[node] = np.asarray(driver.step_compliance(node), dtype=float)
    elif getattr(driver, "compliance_changes", False):  # warped or nonlinear: it follows the motion
        W = np.asarray(driver.step_compliance(node), dtype=float)
    return W


def _loop_paused(obj):
    """The compiled loop driving ``obj`` paused (from another thread), or nothing to pause."""
    with _OWNERS_LOCK:
        loop = _OWNERS.get(id(obj))
    if loop is None or not loop.stats.compiled or threading.current_thread() is loop._thread:
        return contextlib.nullcontext()
    return loop._held()


def _is_impedance(driver) -> bool:
    from ..drivers.impedance_driver import ImpedanceDriver

    return type(driver) is ImpedanceDriver


def _compiled_loop():
    from ..drivers.kernels import loop_kernels

    return loop_kernels()


def _compiled_driver(driver) -> bool:
    """Whether the compiled ticks can drive ``driver``: a linear ModalSimulator with its compiled
    step, or a quasi-static ImpedanceDriver (its ticks are the modal ones with no modes)."""
    from ..drivers.modal import ModalSimulator

    if _is_impedance(driver):
        return not driver.dynamic
    return type(driver) is ModalSimulator and bool(driver.compiled)


class _CompiledTicks:
    """A haptic object (Probe or Grasp) and its ModalSimulator packed into the arrays of a compiled
    loop (kernels.loop_kernels), and unpacked back into them when the ticks end. ``pause``, set
    by the loop, is called when the ticks stop for a waiting grab or release (status 3)."""

    def __init__(self, obj, chunk) -> None:
        self.sim, self.chunk = obj.driver, chunk
        self.impedance = _is_impedance(self.sim)
        self.fout = np.zeros(3)
        self.missed = 0
        self.pause = None

    def ticks(self, sched, positions, mailbox, ctl, capacity: int, max_steps, keep) -> None:
        """Run the compiled ticks; ``keep(lateness, compute, forces, slots)`` receives the records
        each time the record of ``capacity`` ticks fills and at the end."""
        sim = self.sim
        late, comp = np.zeros(capacity), np.zeros(capacity)
        forces, slots = np.zeros((capacity, 3)), np.zeros(capacity, dtype=np.int64)
        counters = np.array([0, 0, 0, -1 if max_steps is None else max_steps, 0], dtype=np.int64)
        clock = np.zeros(2, dtype=np.int64)
        steps0 = sim.steps
        if self.impedance:  # the driver's field follows the ticks' loads (a drawing thread reads them)
            sim._live = self._live_loads
        try:
            while True:
                status = self.chunk(self.arguments(), self.fout, sched, positions, mailbox, ctl, late, comp, forces,
                                    slots, counters, clock)
                if status == 1:  # a vertex touched for the first time: its compliance, then on
                    self.prepare()
                    continue
                if status == 3:  # a grab or release waits: hand over the state, take it back after
                    self._unpack(steps0 + int(counters[1]))
                    steps0, counters[1] = sim.steps, 0
                    ctl[0] = 0
                    self.pause()
                    self.pack()
                    continue
                n = int(counters[4])
                if status == 0 and n == capacity and (max_steps is None or counters[1] < max_steps):
                    keep(late[:n], comp[:n], forces[:n], slots[:n])  # the record is full: empty it and go on
                    counters[4] = 0
                    continue
                break
        finally:
            self.ended = time.perf_counter()
            n = int(counters[4])
            keep(late[:n], comp[:n], forces[:n], slots[:n])
            self.missed = int(counters[2])
            self._unpack(steps0 + int(counters[1]))
            if self.impedance:
                sim._live = None

    def _sim_arguments(self) -> tuple:
        sim = self.sim
        if self.impedance:  # quasi-static: no modes, so predict is 0 and the step moves nothing; the
            # contact compliance is the map's static one (the compliance table) and the loads are
            # read off the ticks' forces (_live_loads, _unpack)
            if getattr(self, "_none", None) is None:
                self._none = (np.zeros((8, 0)), np.zeros((2, 0)), np.zeros(0), np.zeros((sim.n_nodes, 3, 0)), False)
            return self._none
        return sim._coef, sim._S, sim._f_old, sim._phi, sim._G0 is not None

    def _steps_done(self, steps: int) -> None:
        self.sim.steps = steps
        self.sim.time = steps * self.sim.dt
