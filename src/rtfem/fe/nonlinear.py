"""Geometrically nonlinear (corotational) full-order statics: the accuracy reference for large
deformations (issue 14).

:class:`NonlinearSystem` assembles a model's corotational internal forces and consistent
tangent (shell triangles: :class:`rtfem.fe.shell.CorotationalTriangles`; tets:
:class:`rtfem.fe.solid.CorotationalTets`) over a :class:`Configuration` (nodal translations and, on a
shell, nodal rotation matrices updated by spins). :func:`solve_static` is Newton's method with
adaptive load stepping (Crisfield, Non-linear Finite Element Analysis of Solids and Structures,
vol. 1, ch. 9): dead loads, supports held or moved to prescribed positions. Where Newton stalls
(a thin shell pulled into a tent, whose tangent turns near-singular and indefinite on the way),
a load step falls back on a trust-region minimization of the total potential (a Newton step
shifted by mu diag(H) until the shifted Hessian is positive definite, mu adapted to the ratio
of actual to predicted decrease: Nocedal & Wright, Numerical Optimization, 2nd ed., ch. 4 and
10.3); it ends at a stable equilibrium (positive definite Hessian), quadratically once the shift
is zero. The dynamic reference (Newton inside implicit Newmark) is
:class:`rtfem.drivers.nonlinear_newmark.NonlinearNewmarkSimulator`.

Load stepping against the trust region (issue 60). Measured on a strip under P L^2 / EI = 1, 2, 4
asked in one step: Newton diverges, and halving takes 19, 44, 69 Newton iterations in 2, 5, 9
steps where the trust region on the whole step took 4 + 39, 4 + 56, 4 + 65, wandering at
residuals up to 132 times the load (0.19 against 0.6 s at P L^2 / EI = 1); on a shell pulled into
a tent in one step, where Newton stalls, the trust region takes 30 + 11 iterations where halving
takes 30 + 17. Hence "auto": a divergence halves the step, a stall calls the trust region.

Round-off floor. The residual cannot fall below the granularity of the state: the displacements
are doubles, so moving every one by one unit in the last place (|u| * 2.2e-16) changes the
internal forces by about eps |u| times the stiffest (membrane) stiffness. On a slender
corotational shell that is far above eps times the load: on the 10 m strip of 0.1 m thickness
bent by P L^2 / EI = 1 (tip displacements of 3 m, membrane stiffness E t = 1.2e5 N/m against a
1 N load), one-ulp moves of u change the residual by 6e-10 of the load, and Newton ends at 1e-9 to
2e-9 of it, on any BLAS or factorization (PARDISO, SuperLU, MKL_CBWR=COMPATIBLE). No solver of a
double-precision state goes lower; a tolerance below that floor ends on the second test (a
correction below :meth:`NonlinearSystem.resolution`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from scipy.spatial.transform import Rotation

from .. import validate
from ..errors import ModelError, SolverError
from .nonlinear_system import (LOCAL_ROTATION_LIMIT, Configuration, NonlinearSystem, inversion_refused,  # noqa: F401
                               turn_refused)
from .protocol import check_model
from .rotations import rotation

__all__ = ["Configuration", "NonlinearSystem", "NonlinearResult", "solve_static"]


@dataclass
class NonlinearResult:
    """What :func:`solve_static` found.

    ``displacements`` (n, 3); ``rotations`` (n, 3) rotation vectors on a shell (None on a solid);
    ``reactions`` (n, 3): the internal forces at the held dofs (the supports' forces on the
    model, with sign: minus the load they carry); ``load_factors``: the converged load steps;
    ``residuals``: per load step, the free-dof residual norm before each Newton iteration and
    after the last; ``local_rotation``: a shell's largest nodal rotation relative to an element
    frame, in degrees (the element's rotation measure, the rotation vector, is exact to 180
    degrees; past :data:`LOCAL_ROTATION_LIMIT` no step is accepted); ``methods``: per load step, "newton" or
    "trust-region" (the step Newton could not converge, minimized instead); ``converged``; ``energy``: the
    strain energy; ``seconds``.
    """

    displacements: np.ndarray
    rotations: np.ndarray | None
    reactions: np.ndarray
    load_factors: list[float] = field(default_factory=list)
    residuals: list[list[float]] = field(default_factory=list)
    methods: list[str] = field(default_factory=list)
    local_rotation: float = 0.0
    converged: bool = True
    energy: float = 0.0
    seconds: float = 0.0
    configuration: Configuration | None = None

    @property
    def iterations(self) -> int:
        return sum(len(r) - 1 for r in self.residuals)


def _prescribed(model, prescribed) -> np.ndarray:
    """Prescribed values (n, dofs_per_node) on fixed dofs (zeros elsewhere), checked."""
    n, dpn = model.n_nodes, model.dofs_per_node
    P = np.zeros((n, dpn))
    if prescribed is None:
        return P
    A = validate.forces(prescribed, n, tuple(sorted({3, dpn})))
    P[:, :A.shape[1]] = A
    loose = np.flatnonzero((~model.fixed & (P != 0)).any(axis=1))
    if loose.size:
        raise ModelError(f"prescribed motion on dofs that are not fixed (first: node {loose[0]}): a support moves only "
                         "where model.fix(...) holds it; fix those dofs or drop them from prescribed")
    if dpn == 6:
        partial = np.flatnonzero((P[:, 3:] != 0).any(axis=1) & ~model.fixed[:, 3:].all(axis=1))
        if partial.size:
            raise ModelError(f"node {partial[0]}: a prescribed rotation needs all three rotations of the node fixed")
    return model.complete_motion(P)


METHODS = ("auto", "newton", "trust-region")


def solve_static(model, forces=None, *, prescribed=None, steps: int = 1, tol: float = 1e-9,
                 max_iterations: int = 30, max_cuts: int = 12, method: str = "auto",
                 progress=None, time_limit: float | None = 600.0) -> NonlinearResult:
    """Geometrically nonlinear static equilibrium f_int(x) = F by Newton's method with load steps.

    Parameters
    ----------
    model : a model with ``nonlinear()`` (ShellModel, SolidModel).
    forces : dead nodal loads ((n, 3) array or {node: (fx, fy, fz)}; moments (n, 6) on a shell).
    prescribed : motions of fixed dofs ((n, 3) translations, or (n, 6) with rotation vectors on a
        shell whose rotations are all fixed there), applied with the load factor. A rigid
        motion of all the supports moves the model without straining it. On tet10, mid-edge nodes
        that :meth:`~rtfem.SolidModel.fix` held because their corners are held, and that are given
        no motion of their own, follow their corners (:meth:`~rtfem.SolidModel.complete_motion`).
    steps : initial number of equal load steps; a step whose Newton iterations do not converge
        is halved (at most ``max_cuts`` times in a row) and retried from the last equilibrium.
    tol : convergence: free-dof residual <= tol * (|lambda F| + |f_int|) (or a correction below
        :meth:`NonlinearSystem.resolution`, for a motion with no force to measure against).
    method : "newton" (each load step by Newton's method), "trust-region" (each load step by the
        trust-region minimization of the total potential, up to 5 * ``max_iterations``
        iterations: slower per step, but it cannot stall on an indefinite or near-singular
        tangent) or "auto" (Newton; where Newton diverges, its residual growing a thousandfold,
        the step was too long for the tangent and is halved, Crisfield's load stepping, down to
        ``max_cuts`` times; where Newton stalls, or diverges on the last try, the trust region
        on that step before it is halved; measured in the module's notes). The trust region
        needs a potential: dead forces, no moments (a dead moment does no path-independent
        work on finite rotations).
    progress : callback(done, total, message): done is the load factor reached (of 1.0), called after
        every Newton or trust-region iteration (the message says the step, the iteration and its
        residual) and every converged load step.
    time_limit : seconds (default 600) after which the solve stops with a SolverError holding the
        last equilibrium; None: no limit.

    Raises
    ------
    SolverError
        A load step that cannot be halved further, or the time limit; the error's ``result`` holds
        the last equilibrium reached (nothing computed is lost).
    ModelError
        Bad arguments (nothing is computed then).

    Notes
    -----
    No step is accepted where a solid element is turned inside out (det F <= 0) or a shell triad
    turned past :data:`LOCAL_ROTATION_LIMIT` degrees: ``converged`` is never True on such a state.
    The residual's round-off floor on a slender shell is far above eps times the load (1e-9 of it
    on the module notes' strip): the granularity of a double-precision state; see the module.
    """
    t0 = time.perf_counter()
    _check_solver_model(model)
    progress = validate.progress(progress)
    if time_limit is not None:
        time_limit = validate.positive(time_limit, "time_limit", "seconds, or None for no limit")
    system = model.nonlinear()
    F = model.force_vector(forces if forces is not None else np.zeros((model.n_nodes, 3)))
    P = _prescribed(model, prescribed)
    steps = validate.count(steps, "steps", 1, 10**6)
    tol = validate.positive(tol, "tol", "a relative tolerance such as 1e-9")
    max_iterations = validate.count(max_iterations, "max_iterations", 1, 1000)
    max_cuts = validate.count(max_cuts, "max_cuts", 0, 60)
    method = validate.choice(method, "method", METHODS)
    n, dpn = model.n_nodes, model.dofs_per_node
    conservative = _conservative(F, n, dpn, method)
    system.turned, system.inverted = 0.0, 0  # the arguments are checked: this solve's refusals only
    path = _LoadPath(system, F, P, _Settings(tol, max_iterations, max_cuts, method, conservative,
                                             _Watch(t0, time_limit, progress)), t0)
    try:
        return path.run(1.0 / steps)
    except _OutOfTime:
        _fill(path.result, system, path.conf, t0, converged=False)
        exc = SolverError(f"the nonlinear solve stopped at its time limit of {time_limit:g} s (time_limit=) at load "
                          f"factor {path.applied:.4g}, after {path.settings.watch.iterations} iterations: the error's "
                          "result holds the last equilibrium. Pass a longer time_limit (or None), more steps, or a "
                          "coarser mesh")
        exc.result = path.result
        raise exc from None


@dataclass
class _Settings:
    tol: float
    max_iterations: int
    max_cuts: int
    method: str
    conservative: bool
    watch: "_Watch"


class _LoadPath:
    """The load steps of one static solve, from rest to the whole load: the last equilibrium
    (``conf`` at load factor ``applied``) and what the result keeps of the way."""

    def __init__(self, system: NonlinearSystem, F: np.ndarray, P: np.ndarray, settings: _Settings, t0: float) -> None:
        model = system.model
        self.system, self.F, self.P, self.settings, self.t0 = system, F, P, settings, t0
        self.conf = Configuration.rest(model.n_nodes, model.dofs_per_node == 6)
        self.applied = 0.0  # load factor of the last equilibrium
        self.result = NonlinearResult(np.zeros((model.n_nodes, 3)), None, np.zeros((model.n_nodes, 3)))

    def run(self, step: float) -> NonlinearResult:
        """Load steps of ``step`` at first: doubled after an easy one, halved after a failed one."""
        system, st, fixed_mask, result = self.system, self.settings, self.system.model.fixed, self.result
        progress = st.watch.progress
        cuts = 0
        previous: tuple[Configuration, float] | None = None  # the equilibrium before, and the step to it
        while self.applied < 1.0 - 1e-12:
            conf, applied = self.conf, self.applied
            target = min(1.0, applied + step)
            trial = conf.copy()
            if previous is not None:  # secant predictor: continue the last step's motion
                _extrapolate(trial, previous[0], (target - applied) / previous[1])
            _move_supports(trial, self.P, fixed_mask, applied, target)
            _carry_rigidly(trial, conf, system, fixed_mask)
            st.watch.step = (applied, target)
            trial, history, ok, used = _load_step(system, trial, target * self.F, st.tol, st.max_iterations,
                                                  st.method, st.conservative, last=cuts >= st.max_cuts, watch=st.watch)
            if ok:
                previous = (conf, target - applied)
                self.conf, self.applied = trial, target
                result.load_factors.append(target)
                result.residuals.append(history)
                result.methods.append(used)
                if cuts == 0 and len(history) <= (6 if used == "newton" else 12):
                    step *= 2.0  # easy going: longer steps
                cuts = 0
                if progress is not None:
                    progress(target, 1.0, f"load factor {target:.3g}")
                continue
            cuts += 1
            if cuts > st.max_cuts or step < MIN_LOAD_STEP:  # halved too often, or in short steps down to nothing
                _fill(result, system, conf, self.t0, converged=False)
                raise _stalled(result, system, used, applied, st.max_cuts, step, history)
            step *= 0.5
        _fill(result, system, self.conf, self.t0, converged=True)
        return result


def _check_solver_model(model) -> None:
    """A model the nonlinear solve can take: the Model protocol and ``nonlinear()``."""
    check_model(model)
    if not callable(getattr(model, "nonlinear", None)):
        raise ModelError(f"model={validate.show(model)} has no nonlinear(): the geometrically nonlinear solve needs a "
                         "ShellModel or a SolidModel")


def _conservative(F: np.ndarray, n: int, dpn: int, method: str) -> bool:
    """Whether the loads have a potential (no dead moments); the trust region needs one."""
    conservative = dpn == 3 or not F.reshape(n, dpn)[:, 3:].any()
    if method == "trust-region" and not conservative:
        raise ModelError("method='trust-region' minimizes the total potential, which dead moments do not have on finite "
                         "rotations: apply the moments as force couples, or use method='newton'")
    return conservative


class _OutOfTime(Exception):
    """A solve ran past its time limit (caught by :func:`solve_static`)."""


class _Watch:
    """A static solve's clock and progress: :meth:`tick` after each iteration reports it and stops
    the solve (raises :class:`_OutOfTime`) past the time limit."""

    def __init__(self, t0: float, limit: float | None, progress) -> None:
        self.deadline = None if limit is None else t0 + limit
        self.progress = progress
        self.step = (0.0, 1.0)  # the load factors of the last equilibrium and of the step's target
        self.iterations = 0

    def tick(self, residual: float) -> None:
        self.iterations += 1
        if self.progress is not None:
            a, b = self.step
            self.progress(a, 1.0, f"load factor {a:.3g} -> {b:.3g}: iteration {self.iterations}, residual {residual:.3g}")
        if self.deadline is not None and time.perf_counter() > self.deadline:
            raise _OutOfTime


def _load_step(system, trial: Configuration, load: np.ndarray, tol: float, max_iterations: int, method: str,
               conservative: bool, last: bool = True, watch: _Watch | None = None) -> tuple:
    """One load step from ``trial``: Newton, or the trust region (for method "trust-region", or with
    "auto" where Newton did not converge and the loads have a potential: where it stalled, or
    diverged on the ``last`` try before the solve gives up; a divergence before is left to the
    caller, which halves the step). Returns (the configuration reached, the residual history, whether it converged, the
    method that ran)."""
    used = "newton" if method != "trust-region" else "trust-region"
    if used == "newton":
        start = trial.copy() if method == "auto" and conservative else None
        history, ok = _newton(system, trial, load, tol, max_iterations, watch)
        if not ok and start is not None and (last or not _diverged(history)):  # minimize from the same start
            used, trial = "trust-region", start
    if used == "trust-region":
        history, ok = _minimize(system, trial, load, tol, 5 * max_iterations, watch)
    return trial, history, ok, used


def _stalled(result: NonlinearResult, system, used: str, applied: float, max_cuts: int, step: float,
             history: list) -> SolverError:
    """The error of a solve that cannot go past ``applied``, holding the last equilibrium (``result``)."""
    turned = system.turned
    limit = f"; steps were refused where a {turn_refused(turned)}" if turned >= LOCAL_ROTATION_LIMIT else ""
    if system.inverted:
        limit += f"; steps were refused where {inversion_refused(system.inverted)}"
    exc = SolverError(
        f"{'Newton' if used == 'newton' else 'The trust region'} did not converge past load factor "
        f"{applied:.4g} (step halved {max_cuts} times in a row, or to {step:.2g} of the load; residual "
        f"{history[-1]:.3g} after {len(history) - 1} iterations{limit}): the structure may buckle or snap "
        "there, or the load tears elements inside out. Reduce the load, refine the mesh, or pass more steps")
    exc.result = result
    return exc


MIN_LOAD_STEP = 1e-9  # a load step halved below this fraction of the load ends the solve (it stalls there)
def _extrapolate(conf: Configuration, before: Configuration, ratio: float) -> None:
    """Move ``conf`` on by ``ratio`` times its change since ``before`` (rotations by the
    relative rotation's vector)."""
    conf.u += ratio * (conf.u - before.u)
    if conf.Q is not None:
        rel = Rotation.from_matrix(conf.Q @ before.Q.transpose(0, 2, 1)).as_rotvec()
        conf.Q = rotation(ratio * rel) @ conf.Q


def _move_supports(conf: Configuration, P: np.ndarray, fixed: np.ndarray, start: float, end: float) -> None:
    """Set the fixed dofs to the prescribed motion at load factor ``end`` (from ``start``)."""
    if not P.any():
        return
    held = fixed[:, :3]
    conf.u[held] = end * P[:, :3][held]
    if conf.Q is not None:
        rot = np.flatnonzero(fixed[:, 3:].all(axis=1) & (P[:, 3:] != 0).any(axis=1))
        if rot.size:
            conf.Q[rot] = rotation(end * P[rot, 3:])


def _carry_rigidly(trial: Configuration, conf: Configuration, system: NonlinearSystem, fixed: np.ndarray) -> None:
    """Where the supports move rigidly in this step (one rotation and translation takes every held node
    from ``conf`` to ``trial`` within 1e-9 of the motion; Kabsch's fit), the free nodes go with them: the
    predictor of a model carried by its supports. Otherwise a support moved 1 km is a 1 km stretch of
    the elements next to it for Newton to undo (a NaN on a shell, inverted tets on a solid). Applies
    when every node with a fixed translation has all three fixed (a partly held node has no motion to
    fit)."""
    held = fixed[:, :3].all(axis=1)
    if not held.any() or (fixed[:, :3].any(axis=1) & ~held).any():
        return
    X = np.asarray(system.model.mesh.vertices)
    a, b = X[held] + conf.u[held], X[held] + trial.u[held]
    motion = float(np.abs(b - a).max())
    if motion == 0.0:
        return
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    U, _, Vt = np.linalg.svd((a - ca).T @ (b - cb))
    R = Vt.T @ np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))]) @ U.T
    if np.abs((a - ca) @ R.T + cb - b).max() > 1e-9 * motion:
        return  # not rigid: the supports strain the model, and Newton starts from the last equilibrium
    free = ~held
    trial.u[free] = (X[free] + conf.u[free] - ca) @ R.T + cb - X[free]
    if trial.Q is not None:
        turn = ~fixed[:, 3:].all(axis=1)  # triads the supports do not prescribe
        trial.Q[turn] = R @ conf.Q[turn]


