"""Precompute on a Dask cluster (the ``cluster`` extra: ``dask.distributed``): the connection to a
scheduler, each worker process's cache of what it builds once, and a run of independent tasks whose
results come back as they finish.

The stages that are sets of independent solves (an impedance map's columns, ...) take
``scheduler=``: ``None`` (here, as before), ``"tcp://HOST:PORT"`` (a running ``dask scheduler``
with its ``dask worker`` processes; ``"tls://HOST:PORT"`` with certificates, :func:`security`),
``"local:N"`` (a LocalCluster of N worker processes on this machine, one thread each, on loopback)
or a ``distributed.Client``. A worker builds the model and its factorization from a small recipe
(the mesh and the settings) once and keeps them (:func:`worker_cached`); a task carries a list of
nodes. Dask reruns the tasks of a worker that dies on the others; what had come back is kept.

Dask has no sandbox: whoever reaches a scheduler runs code on its workers, and a client unpickles
what comes back, so a hostile scheduler or worker runs code on the client. Connect only to a
cluster you run, across a network over ``tls://`` (both sides' certificates checked).
"""

from __future__ import annotations

import contextvars
import threading
import time
import warnings
from contextlib import contextmanager
from typing import Callable, Iterable, Iterator

from . import validate
from .errors import ModelError, SolverError

__all__ = ["connect", "check_address", "is_loopback", "security", "run_tasks", "worker_cached", "stall_timeout",
           "CONNECT_TIMEOUT", "STALL_TIMEOUT"]

CONNECT_TIMEOUT = 10.0  # s to reach a scheduler before the one-line error
_CACHE: dict = {}  # per process (a worker's): key -> what it built
_CACHE_SIZE = 4  # models kept per worker process (a batch's organs come one after the other)
_LOCK = threading.Lock()
STALL_TIMEOUT = 600.0  # s with no result and no task running before a run stops and says so (:func:`stall_timeout`)
_STALL = contextvars.ContextVar("rtfem_stall_timeout", default=None)
_POLL = 0.1  # s between looks at the cluster while waiting
_FETCH = 10.0  # s to fetch a finished result before looking at the cluster again (doubled on each try)


def _distributed():
    try:
        import distributed
    except ImportError:
        raise ModelError("a scheduler needs the cluster extra (Dask): pip install 'rtfem[cluster]' "
                         "(make installs it)") from None
    return distributed


def check_address(scheduler) -> str:
    """The scheduler's address as text once it is one of the forms :func:`connect` takes:
    ``local:N`` (1 <= N <= 256), ``tcp://HOST:PORT`` or ``tls://HOST:PORT`` (HOST a name, an IPv4
    address or a bracketed IPv6 one; PORT 1 to 65535).

    Raises
    ------
    ModelError
        Any other text (one line saying the forms).
    """
    import re

    text = str(scheduler).strip()
    if text.startswith("local:"):
        n = int(text[6:]) if text[6:].isdigit() else 0
        if not 1 <= n <= 256:
            raise ModelError(f"scheduler={text!r}: local:N takes a number of worker processes from 1 to 256")
        return text
    m = re.fullmatch(r"(tcp|tls)://(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9][A-Za-z0-9.-]*):([0-9]{1,5})", text)
    if m is None or not 1 <= int(m.group(3)) <= 65535:
        raise ModelError(f"scheduler={validate.show(text)}: give a Dask scheduler's address tcp://HOST:PORT (or "
                         "tls://HOST:PORT with certificates), or local:N for N worker processes on this machine")
    return text


def is_loopback(address: str) -> bool:
    """Whether a ``tcp://`` or ``tls://`` address names this machine's loopback (localhost, 127.x, [::1])."""
    host = address.split("://", 1)[-1].rsplit(":", 1)[0].strip("[]").lower()
    return host == "localhost" or host.startswith("127.") or host == "::1"


