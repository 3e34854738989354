"""The fast full-order large-deformation step (issue 55): the same HHT-Newmark equations as
:class:`~rtfem.drivers.nonlinear_newmark.NonlinearNewmarkSimulator`, solved by chord iterations on
a lagged Newmark tangent, factorized once and refreshed when it has gone stale (or on a thread),
with the internal forces from compiled element kernels.

Why it is fast. At a haptic or visual step (dt of a millisecond) the Newmark matrix
A = M / (beta dt^2) + gamma / (beta dt) B + (1 + a) K_t is dominated by its mass term on every mode
the step resolves, so a factor of A at a recent state is a good inverse of today's: each iteration
x <- x - A_ref^-1 r(x) contracts the residual by about |A_ref^-1 (A_t - A_ref)|, the change of the
tangent since the refresh weighed against the mass. An iteration costs one evaluation of the
internal forces (compiled kernels: a tet4's unrolled, :mod:`rtfem.reduction.tet_node_kernels`, the
others the reduced models' :mod:`rtfem.reduction.tet_kernels`; no Python per element, the elements
shared among threads by :func:`rtfem.fe.jit.chunked`) and one pair of triangular solves; the
forces at the end of a step are those at the start of the next, and the step starts from the state
and forces extrapolated from the last three (no evaluation), so a step that converges at once
costs one force evaluation and one solve (a linearly implicit step, Baraff & Witkin 1998, whose
residual is checked). The factor is that of Courtecuisse, Allard, Duriez & Cotin (2010): a
factorization of a recent tangent, refreshed once its extra iterations have cost about a
factorization (``refresh="auto"``: in a calm motion never), every ``refresh`` steps, or in the
background (``background=True``), and at once where the chord stalls; the contact compliances of
the one-step contract come from it (Saupin et al.; Courtecuisse et al. 2014).

The step converges to the same equations as the Newton step (each step's residual below ``tol``
times the force scale), so it settles to the same equilibrium as :func:`rtfem.nonlinear.solve_static`.
"""

from __future__ import annotations

import threading

import numpy as np
import scipy.sparse as sp

from .. import validate
from ..errors import SolverError
from ..fe.jit import chunked
from ..threads import leave_realtime
from .nonlinear_newmark import NonlinearNewmarkSimulator

__all__ = ["LaggedNewmarkSimulator"]


