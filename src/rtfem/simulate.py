"""Run-time dynamics: the Driver protocol and the reduced ModalSimulator (the full-order
simulators are in :mod:`rtfem.fullorder`).

ModalSimulator integrates the decoupled modal equations x_i'' + alpha_i x_i' + w_i^2 x_i = f_i
(Eq. 9-10) and maps back U = Phi_r X (Eq. 11). Integrators:

* ``"exact"`` (default): the exact discrete-time update of each damped oscillator for a force
  held over the step (zero-order hold). No period error at any dt, every damping regime.
* ``"newmark"``: the paper's average-acceleration Newmark (eta = 1/4, delta = 1/2, Eq. 12-15:
  K^ U^ = F^, printed backwards in the paper), with the force taken at the end of the step.

Both are written as one vectorized two-state recursion per step,
[x, v]_{k+1} = C1 * [x, v]_k + C2 * [v, x]_k + G1 f_{k+1} (+ G0 f_k for Newmark),
with coefficients precomputed, so a step costs a handful of numpy operations on r-vectors
and allocates no arrays.
"""

from __future__ import annotations

import math
from typing import Mapping, Protocol, runtime_checkable

import numpy as np

from . import kernels, validate
from .errors import ModelError
from .material import Damping
from .modal import ModalBasis
from .oscillator import transition

__all__ = ["Driver", "DRIVER_MEMBERS", "as_driver", "displacements_at", "predictions", "step_compliances", "prepare",
           "ModalSimulator", "StaticCorrection", "newmark_coefficients", "newmark_constants"]

_NEWMARK_BETA = 0.25  # eta in the paper
_NEWMARK_GAMMA = 0.5  # delta in the paper


def check_dt(dt) -> float:
    """A driver's time step in seconds (the rule every driver applies)."""
    return validate.time_step(dt, "dt")


def check_damping(damping) -> Damping:
    """A driver's damping: an rt.Damping, or None for none."""
    if damping is None:
        return Damping()
    if not isinstance(damping, Damping):
        raise ModelError(f"damping={validate.show(damping)} must be an rt.Damping (or None)")
    return damping


def newmark_constants(dt: float, beta: float = _NEWMARK_BETA, gamma: float = _NEWMARK_GAMMA) -> tuple[float, ...]:
    """The six constants of Newmark's method (Bathe's a0..a5; the paper's Eq. 12-15):
    c0 = 1/(beta dt^2), c1 = gamma/(beta dt), c2 = 1/(beta dt), c3 = 1/(2 beta) - 1,
    c4 = gamma/beta - 1, c5 = dt/2 (gamma/beta - 2); the one copy used by the modal and
    the full-order Newmark updates."""
    return (1.0 / (beta * dt * dt), gamma / (beta * dt), 1.0 / (beta * dt), 1.0 / (2 * beta) - 1.0,
            gamma / beta - 1.0, 0.5 * dt * (gamma / beta - 2.0))


def newmark_velocity(v, acc, acc_new, dt: float, gamma: float = _NEWMARK_GAMMA):
    """v_{t+dt} = v_t + dt ((1 - gamma) a_t + gamma a_{t+dt})."""
    return v + dt * ((1 - gamma) * acc + gamma * acc_new)


def newmark_coefficients(lam, a, dt, beta: float = _NEWMARK_BETA, gamma: float = _NEWMARK_GAMMA):
    """Newmark's scalar update as a linear map (Eq. 12-15).

    For x'' + a x' + lam x = f, with the acceleration at t eliminated through the equation of
    motion at t (a_t = f_t - a v_t - lam x_t), returns Phi (..., 2, 2), G0 (..., 2), G1 (..., 2):
    [x, v]_{t+dt} = Phi [x, v]_t + G0 f_t + G1 f_{t+dt}.
    """
    lam, a = np.broadcast_arrays(np.asarray(lam, float), np.asarray(a, float))
    c0, c1, c2, c3, c4, c5 = newmark_constants(dt, beta, gamma)
    khat = lam + a * c1 + c0

    def advance(x, v, f0, f1):
        acc = f0 - a * v - lam * x
        fhat = f1 + c0 * x + c2 * v + c3 * acc + a * (c1 * x + c4 * v + c5 * acc)
        xn = fhat / khat
        an = c0 * (xn - x) - c2 * v - c3 * acc
        vn = newmark_velocity(v, acc, an, dt, gamma)
        return xn, vn

    one, zero = np.ones_like(lam), np.zeros_like(lam)
    cols = [advance(one, zero, zero, zero), advance(zero, one, zero, zero)]
    Phi = np.stack([np.stack([cols[0][0], cols[1][0]], -1), np.stack([cols[0][1], cols[1][1]], -1)], -2)
    G0 = np.stack(advance(zero, zero, one, zero), -1)
    G1 = np.stack(advance(zero, zero, zero, one), -1)
    return Phi, G0, G1


