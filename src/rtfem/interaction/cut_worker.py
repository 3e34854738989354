"""The scalpel's cut worker: a process of its own that cuts a model and assembles the cut one (its mesh
cut, its stiffness, mass and nonlinear system built), so that the simulation's process only builds the
driver on it (and its factor, on the cut job's thread). In the simulation's process that work held Python's
lock for milliseconds at a time and the haptic ticks waited (benchmarks/scalpel.py: 12-14 ticks of 7,000
over 1 ms with it there, 1 with only the driver built there).

The worker is ``python -m rtfem.interaction.cut_worker``, started by :class:`CutWorker`; the two
processes pass pickles of rtfem's own objects over the worker's stdin and stdout (nothing else reads
or writes them).
"""

from __future__ import annotations

import copy
import os
import pickle
import subprocess
import sys
import threading

from ..errors import ModelError
from ..threads import raise_priority

__all__ = ["CutWorker", "WorkerGone", "cut_and_assemble"]


class WorkerGone(ModelError):
    """The cut worker process stopped or answered nothing readable."""


def cut_and_assemble(model, vertices, triangles, snap, held=None):
    """``rt.cut(model, vertices, triangles, snap=snap, free="remove", held=held)`` with the cut model
    assembled: its stiffness, mass and nonlinear system built (what a driver on it needs)."""
    from ..fe.cut import cut

    new = cut(model, vertices, triangles, snap=snap, free="remove", held=held)
    new.K, new.M  # noqa: B018 - assembled here, not in the simulation's process
    new.nonlinear()
    return new


def _bare(model):
    """The model without what it assembled (its matrices, factor and caches: 28 of its 30 MB on the 9k-tet
    liver), all a cut needs of it: a shallow copy, the model left as it was."""
    bare = copy.copy(model)
    bare._K = bare._M = bare._factor = bare._condensation = None
    bare._cache = {}
    return bare


class CutWorker:
    """A worker process for :func:`cut_and_assemble` (see the module): :meth:`cut` sends a job and waits
    for its answer (the waiting thread gives up Python's lock), :meth:`close` ends the process.

    Raises
    ------
    WorkerGone
        In :meth:`cut`, when the worker has died or answers nothing (the caller cuts in its own
        process then); what the cut raised is raised as it was.
    """

    def __init__(self) -> None:
        env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1",
                   NUMBA_NUM_THREADS="1", PYTHONPATH=os.pathsep.join(p for p in sys.path if p and os.path.isdir(p)))
        self._proc = subprocess.Popen([sys.executable, "-m", "rtfem.interaction.cut_worker"], stdin=subprocess.PIPE,
                                      stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, env=env)
        raise_priority(self._proc.pid)  # the stepping threads' raised priority, where permitted (never raises)
        self._lock = threading.Lock()

    @property
    def alive(self) -> bool:
        return self._proc.poll() is None

    def cut(self, model, vertices, triangles, snap, held=None):
        """The worker's :func:`cut_and_assemble` of these arguments."""
        with self._lock:
            try:
                pickle.dump((_bare(model), vertices, triangles, snap, held), self._proc.stdin,
                            protocol=pickle.HIGHEST_PROTOCOL)
                self._proc.stdin.flush()
                kind, value = pickle.load(self._proc.stdout)
            except (OSError, EOFError, ValueError, pickle.UnpicklingError) as exc:  # ValueError: closed meanwhile
                self.close()
                raise WorkerGone(f"the cut worker process stopped ({type(exc).__name__}); cutting in this process "
                                 "from now on") from None
        if kind == "error":
            raise value
        return value

    def close(self, wait: bool = True, timeout: float = 5.0) -> None:
        """End the worker: its input closed, it ends after the job it is in (``wait``: for up to
        ``timeout`` s, then it is killed; else it is left to end by itself)."""
        proc = self._proc
        if proc.poll() is None:
            try:
                proc.stdin.close()
            except OSError:
                pass
            if wait:
                try:
                    proc.wait(timeout)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()

    def __del__(self) -> None:
        proc = getattr(self, "_proc", None)
        if proc is not None and proc.poll() is None:
            proc.kill()


def main() -> None:
    """The worker's loop: a job from stdin, its answer ("ok", model) or ("error", exception) to stdout."""
    inp, out = sys.stdin.buffer, sys.stdout.buffer
    sys.stdout = sys.stderr  # nothing but answers on the pipe
    while True:
        try:
            job = pickle.load(inp)
        except EOFError:
            return
        try:
            answer = ("ok", cut_and_assemble(*job))
        except Exception as exc:  # noqa: BLE001 - sent back to be raised where the job came from
            answer = ("error", exc)
        pickle.dump(answer, out, protocol=pickle.HIGHEST_PROTOCOL)
        out.flush()


if __name__ == "__main__":
    main()
