"""An a posteriori error indicator for a reduced state (issue 56): how far the full-order equilibrium
is from a displacement field the reduced model produced, estimated from the full-order residual.

A reduced model settles where its *projected* forces balance: V^T (f_int(u) - F) = 0 for the basis V.
The full-order residual r = F - f_int(u) on the free dofs is what the basis cannot carry. One Newton
correction of the full order from u, e = K_t(u)^{-1} r (K_t the corotated or hyperelastic tangent at
u, the same the full-order solvers use), is the displacement that equilibrium still needs: near the
solution Newton's first step is the error itself to second order in it, and it is displacement-like
(metres), so it reads like the error it stands for (Ainsworth and Oden's residual estimators; the
reduced-basis error indicators of Rozza, Huynh, Patera 2008 bound it with the coercivity constant,
which one solve with the tangent replaces here). ``held`` nodes (a grasp's, whose displacement the
jaw prescribes) are taken as fixed at their displacement in u: their rows are left out.

Cost: one assembly of the full-order forces and tangent and one sparse factorization: 0.05-0.5 s on
the organs of ../shared, so it runs beside the step (a thread), never in it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .. import validate
from ..errors import ModelError

__all__ = ["ErrorEstimate", "ErrorMonitor", "driver_inertia", "error_estimate", "probe_monitor"]


@dataclass
class ErrorEstimate:
    """The indicator of one state: ``field`` (n, 3) the Newton correction e (m), ``node_error`` (n,) its
    length at each node, ``max_error`` the largest (m), ``worst_node`` where, ``residual`` the full-order
    residual's norm on the free dofs (N) against ``force_scale`` (|F| + |f_int|), and ``regions``
    {label: largest |e| in it} where labels were given."""

    field: np.ndarray
    node_error: np.ndarray
    max_error: float
    worst_node: int
    residual: float
    force_scale: float
    regions: dict

    def __str__(self) -> str:
        return (f"error estimate {self.max_error * 1e3:.3g} mm at node {self.worst_node} (full-order residual "
                f"{self.residual:.3g} N of {self.force_scale:.3g})")


def error_estimate(model, displacements, forces=None, *, held=None, labels=None, iterations: int = 3,
                   inertia=None) -> ErrorEstimate:
    """The full-order error of ``displacements``, a state of a reduced model of ``model``, as one
    Newton correction of the full order and a few chord steps (see the module).

    Parameters
    ----------
    model : the full-order model (a ShellModel or a SolidModel, its supports fixed).
    displacements : (n, 3) the state (m): a reduced simulator's ``displacements()``.
    forces : the dead nodal loads on it ((n, 3) or {node: (fx, fy, fz)}; None: none).
    held : nodes whose displacement is prescribed as it is in the state (a grasp's jaw): their
        rows are left out, and their estimate is zero.
    labels : (n,) integers: the largest estimate per label too (``regions``).
    inertia : (n, 3) the inertial and damping forces of a moving state (M a + C v at the nodes, N;
        :func:`driver_inertia` of a reduced simulator), taken off the loads: the residual is then the
        full order's equation of motion at the state, not its statics (None: a state at rest).
    iterations : Newton's first correction and up to ``iterations - 1`` chord steps with its
        factor, each taken only while the residual falls (default 3: on the tested block, liver and
        cantilever the estimate went from 0.93-1.22 of the true error after one to 0.999-1.017
        after three).

    Returns
    -------
    ErrorEstimate
        The correction field, its length per node, the largest and where, the residual and the regions.

    Raises
    ------
    ModelError
        A model without the nonlinear full order (``nonlinear()``), a state or forces of another
        shape or not finite, held nodes out of range; SolverError where the tangent at the state
        is singular (an element turned inside out).
    """
    iterations = validate.count(iterations, "iterations", 1, 50)
    if not callable(getattr(model, "nonlinear", None)):
        raise ModelError(f"{validate.show(model)} has no full-order nonlinear forces (a ShellModel or a SolidModel has)")
    n = model.n_nodes
    U = np.asarray(displacements, dtype=float)
    if U.shape != (n, 3) or not np.isfinite(U).all():
        raise ModelError(f"displacements must be a finite ({n}, 3) array of the model's nodes; got shape "
                         f"{getattr(U, 'shape', None)}")
    system = model.nonlinear()
    from ..fe.nonlinear_system import Configuration

    conf = Configuration.rest(n, system.rotations)
    conf.u = U.copy()
    F = model.force_vector(np.zeros((n, 3)) if forces is None else forces, warn=False)
    if inertia is not None:
        A = np.asarray(inertia, dtype=float)
        if A.shape != (n, 3) or not np.isfinite(A).all():
            raise ModelError(f"inertia must be a finite ({n}, 3) array of nodal forces; got shape {getattr(A, 'shape', None)}")
        extra = np.zeros((n, model.dofs_per_node))
        extra[:, :3] = A
        F = F - extra.reshape(-1)
    f, K, _ = system.evaluate(conf, True)
    r = (F - f)[system.free]
    keep = np.ones(system.free.size, dtype=bool)
    if held is not None:
        held = validate.nodes(held, n)
        dpn = system.dpn
        fixed_dofs = (dpn * held[:, None] + np.arange(dpn)).ravel()
        keep &= ~np.isin(system.free, fixed_dofs)
    idx = np.flatnonzero(keep)
    Kk = K[idx][:, idx].tocsr() if idx.size < keep.size else K
    e = _correction(system, conf, F, r, Kk, idx, iterations)
    field = system.expand(e)[:, :3]
    node_error = np.linalg.norm(field, axis=1)
    worst = int(np.argmax(node_error))
    regions = {}
    if labels is not None:
        lab = np.asarray(labels)
        if lab.shape != (n,):
            raise ModelError(f"labels must be ({n},), one per node; got shape {lab.shape}")
        for value in np.unique(lab).tolist():
            regions[value] = float(node_error[lab == value].max())
    scale = float(np.linalg.norm(F[system.free]) + np.linalg.norm(f[system.free]))
    return ErrorEstimate(field, node_error, float(node_error[worst]), worst, float(np.linalg.norm(r[idx])), scale,
                         regions)



def driver_inertia(driver, model) -> np.ndarray | None:
    """(n, 3) M a + alpha M v at the nodes for a reduced simulator's state (its coordinates' rates
    through its linear basis, the lumped mass, the mass-proportional damping; a stiffness-proportional
    or modal part is left out), or None for a driver without reduced coordinates."""
    reduced = getattr(driver, "reduced", None)
    state = driver.get_state() if reduced is not None else None
    if state is None or "qddot" not in state or not callable(getattr(reduced, "displacements", None)):
        return None
    m = np.asarray(model.mass_diagonal).reshape(model.n_nodes, model.dofs_per_node)[:, :3]
    alpha = float(getattr(getattr(driver, "damping", None), "alpha", 0.0) or 0.0)
    a = reduced.displacements(np.asarray(state["qddot"], dtype=float))
    v = reduced.displacements(np.asarray(state["qdot"], dtype=float))
    return m * (a + alpha * v)


def _correction(system, conf, F, r, K, idx, iterations: int) -> np.ndarray:
    """Newton's correction on the free dofs ``idx`` (K their tangent, r the residual) and chord steps
    with its factor while the residual falls: the estimate on the free dofs."""
    e = np.zeros(system.free.size)
    if not idx.size:
        return e
    fac = system.solver(K, "the full-order tangent at the reduced state", dofs=system.free[idx])
    e[idx] = fac.solve(r[idx])
    rn = float(np.linalg.norm(r[idx]))
    for _ in range(iterations - 1):  # chord steps with the same factor: toward the error itself
        trial = conf.copy()
        trial.update(system.expand(e))
        r_e = (F - system.evaluate(trial, False)[0])[system.free][idx]
        if not float(np.linalg.norm(r_e)) < rn:  # the chord does not contract here: keep the last
            break
        rn = float(np.linalg.norm(r_e))
        e[idx] += fac.solve(r_e)
    return e


#: the nice value of the monitor's thread: below the stepping threads (it must not slow the step)
MONITOR_NICE = 10


class ErrorMonitor:
    """:func:`error_estimate` of a running model's state, on a background thread at a low priority,
    every ``period`` seconds: the step never waits for it (a viewer's panel, a haptic loop's
    statistics and ``rtfem simulate`` read :attr:`latest`).

    Parameters
    ----------
    model : the full-order model of the running reduced model.
    state : a callable returning ``(displacements, forces)`` or ``(displacements, forces, inertia)``
        now (the driver's (n, 3) field, the loads it is stepped with and, moving, its inertial forces:
        :func:`driver_inertia`; called on the monitor's thread, so it should copy).
    period : seconds between two estimates (the estimate itself takes 0.01-0.5 s).
    iterations, held : as :func:`error_estimate` (``held`` may be a callable returning the nodes).
    on_estimate : called with each estimate on the monitor's thread (the viewer adapts its model).
    regions : {name: nodes}: each estimate's ``regions`` is then the largest estimate over each
        region's nodes (a labelled solid's regions: nodes on an interface count in both).

    Raises
    ------
    ModelError
        A period that is not positive, a state that is not callable.
    """

    def __init__(self, model, state, *, period: float = 0.5, iterations: int = 3, held=None, on_estimate=None,
                 regions=None) -> None:
        import threading

        if not callable(state):
            raise ModelError(f"state={validate.show(state)} must be a callable returning (displacements, forces)")
        if regions is not None and not isinstance(regions, dict):
            raise ModelError(f"regions={validate.show(regions)} must be a {{name: nodes}} mapping (or None)")
        self.regions = {k: validate.nodes(v, model.n_nodes) for k, v in (regions or {}).items()}
        self.model, self.state, self.held, self.on_estimate = model, state, held, on_estimate
        self.period = validate.positive(period, "period", "seconds between two estimates")
        self.iterations = validate.count(iterations, "iterations", 1, 50)
        self.latest: ErrorEstimate | None = None
        self.history: list[tuple[float, float]] = []  # (seconds since start, largest estimate in m)
        self.cost: list[float] = []  # seconds each estimate took
        self.error: str | None = None  # why the last estimate failed (the monitor goes on)
        self._stop = threading.Event()
        self._thread = None

    def estimate(self) -> ErrorEstimate:
        """One estimate of the state now, on the calling thread (kept as :attr:`latest`)."""
        import time

        t = time.perf_counter()
        got = self.state()
        U, F, inertia = (*got, None)[:3]
        held = self.held() if callable(self.held) else self.held
        est = error_estimate(self.model, U, F, held=held, iterations=self.iterations, inertia=inertia)
        if self.regions:
            est.regions = {k: float(est.node_error[v].max()) for k, v in self.regions.items()}
        self.cost.append(time.perf_counter() - t)
        self.latest = est
        return est

    def start(self) -> "ErrorMonitor":
        import threading

        from ..threads import background

        if self._thread is not None and self._thread.is_alive() and not self._stop.is_set():
            return self
        # a new thread with its own stop flag: one still finishing an estimate after stop() ends by itself
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, args=(self._stop,), name="rtfem-error-monitor", daemon=True)
        background(self._thread, self._stop.set)
        self._thread.start()
        return self

    def stop(self, timeout: float = 10.0) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)
        self._thread = None

    def _run(self, stop) -> None:
        import os
        import threading
        import time

        from ..threads import runtime

        try:
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), MONITOR_NICE)
        except (AttributeError, OSError):  # not Linux, or not allowed: the normal priority
            pass
        t0 = time.perf_counter()
        with runtime():
            while not stop.is_set():
                try:
                    est = self.estimate()
                    self.history.append((time.perf_counter() - t0, est.max_error))
                    self.error = None
                    if self.on_estimate is not None:
                        self.on_estimate(est)
                except Exception as exc:  # noqa: BLE001 - an inverted state, a singular tangent: said, not fatal
                    self.error = f"{type(exc).__name__}: {exc}"
                stop.wait(self.period)


def probe_monitor(probe, model=None, *, period: float = 0.5, iterations: int = 3) -> ErrorMonitor:
    """An :class:`ErrorMonitor` of the organ a haptic tool drives, for ``rt.HapticLoop(...,
    monitor=...)``: its estimates appear in the loop's :class:`~rtfem.LoopStats`
    (``stats.error_estimate``, and said by ``str(stats)``).

    The state is the tool's driver's displacements, the loads the tool applies now (an ``rt.Grasp``'s
    forces on its held vertices, an ``rt.Probe``'s on its contact vertex, otherwise the driver's
    own) and the driver's inertial forces (:func:`driver_inertia`). It is read on the monitor's
    thread while the loop steps, so it may be one step older than the loads: far below the
    estimate at a 0.5 s period.

    Parameters
    ----------
    probe : the tool (anything with a ``driver``).
    model : the full-order model (default: the driver's reduced model's, ``driver.reduced.model``,
        else ``driver.model``, else its modes', ``driver.modes.model``).
    period, iterations : as :class:`ErrorMonitor`.

    Raises
    ------
    ModelError
        A tool without a driver, a driver whose full-order model is not found (pass ``model``).
    """
    driver = getattr(probe, "driver", None)
    if driver is None:
        raise ModelError(f"probe={validate.show(probe)} has no driver: give an rt.Probe, an rt.Grasp or a tool")
    if model is None:
        model = next((m for m in (getattr(getattr(driver, "reduced", None), "model", None), getattr(driver, "model", None),
                                  getattr(getattr(driver, "modes", None), "model", None)) if m is not None), None)
    if model is None or not callable(getattr(model, "nonlinear", None)):
        raise ModelError(f"the full-order model of {type(driver).__name__} is not found: pass model= (a ShellModel "
                         "or a SolidModel)")

    def state():
        U = np.array(driver.displacements(), dtype=float)
        return U, _tool_loads(probe, driver), driver_inertia(driver, model)

    return ErrorMonitor(model, state, period=period, iterations=iterations)


def _tool_loads(probe, driver):
    """The loads a tool applies now ({node: f}), or the driver's own, or None."""
    nodes, forces = getattr(probe, "nodes", None), getattr(probe, "forces", None)
    if nodes is not None and forces is not None and len(nodes) == len(forces):  # a Grasp
        return {int(v): np.array(f, float) for v, f in zip(np.asarray(nodes).tolist(), np.asarray(forces))} or None
    node = getattr(probe, "contact_node", None)
    if node is not None and getattr(probe, "force", None) is not None:  # a Probe: the organ takes -force
        return {int(node): -np.asarray(probe.force, float)}
    loads, array = getattr(driver, "_loads", None), getattr(driver, "_load_array", None)
    return array if array is not None else (dict(loads) if loads else None)

