"""The scalpel's cut worker: a process of its own that cuts a model and assembles the cut one (its mesh
cut, its stiffness, mass and nonlinear system built), so that the simulation's process only builds the
driver on it (and its factor, on the cut job's thread). In the simulation's process that work held Python's
lock for milliseconds at a time and the haptic ticks waited (benchmarks/scalpel.py: 12-14 ticks of 7,000
over 1 ms with it there, 1 with only the driver built there).

The worker is ``python -m rtfem.interaction.cut_worker``, started by :class:`CutWorker`; the two
processes pass pickles of rtfem's own objects over the worker's stdin and stdout (nothing else reads
or writes them). Given the model it will cut (``warm=``), the worker first cuts and assembles a small
block of the same kind, element and law (:func:`warm_up`), while the blade is still on its way: a
fresh worker's first job had imported rtfem's cutting and loaded its compiled kernels, 0.9-1.7 s on
the 9k-tet liver of benchmarks/scalpel.py against 0.13-0.16 s for each job after (the first cut of a
stroke came that much later).
"""

from __future__ import annotations

import copy
import os
import pickle
import subprocess
import sys
import threading

import numpy as np

from ..errors import ModelError
from ..threads import raise_priority

__all__ = ["CutWorker", "WorkerGone", "cut_and_assemble", "warm_up"]


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


def _kind_of(model) -> tuple:
    """What :func:`warm_up` needs of a solid model: its class, material(s) or law and options."""
    from .. import validate
    from ..fe.recipe import ModelRecipe

    if not (hasattr(model, "tetmesh") and hasattr(model, "element")):
        raise ModelError(f"warm={validate.show(model)}: the cut worker warms up for the solid it will cut (an "
                         "rt.SolidModel)")
    recipe = ModelRecipe.of(model)
    return recipe.kind, recipe.material, recipe.options