class _Kernels:
    """A solid's element forces and tangents by the compiled kernels (corotated linear material,
    neo-Hookean, Mooney-Rivlin, Ogden; a model of several regions each region's), or None where
    they do not apply (shells, tet4-anp, a Prony law, no numba): the system's own batched
    evaluation is used then."""

    def __init__(self, system) -> None:
        from ..fe.regions import RegionTets
        from ..fe.solid import CorotationalTets, HyperelasticTets
        from ..fe.viscoelastic import ViscoelasticTets
        from ..reduction import tet_kernels as tk, tet_node_kernels as tnk

        kern = system.kernel
        self.ok = (system.dpn == 3 and isinstance(kern, (CorotationalTets, RegionTets))
                   and not isinstance(kern, ViscoelasticTets) and not getattr(kern, "history_size", 0)
                   and not hasattr(kern, "patch_tangent") and tk.compiled_solid_forces() is not None)
        if not self.ok:
            return
        self.tk, self.tnk, self.system = tk, tnk, system
        cells = system.cells
        self.cells = np.ascontiguousarray(cells, dtype=np.int64)
        self.X = np.ascontiguousarray(np.asarray(system.model.mesh.vertices, dtype=float)[cells])
        self.G = np.ascontiguousarray(np.stack(kern.G, axis=1))
        self.wdet = np.ascontiguousarray(np.stack(kern.wdet, axis=1))
        if isinstance(kern, RegionTets):  # (elements, law or None: the corotated linear material) per region
            self.lm, self.parts = np.ascontiguousarray(kern.lm), kern.laws
        else:
            self.lm = np.tile([kern.lam, kern.mu], (cells.shape[0], 1))
            self.parts = [(None, kern.law if isinstance(kern, HyperelasticTets) else None)]
        self.linear = all(law is None for _, law in self.parts)  # the node kernel's fast path applies
        self.tet4 = cells.shape[1] == 4 and self.G.shape[1] == 1  # its force evaluation counts inversions
        self._last = None  # (u, elements inverted there) of the last tet4 force evaluation
        E, k = cells.shape
        self._F = np.empty((E, 3 * k))
        # the points the inversion check looks at (a tet10's corners too; not an evaluation of all the elements)
        self.G_check = np.ascontiguousarray(np.stack(kern.check_gradients(k), axis=1))

    def inverted(self, u: np.ndarray) -> int:
        """How many elements are turned inside out at nodal displacements u (n, 3) (a tet4's counted by
        the force evaluation at u where that was the last)."""
        last = self._last
        if last is not None and np.array_equal(last[0], u):
            return last[1]
        return int(np.count_nonzero(self.tnk.inverted_elements(self._dofs(u), self.X, self.G_check)))

    def _dofs(self, u: np.ndarray) -> np.ndarray:
        return np.ascontiguousarray(u[self.cells].reshape(self.cells.shape[0], -1))

    def forces(self, u: np.ndarray) -> np.ndarray:
        """The internal forces (n_dofs,) at nodal displacements u (n, 3)."""
        if self.linear:
            f = np.empty(self.system.model.n_dofs)
            u = np.ascontiguousarray(u, dtype=float)
            bad = self.tnk.solid_node_forces(u, self.cells, self.X, self.G, self.wdet, self.lm, f)
            if bad is not None:
                self._last = (u.copy(), bad) if self.tet4 else None
                return f
        self._each(self._dofs(u), self._F, self.tk.solid_element_forces, self.tk.law_forces)
        return self.system.gather(self._F)

    def tangent(self, u: np.ndarray):
        """The tangent stiffness on the free dofs (CSR) at nodal displacements u (n, 3)."""
        V = self._dofs(u)
        Ke = np.empty((V.shape[0], V.shape[1], V.shape[1]))
        self._each(V, Ke, self.tk.solid_element_tangents, self.tk.law_tangents)
        return self.system.tangent_matrix(Ke)

    def _each(self, V: np.ndarray, out: np.ndarray, linear, law_kernel) -> None:
        """out[e] = each element's forces or tangent at its dofs V: ``linear`` (the corotated
        material, Lame constants per element) or ``law_kernel`` (a law's), each region's own."""
        self.tk.by_region(self.parts, V, self.X, self.G, self.wdet, self.lm, out, linear, law_kernel,
                          share=lambda n, work: chunked(n, work, self.G.shape[1]))


