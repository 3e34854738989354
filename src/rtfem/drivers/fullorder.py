"""Full-order dynamics M U'' + B U' + K U = F: the paper's direct-integration baseline.

Two integrators, one class each, both Drivers: :class:`NewmarkSimulator` (implicit average
acceleration, the effective stiffness K + c1 B + c0 M factorized once) and
:class:`CentralDifferenceSimulator` (explicit, on the rotation-condensed system, stable for
dt <= T_n / pi). ``DirectSimulator(model, dt, damping, method=...)`` is the factory users call;
both classes are DirectSimulators.
"""

from __future__ import annotations

import math
from typing import Mapping

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from .. import validate
from ..errors import ModelError
from ..fe.linalg import factorize
from ..fe.material import Damping
from ..fe.protocol import check_model, check_supports, require_lumped_mass
from .base import ForceInput, check_damping, check_dt, newmark_constants, newmark_velocity

__all__ = ["DirectSimulator", "NewmarkSimulator", "CentralDifferenceSimulator"]

METHODS = ("newmark", "central")


class DirectSimulator(ForceInput):
    """Direct integration of the full system M U'' + B U' + K U = F (the paper's baseline).

    ``DirectSimulator(model, dt, damping, method="newmark")`` returns a :class:`NewmarkSimulator`,
    ``method="central"`` a :class:`CentralDifferenceSimulator`.

    Parameters
    ----------
    model : a restrained model (the Model protocol, e.g. :class:`~rtfem.ShellModel`).
    dt : time step (s).
    damping : :class:`~rtfem.Damping` with alpha and/or beta (B = alpha M + beta K).
    method : "newmark" (implicit, average acceleration, unconditionally stable) or "central"
        (explicit central differences; stable only for dt <= T_n / pi).
    large_deformation : the corotational full order (Newton inside implicit Newmark:
        :class:`~rtfem.NonlinearNewmarkSimulator`, which takes the ``options``).
    numerical_damping : Newmark only: Hilber-Hughes-Taylor's d (see :class:`~rtfem.NewmarkSimulator`).

    Raises
    ------
    ModelError
        A model that is not one (or has nothing fixed where the method needs supports), a dt
        that is not a positive time step, damping that is not an :class:`~rtfem.Damping` (or
        modal ratios, which have no full matrix), an unknown method, options of another method.
    """

    method = ""
    _state: tuple[str, ...] = ()  # names of the state vectors

    large_deformation = False

    def __new__(cls, model=None, dt=None, damping=None, *, method: str = "newmark", large_deformation: bool = False,
                **options):
        if "numerical_damping" in options and (method != "newmark" or cls is CentralDifferenceSimulator):
            raise ModelError(f"numerical_damping is Newmark's (HHT): method={validate.show(cls.method or method)} "
                             "has none")
        linear = set(options) <= {"numerical_damping"}
        if options and not (linear or cls.large_deformation
                            or (cls is DirectSimulator and large_deformation is True)):
            raise ModelError(f"DirectSimulator got {', '.join(sorted(options))}: those options are for "
                             "large_deformation=True")
        if cls is DirectSimulator:
            cls = _METHOD_CLASS[validate.choice(method, "method", METHODS)]
            if validate.flag(large_deformation, "large_deformation"):
                if cls is not NewmarkSimulator:
                    raise ModelError("large_deformation=True runs Newton inside implicit Newmark: use method='newmark' "
                                     "(a shell's massless rotations have no explicit update)")
                cls = _large_deformation_class(model, options.get("solver"))
        obj = super().__new__(cls)
        obj._settings = dict(options)  # what carry_over builds its copy with
        return obj

    _nonlinear: type | None = None  # the Newton step's class (rtfem.drivers.nonlinear_newmark registers it)

    def __init__(self, model, dt: float, damping: Damping | None = None, *, method: str | None = None,
                 large_deformation: bool | None = None) -> None:
        if method is not None and method != self.method:
            raise ModelError(f"method={validate.show(method)} given to {type(self).__name__}, which is {self.method!r}")
        if large_deformation is not None and bool(large_deformation) != self.large_deformation:
            raise ModelError(f"large_deformation={validate.show(large_deformation)} given to {type(self).__name__}; "
                             "build it with rt.DirectSimulator(model, dt, damping, large_deformation=...)")
        self.model = check_model(model)
        self.dt = check_dt(dt)
        self.damping = check_damping(damping)
        self.n_nodes = model.n_nodes
        model.check_restrained()
        self._supports = getattr(model, "supports_version", 0)
        self.time = 0.0
        self.steps = 0
        self._fingerprint: str | None = None

    def _check_supports(self) -> None:
        check_supports(self.model, self._supports, type(self).__name__)

    def run(self, forces, n_steps: int) -> None:
        """``n_steps`` steps under the same forces."""
        n_steps = self._n_steps(n_steps)
        self._as_array(forces)
        for _ in range(n_steps):
            self.step(forces)

    _solved: np.ndarray  # the global dofs of the state vector, sorted (set by each integrator)

    def _node_rows(self, node: int) -> tuple[np.ndarray, np.ndarray]:
        """Positions of the node's free translations in the state vector, and their directions."""
        pos = self._rows_of(np.array([node]))[0]
        ok = pos >= 0
        return pos[ok], np.flatnonzero(ok)

    def _rows_of(self, nodes: np.ndarray) -> np.ndarray:
        """(k, 3) positions of the nodes' translations in the state vector; -1 where held."""
        want = np.stack([self.model.translation_dofs(int(i)) for i in nodes.tolist()]).reshape(-1, 3)
        pos = np.minimum(np.searchsorted(self._solved, want), self._solved.size - 1)
        return np.where(self._solved[pos] == want, pos, -1)

    def _gather(self, values: np.ndarray, pos: np.ndarray) -> np.ndarray:
        """Rows of a state vector (n_solved,) or column block (n_solved, 3) at the positions ``pos``
        (:meth:`_rows_of`), zero where held: (k, 3) or (k, 3, 3)."""
        held = (pos < 0).reshape(pos.shape + (1,) * (values.ndim - 1))
        return np.where(held, 0.0, values[np.maximum(pos, 0)])

    def _unit_response(self, solve, node: int) -> np.ndarray:
        """(n_solved, 3) state-vector response ``solve(E)`` to unit forces on the node's three
        directions (zero columns for held directions)."""
        return self._unit_responses(solve, [node])[0]

    def _unit_responses(self, solve, nodes) -> list[np.ndarray]:
        """:meth:`_unit_response` of several nodes, from one multi-column ``solve``."""
        held = [self._node_rows(n) for n in nodes]
        E = np.zeros((self._solved.size, sum(rows.size for rows, _ in held)))
        at = 0
        for rows, _ in held:
            E[rows, at + np.arange(rows.size)] = 1.0
            at += rows.size
        X = solve(E).reshape(self._solved.size, -1) if E.shape[1] else E
        out, at = [], 0
        for rows, dirs in held:
            cols = np.zeros((self._solved.size, 3))
            cols[:, dirs] = X[:, at:at + rows.size]
            out.append(cols)
            at += rows.size
        return out

    def _block(self, nodes, loaded, columns) -> np.ndarray:
        """(3k, 3l) compliance block from ``columns(j)``: the state-vector response (n_solved, 3)
        to unit forces on node j's three directions (zero columns where held)."""
        nodes = validate.nodes(nodes, self.n_nodes)
        loaded = nodes if loaded is None else validate.nodes(loaded, self.n_nodes)
        pos = self._rows_of(nodes)
        W = np.zeros((3 * nodes.size, 3 * loaded.size))
        for b, j in enumerate(loaded.tolist()):
            W[:, 3 * b:3 * b + 3] = self._gather(columns(j), pos).reshape(-1, 3)
        return W

    def displacements(self) -> np.ndarray:
        return self.model.nodal_translations(self._u, self._solved)

    def displacement(self, node: int) -> np.ndarray:
        return self.displacements()[self._node(node)]

    def _state_changed(self) -> None:
        """Called after reset/set_state (caches of the old state are dropped)."""

    def reset(self) -> None:
        for name in self._state:
            getattr(self, name)[:] = 0.0
        self._state_changed()
        self.time = 0.0
        self.steps = 0

    def get_state(self) -> dict[str, np.ndarray]:
        """A copy of the state (solved-dof vectors and the step count)."""
        out = {name[1:]: getattr(self, name).copy() for name in self._state}
        out["steps"] = np.array(self.steps)
        return out

    def set_state(self, state: Mapping[str, np.ndarray]) -> None:
        """Restore a state from :meth:`get_state`; checked whole before anything changes."""
        names = self._state
        if not isinstance(state, Mapping) or set(state) != {n[1:] for n in names} | {"steps"}:
            raise ModelError(f"state must be a mapping with {', '.join(n[1:] for n in names)} and steps, as get_state() "
                             "returns")
        arrays = {}
        for name in names:
            a = validate.real_array(state[name[1:]], f"state[{name[1:]!r}]", 1)
            if a.shape != getattr(self, name).shape:
                raise ModelError(f"state[{name[1:]!r}] must have shape {getattr(self, name).shape}, got {a.shape}")
            arrays[name] = a
        steps = state["steps"]
        steps = validate.count(steps[()] if isinstance(steps, np.ndarray) else steps, "state['steps']", 0)
        for name, a in arrays.items():
            setattr(self, name, a.copy())
        self._state_changed()
        self.steps = steps
        self.time = steps * self.dt

    def carry_over(self, model, transfer, *, into=None) -> "DirectSimulator":
        """This driver carried over to ``model``, a remeshed copy of its model (``rt.cut``'s): a driver
        of the same class and settings holding this one's state, node by node through the remesh's
        interpolation (displacements, velocities, accelerations interpolated; remembered loads shared
        among a node's copies by lumped mass: see :mod:`rtfem.drivers.carry`). This driver is left as
        it was.

        Parameters
        ----------
        model : the remeshed model (same kind, element and material).
        transfer : ``cut_info.transfer()``, the sparse (model.n_nodes, n_nodes) interpolation from this
            model's nodes; or (model.n_nodes,) integers, the node each new node copies.
        into : a driver this call returned before on the same ``model``: it only takes the state
            now (the expensive build done ahead, on another thread; the state mapped at the swap). A
            large-deformation driver's factor, made there by ``into.factorize()``, is kept (that of the
            state it was made at: a lagged factor); else the new driver factorizes at the reference
            carried (to its own model, it steps on bit for bit).

        Returns
        -------
        the new driver.

        Raises
        ------
        ModelError
            A transfer of the wrong shape or range, or one that does not land this model's nodes on
            the new model's (another cut's); a model of another kind or material; a viscoelastic
            law's history (not carried yet); ``into`` built on another model, or of another class or
            dt.
        """
        from .carry import carry_over

        return carry_over(self, model, transfer, into)

    @property
    def fingerprint(self) -> str:
        """The hash of the model's mesh."""
        from ..reduction.modal import mesh_fingerprint

        if self._fingerprint is None:
            self._fingerprint = mesh_fingerprint(self.model.mesh)
        return self._fingerprint


