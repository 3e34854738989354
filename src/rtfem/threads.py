"""Thread pools of the BLAS libraries, limited where they measurably get in each other's way.

numpy and scipy each carry an OpenBLAS whose worker threads keep spinning for a while after a
call, and MKL (PARDISO's solves, the fast extra) runs its own threads: on a 2-core machine the
100-mode eigen-solve of the OpenHELP liver spends 3.3 s in PARDISO solves beside spinning
OpenBLAS threads and 2.1 s without them (benchmarks/eigen.py). The limits need threadpoolctl
(part of rtfem[fast]); without it nothing is limited.

At run time (a simulator stepped in real time, a haptic loop, the viewer's session, ``rtfem
simulate`` and ``rtfem bench``) every product is small (a few hundred rows) or drawn at a frame
rate, and BLAS threads only hurt: with another process busy on a 2-core machine, OpenBLAS's
two-thread products of the reduced nonlinear step took 15 ms instead of 1.1-2 ms, the r = 100
modal step 8-16 ms instead of 0.11 ms. :func:`runtime` holds every BLAS pool to
:data:`RUNTIME_THREADS` (one) while any run-time loop of the process runs
(benchmarks/runtime_load.py measures each path quiet and beside a busy process).
"""

from __future__ import annotations

import atexit
import contextlib
import os
import threading
import time
import weakref

__all__ = ["blas_limits", "usable_cores", "SharedLimit", "runtime", "RUNTIME_THREADS", "background",
           "raise_priority", "PHYSICS_NICE", "raise_to_realtime", "HAPTIC_RT_PRIORITY", "leave_realtime", "below_ticks"]