@runtime_checkable
class Driver(Protocol):
    """What Probe, Grasp, HapticLoop and the viewer ask of anything that advances in time.

    ``step(forces)`` advances one step of ``dt`` under ``forces`` ({node: (fx, fy, fz)} or an
    (n, 3) array; None for no load) and, like every member, refuses bad input before changing
    any state. ``predict(node)`` is where the node would be after one more step with no load and
    ``step_compliance(node)`` the 3x3 W with u(k+1) = predict(node) + W f for a force f on it.
    Implemented by :class:`ModalSimulator`, the full-order simulators of :class:`DirectSimulator`
    and the impedance map's driver (:meth:`ImpedanceMap.as_driver`); a user's own class with
    these members works with every consumer. Optional, with a fallback on the members:
    ``displacements_at(nodes)`` (a batched query), ``prepare(nodes)`` (precompute what loads on
    those nodes will need; see :func:`prepare`), ``fingerprint`` (the mesh hash, checked by the
    consumers when present), ``predict_at(nodes)`` ((k, 3) predictions, batched) and
    ``step_compliances(nodes, loaded)`` (the cross compliances of a contact set: block (a, b) is
    d u_a(k+1) / d f_b; see :func:`step_compliances`).
    """

    dt: float
    time: float
    n_nodes: int

    def step(self, forces=None) -> None: ...
    def predict(self, node: int) -> np.ndarray: ...
    def step_compliance(self, node: int) -> np.ndarray: ...
    def displacement(self, node: int) -> np.ndarray: ...
    def displacements(self) -> np.ndarray: ...
    def reset(self) -> None: ...
    def get_state(self) -> dict: ...
    def set_state(self, state) -> None: ...


DRIVER_MEMBERS = ("step", "predict", "step_compliance", "displacement", "displacements", "reset", "get_state",
                  "set_state", "dt", "time", "n_nodes")


def as_driver(obj, what: str = "probe"):
    """``obj`` as a Driver: objects with ``as_driver()`` (an ImpedanceMap) are converted; anything
    lacking a protocol member is refused, naming what it lacks."""
    if hasattr(obj, "as_driver") and callable(obj.as_driver):
        obj = obj.as_driver()
    missing = [m for m in DRIVER_MEMBERS if not hasattr(obj, m)]
    if missing:
        raise ModelError(f"the {what} drives a ModalSimulator, a Newmark DirectSimulator, an ImpedanceMap or any Driver "
                         f"(a class with {', '.join(DRIVER_MEMBERS)}); {validate.show(obj)} lacks {', '.join(missing)}")
    return obj


def rows_times(A: np.ndarray, x: np.ndarray) -> np.ndarray:
    """(k, 3, r) times (r,) -> (k, 3) as one matrix-vector product (numpy's stacked matmul of the
    (k, 3, r) array is 4-6x slower: 1.5 ms against 0.23 ms for 10,242 nodes and r = 40)."""
    return (A.reshape(-1, A.shape[-1]) @ x).reshape(-1, 3)


def prepare(driver, nodes) -> None:
    """Let the driver compute what it needs at ``nodes`` before they are loaded (its optional
    ``prepare(nodes)``: static-correction or compliance columns, impedance maps); a no-op for
    drivers without one. Consumers call it when a node is first touched, outside the force loop."""
    fn = getattr(driver, "prepare", None)
    if fn is not None:
        fn(nodes)


def displacements_at(driver, nodes: np.ndarray) -> np.ndarray:
    """(k, 3) displacements of some nodes: the driver's batched query when it has one."""
    fn = getattr(driver, "displacements_at", None)
    return fn(nodes) if fn is not None else np.asarray(driver.displacements())[nodes]


def predictions(driver, nodes: np.ndarray) -> np.ndarray:
    """(k, 3) :meth:`Driver.predict` of some nodes: the driver's batched ``predict_at`` when it has one."""
    fn = getattr(driver, "predict_at", None)
    if fn is not None:
        return fn(nodes)
    return np.array([driver.predict(int(i)) for i in np.asarray(nodes).tolist()]).reshape(-1, 3)


