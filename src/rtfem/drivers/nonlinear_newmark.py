"""The full-order large-deformation simulator: corotational internal forces, Newton inside implicit
Newmark (``DirectSimulator(..., large_deformation=True)`` makes one)."""

from __future__ import annotations

from typing import Mapping

import numpy as np
import scipy.sparse as sp

from .. import validate
from ..errors import ModelError, SolverError
from ..fe.material import Damping
from .base import newmark_constants

from .fullorder import DirectSimulator, _numerical_damping

__all__ = ["NonlinearNewmarkSimulator"]


class NonlinearNewmarkSimulator(DirectSimulator):
    """Geometrically nonlinear (corotational) full-order dynamics: Newton's method inside an
    implicit Newmark step on the model's consistent tangent (:meth:`model.nonlinear`). The
    large-deformation reference; a Driver like the others.

    The step is Hilber-Hughes-Taylor's alpha method (Hilber, Hughes & Taylor 1977):
    M a_{n+1} + (1 + a)(f(u_{n+1}) + B v_{n+1} - F_{n+1}) - a (f(u_n) + B v_n - F_n) = 0 with
    a = -``numerical_damping``, beta = (1 - a)^2 / 4, gamma = 1/2 - a. With
    ``numerical_damping=0`` it is the average-acceleration rule of the linear simulators, which
    conserves energy for linear models but can gain energy without bound on a nonlinear one
    when the step leaves the stiff high modes unresolved (Simo & Tarnow 1992; measured here: a
    cantilever swung by P L^2/EI = 6 gains 14 % in 3 s at dt = 0.01, 0.1 % at 0.0025). The default
    0.05 damps the unresolved modes and leaves the resolved ones (second-order accurate).

    Rotations (a shell's) are rotation matrices for the elastic forces; their velocities and
    accelerations (which matter only with rotary inertia or stiffness-proportional damping) are
    those of the accumulated spins. Damping B = alpha M + beta K0 with K0 the initial stiffness.
    ``tol``: Newton stops when the residual is below ``tol`` times the force scale.

    The one-step contract (:meth:`predict`, :meth:`step_compliances`) is linearized at the next
    step with the last step's loads held, so that a consumer's u = predict + W f is exact for the
    loads it holds and off only to second order in their change (a tool resting on the tissue);
    linearized at no load it is off by the nonlinearity of the whole load.

    Parameters
    ----------
    model, dt, damping : as :class:`~rtfem.DirectSimulator` (a model with ``nonlinear()``).
    numerical_damping : HHT's d in 0 .. 1/3 (default 0.05).
    tol : Newton's tolerance relative to the force scale (default 1e-8).
    max_iterations : Newton iterations per step before it fails (default 25).

    Raises
    ------
    ModelError
        As :class:`~rtfem.DirectSimulator`; d, tol or max_iterations out of range.
    SolverError
        At run time: Newton does not converge in a step (take a smaller dt or more damping).
    """

    method = "newmark"
    large_deformation = True
    compliance_changes = True  # the tangent follows the motion (consumers must not cache W)
    _state = ("_u", "_v", "_a", "_g", "_held")  # the held loads: where the one-step contract is linearized

    solver = "newton"
    #: the large-deformation steps by name (rtfem.drivers.lagged_newmark registers "lagged")
    _solvers: dict = {}

    def __init__(self, model, dt: float, damping: Damping | None = None, *, method: str | None = None,
                 large_deformation: bool | None = None, numerical_damping: float = 0.05, tol: float = 1e-8,
                 max_iterations: int = 25, solver: str | None = None) -> None:
        if solver is not None and solver != self.solver:
            raise ModelError(f"solver={validate.show(solver)} given to {type(self).__name__}, whose step is "
                             f"{self.solver!r}; build it with rt.DirectSimulator(model, dt, damping, "
                             "large_deformation=True, solver=...)")
        super().__init__(model, dt, damping, method=method, large_deformation=large_deformation)
        from ..fe.nonlinear import Configuration

        model = self.model
        nd_ = self.numerical_damping = _numerical_damping(numerical_damping)
        self._hht = -nd_
        beta, gamma = (1 + nd_) ** 2 / 4, 0.5 + nd_
        self._gamma = gamma
        self.system = model.nonlinear()
        free = self._solved = self.system.free
        M = sp.csr_matrix(model.M)[free][:, free]
        B = self.damping.matrix(M, model.K[free][:, free])
        self._c = newmark_constants(self.dt, beta, gamma)
        self._M, self._B = M.tocsr(), sp.csr_matrix(B)
        self._dyn = (self._c[0] * self._M + (1 - nd_) * self._c[1] * self._B).tocsr()
        self.tol = validate.positive(tol, "tol", "a relative tolerance such as 1e-8")
        self.max_iterations = validate.count(max_iterations, "max_iterations", 1, 1000)
        nd = free.size
        self._u, self._v, self._a, self._g = np.zeros(nd), np.zeros(nd), np.zeros(nd), np.zeros(nd)
        self.configuration = Configuration.rest(model.n_nodes, model.dofs_per_node == 6)
        self._free = None  # (step, configuration, u, g, factorization, prediction) of the step with the last loads held
        self._held = np.zeros(model.n_dofs)  # the last step's load vector
        self.iterations = 0  # Newton iterations of the last step
        self._visc = np.zeros(getattr(self.system.kernel, "history_size", 0))  # a viscoelastic law's internal variables
        if self._visc.size:  # (rt.Prony: each quadrature point's Q_i and S_iso), stepped here, kept in the state
            self._state = (*type(self)._state, "_visc")

    def _state_changed(self) -> None:
        self.configuration = self._configuration_at(self._u)
        self._free = None

    def _configuration_at(self, u: np.ndarray):
        """The configuration of displacements u on the solved dofs, from rest."""
        from ..fe.nonlinear import Configuration

        conf = Configuration.rest(self.model.n_nodes, self.model.dofs_per_node == 6)
        conf.update(self.system.expand(u))
        return conf

    def get_state(self) -> dict[str, np.ndarray]:
        """A copy of the state; on a shell also the nodal rotations (n, 3) as rotation vectors."""
        out = super().get_state()
        if self.configuration.Q is not None:
            out["rotations"] = self.configuration.rotation_vectors()
        return out

    def set_state(self, state) -> None:
        """Restore a state from :meth:`get_state` (checked whole before anything changes)."""
        from ..fe.rotations import rotation

        rot = None
        if isinstance(state, Mapping) and self.configuration.Q is not None:
            if "rotations" not in state:
                raise ModelError("state needs 'rotations' (n, 3) on a shell, as get_state() returns")
            rot = validate.real_array(state["rotations"], "state['rotations']", 2)
            if rot.shape != (self.n_nodes, 3):
                raise ModelError(f"state['rotations'] must have shape ({self.n_nodes}, 3), got {rot.shape}")
            state = {k: v for k, v in state.items() if k != "rotations"}
        super().set_state(state)
        if rot is not None:
            self.configuration.Q = rotation(rot)

    def _kinematics(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        c0, c2, c3 = self._c[0], self._c[2], self._c[3]
        a = c0 * (u - self._u) - c2 * self._v - c3 * self._a
        return a, self._v + self.dt * ((1 - self._gamma) * self._a + self._gamma * a)

    def _evaluate(self, conf, tangent: bool, history):
        """(internal forces, tangent or None) at ``conf``: the system's batched evaluation."""
        f, K, _ = self.system.evaluate(conf, tangent, history)
        return f, K

    def _solve_step(self, F: np.ndarray):
        """Newton on the HHT residual from the current state; returns (configuration, u, g,
        last factorization) without changing the state."""
        al = self._hht
        conf = self.configuration.copy()
        u = self._u.copy()
        Ff = F[self._solved]
        fac = None

        history = (self._visc, self.dt) if self._visc.size else None

        def residual(conf, u, tangent):
            f, K = self._evaluate(conf, tangent, history)
            a, v = self._kinematics(u)
            g = f[self._solved] + self._B @ v - Ff
            ref = np.linalg.norm(Ff) + np.linalg.norm(f) + np.linalg.norm(self._M @ a) + 1e-300
            return self._M @ a + (1 + al) * g - al * self._g, g, K, ref

        def converged(conf, u, g, fac):
            self.system.turned, self.system.inverted = 0.0, 0
            if not self.system.within_limit(conf):  # an element inverted, or a shell triad turned too far
                from ..fe.nonlinear import inversion_refused, turn_refused

                why = inversion_refused(self.system.inverted) if self.system.inverted else \
                    f"a {turn_refused(self.system.turned)}"
                raise SolverError(f"step {self.steps + 1} was refused: {why} (the state is unchanged)")
            return conf, u, g, fac

        r, g, K, ref = residual(conf, u, True)
        for it in range(self.max_iterations):
            rn = np.linalg.norm(r)
            if rn <= self.tol * ref and it > 0:
                self.iterations = it
                return converged(conf, u, g, fac)
            fac = self.system.solver((self._dyn + (1 + al) * K).tocsr(), "the Newmark tangent")
            delta = -fac.solve(r)
            full = self.system.expand(delta)
            if np.abs(full[:, :3]).max() <= 1e-13 * self.system.size:  # nothing left to move (e.g. at rest)
                conf.update(full)
                u = u + delta
                self.iterations = it + 1
                return converged(conf, u, residual(conf, u, False)[1], fac)
            # backtracking line search on the residual norm: a point load on a thin shell can
            # make the full Newton correction overshoot and cycle; each trial is evaluated with
            # its tangent, which the accepted one (nearly always the first) passes to the next
            # iteration
            s = 1.0
            for _ in range(6):
                trial = conf.copy()
                trial.update(s * full)
                trial_state = residual(trial, u + s * delta, True)
                if np.linalg.norm(trial_state[0]) < rn or s < 0.05:
                    break
                s *= 0.5
            conf, u = trial, u + s * delta
            r, g, K, ref = trial_state
        raise SolverError(f"Newton did not converge in {self.max_iterations} iterations at step {self.steps + 1} "
                          f"(residual {np.linalg.norm(r):.3g}): the step is too large for this motion; use a "
                          "smaller dt (the state is unchanged)")

    def _commit(self, conf, u: np.ndarray, g: np.ndarray) -> None:
        if self._visc.size:
            self._visc = self.system.kernel.committed(self.system.deformed(conf), (self._visc, self.dt))
        self._a, self._v = self._kinematics(u)
        self._u, self._g = u, g
        self.configuration = conf
        self._free = None
        self.steps += 1
        self.time = self.steps * self.dt

    def _free_step(self):
        """The next step with the last step's loads held (a Newton solve, kept for the step that
        follows): the point the one-step contract is linearized at."""
        if self._free is None or self._free[0] != self.steps:
            self._free = (self.steps, *self._solve_step(self._held), None)
        return self._free

    def _unloaded(self) -> np.ndarray:
        """(n, 3) the one-step contract's prediction: the held-load step minus the tangent response
        to the held loads, u_h - W_h f_held, so that u(k+1) ~ predict + W_h f is exact for the loads
        held and accurate to second order in their change (linearized at no load, a contact holding
        a large deformation was off by the nonlinearity itself: a sphere pressed 3 mm into a 4 mm
        plate sat 0.7 mm inside it). Without loads held: the no-load step itself."""
        free = self._free_step()
        if free[5] is None:
            u = free[1].u.copy()
            if self._held.any() and free[4] is not None:
                u -= self.model.nodal_translations((1 + self._hht) * free[4].solve(self._held[self._solved]),
                                                   self._solved)
            self._free = free = (*free[:5], u)
        return free[5]

    def predict(self, node: int) -> np.ndarray:
        """Displacement (3,) of ``node`` after one more step with no new load, as the step's
        linearization at the loads held sees it (:meth:`_unloaded`: the no-load step itself
        when no load is held; the two agree to second order in the loads)."""
        node = self._node(node)
        return self._unloaded()[node].copy()

    def predict_at(self, nodes) -> np.ndarray:
        """(k, 3) :meth:`predict` of ``nodes`` (one Newton solve, kept for the step)."""
        nodes = validate.nodes(nodes, self.n_nodes)
        return self._unloaded()[nodes].copy()

    def step_compliances(self, nodes, loaded=None) -> np.ndarray:
        """The cross compliances (3k, 3l) linearized at the step with the last loads held (solves
        with the inverse Newmark tangent, weighted 1 + alpha as the load enters HHT's residual)."""
        fac = self._free_step()[4]

        def columns(j):
            if fac is None:
                return np.zeros((self._solved.size, 3))
            return (1 + self._hht) * self._unit_response(fac.solve, j)
        return self._block(nodes, loaded, columns)

    def step_compliance(self, node: int) -> np.ndarray:
        """W (3x3): the node's displacement per unit force after one step, linearized at the
        no-load step (the inverse Newmark tangent's block)."""
        return self.step_compliances(np.array([self._node(node)]))

    def step(self, forces=None) -> None:
        """Advance one step; ``forces`` (dead loads) act at the end of the step."""
        self._check_supports()
        F = self.model.force_vector(self._as_array(forces), warn=False)
        if np.array_equal(F, self._held):
            conf, u, g = self._free_step()[1:4]
        else:
            conf, u, g, _ = self._solve_step(F)
        self._commit(conf, u, g)
        self._held = F

    def displacements(self) -> np.ndarray:
        return self.configuration.u.copy()

    def energy(self) -> float:
        """Kinetic plus strain energy (the undamped, unloaded motion keeps it)."""
        return float(0.5 * self._v @ (self._M @ self._v)) + self.system.energy(self.configuration)


NonlinearNewmarkSimulator._solvers["newton"] = NonlinearNewmarkSimulator
DirectSimulator._nonlinear = NonlinearNewmarkSimulator