def security(ca_file, cert, key=None):
    """A ``distributed.security.Security`` for a client of a ``tls://`` scheduler: the CA's
    certificates (PEM) that the scheduler's certificate must be signed by, and this client's
    certificate (and its key, when the certificate file does not hold it), also signed by that CA:
    Dask's TLS checks both sides, so only holders of such a certificate reach the scheduler.

    The command line checks that each is a regular file first (a pipe would block the ssl module).

    Raises
    ------
    ModelError
        Dask is not installed; files Python's ssl module cannot load (missing, not PEM, a key that
        does not match the certificate).
    """
    import ssl

    distributed = _distributed()
    try:
        sec = distributed.security.Security(tls_ca_file=str(ca_file), tls_client_cert=str(cert),
                                            tls_client_key=None if key is None else str(key), require_encryption=True)
        sec.get_connection_args("client")  # loads them now: a bad file is said before any work
    except (ssl.SSLError, OSError, ValueError) as exc:
        raise ModelError(f"the TLS files (--tls-ca-file {ca_file}, --tls-cert {cert}"
                         + (f", --tls-key {key}" if key else "") + f") cannot be used: {validate.one_line(str(exc))}; "
                         "give PEM files: the CA's certificate, and this client's certificate and key signed by it"
                         ) from None
    return sec


@contextmanager
def connect(scheduler, *, security=None) -> Iterator[object]:
    """A ``distributed.Client`` for ``scheduler`` (see the module's docstring), closed on exit
    (a LocalCluster with it; a Client given is left open).

    A ``local:N`` cluster listens on this machine's loopback only (its scheduler, workers and
    dashboard): nothing on the network reaches it. Whoever reaches a Dask scheduler runs code on its
    workers and, through the results it sends back (unpickled here), on this client: connect only to
    a scheduler you trust, over ``tls://`` across a network.

    Parameters
    ----------
    scheduler : "tcp://HOST:PORT", "tls://HOST:PORT", "local:N" or a ``distributed.Client``.
    security : a ``distributed.security.Security`` (:func:`security`) for a ``tls://`` address.

    Returns
    -------
    a context manager yielding the Client.

    Raises
    ------
    ModelError
        Dask is not installed, the text is none of the forms (:func:`check_address`), a ``tls://``
        address without ``security``, or the scheduler cannot be reached within
        :data:`CONNECT_TIMEOUT` s (one line naming the address).
    """
    distributed = _distributed()
    if isinstance(scheduler, distributed.Client):
        yield scheduler
        return
    text = check_address(scheduler)
    if text.startswith("local:"):
        n = int(text[6:])
        try:
            cluster = distributed.LocalCluster(n_workers=n, threads_per_worker=1, processes=True, host="127.0.0.1",
                                               dashboard_address="127.0.0.1:0", silence_logs=50)
        except (RuntimeError, OSError) as exc:
            raise ModelError(f"could not start a LocalCluster of {n} worker processes ({exc}): worker processes "
                             "re-import the main script, so a script read from standard input cannot start them; "
                             "run it from a file, or start 'dask scheduler' and 'dask worker' and pass "
                             "tcp://HOST:PORT") from None
        with cluster, distributed.Client(cluster) as client:
            yield client
        return
    if text.startswith("tls://") and security is None:
        raise ModelError(f"{text}: a tls:// scheduler needs certificates: --tls-ca-file, --tls-cert and --tls-key on the "
                         "command line (security=rtfem.cluster.security(...) in Python)")
    try:
        client = distributed.Client(text, timeout=CONNECT_TIMEOUT, security=security)
    except (OSError, TimeoutError, ValueError, TypeError) as exc:
        tls = " over TLS (are the certificates the cluster's?)" if text.startswith("tls://") else ""
        raise ModelError(f"could not reach the Dask scheduler at {text} within {CONNECT_TIMEOUT:g} s{tls} "
                         f"({validate.one_line(str(exc), 120)}): start it with 'dask scheduler' and its workers with "
                         "'dask worker ADDRESS'") from None
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


@contextmanager
def stall_timeout(seconds: float) -> Iterator[float]:
    """Within the block, a cluster run (:func:`run_tasks`: impedance maps, derivatives, cubature,
    compliance, ``rtfem batch``) stops when for ``seconds`` (default :data:`STALL_TIMEOUT`) no result
    has come back and none of its tasks has run on a live worker (a long task that runs is not a
    stall), and when no worker is left for ``min(seconds, 30)`` s; it keeps what came back and says
    why. The command line's ``--stall-timeout``.

    Parameters
    ----------
    seconds : a number > 0.

    Returns
    -------
    a context manager yielding ``seconds``.

    Raises
    ------
    ModelError
        ``seconds`` not a number > 0.
    """
    value = validate.positive(seconds, "stall timeout", "a number of seconds > 0")
    token = _STALL.set(value)
    try:
        yield value
    finally:
        _STALL.reset(token)