def step_compliances(driver, nodes, loaded=None) -> np.ndarray:
    """The one-step cross compliances of a contact set, (3k, 3l): block (a, b) is the displacement
    of ``nodes[a]`` after one step per unit force on ``loaded[b]`` (default: ``nodes``), so that
    u_S(k+1) = predict_S + W_SS f_S (James & Pai's capacitance matrix).

    The driver's own ``step_compliances`` when it has one; otherwise, for one node its
    ``step_compliance``, and for a set the block is measured by stepping the driver from its
    saved state under unit loads (3 l steps, state restored: a user's driver needs only the
    protocol)."""
    nodes = validate.nodes(nodes, driver.n_nodes)
    loaded = nodes if loaded is None else validate.nodes(loaded, driver.n_nodes)
    fn = getattr(driver, "step_compliances", None)
    if fn is not None:
        return fn(nodes, loaded)
    if nodes.size == 1 and loaded.size == 1 and nodes[0] == loaded[0]:
        return np.asarray(driver.step_compliance(int(nodes[0])), dtype=float)
    state = driver.get_state()
    base = predictions(driver, nodes).reshape(-1)
    W = np.zeros((3 * nodes.size, 3 * loaded.size))
    try:
        for b, j in enumerate(loaded.tolist()):
            for k in range(3):
                f = [0.0, 0.0, 0.0]
                f[k] = 1.0
                driver.set_state(state)
                driver.step({j: tuple(f)})
                W[:, 3 * b + k] = displacements_at(driver, nodes).reshape(-1) - base
    finally:
        driver.set_state(state)
    return W


class ForceInput:
    """For driver classes: the two load formats, {node: (fx, fy, fz)} or an (n, 3) array, and the
    node and count rules, checked the same way in every driver."""

    n_nodes: int

    def _as_array(self, forces) -> np.ndarray:
        if forces is None:
            return np.zeros((self.n_nodes, 3))
        return validate.forces(forces, self.n_nodes)

    def _node(self, node) -> int:
        return validate.node(node, self.n_nodes)

    @staticmethod
    def _vec(node, f) -> np.ndarray:
        return validate.vector(f, f"force on node {node}", 3)

    @staticmethod
    def _n_steps(n_steps) -> int:
        return validate.count(n_steps, "n_steps", 0, 10**9)

    def _parse_loads(self, forces: Mapping) -> tuple[np.ndarray, np.ndarray]:
        """{node: f} as (nodes, (k, 3)): in one pass where it can (a grasp loads tens of nodes per
        tick), else entry by entry, which names a bad entry."""
        parsed = self._load_arrays(forces)
        if parsed is not None:
            return parsed
        items = [(self._node(k), self._vec(k, f)) for k, f in forces.items()]
        return np.array([i for i, _ in items], dtype=np.int64), np.array([f for _, f in items]).reshape(-1, 3)

    def _load_arrays(self, forces: Mapping):
        """A {node: f} mapping as (nodes (k,), forces (k, 3)) in one pass, when every key is a plain
        int node on the mesh and every value three finite numbers (a contact patch's or a grasp's
        loads); None for anything else, which the caller parses entry by entry (naming a bad one)."""
        nodes = list(forces)
        if not all(type(v) is int for v in nodes):
            return None
        try:
            F = np.array(list(forces.values()), dtype=float)
        except (TypeError, ValueError):
            return None
        idx = np.array(nodes, dtype=np.int64)
        if F.shape != (idx.size, 3) or not np.isfinite(F).all() or idx.min() < 0 or idx.max() >= self.n_nodes:
            return None
        return idx, F