def _numerical_damping(value) -> float:
    """HHT's -alpha, checked: a number in [0, 1/3]."""
    v = validate.number(value, "numerical_damping", "a number in [0, 1/3]")
    if not 0.0 <= v <= 1.0 / 3.0:
        raise ModelError(f"numerical_damping={validate.show(value)} must be in [0, 1/3] (HHT's -alpha; "
                         "0 is the average-acceleration rule)")
    return v


class NewmarkSimulator(DirectSimulator):
    """Implicit Newmark on the full model (Eq. 12-15): the effective stiffness
    K^ = c0 M + (1 - d)(c1 B + K) is factorized once; forces act at the end of the step.

    ``numerical_damping`` d = 0 (default) is the paper's average-acceleration rule, which keeps the
    energy of every mode, resolved or not. d > 0 is Hilber-Hughes-Taylor's alpha method (alpha = -d,
    beta = (1 + d)^2 / 4, gamma = 1/2 + d; second order): M a_{n+1} + (1 - d)(B v_{n+1} + K u_{n+1}
    - F_{n+1}) + d (B v_n + K u_n - F_n) = 0, which damps the modes the step does not resolve and
    leaves the resolved ones. Contact needs it: a rigid tool's unilateral constraint kicks the
    touched nodes' unresolved modes every time the contact set changes, and the average-
    acceleration rule keeps them ringing (a sphere on the 16 x 16 plate at dt = 0.01 s: the force
    still swings by 440 % of itself over the sixth second; with d = 0.1 it settles to the
    quasi-static force, tests/verification/test_tool_contact.py).

    Parameters
    ----------
    model, dt, damping : as :class:`~rtfem.DirectSimulator`.
    numerical_damping : HHT's d in 0 .. 1/3 (default 0: average acceleration).

    Raises
    ------
    ModelError
        As :class:`~rtfem.DirectSimulator`; d outside 0 .. 1/3.
    SolverError
        The effective stiffness cannot be factorized (a mechanism).
    """

    method = "newmark"
    _state = ("_u", "_v", "_a")

    def __init__(self, model, dt: float, damping: Damping | None = None, *, method: str | None = None,
                 large_deformation: bool | None = None, numerical_damping: float = 0.0) -> None:
        super().__init__(model, dt, damping, method=method, large_deformation=large_deformation)
        model = self.model
        d = self.numerical_damping = _numerical_damping(numerical_damping)
        self._w = 1.0 - d  # the weight of the step's end in the HHT equation
        K, dofs = model.constrained_stiffness()
        M, _ = model.constrained_mass()
        self._solved = dofs
        B = self.damping.matrix(M, K)
        self._gamma = 0.5 + d
        self._c = newmark_constants(self.dt, (1 + d) ** 2 / 4, self._gamma)
        c0, c1 = self._c[0], self._c[1]
        Khat = (self._w * (K + c1 * B) + c0 * M).tocsc()
        self._M = sp.csr_matrix(M)
        self._B = sp.csr_matrix(B) if sp.issparse(B) else None
        self._K = sp.csr_matrix(K) if d > 0 else None
        self._fac = factorize(Khat, spd=True, what="the Newmark effective stiffness", order=lambda: model.dof_order(dofs))
        nd = dofs.size
        self._u, self._v, self._a = np.zeros(nd), np.zeros(nd), np.zeros(nd)
        if d > 0:
            self._state = ("_u", "_v", "_a", "_f")
            self._f = np.zeros(nd)  # the last step's forces (HHT weighs them in the next step)
        self._cols: dict[int, np.ndarray] = {}  # node -> (1 - d) K^-1 columns (n_solved, 3), zero where held
        self._free: tuple[int, np.ndarray] | None = None  # (step, no-new-load solution) of predict()

    def _rhs_free(self) -> np.ndarray:
        c0, c1, c2, c3, c4, c5 = self._c
        u, v, a = self._u, self._v, self._a
        rhs = self._M @ (c0 * u + c2 * v + c3 * a)
        if self._B is not None:
            rhs += self._w * (self._B @ (c1 * u + c4 * v + c5 * a))
        if self._K is not None:  # HHT: the step's start, weighed by d
            d = self.numerical_damping
            rhs += d * (self._f - self._K @ u - (self._B @ v if self._B is not None else 0.0))
        return rhs

    def _unit_solve(self, E: np.ndarray) -> np.ndarray:
        """Responses of the step's end to unit forces: (1 - d) K^-1 E."""
        X = self._fac.solve(E)
        return X if self._w == 1.0 else self._w * X

    def prepare(self, nodes) -> None:
        """Solve the step-compliance columns of the nodes that will be loaded (the missing ones in
        multi-column solves of at most 64 MB of right-hand sides)."""
        missing = [n for n in dict.fromkeys(validate.nodes(nodes, self.n_nodes).tolist()) if n not in self._cols]
        per = max(1, (64 * 2**20) // (8 * 3 * self._solved.size))
        for start in range(0, len(missing), per):
            chunk = missing[start:start + per]
            self._cols.update(zip(chunk, self._unit_responses(self._unit_solve, chunk)))

    def predict(self, node: int) -> np.ndarray:
        """Displacement (3,) of ``node`` after one more step with no new load (one sparse solve).

        With :meth:`step_compliance` W, a step under a force f on that node gives
        u(k+1) = predict(node) + W f; the following :meth:`step` reuses this solve when its
        loads are on nodes whose compliance is known.
        """
        rows, dirs = self._node_rows(self._node(node))
        out = np.zeros(3)
        out[dirs] = self._free_solution()[rows]
        return out

    def _free_solution(self) -> np.ndarray:
        """The next step's state with no new load (one solve per step, kept for the step)."""
        if self._free is None or self._free[0] != self.steps:
            self._free = (self.steps, self._fac.solve(self._rhs_free()))
        return self._free[1]

    def predict_at(self, nodes) -> np.ndarray:
        """(k, 3) :meth:`predict` of ``nodes`` (the same one solve)."""
        return self._gather(self._free_solution(), self._rows_of(validate.nodes(nodes, self.n_nodes)))

    def step_compliances(self, nodes, loaded=None) -> np.ndarray:
        """The cross compliances (3k, 3l) of a contact set: blocks of K_eff^-1 (three solves per
        loaded node the first time)."""
        def columns(j):
            self.step_compliance(j)
            return self._cols[j]
        return self._block(nodes, loaded, columns)

    def step_compliance(self, node: int) -> np.ndarray:
        """W (3x3): displacement of ``node`` after one step per unit force on it (K^-1 block)."""
        node = self._node(node)
        if node not in self._cols:
            self._cols[node] = self._unit_response(self._unit_solve, node)
        return self._gather(self._cols[node], self._rows_of(np.array([node])))[0]

    def _superposed(self, forces) -> np.ndarray | None:
        """The next step by superposition on predict()'s solve, when every load has its columns."""
        if self._free is None or self._free[0] != self.steps:
            return None
        if forces is None:
            return self._free[1].copy()
        if not isinstance(forces, Mapping):
            return None
        un = self._free[1].copy()
        for node, f in forces.items():
            i = self._node(node)
            if i not in self._cols:
                return None
            un += self._cols[i] @ self._vec(node, f)
        return un

    def step(self, forces=None) -> None:
        """Advance one step; ``forces`` act at the end of the step."""
        self._check_supports()
        c0, c2, c3 = self._c[0], self._c[2], self._c[3]
        u, v, a = self._u, self._v, self._a
        un = self._superposed(forces)
        F = None
        if un is None:
            F = self.model.force_vector(self._as_array(forces), warn=False)[self._solved]
            un = self._fac.solve(self._w * F + self._rhs_free())
        if self._K is not None:  # HHT keeps this step's forces for the next
            self._f = F if F is not None else self._loads_vector(forces)
        self._free = None
        an = c0 * (un - u) - c2 * v - c3 * a
        self._v = newmark_velocity(v, a, an, self.dt, self._gamma)
        self._u, self._a = un, an
        self.steps += 1
        self.time = self.steps * self.dt

    def _loads_vector(self, forces) -> np.ndarray:
        """The solved-dof force vector of a {node: force} mapping (``_superposed``'s loads), or zero."""
        F = np.zeros(self._solved.size)
        for node, f in (forces or {}).items():
            rows, dirs = self._node_rows(self._node(node))
            F[rows] = self._vec(node, f)[dirs]
        return F

    def _state_changed(self) -> None:
        self._free = None


class CentralDifferenceSimulator(DirectSimulator):
    """Explicit central differences on the condensed system (Eq. 5) with diagonal mass and
    mass-proportional damping: m u_{k+1} (1 + dt a/2) = dt^2 (F_k - K_c u_k) + 2 m u_k
    - m (1 - dt a/2) u_{k-1}. Forces act at the start of the step; stable for dt <= T_n / pi.

    Parameters
    ----------
    model, dt, damping : as :class:`~rtfem.DirectSimulator`; the model's constraints must be
        "elimination" (a penalty puts a huge eigenvalue in every fixed massed dof) and the damping
        mass-proportional (a diagonal B).

    Raises
    ------
    ModelError
        As :class:`~rtfem.DirectSimulator`; beta or modal damping, penalty constraints, or a dt
        above the stability limit T_n / pi (the message gives the limit).
    """

    method = "central"
    _state = ("_u", "_u_old")

    def __init__(self, model, dt: float, damping: Damping | None = None, *, method: str | None = None,
                 large_deformation: bool | None = None) -> None:
        super().__init__(model, dt, damping, method=method, large_deformation=large_deformation)
        model, dt = self.model, self.dt
        if self.damping.beta != 0 or self.damping.is_modal_only:
            raise ModelError("the central-difference method needs diagonal damping: use Damping(alpha=...) only")
        if model.constraints != "elimination":
            raise ModelError("the central-difference method needs fixes by elimination (penalty dofs are far too stiff)")
        require_lumped_mass(model, "the central-difference method")
        c = model.condensation()
        self._Kc = c.apply
        self._solved = c.t
        self._mt = model.mass_diagonal[c.t]
        if np.any(self._mt <= 0):
            raise ModelError("the central-difference method needs mass on every free translation")
        self.critical_dt, self.omega_max = self._stability_limit()
        if dt > self.critical_dt:
            raise ModelError(
                f"central differences are unstable for dt = {dt:.3g} s: the limit is T_n/pi = "
                f"{self.critical_dt:.3g} s (highest frequency {self.omega_max / 2 / np.pi:.4g} Hz, "
                f"shortest period T_n = {2 * np.pi / self.omega_max:.3g} s). Use dt <= {self.critical_dt:.3g} "
                "or method='newmark'"
            )
        al = self.damping.alpha
        self._gain = dt * dt / (self._mt * (1 + 0.5 * dt * al))  # u_{k+1} per unit force at step k
        self._keep = 2.0 / (1 + 0.5 * dt * al)
        self._back = (1 - 0.5 * dt * al) / (1 + 0.5 * dt * al)
        self._u = np.zeros(self._solved.size)
        self._u_old = np.zeros(self._solved.size)

    def _stability_limit(self) -> tuple[float, float]:
        """dt_crit = 2 / w_max = T_n / pi, with w_max from Lanczos on M^-1/2 K_c M^-1/2."""
        s = 1.0 / np.sqrt(self._mt)
        op = spla.LinearOperator((s.size, s.size), matvec=lambda x: s * self._Kc(s * x), dtype=float)
        lam = spla.eigsh(op, k=1, which="LA", tol=1e-6, return_eigenvectors=False)[0]
        w = math.sqrt(lam * (1 + 1e-5))  # a hair above: the Lanczos estimate is from below
        return 2.0 / w, w

    def _free_update(self) -> np.ndarray:
        return self._keep * self._u - self._back * self._u_old - self._gain * self._Kc(self._u)

    def predict(self, node: int) -> np.ndarray:
        """Displacement (3,) of ``node`` after one more step with no load (one K_c product)."""
        rows, dirs = self._node_rows(self._node(node))
        out = np.zeros(3)
        out[dirs] = self._free_update()[rows]
        return out

    def predict_at(self, nodes) -> np.ndarray:
        """(k, 3) :meth:`predict` of ``nodes``."""
        return self._gather(self._free_update(), self._rows_of(validate.nodes(nodes, self.n_nodes)))

    def step_compliances(self, nodes, loaded=None) -> np.ndarray:
        """The cross compliances (3k, 3l): the explicit step moves only the loaded nodes."""
        def columns(j):
            out = np.zeros((self._solved.size, 3))
            rows, dirs = self._node_rows(j)
            out[rows, dirs] = self._gain[rows]
            return out
        return self._block(nodes, loaded, columns)

    def step_compliance(self, node: int) -> np.ndarray:
        """W (3x3) = dt^2 / (m (1 + dt a / 2)) on the node's free translations: the explicit step
        moves only the loaded node."""
        rows, dirs = self._node_rows(self._node(node))
        W = np.zeros((3, 3))
        W[dirs, dirs] = self._gain[rows]
        return W

    def step(self, forces=None) -> None:
        """Advance one step; ``forces`` act at the start of the step."""
        self._check_supports()
        F = self.model.force_vector(self._as_array(forces), warn=False)
        un = self._free_update() + self._gain * F[self._solved]
        self._u_old, self._u = self._u, un
        self.steps += 1
        self.time = self.steps * self.dt


_METHOD_CLASS = {"newmark": NewmarkSimulator, "central": CentralDifferenceSimulator}


LARGE_DEFORMATION_SOLVERS = ("lagged", "newton")


def _large_deformation_class(model, solver):
    """The class of DirectSimulator(..., large_deformation=True, solver=...): "lagged" (chord iterations
    on a lagged tangent: :class:`~rtfem.drivers.lagged_newmark.LaggedNewmarkSimulator`, the default for
    a solid) or "newton" (Newton every step: the reference, and the default for a shell, whose
    rotations the fast kernels do not take)."""
    if solver is None:
        solver = "lagged" if getattr(model, "dofs_per_node", 6) == 3 else "newton"
    solver = validate.choice(solver, "solver", LARGE_DEFORMATION_SOLVERS)
    return DirectSimulator._nonlinear._solvers[solver]