def _newton(system: NonlinearSystem, conf: Configuration, F: np.ndarray, tol: float,
            max_iterations: int, watch: _Watch | None = None) -> tuple[list[float], bool]:
    """Newton iterations on the free dofs from ``conf`` (changed in place). Converged when the
    residual is below ``tol`` times the force scale (|F| + |f_int|), or when a correction moves no
    translation by more than :meth:`NonlinearSystem.resolution` (a state with no force to measure
    against, such as a rigid motion of the supports). Returns the residual norms (before each
    iteration, and the last) and whether it converged."""
    free = system.free
    history: list[float] = []

    def failed():
        system.within_limit(conf)  # records an inverted element or a triad turned too far, for the error message
        return history, False

    for _ in range(max_iterations):
        f, K, _ = system.evaluate(conf)
        r = f[free] - F[free]
        rn = float(np.linalg.norm(r))
        history.append(rn)
        if watch is not None:
            watch.tick(rn)
        if _diverged(history):
            return failed()
        if rn <= tol * (float(np.linalg.norm(F)) + float(np.linalg.norm(f))):
            return history, system.within_limit(conf)
        try:
            delta = -system.solver(K, "the tangent stiffness").solve(r)
        except SolverError:
            return failed()
        full = system.expand(delta)
        conf.update(full)
        if np.abs(full[:, :3]).max() <= system.resolution(conf):
            f, _, _ = system.evaluate(conf, tangent=False)
            history.append(float(np.linalg.norm(f[free] - F[free])))
            return history, system.within_limit(conf)
    return failed()