class StaticCorrection:
    """The static correction of a driver on a truncated basis (mode-acceleration method): the
    displacement the basis cannot hold, D f with D = K^-1 - P G P^T, added quasi-statically for
    the current loads f. P (3n, r) are the basis rows of the node translations and G (r,) the
    basis's static compliance (1 / w^2 for mass-normalized modes; 1 for a stiffness-orthonormal
    basis), so that at small load P q + D f is the exact linear static answer K^-1 f. The driver
    calls :meth:`_init_correction` and keeps ``_loads`` ({node: f}) or ``_load_array`` ((n, 3))
    as its last step's loads."""

    static_correction = False

    def _init_correction(self, on: bool, model, rows: np.ndarray, weights: np.ndarray) -> None:
        self.static_correction = bool(on)
        self._sc_model, self._sc_rows, self._sc_weights = model, rows, weights
        self._sc_supports = getattr(model, "supports_version", 0)  # the supports the basis was computed on
        self._loads: dict[int, np.ndarray] = {}
        self._load_array: np.ndarray | None = None
        self._D: dict[int, np.ndarray] = {}
        self._patch_rows: tuple | None = None  # (nodes, loaded nodes, their D rows at nodes) of the last patch read
        self._D_array: dict[bytes, np.ndarray] = {}  # static corrections of (n, 3) loads, last few kept

    def _correction_column(self, node: int) -> np.ndarray:
        """D for the 3 load directions of ``node``: (n, 3, 3) (displacement, load direction)."""
        D = self._D.get(node)
        if D is None:
            self._check_correction_supports()
            cols = [self._sc_model.unit_load_response(node, k) for k in range(3)]
            Kinv = np.stack(cols, axis=2)
            D = Kinv - self._modal_statics(np.array([node]))[0]
            self._D[node] = D
        return D

    def _check_correction_supports(self) -> None:
        """The correction's solves use the model's current supports: refuse them once the model
        was fixed otherwise than the basis was computed on (the two would not match)."""
        from .model import check_supports

        check_supports(self._sc_model, self._sc_supports, f"{type(self).__name__}'s static correction")

    def _modal_statics(self, nodes: np.ndarray) -> np.ndarray:
        """P G P^T for unit loads on ``nodes``: (k, n, 3, 3), one matrix product."""
        P = self._sc_rows
        Pk = P.reshape(-1, 3, P.shape[1])[nodes].reshape(3 * nodes.size, -1)
        G = (P * self._sc_weights) @ Pk.T
        return G.reshape(-1, 3, nodes.size, 3).transpose(2, 0, 1, 3)

    def _array_correction(self, F: np.ndarray) -> np.ndarray:
        """D F for an (n, 3) load: one static solve per distinct load, kept for the next call
        (a load schedule repeats a few patterns; haptic loads are dicts on prepared nodes)."""
        key = F.tobytes()
        hit = self._D_array.get(key)
        if hit is None:
            self._check_correction_supports()
            Kinv_f = self._sc_model.solve_static(F, warn=False)
            P = self._sc_rows
            modal = (P @ ((P.T @ F.reshape(-1)) * self._sc_weights)).reshape(-1, 3)
            if len(self._D_array) >= 8:
                self._D_array.pop(next(iter(self._D_array)))
            hit = self._D_array[key] = Kinv_f - modal
        return hit

    def prepare(self, nodes) -> None:
        """Precompute the static-correction columns of the nodes that will be loaded (the missing
        ones together: multi-column solves when the model has ``unit_load_responses``)."""
        nodes = validate.nodes(nodes, self.n_nodes)
        if not self.static_correction:
            return
        missing = np.array([n for n in dict.fromkeys(nodes.tolist()) if n not in self._D], dtype=np.int64)
        batched = getattr(self._sc_model, "unit_load_responses", None)
        if missing.size < 2 or batched is None:
            for n in missing.tolist():
                self._correction_column(n)
            return
        self._check_correction_supports()
        Kinv = batched(missing)  # (k, n, 3, 3)
        modal = self._modal_statics(missing)
        for i, n in enumerate(missing.tolist()):
            self._D[n] = Kinv[i] - modal[i]

    def _add_correction(self, u: np.ndarray) -> None:
        """Add the static correction of the current loads to the field u (n, 3), in place (a
        float32 field takes each float64 term rounded)."""
        if self._load_array is not None:
            u += self._array_correction(self._load_array)
        for node, f in self._loads.items():
            u += self._correction_column(node) @ f

    def _point_correction(self, i: int):
        """The static correction (3,) of the current loads at node i, or None with no loads."""
        if self._load_array is not None:
            return self._array_correction(self._load_array)[i]
        c = None
        for j, f in self._loads.items():
            c = self._correction_column(j)[i] @ f if c is None else c + self._correction_column(j)[i] @ f
        return c

    def _correction_at(self, nodes: np.ndarray, u: np.ndarray) -> np.ndarray:
        """u (k, 3) at ``nodes`` plus the static correction of the current loads there."""
        if self._load_array is not None:
            return u + self._array_correction(self._load_array)[nodes]
        if len(self._loads) > 2:  # a contact patch, asked again about the same nodes next tick
            G = self._gathered(nodes)
            return u + (G @ np.array(list(self._loads.values())).reshape(-1)).reshape(-1, 3)
        for j, f in self._loads.items():
            u = u + self._correction_column(j)[nodes] @ f
        return u

    def _correction_block(self, nodes: np.ndarray, loaded: np.ndarray) -> np.ndarray:
        """D_ab (3k, 3l) for ``nodes`` against ``loaded`` (columns computed the first time, as
        :meth:`prepare` does)."""
        if nodes.size < loaded.size and all(v in self._D for v in nodes.tolist()):
            # D is symmetric (K^-1 minus the basis's part): rows of a few nodes against many loads
            # are the transposed columns of those few (one gather each, not one per load)
            return np.concatenate([self._D[j][loaded].reshape(-1, 3) for j in nodes.tolist()], axis=1).T
        return np.concatenate([self._correction_column(j)[nodes].reshape(-1, 3) for j in loaded.tolist()], axis=1)

    def _gathered(self, nodes: np.ndarray) -> np.ndarray:
        """The loaded nodes' static-correction columns at ``nodes`` as one (3k, 3 loads) matrix, kept
        while the loaded nodes and the nodes asked about stay the same (a tool resting on a patch:
        one matrix-vector product instead of a gather per load each tick)."""
        keys = tuple(self._loads)
        hit = self._patch_rows
        same = hit is not None and hit[0].size == nodes.size and np.array_equal(hit[0], nodes)
        if same and hit[1] == keys:
            return hit[2]
        cols = hit[3] if same and len(hit[3]) < 256 else {}  # each load's rows, for the loads to come
        for j in keys:
            if j not in cols:
                cols[j] = self._correction_column(j)[nodes].reshape(-1, 3)
        G = np.concatenate([cols[j] for j in keys], axis=1)
        self._patch_rows = (nodes.copy(), keys, G, cols) if G.size <= 4_000_000 else None
        return G