def warm_up(kind, material, options) -> None:
    """Cut and assemble a small block (10 mm cells, 4 x 1 x 2 of them, more along x for over 48 regions: a tet of
    each; clamped at one end) of the given model class, material(s) or law and options, slit from its top to half
    its height in its second cell, the elements split, as a scalpel's job does: every import and compiled kernel
    a job of that kind of model needs is then loaded."""
    from ..mesh.meshes import box
    from ..mesh.tetmesh import TetMesh

    nx = 4 if not isinstance(material, dict) else max(4, -(-len(material) // 12))  # (12 tets a cell: one per region)
    mesh = box(0.01 * nx, 0.01, 0.01, nx=nx, ny=1, nz=2)
    if isinstance(material, dict):  # a model of regions: the block's tets take each region's label in turn
        labels = np.array(list(material))[np.arange(mesh.n_tets) % len(material)]
        mesh = TetMesh(mesh.vertices, mesh.tets, labels=labels, groups=mesh.groups)
    model = kind(mesh, material, **options).fix(mesh.groups["x0"])
    # a slit from the top to half the height (a layer of nodes): nothing cut free, every region kept
    plane = np.array([[0.017, -0.001, 0.005], [0.017, 0.011, 0.005], [0.017, 0.011, 0.011], [0.017, -0.001, 0.011]])
    cut_and_assemble(model, plane, np.array([[0, 1, 2], [0, 2, 3]]), "split")


def _bare(model):
    """The model without what it assembled (its matrices, factor and caches: 28 of its 30 MB on the 9k-tet
    liver), all a cut needs of it: a shallow copy, the model left as it was."""
    bare = copy.copy(model)
    bare._K = bare._M = bare._factor = bare._condensation = None
    bare._cache = {}
    return bare


class CutWorker:
    """A worker process for :func:`cut_and_assemble` (see the module): :meth:`cut` sends a job and waits
    for its answer (the waiting thread gives up Python's lock), :meth:`close` ends the process. ``warm``:
    the solid model it will cut: the worker warms up for its kind first (:func:`warm_up`; the answer is
    read with the first job's, ``warm_note`` then says how it went). ``timeout``: s a job (with a warm-up's
    answer before it) may take before the worker is taken for stopped and killed (default 120; a job on the
    9k-tet liver takes 0.1-0.3 s).

    Raises
    ------
    WorkerGone
        In :meth:`cut`, when the worker has died or answers nothing within ``timeout`` (the caller cuts in
        its own process then); what the cut raised is raised as it was.
    """

    def __init__(self, warm=None, timeout: float = 120.0) -> None:
        from .. import validate

        self.timeout = validate.positive(timeout, "timeout", "seconds a cut job may take, such as 120")
        job = None if warm is None else ("warm", *_kind_of(warm))  # (a model it cannot warm for is refused first)
        env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1",
                   NUMBA_NUM_THREADS="1", PYTHONPATH=os.pathsep.join(p for p in sys.path if p and os.path.isdir(p)))
        self._proc = subprocess.Popen([sys.executable, "-m", "rtfem.interaction.cut_worker"], stdin=subprocess.PIPE,
                                      stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, env=env)
        raise_priority(self._proc.pid)  # the stepping threads' raised priority, where permitted (never raises)
        self._lock = threading.Lock()
        self._owed = 0  # answers to warm-up jobs not read yet (read before the next job's)
        #: None: no warm-up asked (or its answer not read yet); "" it went well; else why it failed (the jobs
        #: after it are not affected: they only pay the loading it would have done)
        self.warm_note = None
        if job is not None:  # a few hundred bytes: the pipe takes them without waiting for the worker
            pickle.dump(job, self._proc.stdin, protocol=pickle.HIGHEST_PROTOCOL)
            self._proc.stdin.flush()
            self._owed = 1

    @property
    def alive(self) -> bool:
        return self._proc.poll() is None

    def cut(self, model, vertices, triangles, snap, held=None):
        """The worker's :func:`cut_and_assemble` of these arguments."""
        with self._lock:
            late = threading.Event()

            def kill() -> None:  # no answer in time: a stopped (or looping) worker, killed; the read below ends
                late.set()
                self._proc.kill()

            watchdog = threading.Timer(self.timeout, kill)
            watchdog.daemon = True
            watchdog.start()
            try:
                pickle.dump((_bare(model), vertices, triangles, snap, held), self._proc.stdin,
                            protocol=pickle.HIGHEST_PROTOCOL)
                self._proc.stdin.flush()
                kind, value = pickle.load(self._proc.stdout)
                while self._owed:  # the warm-up's answer came first
                    self._owed -= 1
                    self.warm_note = value or ""
                    kind, value = pickle.load(self._proc.stdout)
            except (OSError, EOFError, ValueError, pickle.UnpicklingError) as exc:  # ValueError: closed meanwhile
                self.close()
                why = f"answered nothing in {self.timeout:g} s and was killed" if late.is_set() else \
                    f"stopped ({type(exc).__name__})"
                raise WorkerGone(f"the cut worker process {why}; cutting in this process from now on") from None
            finally:
                watchdog.cancel()
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
    """The worker's loop: a job from stdin, its answer ("ok", model) or ("error", exception) to stdout; a
    warm-up job ("warm", class, material, options) answered ("warm", "" or why it failed)."""
    inp, out = sys.stdin.buffer, sys.stdout.buffer
    sys.stdout = sys.stderr  # nothing but answers on the pipe
    while True:
        try:
            job = pickle.load(inp)
        except EOFError:
            return
        try:
            if job[0] == "warm":
                try:
                    warm_up(*job[1:])
                    answer = ("warm", "")
                except Exception as exc:  # noqa: BLE001 - said in CutWorker.warm_note; the jobs go on
                    answer = ("warm", f"{type(exc).__name__}: {exc}")
            else:
                answer = ("ok", cut_and_assemble(*job))
        except Exception as exc:  # noqa: BLE001 - sent back to be raised where the job came from
            answer = ("error", exc)
        pickle.dump(answer, out, protocol=pickle.HIGHEST_PROTOCOL)
        out.flush()


if __name__ == "__main__":
    main()