def _given(value):
    """A task that returns what it was given: data a worker lost is made again from the graph."""
    return value


def _send_shared(client, shared: tuple) -> list:
    """``shared`` on the cluster, one future each. Not scattered: a scattered value exists only on
    the workers it reached, and a broadcast's replication waits on a worker that died (issue 59);
    as a task's argument the scheduler holds it, and a worker lost before, during or after the copy
    has it made again on a live one."""
    with warnings.catch_warnings():  # the modes are meant to travel once, in the graph
        warnings.filterwarnings("ignore", message="Sending large graph")
        warnings.filterwarnings("ignore", message="Large object")
        return [client.submit(_given, value, pure=False) for value in shared]


class _Watch:
    """Why a cluster run should stop while it waits, or None: nothing done for the stall timeout (no
    result came back, and none of the run's ``keys`` ran on a live worker), no live worker, the
    scheduler unreachable."""

    def __init__(self, client, stall: float, keys) -> None:
        self.client, self.stall, self.keys = client, stall, set(keys)
        self.last = self.looked = self.alive = self.reached = time.monotonic()
        self.workers = self.frozen = 0
        self.heard: dict = {}  # worker -> (its last heartbeat as the scheduler stamped it, when that changed here)

    def _answering(self, workers: dict, now: float, grace: float) -> set:
        """The workers whose heartbeat the scheduler saw change within ``grace`` s (a frozen worker,
        SIGSTOP or a machine gone quiet, stays listed until Dask's worker-ttl, 5 min)."""
        live = set()
        for address, info in workers.items():
            stamp = info.get("last_seen")
            seen, since = self.heard.get(address, (None, now))
            if stamp != seen:
                self.heard[address] = (stamp, now)
                since = now
            if now - since <= grace:
                live.add(address)
        return live

    def progress(self) -> None:
        self.last = time.monotonic()

    def why(self) -> str | None:
        now = time.monotonic()
        grace = min(self.stall, 30.0)
        if now - self.looked >= 1.0:  # the scheduler's view, once a second
            self.looked = now
            try:
                if self.client.status != "running":
                    raise OSError(f"the client is {self.client.status}")
                workers = self.client.scheduler_info()["workers"]
                live = self._answering(workers, now, grace)
                self.workers, self.frozen = len(live), len(workers) - len(live)
                if live:
                    self.alive = now
                    running = self.client.processing(list(live))  # worker -> the keys it runs
                    if any(key in self.keys for keys in running.values() for key in keys):
                        self.last = now  # a task of this run runs on a worker that answers: not stalled
                self.reached = now
            except Exception as exc:  # noqa: BLE001 - a lost scheduler raises what its comm raises
                if now - self.reached > grace:
                    return f"the scheduler stopped answering ({type(exc).__name__}: {validate.one_line(str(exc), 80)})"
                return None
        if now - self.alive > grace:
            silent = f" ({self.frozen} listed but silent: frozen or cut off?)" if self.frozen else ""
            return (f"no live Dask worker answering for {grace:g} s{silent}: start workers with 'dask worker ADDRESS' "
                    "and run it again")
        if now - self.last > self.stall:
            frozen = f", and {self.frozen} worker(s) have not answered for {grace:g} s" if self.frozen else ""
            return (f"no result came back and no task ran for {self.stall:g} s on {self.workers} answering worker(s)"
                    f"{frozen} (--stall-timeout; rtfem.cluster.stall_timeout)")
        return None


