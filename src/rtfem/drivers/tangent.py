"""The reduced nonlinear driver's linearization: the step's matrix for a tangent (kept positive
definite), the cubature's tangent at a state, and its refresh, in the step or on a background
thread (the step keeps the last finished tangent while the next one is computed from a recent
state)."""

from __future__ import annotations

import os
import threading
import weakref

import numpy as np

from .. import threads
from ..errors import SolverError


__all__ = ["Linearization", "TangentWorker"]


class TangentWorker:
    """A simulator's linearizations computed on a background thread at the normal priority
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
        # The normal priority (Linux: per thread; the stepping thread's where that is lower): below a
        # raised stepping thread, which it never keeps from a core, and beside the machine's other
        # processes, which never starve it. Not nice 19: the worker holds the GIL between its numpy
        # calls, and starved on a busy machine it held it for up to a second while the stepping
        # thread waited (the viewer's default scene beside two busy processes: 0.75-0.94 of real
        # time, its longest step 0.17 s as a median over runs, the step refreshing the tangent itself
        # 16 times in 4 s; at nice 0: 1.00-1.01, 27 ms; benchmarks/results/viewer_step.txt).
        from ..threads import leave_realtime

        leave_realtime()  # (nor a stepping thread's real-time scheduling, where it has one)
        try:
            me = threading.get_native_id()
            os.setpriority(os.PRIO_PROCESS, me, max(os.getpriority(os.PRIO_PROCESS, me), 0))
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


class Linearization:
    """For :class:`rtfem.drivers.reduced_nonlinear.ReducedNonlinearSimulator`: the step's
    linearization (its state: ``_Sinv``, ``_dK``, ``_tangent_q``, ``_tangent_step``,
    ``_tangent_at``, ``_worker``, ``sync_refreshes``, set by the simulator's reset and set_state; and
    ``_patch_margin``, a localized patch's over-stiff margin or None, set by its ``__init__``)."""

    # background=True: a linearization older than this many steps (a worker starved by a busy
    # machine) is replaced by one computed on the stepping thread
    MAX_TANGENT_AGE = 200

    def _use_rest(self) -> None:
        """The linearization about rest (the state reset() leaves), and no refresh in flight."""
        if self._worker is not None:
            self._worker.forget()
        self._dK, self._Sinv = self._rest_linearization
        self._tangent_q = None  # where the linearization was computed (None: rest)

    def _step_inverse(self, K: np.ndarray) -> np.ndarray | None:
        """(M + dt/2 C + dt^2/4 K)^-1, the step's matrix for a tangent K, kept positive definite: a
        tangent with negative eigenvalues (compressed, past a limit point: a grasp jumping
        centimetres passes through such states) has them clipped at zero, since the step's fixed
        point does not depend on this matrix, only its stability does, and an indefinite one made
        the one-step compliances (and a stiff grasp's force) blow up. None where it is not finite."""
        h = self.dt
        K = 0.5 * (K + K.T)
        if self._patch_margin is not None:  # a localized patch's coordinates, linearized over-stiff
            K = K + self._patch_margin
        S = self._M + 0.5 * h * self._C + 0.25 * h * h * K
        S = 0.5 * (S + S.T)
        try:
            np.linalg.cholesky(S)
        except np.linalg.LinAlgError:
            lam, V = np.linalg.eigh(K)
            S = self._M + 0.5 * h * self._C + 0.25 * h * h * ((V * np.maximum(lam, 0.0)) @ V.T)
            S = 0.5 * (S + S.T)
        try:
            Sinv = np.linalg.inv(S)
        except np.linalg.LinAlgError:
            return None
        return Sinv if np.isfinite(Sinv).all() else None

    def _linearization(self, q: np.ndarray) -> tuple[np.ndarray | None, np.ndarray | None]:
        """The step's linearization about the force model's tangent at q: (each group's change of
        tangent (spread > 1, to carry its lagged remainder from where it was evaluated; else None),
        the step matrix's inverse (None where singular)). The tangent is the cubature's (every
        element's with ``cubature=False``). Reads nothing that a step changes (the worker thread's
        work)."""
        red = self.reduced
        dK = None
        if self._visc_terms is not None:  # a Prony law: its instantaneous law's tangent (see the simulator)
            T = self._visc_terms.tangent(red, q, self.single)
        elif not self.cubature:
            T = red.reduced_forces(q)[1]
            T = 0.5 * (T + T.T)
        elif self.spread == 1:
            data, w = red._cubature
            Ke, _ = red.cubature_rest()
            T = self._Kc + red.tangent_change(q, data, w, Ke, red.cubature_rows(self.single))
        else:
            dK = np.stack([red.tangent_change(q, data, w, Ke, (U, UT)) for data, w, Ke, U, UT in self._groups])
            T = self._Kc + dK.sum(axis=0)
            if self._always is not None:
                data, w, Ke, U, UT = self._always
                T = T + red.tangent_change(q, data, w, Ke, (U, UT))
        return dK, self._step_inverse(T)

    def _use(self, linearization, q: np.ndarray) -> None:
        """Step from now on with ``linearization`` (:meth:`_linearization` at coordinates q)."""
        dK, Sinv = linearization
        if Sinv is not None:  # else the last good one stays: the step is still consistent, only less implicit
            # the groups' tangents side by side (r, groups r): their sum over the lags in one product
            self._dK = None if dK is None else np.ascontiguousarray(dK.transpose(1, 0, 2).reshape(dK.shape[1], -1))
            self._Sinv, self._tangent_q = Sinv, np.array(q, dtype=float)

    def _refresh_tangent(self, qs: np.ndarray) -> None:
        """Before a step (at its predictor qs): refresh the linearization every ``refresh`` steps,
        here, or with ``background`` take the worker's newest and ask it for the next."""
        due = self._tangent_step is None or self.steps - self._tangent_step >= self.refresh
        if not self.background:
            if due:
                self._use(self._linearization(qs), qs)
                self._tangent_step = self.steps
            return
        if self._worker is None:
            self._worker = TangentWorker(self)
        done = self._worker.take()
        if done is not None:
            self._use(done[1], done[0])
            self._tangent_at = self.steps
        if due and self._worker.ask(qs):
            self._tangent_step = self.steps
        elif self.steps - self._tangent_at > self.MAX_TANGENT_AGE:  # the worker is starved (a busy machine)
            self._worker.forget()
            self._use(self._linearization(qs), qs)
            self._tangent_at = self._tangent_step = self.steps
            self.sync_refreshes += 1