class ModalSimulator(StaticCorrection, ForceInput):
    """Reduced dynamics in modal coordinates (paper section 3).

    Parameters
    ----------
    modes : a :class:`~rtfem.modal.ModalBasis` (r modes).
    dt : time step in seconds (1e-3 for a 1 kHz haptic loop).
    damping : :class:`~rtfem.Damping` (mass-proportional, Rayleigh or modal ratios).
    integrator : "exact" (default) or "newmark".
    static_correction : add the static contribution of the truncated modes (mode-acceleration
        method, D = K^-1 - Phi_r Lambda_r^-1 Phi_r^T applied to the current loads), so that a
        few modes still give the right static deflection. Needs ``modes.model``.
    warping : rotation-aware (modal warping, Choi & Ko 2005): gives a
        :class:`~rtfem.warping.WarpedModalSimulator`, whose displacements follow each node's
        rotation and whose loads act in each node's frame. Needs ``modes.model``.
    """

    def __new__(cls, modes=None, dt=None, damping=None, *, integrator: str = "exact", static_correction: bool = False,
                warping: bool = False):
        if cls is ModalSimulator and validate.flag(warping, "warping"):
            from .warping import WarpedModalSimulator

            cls = WarpedModalSimulator
        return super().__new__(cls)

    compliance_changes = False  # step_compliance is constant (consumers may cache it)
    warping = False

    def __init__(
        self,
        modes: ModalBasis,
        dt: float,
        damping: Damping | None = None,
        *,
        integrator: str = "exact",
        static_correction: bool = False,
        warping: bool = False,
    ) -> None:
        if not isinstance(modes, ModalBasis):
            raise ModelError(f"modes must be a ModalBasis (rt.modal_analysis), got {type(modes).__name__}")
        self.modes = modes
        self.dt = check_dt(dt)
        self.damping = check_damping(damping)
        validate.choice(integrator, "integrator", ("exact", "newmark"))
        static_correction = validate.flag(static_correction, "static_correction")
        self.integrator = integrator
        self.n_nodes = modes.n_nodes
        r = modes.n_modes
        lam = modes.omega**2
        self.modal_alpha = self.damping.modal_alpha(modes.omega)
        if integrator == "exact":
            Phi, G1 = transition(lam, self.modal_alpha, self.dt)
            G0 = None
        elif integrator == "newmark":
            Phi, G0, G1 = newmark_coefficients(lam, self.modal_alpha, self.dt)
        else:
            raise ModelError(f"integrator={integrator!r}; choose 'exact' or 'newmark'")
        # [x; v]_new = C1 * [x; v] + C2 * [v; x] + G1 * f_new (+ G0 * f_old): one (8, r) array whose
        # row pairs the numpy path views and the compiled kernel takes whole
        self._coef = np.ascontiguousarray(np.vstack([Phi[:, 0, 0], Phi[:, 1, 1], Phi[:, 0, 1], Phi[:, 1, 0], G1.T,
                                                     np.zeros((2, r)) if G0 is None else G0.T]))
        self._C1, self._C2, self._G1 = self._coef[0:2], self._coef[2:4], self._coef[4:6]
        self._G0 = None if G0 is None else self._coef[6:8]
        self.compiled = kernels.HAVE_NUMBA  # the compiled point step (set False for the numpy path)
        self._phi = np.ascontiguousarray(modes.shapes)  # (n, 3, r)
        self._P = self._phi.reshape(-1, r)  # (3n, r) view
        self._fv = np.zeros(3)
        self._S = np.zeros((2, r))
        self._T1 = np.zeros((2, r))
        self._T2 = np.zeros((2, r))
        self._f = np.zeros(r)
        self._f_next = np.zeros(r)
        self._f_old = np.zeros(r)
        self._fn = np.zeros(r)
        self.time = 0.0
        self.steps = 0
        self._init_correction(static_correction, modes.model, self._P,
                              np.divide(1.0, lam, out=np.zeros_like(lam), where=lam > 0))
        self._shape_rows: tuple | None = None  # (nodes, the shapes there) of the last batched query
        if self.static_correction:
            model = modes.model
            if model is None:
                raise ModelError("static_correction needs the model: load the basis with ModalBasis.load(path, model=...)")
            if np.any(modes.omega < 1e-8 * max(modes.omega.max(), 1.0)):
                raise ModelError("static_correction needs a restrained model (this basis has rigid-body modes)")

    # ---------------------------------------------------------------- stepping
    def _modal_force(self, forces) -> None:
        """Parse ``forces`` into the modal force of the next step; on a refusal nothing changes.

        The modal force is accumulated in a scratch vector and the loads in a local dict;
        only when every entry is valid do they replace the simulator's.
        """
        out = self._f_next
        out.fill(0.0)
        loads: dict[int, np.ndarray] = {}
        load_array = None
        if forces is None:
            pass
        elif type(forces) is dict or isinstance(forces, Mapping):
            if not self._patch_force(forces, out, loads):
                fn, fv = self._fn, self._fv
                for node, f in forces.items():
                    i, fx, fy, fz = self._point(node, f)
                    fv[0], fv[1], fv[2] = fx, fy, fz
                    np.dot(fv, self._phi[i], out=fn)
                    out += fn
                    if self.static_correction:
                        loads[i] = loads.get(i, 0.0) + fv.copy()
        else:
            A = self._as_array(forces)
            np.dot(A.reshape(-1), self._P, out=out)
            if self.static_correction:
                load_array = A
        self._f, self._f_next = out, self._f
        self._loads, self._load_array = loads, load_array

    def step(self, forces=None) -> None:
        """Advance one time step under ``forces``: {node: (fx, fy, fz)} or an (n, 3) array.

        With the "exact" integrator the force is held over the step; with "newmark" it is the
        force at the end of the step (Eq. 14). Cost O(k r) for k loaded nodes.
        """
        if self.compiled and self._compiled_step(forces):
            return
        self._modal_force(forces)
        S, T1, T2 = self._S, self._T1, self._T2
        np.multiply(self._C1, S, out=T1)
        np.multiply(self._C2, S[::-1], out=T2)
        T1 += T2
        np.multiply(self._G1, self._f, out=T2)
        T1 += T2
        if self._G0 is not None:
            np.multiply(self._G0, self._f_old, out=T2)
            T1 += T2
            self._f_old[:] = self._f
        self._S, self._T1 = T1, S
        self.steps += 1
        self.time = self.steps * self.dt

    def _patch_force(self, forces, out: np.ndarray, loads: dict) -> bool:
        """A contact patch's dict (eight or more loads, plain int nodes, finite 3-vectors) into the
        modal force ``out`` and ``loads`` in one product; False (nothing written) for anything
        else, which the entry-by-entry path then parses or refuses."""
        if len(forces) < 8:
            return False
        parsed = self._load_arrays(forces)
        if parsed is None:
            return False
        idx, F = parsed
        np.dot(F.reshape(-1), self._phi[idx].reshape(3 * idx.size, -1), out=out)
        if self.static_correction:
            loads.update(zip(idx.tolist(), F))
        return True

    def _point(self, node, f) -> tuple[int, float, float, float]:
        """One load entry, checked: the node index and three finite components (inline for plain
        ints and 3-sequences of numbers, the haptic loop's case; a refusal names the entry)."""
        i = node if type(node) is int and 0 <= node < self.n_nodes else self._node(node)
        try:
            fx, fy, fz = f
            fx, fy, fz = float(fx), float(fy), float(fz)
        except (TypeError, ValueError):
            fx, fy, fz = self._vec(node, f)
        if not (math.isfinite(fx) and math.isfinite(fy) and math.isfinite(fz)):
            self._vec(node, f)  # raises with the message
        return i, fx, fy, fz

    def _compiled_step(self, forces) -> bool:
        """The step of the haptic loop in one compiled call: no load, or a dict with one load.
        False (nothing changed) for anything else; a bad load is refused before any change."""
        if forces is None:
            node, fx, fy, fz = -1, 0.0, 0.0, 0.0
        elif type(forces) is dict and len(forces) == 1:
            ((node, f),) = forces.items()
            node, fx, fy, fz = self._point(node, f)
        else:
            return False
        kernels.point_step(self._coef, self._S, self._f_old, self._phi, node, fx, fy, fz, self._G0 is not None)
        if self.static_correction:
            self._loads = {node: np.array((fx, fy, fz))} if node >= 0 else {}
            self._load_array = None
        self.steps += 1
        self.time = self.steps * self.dt
        return True

    def run(self, forces, n_steps: int) -> None:
        """``n_steps`` steps under the same forces."""
        n_steps = self._n_steps(n_steps)
        self._as_array(forces)  # refuse bad forces before the first step
        for _ in range(n_steps):
            self.step(forces)

    # ---------------------------------------------------------------- outputs
    @property
    def q(self) -> np.ndarray:
        """Modal coordinates x (r,) (a view)."""
        return self._S[0]

    @property
    def qdot(self) -> np.ndarray:
        """Modal velocities (r,) (a view)."""
        return self._S[1]

    def predict(self, node: int) -> np.ndarray:
        """Displacement (3,) of ``node`` after one more step with no new load, O(r).

        With :meth:`step_compliance` W, the next step under a force f on that node gives
        u(k+1) = predict(node) + W f: the relation a haptic contact solves (James & Pai's
        capacitance approach) before stepping.
        """
        if type(node) is not int or not 0 <= node < self.n_nodes:
            node = self._node(node)
        return self._phi[node] @ self._q_free()

    def _q_free(self) -> np.ndarray:
        """The modal coordinates (r,) after one more step with no new load."""
        S = self._S
        x = self._C1[0] * S[0] + self._C2[0] * S[1]
        if self._G0 is not None:
            x = x + self._G0[0] * self._f_old
        return x

    def step_compliance(self, node: int) -> np.ndarray:
        """W (3x3): displacement of ``node`` after one step per unit force held on it.

        W = sum_i phi_i(p) phi_i(p)^T Gamma_i (+ D_pp with the static correction).
        """
        return self.step_compliances(np.array([self._node(node)]))

    def predict_at(self, nodes) -> np.ndarray:
        """(k, 3) :meth:`predict` of ``nodes``, O(k r)."""
        return (self._shapes_at(validate.nodes(nodes, self.n_nodes)) @ self._q_free()).reshape(-1, 3)

    def step_compliances(self, nodes, loaded=None) -> np.ndarray:
        """The cross compliances (3k, 3l) of a contact set (see :func:`step_compliances`):
        Phi_a diag(Gamma) Phi_b^T, plus D_ab with the static correction (its columns are
        computed for the loaded nodes the first time, as :meth:`prepare` does)."""
        nodes = validate.nodes(nodes, self.n_nodes)
        loaded = nodes if loaded is None else validate.nodes(loaded, self.n_nodes)
        r = self._phi.shape[2]
        Pa, Pb = self._phi[nodes].reshape(-1, r), self._phi[loaded].reshape(-1, r)
        W = (Pa * self._G1[0]) @ Pb.T
        if self.static_correction and loaded.size:
            W += self._correction_block(nodes, loaded)
        return W

    def displacements(self, out: np.ndarray | None = None, *, dtype=np.float64, device: str = "cpu") -> np.ndarray:
        """The (n, 3) displacement field, U = Phi_r X (Eq. 11), plus the static correction.

        ``dtype=np.float32`` is for drawing: the product runs on a single-precision copy of the
        shapes (made on first use), which halves the memory read per frame, the limit of this
        O(n r) product (benchmarks/haptic_loop.py: 1.8 -> 0.9 ms at 40,962 vertices, r = 100, on
        2 cores); relative error ~1e-7. ``out`` (n, 3) of that dtype is filled when given.
        ``device="gpu"``: the product on a CUDA GPU through CuPy (:mod:`rtfem.gpu`; the shapes
        uploaded once per dtype, the field copied back), the static correction on the host."""
        validate.choice(device, "device", ("cpu", "gpu"))
        if np.dtype(dtype) not in (np.dtype(np.float64), np.dtype(np.float32)):
            raise ModelError(f"dtype={validate.show(dtype)}: displacements come as float64 or float32")
        if out is not None and (not isinstance(out, np.ndarray) or out.shape != (self.n_nodes, 3)
                                or out.dtype != np.dtype(dtype) or not out.flags.c_contiguous):
            raise ModelError(f"out={validate.show(out)} must be a C-contiguous ({self.n_nodes}, 3) array of "
                             f"{np.dtype(dtype).name} (the dtype asked for), or None")
        flat = None if out is None else out.reshape(-1)
        if device == "gpu":
            if getattr(self, "_gpu_field", None) is None:
                from .gpu import Field

                self._gpu_field = Field(self._P)
            u = self._gpu_field.product(self._S[0], dtype, out)
        elif np.dtype(dtype) == np.float32:
            if getattr(self, "_P32", None) is None:
                self._P32 = self._P.astype(np.float32)
            u = np.dot(self._P32, self._S[0].astype(np.float32), out=flat).reshape(-1, 3)
        else:
            u = np.dot(self._P, self._S[0], out=flat).reshape(-1, 3)
        if self.static_correction:
            self._add_correction(u)
        return u

    def displacement(self, node: int) -> np.ndarray:
        """Displacement (3,) of one node, O(r)."""
        i = node if type(node) is int and 0 <= node < self.n_nodes else self._node(node)
        if self.compiled:
            u = np.empty(3)
            kernels.point_displacement(self._phi, self._S, i, u)
        else:
            u = self._phi[i] @ self._S[0]
        c = self._point_correction(i) if self.static_correction else None
        return u if c is None else u + c

    def displacements_at(self, nodes: np.ndarray) -> np.ndarray:
        """(k, 3) displacements of ``nodes`` (indices), O(k r) plus the static correction of the loads."""
        nodes = validate.nodes(nodes, self.n_nodes)
        u = (self._shapes_at(nodes) @ self._S[0]).reshape(-1, 3)
        if self.static_correction:
            return self._correction_at(nodes, u)
        return u

    def _shapes_at(self, nodes: np.ndarray) -> np.ndarray:
        """The mode shapes at ``nodes`` as (3k, r) rows, kept while the same nodes are asked about (a
        contact's candidates: their prediction and displacement each tick, one gather). (A product
        with the (k, 3, r) stack would be numpy's stacked matmul, several times slower.)"""
        hit = self._shape_rows
        if hit is not None and hit[0].size == nodes.size and np.array_equal(hit[0], nodes):
            return hit[1]
        P = self._phi[nodes].reshape(3 * nodes.size, -1)
        self._shape_rows = (nodes.copy(), P) if P.size <= 1_000_000 else None
        return P

    @property
    def fingerprint(self) -> str:
        """The hash of the mesh the basis belongs to."""
        return self.modes.fingerprint

    def velocities(self) -> np.ndarray:
        r = self._phi.shape[2]
        return (self._phi.reshape(-1, r) @ self._S[1]).reshape(-1, 3)

    def energy(self) -> float:
        """Modal energy sum 1/2 (v_i^2 + w_i^2 x_i^2) (mass-normalized modes)."""
        x, v = self._S
        return float(0.5 * (v @ v + (self.modes.omega**2 * x) @ x))

    # ---------------------------------------------------------------- state
    def reset(self) -> None:
        """Back to rest at t = 0."""
        self._S[:] = 0.0
        self._f_old[:] = 0.0
        self._loads = {}
        self._load_array = None
        self.time = 0.0
        self.steps = 0

    def get_state(self) -> dict[str, np.ndarray]:
        """A copy of the state: modal coordinates, velocities, last modal force, step count."""
        return {"q": self._S[0].copy(), "qdot": self._S[1].copy(), "f_old": self._f_old.copy(),
                "steps": np.array(self.steps)}

    def set_state(self, state: Mapping[str, np.ndarray]) -> None:
        """Restore a state from :meth:`get_state` (or q/qdot arrays of length r)."""
        r = self._S.shape[1]
        if not isinstance(state, Mapping) or "q" not in state:
            raise ModelError(f"state={validate.show(state)} must be a mapping with 'q' (and optionally 'qdot', "
                             "'f_old', 'steps'), as get_state() returns")
        unknown = set(state) - {"q", "qdot", "f_old", "steps"}
        if unknown:
            raise ModelError(f"state has unknown entries {sorted(map(str, unknown))}; expected q, qdot, f_old, steps")
        arrays = {}
        for key in ("q", "qdot", "f_old"):
            a = validate.real_array(state.get(key, np.zeros(r)), f"state[{key!r}]", 1)
            if a.shape != (r,):
                raise ModelError(f"state[{key!r}] must have shape ({r},), got {a.shape}")
            arrays[key] = a
        steps = state.get("steps", 0)
        if isinstance(steps, np.ndarray) and steps.ndim == 0:
            steps = steps[()]
        steps = validate.count(steps, "state['steps']", 0)
        self._S[0], self._S[1] = arrays["q"], arrays["qdot"]
        self._f_old[:] = arrays["f_old"]
        self.steps = steps
        self.time = self.steps * self.dt
