"""Compiled kernels (the reduced models', the assembly's): a kernel and the helpers it calls, compiled by numba once
(cached on disk) with one shared globals dict, so that a helper calling another calls its compiled
twin; None where numba is absent or cannot compile it (the callers then take a numpy path); and
:func:`chunked`, an element loop shared among threads."""

from __future__ import annotations

import itertools
import os
import threading

_COMPILED: dict = {}


def compiled(key: str, kernel, *helpers):
    """``kernel`` compiled by numba with its helper functions compiled too (cached), or None
    where numba is absent or cannot compile it."""
    if key not in _COMPILED:
        try:
            import numba

            opts = dict(cache=True, nogil=True, fastmath=False, error_model="numpy")
            g = dict(kernel.__globals__)  # shared: a helper calling another finds its compiled twin
            for h in helpers:
                g[h.__name__] = numba.njit(**opts)(type(h)(h.__code__, g, h.__name__))
            _COMPILED[key] = numba.njit(**opts)(type(kernel)(kernel.__code__, g, kernel.__name__))
        except Exception:  # pragma: no cover - numba absent or unable to compile here
            _COMPILED[key] = None
    return _COMPILED[key]


# ---------------------------------------------------------------- elements shared among threads
_POOL: list = [None, 0]  # (the pool, the process it was made in: a forked child makes its own)
_POOL_LOCK = threading.Lock()
MIN_CHUNK = 1024  # elements: below two of these an evaluation runs on the calling thread alone


_RESERVED = [0]  # latency-critical threads running (multi-rate haptic ticks): element loops leave them a core


def element_threads() -> int:
    """How many threads an element loop uses: RTFEM_ELEMENT_THREADS (a whole number >= 1), else the
    cores this process may run on, at most 8, less one while a latency-critical thread runs
    (:func:`reserve_core`)."""
    text = os.environ.get("RTFEM_ELEMENT_THREADS", "").strip()
    if text:
        try:
            value = int(text)
        except ValueError:
            value = 0
        if value < 1:  # a warning (once), not an error: the variable is read at every evaluation
            import warnings

            from ..errors import RtfemWarning

            warnings.warn(f"RTFEM_ELEMENT_THREADS={text!r} is not a whole number >= 1; using 1 thread",
                          RtfemWarning, stacklevel=2)
        return max(1, value)
    from ..threads import usable_cores

    return max(1, min(8, usable_cores() - (_RESERVED[0] > 0)))


def reserve_core(held: bool) -> None:
    """A latency-critical thread starts (``held``) or ends: while any runs (a multi-rate probe's 1 kHz
    ticks beside its physics thread), element loops use a core less, so that the ticks find one
    free (benchmarks/haptic_fullorder.py: on 2 cores the physics' two element threads held ticks
    for up to 4 ms)."""
    with _POOL_LOCK:
        _RESERVED[0] = max(0, _RESERVED[0] + (1 if held else -1))


def _pool(workers: int):
    from concurrent.futures import ThreadPoolExecutor

    with _POOL_LOCK:
        pool, pid = _POOL
        if pool is None or pid != os.getpid() or pool._max_workers < workers:
            pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="rtfem-elements")
            _POOL[:] = [pool, os.getpid()]
        return pool


def chunked(n: int, work, weight: int = 1) -> list:
    """[work(lo, hi) for each chunk of range(n)], the chunks shared among :func:`element_threads`
    threads: this one and a pool's (the kernels release the GIL). Each thread takes the next chunk
    not yet taken, so a thread the system keeps waiting (a busy core) holds up nothing but its own
    chunk; the caller returns as soon as every chunk is done, whatever the pool is busy with. A
    chunk's result does not depend on the thread that made it: the results are those of one thread.
    ``weight``: an element's work in elements of one point (a tet10's four quadrature points: 4)."""
    threads = element_threads()
    if threads <= 1 or n * weight < 2 * MIN_CHUNK or n < 2:
        return [work(0, n)]
    m = min(2 * threads, n * weight // MIN_CHUNK, n)
    bounds = [n * i // m for i in range(m + 1)]
    results: list = [None] * m
    taken = itertools.count()
    lock, done, left, errors = threading.Lock(), threading.Event(), [m], []

    def drain() -> None:
        while (i := next(taken)) < m:
            try:
                results[i] = work(bounds[i], bounds[i + 1])
            except BaseException as exc:  # noqa: BLE001 - raised in the caller below
                errors.append(exc)
            with lock:
                left[0] -= 1
                if left[0] == 0:
                    done.set()

    work(0, 0)  # an empty chunk here first: a kernel compiled (or loaded from numba's cache) on first use is
    # compiled by the calling thread, not a pool's beside it (CPython 3.11's compile() is not safe in two
    # threads at once: a test importing its module there failed with "AST constructor recursion depth mismatch")
    pool = _pool(threads - 1)
    helpers = [pool.submit(drain) for _ in range(threads - 1)]
    drain()
    done.wait()
    for h in helpers:
        h.cancel()  # those still queued behind another caller's work: nothing is left for them
    if errors:
        raise errors[0]
    return results