class LaggedNewmarkSimulator(NonlinearNewmarkSimulator):
    """The full-order large-deformation step by chord iterations on a lagged Newmark tangent (see
    the module): what ``rt.DirectSimulator(model, dt, damping, large_deformation=True)`` makes for a
    solid (``solver="newton"`` makes the Newton-converged reference,
    :class:`~rtfem.NonlinearNewmarkSimulator`, for any model). A Driver like the others.

    Parameters
    ----------
    model, dt, damping, numerical_damping : as :class:`~rtfem.NonlinearNewmarkSimulator`.
    tol : each step iterates until its residual is below ``tol`` times the force scale (|F| + |f| +
        |M a|; default 1e-4: on a bar swung to a tenth of its length the motion then agrees with the
        Newton reference's, converged to 1e-8, to 3e-5 .. 6.5e-5 of it; at rest the equilibrium is the
        same whatever the tolerance, a residual of zero).
    max_iterations : chord iterations per step before Newton's method takes the step (default 40): the step
        fails only where Newton's does too.
    refresh : when the tangent is refactorized: ``"auto"`` (the default) once the chord iterations the
        factor has cost beyond the fewest a step of it took add up to ``refresh_cost``: a factor that
        still converges as it did when fresh is kept (in a calm motion for good), one the motion left
        behind is replaced as soon as it has cost about a factorization; or every ``refresh`` steps
        (a whole number). Either way also at once in a step whose chord iterations pass ``stall``
        (default 4); the run is reproducible.
    refresh_cost : a factorization's cost in chord iterations, for ``refresh="auto"`` (default 25: on
        the 9k-tet liver of benchmarks/fullorder.py the tangent and its factorization took 30-40 ms,
        an iteration (forces and a solve) 0.7-1.3 ms).
    predictor : start each step's iterations from the displacements and forces extrapolated from the
        last three committed states (default True; see ``_predicted``): on the swinging liver of
        benchmarks/fullorder.py 1.70 force evaluations a step instead of 1.86 over the first 500
        steps, the same answer to the tolerance.
    background : refresh on a thread instead (when ``refresh`` says), each step taking the newest
        factor ready (the real-time setting: a step never waits for a factorization; not
        reproducible run to run).

    Raises
    ------
    ModelError
        As :class:`~rtfem.NonlinearNewmarkSimulator`; tol, max_iterations, refresh or stall out of
        range.
    SolverError
        At run time: a step does not converge (a smaller dt or more damping), or its state is one the
        elements cannot describe (an element turned inside out).
    """

    solver = "lagged"

    def __init__(self, model, dt: float, damping=None, *, method: str | None = None,
                 large_deformation: bool | None = None, numerical_damping: float = 0.05, tol: float = 1e-4,
                 max_iterations: int = 40, refresh: int | str = "auto", refresh_cost: int = 25, stall: int = 4,
                 background: bool = False, predictor: bool = True, solver: str | None = None) -> None:
        super().__init__(model, dt, damping, method=method, large_deformation=large_deformation,
                         numerical_damping=numerical_damping, tol=tol, max_iterations=max_iterations,
                         solver=solver)
        self.refresh = refresh if isinstance(refresh, str) and refresh == "auto" else \
            validate.count(refresh, "refresh", 1, 10**6, what='or "auto"')
        self.refresh_cost = validate.count(refresh_cost, "refresh_cost", 1, 10**6)
        self.stall = validate.count(stall, "stall", 1, 1000)
        self.background = validate.flag(background, "background")
        self.predictor = validate.flag(predictor, "predictor")
        self._kernels = _Kernels(self.system)
        self._f = None  # the internal forces at the committed configuration (the next step's first residual)
        self._factor = None  # (factorization of the Newmark tangent, the step it was made at)
        self._dyn_on_K = None  # the mass and damping on the tangent's pattern (False: not within it); at first use
        # where the factor was made (its displacements, its step, a Prony law's history then): part of
        # the state, so that a restored state iterates with the same factor and replays bit for bit
        self._ref_u, self._ref_step = np.zeros_like(self._u), np.zeros(1)
        # the fewest chord iterations a step took on the factor (-1: none yet) and the iterations beyond
        # those since it was made (refresh="auto")
        self._chord = np.array([-1.0, 0.0])
        # the two committed displacements before this one and how many of them the next step may
        # extrapolate from (the predictor: see _predicted); their forces are evaluated again after a restore
        self._u_1, self._u_2, self._past = np.zeros_like(self._u), np.zeros_like(self._u), np.zeros(1)
        self._f_past: list = []  # the forces at _u_1, _u_2 (n_dofs each)
        self._state = (*self._state, "_ref_u", "_ref_step", "_chord", "_u_1", "_u_2", "_past")
        if self._visc.size:
            self._ref_visc = self._visc.copy()
            self._state = (*self._state, "_ref_visc")
        self._pending: threading.Thread | None = None
        self._ready = None  # a factor made on the thread, waiting for the next step
        self._lock = threading.Lock()
        self.refreshes = 0  # factorizations made (all of them, the thread's and Newton's included)
        self.newton_steps = 0  # steps where the chord diverged and Newton's method took the step
        self.iterations = 0

    # ---------------------------------------------------------------- forces and the lagged factor
    def _forces(self, conf, history) -> np.ndarray:
        if self._kernels.ok:
            return self._kernels.forces(conf.u)
        return self.system.evaluate(conf, False, history)[0]

    def _evaluate(self, conf, tangent: bool, history):
        """Newton's evaluations (where the chord diverges) by the compiled kernels too, where they apply: the
        numpy corotated stress took 70 ms of each on the cut example liver, four a Newton step."""
        if self._kernels.ok:
            return self._kernels.forces(conf.u), self._kernels.tangent(conf.u) if tangent else None
        return super()._evaluate(conf, tangent, history)

    def _tangent(self, conf, history):
        if self._kernels.ok:
            return self._kernels.tangent(conf.u)
        return self.system.evaluate(conf, True, history)[1]

    def _factorize(self, conf, history, reuse=None):
        """The factorization of the Newmark tangent at ``conf`` (the HHT-weighted stiffness): ``reuse``
        (a factorization of this system's pattern, not in use elsewhere) factorized again in place where
        the backend can (PARDISO's numeric phase alone: the ordering kept), else a new one."""
        A = self._newmark_matrix(self._tangent(conf, history))
        with self._lock:
            self.refreshes += 1
        if reuse is not None:
            try:
                if reuse.refactor(A):
                    return reuse
            except SolverError:  # indefinite (slivers a cut left, compressed): the solver's LU below; the handle
                pass  # ``reuse`` is spent (its numeric factor failed) and is replaced
        return self.system.solver(A, "the Newmark tangent", refactorable=not self.background)

    def _newmark_matrix(self, K):
        """dyn + (1 + a) K: on the tangent pattern's own arrays one product and sum of their values (the
        mass and damping, whose pattern is within the tangent's, put there once), else scipy's sum
        (which holds the GIL for the whole merge of the patterns)."""
        indices, indptr, n = self.system._pattern
        if K.indices is indices and K.indptr is indptr:
            if self._dyn_on_K is None:
                P = (sp.csr_matrix((np.zeros(indices.size), indices, indptr), shape=(n, n)) + self._dyn).tocsr()
                P.sort_indices()
                ok = P.nnz == indices.size and np.array_equal(P.indices, indices) and np.array_equal(P.indptr, indptr)
                self._dyn_on_K = P.data if ok else False
            if self._dyn_on_K is not False:
                return sp.csr_matrix((self._dyn_on_K + (1 + self._hht) * K.data, indices, indptr), shape=(n, n))
        return (self._dyn + (1 + self._hht) * K).tocsr()

    def _refactor(self, conf, u: np.ndarray, history) -> None:
        """The factor of the Newmark tangent at ``conf`` (displacements ``u``), kept with where it was made
        (the old one factorized again in place where nothing else holds it: no thread is at work)."""
        reuse = None if self.background or self._factor is None else self._factor[0]
        self._factor = (self._factorize(conf, history, reuse), self.steps)
        self._ref_u, self._ref_step = u.copy(), np.array([float(self.steps)])
        self._chord = np.array([-1.0, 0.0])
        if self._visc.size:
            self._ref_visc = self._visc.copy()

    def _refresh_on_thread(self) -> None:
        conf, u, steps = self.configuration.copy(), self._u.copy(), self.steps
        history = (self._visc.copy(), self.dt) if self._visc.size else None

        def work():
            leave_realtime()  # (started by a stepping thread that may run under real-time scheduling)
            try:
                fac = self._factorize(conf, history)
            except Exception:  # an indefinite tangent (a buckling state): keep the old factor
                return
            with self._lock:
                self._ready = (fac, steps, u, None if history is None else history[0])

        self._pending = threading.Thread(target=work, name="rtfem-fullorder-tangent", daemon=True)
        self._pending.start()

    def _lagged(self, conf, history):
        """The factor this step iterates with: refreshed on schedule (here, or the thread's newest)."""
        if self._factor is None:  # at the start, or after a restore: the factor of the state's reference
            self.factorize()
        stale = self._chord[1] >= self.refresh_cost if self.refresh == "auto" else \
            self.steps - self._factor[1] >= self.refresh
        if self.background:
            with self._lock:
                ready, self._ready = self._ready, None
            if ready is not None:
                self._factor = ready[:2]
                self._ref_u, self._ref_step = ready[2], np.array([float(ready[1])])
                self._chord = np.array([-1.0, 0.0])
                if ready[3] is not None:
                    self._ref_visc = ready[3]
            elif stale and (self._pending is None or not self._pending.is_alive()):
                self._refresh_on_thread()
        elif stale:
            self._refactor(conf, self._u, history)
        return self._factor[0]

    def factorize(self) -> None:
        """Make the factor the next step iterates with, that of the state's reference, now (where there is
        none): on another thread, a driver about to be swapped in (a cut model's) then steps at once."""
        if self._factor is None:
            ref = self._configuration_at(self._ref_u)
            ref_history = (self._ref_visc, self.dt) if self._visc.size else None
            self._factor = (self._factorize(ref, ref_history), int(self._ref_step[0]))

    def set_state(self, state) -> None:
        """As :meth:`DirectSimulator.set_state`; a state of the same reference as now keeps the factor (the
        one the first step would make again, bit for bit)."""
        kept = None if self._factor is None or self._visc.size else (self._factor, self._ref_u.copy(),
                                                                      self._ref_step.copy())
        super().set_state(state)
        if kept is not None and np.array_equal(kept[1], self._ref_u) and np.array_equal(kept[2], self._ref_step):
            self._factor = kept[0]

    # ---------------------------------------------------------------- the step
    def _solve_step(self, F: np.ndarray):
        """Chord iterations on the HHT residual from the current state; returns (configuration, u,
        g, the factor iterated with) without changing the state."""
        al = self._hht
        conf = self.configuration.copy()
        u = self._u.copy()
        Ff = F[self._solved]
        history = (self._visc, self.dt) if self._visc.size else None
        if self._f is None:  # (after a restore, or a Prony law's commit)
            self._f = self._forces(conf, history)
        f = self._f
        fac = self._lagged(conf, history)
        first = 1
        warm = self._free
        if warm is not None and warm[0] == self.steps and warm[4] is fac and not np.array_equal(F, self._held):
            # a contact's step after its predict: from the held-load step plus the tangent's response to
            # the change of load (what step_compliance promised), so the chord has only the
            # nonlinearity of the change left (1-2 iterations, not the 3-5 from the start of the step)
            delta = (1 + al) * fac.solve(Ff - self._held[self._solved])
            conf = warm[1].copy()
            conf.update(self.system.expand(delta))
            u = warm[2] + delta
            f = self._forces(conf, history)
            first = 0
        predicted = first == 1 and self._past[0] > 0
        if predicted:
            u, f = self._predicted(conf, u, f)
        norm_F = float(np.linalg.norm(Ff))
        previous = np.inf
        for it in range(self.max_iterations + 1):
            a, v = self._kinematics(u)
            g = f[self._solved] + self._B @ v - Ff
            Ma = self._M @ a
            r = Ma + (1 + al) * g - al * self._g
            rn = float(np.linalg.norm(r))
            # converged: asked first (a residual already below the tolerance is taken even where it did not fall,
            # as at the roundoff floor it need not)
            if it >= first and rn <= self.tol * (norm_F + float(np.linalg.norm(f)) + float(np.linalg.norm(Ma)) + 1e-300):
                return self._converged(it, f, conf, u, g, fac)
            # the chord does not contract (a stale tangent far from this motion, or a step the mass does not
            # dominate): Newton's step here (the first residual after a prediction is compared with nothing:
            # the one before it was the predictor's model)
            if not rn < previous and not (predicted and it == 1):
                return self._newton_step(F, history)
            if it == self.max_iterations:
                break
            if it == self.stall:  # the tangent moved far since the refresh: a fresh factor here (Newton's)
                self._refactor(conf, u, history)
                fac = self._factor[0]
            delta = -fac.solve(r)
            if it >= first and np.abs(delta).max() <= 1e-13 * self.system.size:
                # nothing left to move (Newton's rule): an organ at rest, its residual the roundoff of forces that
                # vanish (7e-13 N on the viewer's block, against a tolerance of 1e-4 times that), which no
                # iteration lowers: read as a stalled chord, every such step was Newton's (36 ms a step on that
                # block, against 1.3 ms; benchmarks/at_rest.py)
                return self._converged(it, f, conf, u, g, fac)
            conf.update(self.system.expand(delta))
            u = u + delta
            f = self._forces(conf, history)
            previous = rn
        # the chord contracted, but too slowly to converge within its iterations (a cut's slivers: 34 cuts in,
        # residual 0.0033 after 40): Newton's step, which raises where it does not converge either
        return self._newton_step(F, history)

    def _converged(self, it: int, f: np.ndarray, conf, u: np.ndarray, g: np.ndarray, fac):
        """The chord's answer after ``it`` iterations, the forces ``f`` at it (the next step's first residual)."""
        self.iterations = it
        self._f_trial = f
        return self._accepted(conf, u, g, fac)

    def _predicted(self, conf, u: np.ndarray, f: np.ndarray):
        """The step's first iterate extrapolated in time from the committed displacements (u_p = 3 u - 3 u_1
        + u_2, or 2 u - u_1 with one before), with the forces extrapolated alike (a secant model along
        the motion: no evaluation); ``conf`` is moved there. Only the first iteration's residual is the
        model's: the chord then iterates on true residuals to the same tolerance, so the predictor
        changes how many iterations a step takes, not what it converges to. ``conf`` is a solid's."""
        n = int(self._past[0])
        if len(self._f_past) < n:  # after a restore: the history's forces, evaluated again (bit for bit)
            self._f_past = [self._forces(self._configuration_at(x), None) for x in (self._u_1, self._u_2)[:n]]
        if n >= 2:
            up = 3.0 * (u - self._u_1) + self._u_2
            fp = 3.0 * (f - self._f_past[0]) + self._f_past[1]
        else:
            up, fp = 2.0 * u - self._u_1, 2.0 * f - self._f_past[0]
        conf.u = self.system.expand(up)[:, :3].copy()  # (set, not moved by up - u: the same bits as u)
        return up, fp

    def _newton_step(self, F: np.ndarray, history):
        """The step by Newton's method with its line search (the reference's), from the step's start:
        where the chord diverges. The tangent at its answer is the lagged one after."""
        tol = self.tol
        self.tol = min(tol, 1e-8)  # as the reference converges it
        try:
            conf, u, g, _ = NonlinearNewmarkSimulator._solve_step(self, F)
        finally:
            self.tol = tol
        self.newton_steps += 1
        self._refactor(conf, u, history)  # the lagged factor from here on: at Newton's answer (reproducibly)
        self._f_trial = self._forces(conf, history)
        return self._accepted(conf, u, g, self._factor[0])

    def _accepted(self, conf, u, g, fac):
        self.system.turned, self.system.inverted = 0.0, 0
        if self._kernels.ok:
            self.system.inverted = self._kernels.inverted(conf.u)
            within = self.system.inverted == 0
        else:
            within = self.system.within_limit(conf)
        if not within:
            from ..fe.nonlinear import inversion_refused, turn_refused

            why = inversion_refused(self.system.inverted) if self.system.inverted else \
                f"a {turn_refused(self.system.turned)}"
            raise SolverError(f"step {self.steps + 1} was refused: {why} (the state is unchanged)")
        return conf, u, g, fac

    def _commit(self, conf, u, g) -> None:
        f = getattr(self, "_f_trial", None)
        if self._f is not None and not self._visc.size and self.predictor:  # the history the predictor extrapolates
            self._u_1, self._u_2 = self._u, self._u_1
            self._f_past = [self._f] + self._f_past[:1]
            self._past = np.array([min(2.0, self._past[0] + 1)])
        else:
            self._past = np.zeros(1)
        super()._commit(conf, u, g)
        fewest = self.iterations if self._chord[0] < 0 else min(self._chord[0], self.iterations)
        self._chord = np.array([fewest, self._chord[1] + self.iterations - fewest])
        # the forces at the committed state, for the next step's first residual (a Prony history
        # changed at the commit: its forces are evaluated again)
        self._f = f if not self._visc.size else None

    def step(self, forces=None) -> None:
        if self._free is not None and self._free[0] == self.steps:  # the held-load step's forces were its own
            self._f_trial = self._free_forces
        super().step(forces)

    def step_compliances(self, nodes, loaded=None) -> np.ndarray:
        """As :meth:`NonlinearNewmarkSimulator.step_compliances`, with the lagged factor's: the same
        between two refreshes, so the last set's is kept (a tool asking every step for its contact
        set's pays its 3 k solves once per refresh)."""
        fac = self._free_step()[4]
        key = (self.refreshes, id(fac), np.asarray(nodes).tobytes(), None if loaded is None else np.asarray(loaded).tobytes())
        kept = getattr(self, "_kept_W", None)
        if kept is None or kept[0] != key:
            self._kept_W = kept = (key, super().step_compliances(nodes, loaded))
        return kept[1].copy()

    def _free_step(self):
        if self._free is None or self._free[0] != self.steps:
            self._free = (self.steps, *self._solve_step(self._held), None)
            self._free_forces = self._f_trial
        return self._free

    def _state_changed(self) -> None:
        super()._state_changed()
        self._f = None
        self._factor = None
        self._f_past = []
        if hasattr(self, "_lock"):
            with self._lock:
                self._ready = None


NonlinearNewmarkSimulator._solvers["lagged"] = LaggedNewmarkSimulator
