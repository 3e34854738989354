"""Finding and loading a device SDK's shared library (ctypes), and the servo thread of the adapters
whose SDK has no scheduler of its own."""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import threading
import time

from ...errors import DeviceError

__all__ = ["load_library", "find_library", "ServoThread"]


def find_library(library, env: str, names: tuple[str, ...]) -> str | None:
    """The library to load: ``library`` (a path or a name), else ``$env``, else the first of
    ``names`` the system's loader finds; None when none is found."""
    for candidate in (library, os.environ.get(env)):
        if candidate:
            return str(candidate)
    for name in names:
        found = ctypes.util.find_library(name)
        if found:
            return found
    return None


def load_library(library, env: str, names: tuple[str, ...], what: str, how: str, signatures: dict) -> ctypes.CDLL:
    """``ctypes.CDLL`` of :func:`find_library`'s answer with the functions of ``signatures`` ({name:
    (argtypes, restype)}) declared, or a :class:`DeviceError` saying where it was looked for, or which
    function it lacks, and ``how`` to get the SDK (``what`` names it)."""
    path = find_library(library, env, names)
    if path is None:
        raise DeviceError(f"{what}: its library was not found (looked for library=, ${env}, then "
                          f"{', '.join(names)} on the system's library path). {how}")
    try:
        lib = ctypes.CDLL(path)
    except OSError as exc:
        raise DeviceError(f"{what}: cannot load {path!r} ({exc}). {how}") from None
    for name, (args, res) in signatures.items():
        try:
            fn = getattr(lib, name)
        except AttributeError:
            raise DeviceError(f"{what}: {path} has no {name}(): not the {what} library. {how}") from None
        fn.argtypes, fn.restype = args, res
    return lib


class ServoThread:
    """A thread calling ``tick()`` at ``rate`` Hz on an absolute schedule (sleep, then spin the last
    ``spin`` seconds), until ``stop()`` or until ``tick`` returns False; an exception in ``tick`` (any
    BaseException: a RecursionError, a MemoryError) ends it, is kept in ``error`` and handed to
    ``on_error`` (an adapter's fault: zero force, the reason recorded), which is called on this
    thread and whose own exceptions are dropped. For SDKs without a scheduler of their own (Force
    Dimension's)."""

    def __init__(self, tick, rate: float, name: str, spin: float = 2e-4, on_error=None) -> None:
        self._tick, self.period, self.spin, self.on_error = tick, 1.0 / rate, spin, on_error
        self._stop = threading.Event()
        self.error: BaseException | None = None
        self.ticks = 0
        self.ident: int | None = None  # the thread's threading.get_ident() once it runs
        self.thread = threading.Thread(target=self._run, name=name, daemon=True)

    def start(self, at_exit=None) -> "ServoThread":
        """Start the thread; at the interpreter's exit ``at_exit()`` is called (an adapter's close: zero
        force, the device released), else :meth:`stop`."""
        from ...threads import background

        background(self.thread, self.stop if at_exit is None else at_exit)
        self.thread.start()
        return self

    def _run(self) -> None:
        self.ident = threading.get_ident()
        t0 = time.perf_counter()
        k = 0
        try:
            while not self._stop.is_set():
                target = t0 + k * self.period
                wait = target - time.perf_counter()
                if wait > self.spin:
                    time.sleep(wait - self.spin)
                while time.perf_counter() < target:
                    pass
                if self._tick() is False:
                    return
                self.ticks += 1
                k = max(k + 1, int((time.perf_counter() - t0) / self.period))  # late: no burst
        except BaseException as exc:  # noqa: BLE001 - kept for the owner and handed to on_error
            self.error = exc
            if self.on_error is not None:
                try:
                    self.on_error(exc)
                except BaseException:  # noqa: BLE001, S110 - the owner's fault path never raises; nothing left to do
                    pass

    def stop(self, timeout: float = 2.0) -> None:
        """Ask the thread to end and wait for it (``timeout`` s; not when called on the thread itself)."""
        self._stop.set()
        if self.thread.is_alive() and threading.current_thread() is not self.thread:
            self.thread.join(timeout)