def run_tasks(client, fn: Callable, shared: tuple, chunks: Iterable, collect: Callable[[object], None], *,
              stage: Callable[[str], None] | None = None) -> str:
    """``fn(*shared, chunk)`` on the cluster for every chunk; ``collect(result)`` for each result as it
    arrives, here. ``shared`` is sent once (one task holding it: :func:`_send_shared`), fetched by
    each worker that needs it, and made again from the graph if the worker holding it is lost; Dask
    reruns the tasks of a lost worker on the others.

    Returns "" when every chunk came back, else why not, in one line: a KeyboardInterrupt (Ctrl-C),
    a task that failed (a worker killed more often than Dask retries it), no result for the stall
    timeout (:func:`stall_timeout`), no live worker, the scheduler gone. The rest is cancelled and
    what came back stays collected. ``stage(message)`` hears each stage from the start: the copy of
    ``shared``, then the tasks running (a caller's progress line before the first result).

    Raises
    ------
    KeyboardInterrupt
        An interruption before any result (nothing to keep).
    SolverError
        A failure before any result (the first task's error, or why the run stopped).
    """
    distributed = _distributed()
    chunks = list(chunks)
    stall = _STALL.get() or STALL_TIMEOUT
    futures: list = []
    got = [0]  # results collected (by _collect), also when the wait is left by an exception
    say = stage or (lambda message: None)
    try:
        from dask.sizeof import sizeof

        say(f"copying {sizeof(list(shared)) / 2**20:.1f} MiB to the workers")
        shared_f = _send_shared(client, shared)
        futures = [client.submit(fn, *shared_f, chunk, pure=False) for chunk in chunks]
        why = _collect(distributed, client, shared_f, futures, collect, got, say, stall)
    except KeyboardInterrupt:
        _cancel(client, futures)
        if not got[0]:
            raise
        return "interrupted"
    except Exception as exc:  # noqa: BLE001 - a task's error, a lost connection: keep what came back
        _cancel(client, futures)
        why, lost = _reason(distributed, client, exc)
        if not got[0]:
            raise SolverError(f"the cluster run stopped before any result: {why}" if lost else
                              f"the cluster's first tasks failed: {why}") from exc
        return why
    if why:
        _cancel(client, futures)
        if not got[0]:
            raise SolverError(f"the cluster run stopped before any result: {why}")
    return why


def _collect(distributed, client, shared_f, futures, collect, got: list, say, stall: float) -> str:
    """Wait for ``futures``, ``collect`` each result as it comes (counted in ``got[0]``); why it
    stopped, or "" when all came."""
    watch = _Watch(client, stall, [f.key for f in (*shared_f, *futures)])
    pending = distributed.as_completed(futures, loop=client.loop)  # not the default client's loop
    copied = not shared_f
    wait = {}  # s to wait for a finished task's result before looking at the cluster again
    while got[0] < len(futures):
        batch = pending.next_batch(block=False)
        for future in sorted(batch, key=lambda f: f.status != "finished"):  # results first, then a failure
            if future.status in ("error", "cancelled"):
                future.result()  # raises the task's error (or says it was cancelled)
            if future.status != "finished":  # its result was lost with its worker and is being made again
                pending.add(future)
                continue
            try:
                result = future.result(timeout=wait.get(future.key, _FETCH))
            except TimeoutError:
                # its worker died after it finished: Dask runs it again (on a live worker, if any), and
                # a slow copy of a large result gets longer next time
                wait[future.key] = 2 * wait.get(future.key, _FETCH)
                pending.add(future)
                continue
            collect(result)
            got[0] += 1
            watch.progress()
        if not copied and all(f.status == "finished" for f in shared_f):
            copied = True
            watch.progress()
            say(f"copied; {len(futures)} task(s) running")
        why = watch.why()
        if why:
            return why
        if not batch:
            time.sleep(_POLL)
    return ""


def _reason(distributed, client, exc: BaseException) -> tuple[str, bool]:
    """One line for what ended a run, and whether it was the scheduler lost (said as such, without
    Dask's own text about the keys it cancelled) rather than a task's error."""
    if isinstance(exc, distributed.comm.CommClosedError) or client.status != "running" \
            or "scheduler-connection-lost" in str(exc):
        return f"lost the connection to the Dask scheduler ({type(exc).__name__})", True
    return f"{type(exc).__name__}: {validate.one_line(str(exc), 200)}", False


def _cancel(client, futures) -> None:
    """Cancel what is left, unless the scheduler is gone (the call would wait on it)."""
    try:
        if futures and client.status == "running":
            client.cancel(futures)
    except Exception:  # noqa: BLE001 - nothing left to cancel on
        pass
