"""The compliances of the vertices a tool touched lately, kept in one pool from step to step, and
what a vertex needs from the driver first, prepared on a background thread while the tool is
still ``lookahead`` away (see :mod:`rtfem.interaction.contact`)."""

from __future__ import annotations

import threading
import weakref

import numpy as np

from ..drivers.base import prepare, step_compliances
from ..threads import background, runtime

_LOCKS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # driver -> its preparations' lock


def _driver_lock(driver) -> threading.Lock:
    """One lock per driver, shared by every ToolContact on it (two tools' background threads would
    otherwise prepare the same vertices at once); a fresh lock for a driver without weak
    references."""
    try:
        return _LOCKS.setdefault(driver, threading.Lock())
    except TypeError:  # not weakly referenceable (__slots__ without __weakref__)
        return threading.Lock()


class _Preparer:
    """Prepares driver nodes (static-correction or compliance columns: sparse solves of
    milliseconds each) before the force loop needs them: :meth:`want` names the vertices the tool
    is about to reach and a background thread prepares them, nearest first, in small batches;
    :meth:`ensure` (the loop) prepares whatever is still missing itself, so the results never
    depend on the timing. One lock keeps the driver's preparation to one thread at a time. The
    thread ends after a second with nothing to do and starts again on the next :meth:`want`; an
    error there stops the background work (the loop's own preparation then raises it)."""

    BATCH = 4  # nodes per background preparation: short lock holds, multi-column solves

    def __init__(self, driver) -> None:
        self.driver = driver
        self.ready: set[int] = set()
        self.lock = _driver_lock(driver)  # shared by every tool on this driver
        self._cv = threading.Condition()
        self._pending = np.zeros(0, dtype=np.int64)
        self._where = np.zeros((0, 3))  # rest positions of the pending vertices
        self._at = np.zeros(3)
        self._thread = None
        self.failed: BaseException | None = None
        self.background = 0  # nodes prepared by the thread (for benchmarks)

    def ensure(self, nodes: np.ndarray) -> int:
        """Prepare ``nodes`` now (those not ready); returns how many this call prepared."""
        missing = [v for v in nodes.tolist() if v not in self.ready]
        if missing:
            with self.lock:
                missing = [v for v in missing if v not in self.ready]
                if missing:
                    prepare(self.driver, np.asarray(missing, dtype=np.int64))
                    self.ready.update(missing)
        return len(missing)

    def want(self, nodes: np.ndarray, where: np.ndarray, at: np.ndarray) -> None:
        """Prepare ``nodes`` (rest positions ``where``) in the background, nearest ``at`` first."""
        if self.failed is not None:
            return
        fresh = np.fromiter((v not in self.ready for v in nodes.tolist()), dtype=bool, count=nodes.size)
        with self._cv:
            self._pending, self._where, self._at = nodes[fresh], where[fresh], np.asarray(at, dtype=float)
            if self._pending.size and (self._thread is None or not self._thread.is_alive()):
                self._thread = threading.Thread(target=self._run, name="rtfem-prepare", daemon=True)
                background(self._thread, self.close)
                self._thread.start()
            self._cv.notify()

    def close(self) -> None:
        """Drop what is pending: the thread ends after the batch in hand (the interpreter's exit)."""
        with self._cv:
            self._pending, self._where = self._pending[:0], self._where[:0]
            self._cv.notify_all()

    def _run(self) -> None:
        # BLAS and MKL held to one thread while this thread lives (the run-time limit the loops
        # share): their worker threads (spinning after each call) took the loop's core on 2 cores,
        # p99 of the slide 1.7 -> 4.8 ms
        with runtime():
            while True:
                with self._cv:
                    if not self._pending.size and not self._cv.wait_for(lambda: self._pending.size > 0, timeout=1.0):
                        return
                    gap = np.einsum("ij,ij->i", self._where - self._at, self._where - self._at)
                    first = np.argsort(gap, kind="stable")[:self.BATCH]
                    batch = self._pending[first]
                    rest = np.setdiff1d(np.arange(self._pending.size), first)
                    self._pending, self._where = self._pending[rest], self._where[rest]
                try:
                    with self.lock:
                        todo = [v for v in batch.tolist() if v not in self.ready]
                        if todo:
                            prepare(self.driver, np.asarray(todo, dtype=np.int64))
                            self.ready.update(todo)
                            self.background += len(todo)
                except BaseException as exc:  # noqa: BLE001 - the loop's own preparation raises it
                    self.failed = exc
                    return


class _ComplianceBlock:
    """The driver's cross compliances W of the vertices touched lately, kept between steps in one
    buffer (a pool of slots): a vertex touched for the first time gets a slot, and its rows and
    columns against the pool are computed then; a contact set's block is read in place through
    its vertices' slots, so a set that changes costs only its new vertices. When the pool is full
    the vertices of the current set are kept (copied to the front) and the rest let go. Drivers
    whose W follows the motion (``compliance_changes``) get the set's whole block each step."""

    def __init__(self, driver, slots: int = 64) -> None:
        self.driver = driver
        self.min_slots = slots
        self.preparer = _Preparer(driver)
        self.slot = np.full(driver.n_nodes, -1, dtype=np.int64)  # node -> slot (-1: not in the pool)
        self.nodes = np.zeros(0, dtype=np.int64)  # the pool's nodes, by slot
        self.W = np.zeros((3 * slots, 3 * slots))
        self.new_rows = 0  # vertices whose rows were computed in the last call (for benchmarks)
        self.prepared_here = 0  # of them, vertices the loop had to prepare itself (for benchmarks)

    def block(self, nodes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(W, slots): the compliance of ``nodes`` (ascending) is W at rows and columns 3 slot + (0, 1, 2)."""
        d = self.driver
        if getattr(d, "compliance_changes", False):
            self.new_rows = nodes.size
            return np.ascontiguousarray(step_compliances(d, nodes)), np.arange(nodes.size, dtype=np.int64)
        slots = self.slot[nodes]
        fresh = nodes[slots < 0]
        self.new_rows = self.prepared_here = int(fresh.size)
        if not fresh.size:
            return self.W, slots
        self.prepared_here = self.preparer.ensure(fresh)
        used, cap = self.nodes.size, self.W.shape[0] // 3
        if used + fresh.size > cap:  # full: keep the current set's vertices, let the others go
            kept = nodes[slots >= 0]
            need = kept.size + fresh.size
            cap = max(cap, 2 * need, self.min_slots) if need > cap // 2 else cap
            idx = (3 * self.slot[kept][:, None] + np.arange(3)).reshape(-1)
            W = np.empty((3 * cap, 3 * cap))
            W[:idx.size, :idx.size] = self.W[idx][:, idx]
            self.slot[self.nodes] = -1
            self.slot[kept] = np.arange(kept.size)
            self.nodes, self.W, used = kept, W, kept.size
        old = self.nodes
        self.slot[fresh] = used + np.arange(fresh.size)
        self.nodes = np.concatenate([old, fresh])
        j = slice(3 * used, 3 * self.nodes.size)
        self.W[:3 * self.nodes.size, j] = step_compliances(d, self.nodes, fresh)
        if used:
            self.W[j, :3 * used] = step_compliances(d, fresh, old)
        return self.W, self.slot[nodes]
