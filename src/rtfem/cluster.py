"""Precompute on a Dask cluster (the ``cluster`` extra: ``dask.distributed``): the connection to a
scheduler, each worker process's cache of what it builds once, and a run of independent tasks whose
results come back as they finish.

The stages that are sets of independent solves (an impedance map's columns, ...) take
``scheduler=``: ``None`` (here, as before), ``"tcp://HOST:PORT"`` (a running ``dask scheduler``
with its ``dask worker`` processes), ``"local:N"`` (a LocalCluster of N worker processes on this
machine, one thread each) or a ``distributed.Client``. A worker builds the model and its
factorization from a small recipe (the mesh and the settings) once and keeps them
(:func:`worker_cached`); a task carries a list of nodes. Dask reruns the tasks of a worker that dies
on the others; what had come back is kept.
"""

from __future__ import annotations

import threading
from contextlib import contextmanager
from typing import Callable, Iterable, Iterator

from .errors import ModelError, SolverError

__all__ = ["connect", "run_tasks", "worker_cached", "CONNECT_TIMEOUT"]

CONNECT_TIMEOUT = 10.0  # s to reach a scheduler before the one-line error
_CACHE: dict = {}  # per process (a worker's): key -> what it built
_CACHE_SIZE = 4  # models kept per worker process (a batch's organs come one after the other)
_LOCK = threading.Lock()


def _distributed():
    try:
        import distributed
    except ImportError:
        raise ModelError("a scheduler needs the cluster extra (Dask): pip install 'rtfem[cluster]' "
                         "(make installs it)") from None
    return distributed


@contextmanager
def connect(scheduler) -> Iterator[object]:
    """A ``distributed.Client`` for ``scheduler`` (see the module's docstring), closed on exit
    (a LocalCluster with it; a Client given is left open).

    Parameters
    ----------
    scheduler : "tcp://HOST:PORT", "local:N" or a ``distributed.Client``.

    Returns
    -------
    a context manager yielding the Client.

    Raises
    ------
    ModelError
        Dask is not installed, the text is neither form, or the scheduler cannot be reached within
        :data:`CONNECT_TIMEOUT` s (one line naming the address).
    """
    distributed = _distributed()
    if isinstance(scheduler, distributed.Client):
        yield scheduler
        return
    text = str(scheduler).strip()
    if text.startswith("local:"):
        try:
            n = int(text[6:])
        except ValueError:
            n = 0
        if not 1 <= n <= 256:
            raise ModelError(f"scheduler={text!r}: local:N takes a number of worker processes from 1 to 256")
        try:
            cluster = distributed.LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                                               dashboard_address=":0", silence_logs=50)
        except (RuntimeError, OSError) as exc:
            raise ModelError(f"could not start a LocalCluster of {n} worker processes ({exc}): worker processes "
                             "re-import the main script, so a script read from standard input cannot start them; "
                             "run it from a file, or start 'dask scheduler' and 'dask worker' and pass "
                             "tcp://HOST:PORT") from None
        with cluster, distributed.Client(cluster) as client:
            yield client
        return
    if "://" not in text:
        raise ModelError(f"scheduler={text!r}: give a Dask scheduler's address tcp://HOST:PORT, or local:N for N "
                         "worker processes on this machine")
    try:
        client = distributed.Client(text, timeout=CONNECT_TIMEOUT)
    except (OSError, TimeoutError):
        raise ModelError(f"could not reach the Dask scheduler at {text} within {CONNECT_TIMEOUT:g} s: start it with "
                         "'dask scheduler' and its workers with 'dask worker ADDRESS'") from None
    try:
        yield client
    finally:
        client.close()


def worker_cached(key: str, build: Callable[[], object]):
    """What ``build()`` returns, built once per process for ``key`` (a worker keeps its model and
    factorization between tasks; the newest :data:`_CACHE_SIZE` kept)."""
    with _LOCK:
        if key in _CACHE:
            return _CACHE[key]
    value = build()
    with _LOCK:
        _CACHE[key] = value
        while len(_CACHE) > _CACHE_SIZE:
            _CACHE.pop(next(iter(_CACHE)))
    return value


def run_tasks(client, fn: Callable, shared: tuple, chunks: Iterable, collect: Callable[[object], None]) -> str:
    """``fn(*shared, chunk)`` on the cluster for every chunk; ``collect(result)`` for each result as it
    arrives, here. ``shared`` is sent to every worker once (scattered, broadcast), not per task.
    Returns "" when every chunk came back, else why not: a KeyboardInterrupt (Ctrl-C) or a task that
    failed (a worker killed more often than Dask retries it) cancels the rest, and what came back
    stays collected.

    Raises
    ------
    KeyboardInterrupt
        An interruption before any result (nothing to keep).
    SolverError
        A failure before any result (the first task's error).
    """
    distributed = _distributed()
    futures = []
    got = 0
    try:
        shared_f = client.scatter(list(shared), broadcast=True, hash=False) if shared else []
        futures = [client.submit(fn, *shared_f, chunk, pure=False) for chunk in chunks]
        for future in distributed.as_completed(futures):
            collect(future.result())
            got += 1
        return ""
    except KeyboardInterrupt:
        client.cancel(futures)
        if not got:
            raise
        return "interrupted"
    except Exception as exc:  # noqa: BLE001 - a task's error, a lost connection: keep what came back
        client.cancel(futures)
        if not got:
            raise SolverError(f"the cluster's first tasks failed: {type(exc).__name__}: {exc}") from exc
        return f"{type(exc).__name__}: {exc}"