def _diverged(history: list[float]) -> bool:
    """Whether Newton's residuals ran away: not finite, or past 1e3 times the first after three
    iterations (the step is too long for the tangent)."""
    rn = history[-1]
    return not np.isfinite(rn) or (len(history) > 3 and rn > 1e3 * history[0])


def _potential(c: Configuration, energy: float, load: np.ndarray) -> float:
    """The total potential E - F . u of dead forces ``load`` (n, 3)."""
    return energy - float(np.sum(load * c.u))


def _more_shift(mu: float) -> float:
    """The trust region's shift after a refused step."""
    return max(4.0 * mu, 1e-6)


def _minimize(system: NonlinearSystem, conf: Configuration, F: np.ndarray, tol: float,
              max_iterations: int, watch: _Watch | None = None) -> tuple[list[float], bool]:
    """Trust-region minimization of the total potential Pi = E(x) - F . u from ``conf`` (changed
    in place), by Levenberg-Marquardt shifted Newton steps: (H + mu D) p = -r with H the
    symmetric Hessian (the symmetric part of the spin tangent: its skew part, -1/2 [m]x, is the
    multiplicative update's and vanishes at equilibrium), D = |diag H| at the start, and mu
    raised until H + mu D is positive definite (a Cholesky factorization) and the step decreases
    Pi by at least 1e-4 of the quadratic model's prediction; mu shrinks by 4 after a step the
    model predicted well (ratio > 0.75) and is dropped below 1e-6, where the steps are Newton's
    (Nocedal & Wright, ch. 4; Conn, Gould & Toint, Trust-Region Methods, 7.3). The potential
    never rises, so the iterates cannot run off along a negative curvature as Newton's do, and
    the end is a minimum: a stable equilibrium. Returns the residual norms (as :func:`_newton`)
    and whether it converged."""
    free = system.free
    n, dpn = system.model.n_nodes, system.dpn
    load = F.reshape(n, dpn)[:, :3]  # dead forces; no moments (checked by the caller)
    f, K, energy = system.evaluate(conf)
    pi = _potential(conf, energy, load)
    scale = float(np.linalg.norm(F))
    history: list[float] = []
    if not system.within_limit(conf):  # a start the elements cannot describe: a shorter step
        return [float(np.linalg.norm(f[free] - F[free]))], False
    mu, D = 0.0, None
    more = _more_shift
    for _ in range(max_iterations):
        r = f[free] - F[free]
        rn = float(np.linalg.norm(r))
        history.append(rn)
        if watch is not None:
            watch.tick(rn)
        if not np.isfinite(rn):
            return history, False
        if rn <= tol * (scale + float(np.linalg.norm(f))):
            return history, True
        H = (0.5 * (K + K.T)).tocsr()
        if D is None:
            D = np.abs(H.diagonal())
            D = np.maximum(D, 1e-12 * D.max())
        while True:  # shift until the step is a descent the quadratic model predicts
            if mu > 1e12:
                return history, False  # no decrease even along the scaled gradient: a non-smooth potential
            A = H + sp.diags(mu * D) if mu > 0 else H
            try:
                p = -system.solver(A, "the shifted Hessian", spd_only=True).solve(r)
            except SolverError:  # not positive definite: shift more
                mu = more(mu)
                continue
            predicted = -(r @ p + 0.5 * p @ (H @ p))
            if not (-r @ p > 0 and predicted > 0):  # not a descent direction: indefinite after all
                mu = more(mu)
                continue
            trial = conf.copy()
            full = system.expand(p)
            trial.update(full)
            if not system.within_limit(trial):  # would invert an element or turn a triad too far: a shorter step
                mu = more(mu)
                continue
            ft, Kt, et = system.evaluate(trial)
            pt = _potential(trial, et, load)
            ratio = (pi - pt) / predicted
            # near the end the decrease is below the round-off of Pi: judge by the residual there
            tiny = predicted <= 1e-12 * (abs(pi) + abs(energy)) and \
                float(np.linalg.norm(ft[free] - F[free])) < rn
            if np.isfinite(pt) and (ratio > 1e-4 or tiny):
                break
            mu = more(mu)
        conf.u, conf.Q = trial.u, trial.Q
        f, K, energy, pi = ft, Kt, et, pt
        newton = mu == 0.0
        if ratio > 0.75 or tiny:
            mu = mu / 4.0 if mu > 1e-6 else 0.0
        elif ratio < 0.25:
            mu = more(mu)
        if newton and np.abs(full[:, :3]).max() <= system.resolution(conf):  # a Newton step that moved nothing
            history.append(float(np.linalg.norm(f[free] - F[free])))
            return history, True
    return history, False


def _fill(result: NonlinearResult, system: NonlinearSystem, conf: Configuration, t0: float, converged: bool) -> None:
    f, _, energy = system.evaluate(conf, tangent=False)
    model = system.model
    reactions = f.reshape(model.n_nodes, system.dpn)[:, :3] * model.fixed[:, :3]
    result.displacements = conf.u.copy()
    result.rotations = conf.rotation_vectors()
    result.reactions = reactions
    result.energy = energy
    result.local_rotation = system.local_rotation(conf)
    result.converged = converged
    result.seconds = time.perf_counter() - t0
    result.configuration = conf
