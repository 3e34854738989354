"""The reduced nonlinear driver's tangent, refreshed on a background thread: the step keeps the
last finished tangent while the next one is computed from a recent state."""

from __future__ import annotations

import os
import threading
import weakref

import numpy as np

from .. import threads
from ..errors import SolverError


__all__ = ["TangentWorker"]


class TangentWorker:
    """A simulator's linearizations computed on a low-priority background thread
    (``background=True``): the step asks with its predictor and takes the newest result at a
    later step, never waiting. While any worker lives, BLAS is held to one thread by the
    limit every run-time loop shares (:func:`rtfem.threads.runtime`; entered on the stepping
    thread when the first worker starts, left when the last ends: never changed under a running
    step). A worker ends after 5 s with
    nothing to do and starts again on the next request; ``forget`` drops a result from before a
    reset or set_state."""

    IDLE = 5.0  # s without a request before the thread ends

    def __init__(self, sim) -> None:
        self._sim = weakref.ref(sim)  # the thread must not keep a dropped simulator alive
        self._cv = threading.Condition()
        self._request = None  # (epoch, q) waiting
        self._result = None  # (epoch, (q, linearization)) done
        self._busy = False
        self._epoch = 0
        self._thread = None
        self.failed: BaseException | None = None
        self._closing = False
        self.done = 0  # linearizations computed (for tests and benchmarks)

    def ask(self, q: np.ndarray) -> bool:
        """Ask for the linearization at q unless one is in flight; True when asked."""
        if self.failed is not None:
            raise SolverError(f"the background tangent refresh failed: {self.failed}") from self.failed
        with self._cv:
            if self._busy or self._request is not None:
                return False
            self._request = (self._epoch, np.array(q, dtype=float))
            if self._thread is None or not self._thread.is_alive():
                threads._RUNTIME.acquire()  # here, on the stepping thread: no BLAS call of its runs meanwhile
                self._thread = threading.Thread(target=self._run, name="rtfem-tangent", daemon=True)
                threads.background(self._thread, self.close)
                self._thread.start()
            self._cv.notify()
        return True

    def take(self):
        """The newest finished (coordinates, linearization) of this epoch, once; else None."""
        with self._cv:
            done, self._result = self._result, None
        return done[1] if done is not None and done[0] == self._epoch else None

    def forget(self) -> None:
        with self._cv:
            self._epoch += 1
            self._request = self._result = None

    def close(self) -> None:
        """End the thread after the linearization in hand (the interpreter's exit calls this)."""
        with self._cv:
            self._closing = True
            self._request = None
            self._cv.notify_all()

    def _run(self) -> None:
        try:
            self._work()
        finally:
            threads._RUNTIME.release()

    def _work(self) -> None:
        try:  # the lowest priority (Linux: per thread): it takes only the time the loop leaves
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), 19)
        except (AttributeError, OSError):  # pragma: no cover - other systems
            pass
        while True:
            with self._cv:
                if self._request is None and not self._cv.wait_for(
                        lambda: self._request is not None or self._closing, timeout=self.IDLE):
                    return
                if self._closing:
                    return
                (epoch, q), self._request, self._busy = self._request, None, True
            try:
                sim = self._sim()
                if sim is None:
                    return
                out = sim._linearization(q)
                del sim
            except BaseException as exc:  # noqa: BLE001 - the next step raises it
                self.failed = exc
                return
            finally:
                with self._cv:
                    self._busy = False
            with self._cv:
                if epoch == self._epoch:
                    self._result = (epoch, (q, out))
                self.done += 1