def usable_cores() -> int:
    """The cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # macOS, Windows
        return os.cpu_count() or 1


def blas_limits(threads: int, internal_api: str | None = None):
    """A context manager holding the BLAS thread pools (only those of ``internal_api``, e.g.
    "openblas", when given) to ``threads``; it does nothing without threadpoolctl."""
    try:
        from threadpoolctl import ThreadpoolController
    except ImportError:
        return contextlib.nullcontext()
    controller = ThreadpoolController()
    if internal_api is not None:
        controller = controller.select(internal_api=internal_api)
    return controller.limit(limits=int(threads))


class SharedLimit:
    """One BLAS limit held while any of its holders needs it: the first :meth:`acquire` enters it,
    the last :meth:`release` restores the pools. Changing OpenBLAS's thread count while another
    thread is inside a BLAS call stalled that call for 0.5-2.7 s (a haptic loop's step, when a
    background thread's limit was entered or left beside it), so background workers that come
    and go share one limit instead of each setting and restoring it."""

    def __init__(self, threads: int) -> None:
        self.threads = int(threads)
        self._lock = threading.Lock()
        self._count = 0
        self._held = None

    def acquire(self) -> None:
        with self._lock:
            if self._count == 0:
                self._held = blas_limits(self.threads)
                self._held.__enter__()
            self._count += 1

    def release(self) -> None:
        with self._lock:
            self._count -= 1
            if self._count == 0 and self._held is not None:
                self._held.__exit__(None, None, None)
                self._held = None


def _runtime_threads() -> int:
    """RTFEM_RUNTIME_THREADS (default 1; 0: no limit, BLAS's own thread count, the comparison
    benchmarks/runtime_load.py measures against)."""
    text = os.environ.get("RTFEM_RUNTIME_THREADS", "1").strip()
    try:
        value = int(text)
    except ValueError:
        value = -1
    if value < 0:  # a warning, not an error: the variable is read when rtfem is imported
        import warnings

        from .errors import RtfemWarning

        warnings.warn(f"RTFEM_RUNTIME_THREADS={text!r} is not a whole number >= 0 (0: no limit); using 1",
                      RtfemWarning, stacklevel=2)
        value = 1
    return value


RUNTIME_THREADS = _runtime_threads()
_RUNTIME = SharedLimit(RUNTIME_THREADS or usable_cores())


@contextlib.contextmanager
def runtime():
    """Hold BLAS to :data:`RUNTIME_THREADS` while the block runs (shared by every run-time loop
    and background worker of the process: the pools change only when the first enters and the
    last leaves, never under a running step)."""
    _RUNTIME.acquire()
    try:
        yield
    finally:
        _RUNTIME.release()


# ---------------------------------------------------------------- the stepping threads' priority
PHYSICS_NICE = -10  # the nice value a stepping thread asks for (RTFEM_PHYSICS_NICE overrides; 0: normal)


def raise_priority(native_id: int | None = None) -> str:
    """Raise the calling thread's scheduling priority (or that of thread or process ``native_id``: a worker
    process's pid) to :data:`PHYSICS_NICE` (or the whole
    number in ``RTFEM_PHYSICS_NICE``; 0 leaves it), as haptic frameworks do with their servo
    threads (CHAI3D's haptics thread priority, OpenHaptics' servo loop). The viewer's session,
    the scene viewer's and the haptic loop call it on their stepping thread. Linux only (a
    thread's own nice value, setpriority on its thread id), and only where permitted: root,
    CAP_SYS_NICE, or an RLIMIT_NICE that allows it (``/etc/security/limits.conf``: ``@users - nice
    -10``). Measured (benchmarks/viewer_browser.py, 2 cores, a browser drawing in software and
    another process spinning): the default organ stepped at 0.40-0.66 of real time at the normal
    priority and 0.93-1.00 raised, the browser drawing what is left.
    Returns what the thread got, in words ("nice -10", or "normal: ..." with the reason); raises only for a
    ``native_id`` that is not a positive whole number (ModelError)."""
    if native_id is not None:
        from .validate import count

        native_id = count(native_id, "native_id", 1, what="a thread or process id")
    text = os.environ.get("RTFEM_PHYSICS_NICE", "").strip()
    try:
        nice = int(text) if text else PHYSICS_NICE
    except ValueError:
        return f"normal: RTFEM_PHYSICS_NICE={text!r} is not a whole number"
    if nice >= 0:
        return "normal: RTFEM_PHYSICS_NICE asks for none"
    if not hasattr(os, "setpriority") or not hasattr(threading, "get_native_id"):
        return "normal: not supported on this system"
    try:
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id() if native_id is None else native_id, nice)
    except OSError as exc:
        return (f"normal: not permitted ({exc.strerror}); allow it with CAP_SYS_NICE or an RLIMIT_NICE "
                f"(limits.conf: '@users - nice {nice}')")
    return f"nice {nice}"


def leave_realtime() -> bool:
    """Put the calling thread under the normal policy (SCHED_OTHER) where it runs under a real-time one
    (True where it did): a thread inherits the scheduling of the thread that starts it, and a helper
    started by a real-time thread (a scalpel's cut job, a factor refreshed on a thread, started by a
    multi-rate tool's physics thread) would take a core at real-time priority for its whole work.
    Linux only; never raises."""
    if not hasattr(os, "sched_getscheduler") or not hasattr(threading, "get_native_id"):
        return False
    try:
        me = threading.get_native_id()
        if os.sched_getscheduler(me) not in (os.SCHED_FIFO, os.SCHED_RR):
            return False
        os.sched_setscheduler(me, os.SCHED_OTHER, os.sched_param(0))
    except OSError:  # pragma: no cover - leaving a real-time policy is always permitted
        return False
    return True


def below_ticks() -> str:
    """The scheduling of a multi-rate tool's physics thread, which the loop's first tick starts: where that
    tick runs under SCHED_FIFO (:func:`raise_to_realtime`), the same policy one priority below it, so that
    a tick pre-empts the physics (it inherited the ticks' own priority, and a tick cannot pre-empt a thread
    of its FIFO priority: a scalpel's cut job, started by the physics thread alike, held the ticks off for
    0.35-0.57 s of 6.5 s, 330-550 of 7,000 missed, benchmarks/scalpel.py), and the physics still runs ahead
    of the machine's other processes and moves to a free core at once, as real-time threads do (the
    full-order liver with a probe or a grasp, beside a busy core: 37-55 steps/s here, 49-69 at the ticks' own
    priority, 14-27 at nice -10 instead; quiet 35-57, 39-54 and 29-61; benchmarks/haptic_fullorder.py --busy); else
    :func:`raise_priority`. The threads it starts leave the real-time policy (:func:`leave_realtime`).
    Returns what the thread got, in words; never raises."""
    if hasattr(os, "sched_getscheduler") and hasattr(threading, "get_native_id"):
        try:
            me = threading.get_native_id()
            if os.sched_getscheduler(me) == os.SCHED_FIFO:
                prio = os.sched_getparam(me).sched_priority - 1
                if prio >= 1:
                    os.sched_setscheduler(me, os.SCHED_FIFO, os.sched_param(prio))
                    return f"SCHED_FIFO {prio}"
                leave_realtime()
        except OSError:  # pragma: no cover - lowering a real-time priority is always permitted
            pass
    return raise_priority()


HAPTIC_RT_PRIORITY = 10  # the SCHED_FIFO priority of a multi-rate loop's ticks (RTFEM_HAPTIC_RT overrides; 0: none)


def raise_to_realtime() -> str:
    """Put the calling thread under real-time scheduling (Linux's SCHED_FIFO at
    :data:`HAPTIC_RT_PRIORITY`, or the whole number in ``RTFEM_HAPTIC_RT``; 0 asks for none), as a
    haptic servo thread is (CHAI3D, OpenHaptics): it then runs whenever it is ready, ahead of every
    normal thread of the machine. For a thread whose work is short and which sleeps between ticks:
    ``rt.HapticLoop`` asks for it when its tool is multi-rate (its ticks are a few array reads, its
    physics on another thread). Measured (benchmarks/haptic_fullorder.py's probe on the full-order
    liver, another process spinning on one of the 2 cores, 4.5 s of 1 kHz ticks): at nice -10 1-4
    ticks over 1 ms (1.2-5 ms: the thread kept waiting), under SCHED_FIFO none (the longest 0.53 ms).
    Only where permitted (root, CAP_SYS_NICE, or an RLIMIT_RTPRIO, limits.conf: ``@users - rtprio
    10``); else :func:`raise_priority`. Returns what the thread got, in words; never raises."""
    text = os.environ.get("RTFEM_HAPTIC_RT", "").strip()
    try:
        prio = int(text) if text else HAPTIC_RT_PRIORITY
    except ValueError:
        return f"{raise_priority()} (RTFEM_HAPTIC_RT={text!r} is not a whole number)"
    if prio <= 0:
        return raise_priority()
    if not hasattr(os, "sched_setscheduler") or not hasattr(threading, "get_native_id"):
        return f"{raise_priority()} (no real-time scheduling on this system)"
    prio = min(prio, 99)
    try:
        os.sched_setscheduler(threading.get_native_id(), os.SCHED_FIFO, os.sched_param(prio))
    except OSError as exc:
        return (f"{raise_priority()} (real-time scheduling not permitted: {exc.strerror}; allow it with "
                f"CAP_SYS_NICE or an RLIMIT_RTPRIO, limits.conf: '@users - rtprio {prio}')")
    return f"SCHED_FIFO {prio}"


# ---------------------------------------------------------------- background threads at exit
_BACKGROUND: list = []  # (weak reference to a thread, its stop callable or None)
EXIT_WAIT = 30.0  # s: how long the interpreter's exit waits for background threads in all


def background(thread: threading.Thread, stop=None) -> threading.Thread:
    """Register a daemon thread to be stopped (``stop()``) and joined when the interpreter exits.
    A daemon thread still inside a C++ routine (scipy's sparse kernels, the sparse solvers) when
    Python finalizes is unwound by force on its way back to the GIL, and libstdc++ aborts the
    whole process ("terminate called without an active exception": a fresh clone's test run
    that had passed every test exited 134 so). Joined at exit (atexit runs before the
    finalization), it ends first."""
    _BACKGROUND.append((weakref.ref(thread), stop))
    if len(_BACKGROUND) > 256:  # forget the finished ones
        _BACKGROUND[:] = [(r, f) for r, f in _BACKGROUND if r() is not None and r().is_alive()]
    return thread


@atexit.register
def _stop_background() -> None:
    live = [(r(), f) for r, f in _BACKGROUND]
    live = [(t, f) for t, f in live if t is not None and t.is_alive()]
    for _, stop in live:
        if stop is not None:
            try:
                stop()
            except Exception:  # noqa: BLE001 - exiting anyway
                pass
    deadline = time.monotonic() + EXIT_WAIT
    for t, _ in live:
        t.join(max(0.0, deadline - time.monotonic()))
