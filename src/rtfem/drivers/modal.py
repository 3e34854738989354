"""Run-time dynamics: the Driver protocol and the reduced ModalSimulator (the full-order
simulators are in :mod:`rtfem.drivers.fullorder`).

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
from typing import Mapping

import numpy as np

from . import kernels
from .. import validate
from ..errors import ModelError
from ..fe.material import Damping
from ..reduction.modal import ModalBasis
from ..reduction.oscillator import transition
from .base import ForceInput, StaticCorrection, check_damping, check_dt, newmark_coefficients


__all__ = ["ModalSimulator"]


class ModalSimulator(StaticCorrection, ForceInput):
    """Reduced dynamics in modal coordinates (paper section 3).

    Parameters
    ----------
    modes : a :class:`~rtfem.reduction.modal.ModalBasis` (r modes).
    dt : time step in seconds (1e-3 for a 1 kHz haptic loop).
    damping : :class:`~rtfem.Damping` (mass-proportional, Rayleigh or modal ratios).
    integrator : "exact" (default) or "newmark".
    static_correction : add the static contribution of the truncated modes (mode-acceleration
        method, D = K^-1 - Phi_r Lambda_r^-1 Phi_r^T applied to the current loads), so that a
        few modes still give the right static deflection. Needs ``modes.model``.
    warping : rotation-aware (modal warping, Choi & Ko 2005): gives a
        :class:`~rtfem.drivers.warping.WarpedModalSimulator`, whose displacements follow each node's
        rotation and whose loads act in each node's frame. Needs ``modes.model``.

    Raises
    ------
    ModelError
        Modes that are not a ModalBasis, a dt that is not a positive time step, damping that is
        not an :class:`~rtfem.Damping`, an unknown integrator, the static correction or warping
        without ``modes.model`` (a basis loaded without its model); at run time, loads on nodes
        off the mesh or not finite, a driver stepped after its model's supports changed.
    """

    def __new__(cls, modes=None, dt=None, damping=None, *, integrator: str = "exact", static_correction: bool = False,
                warping: bool = False):
        if cls is ModalSimulator and validate.flag(warping, "warping"):
            cls = ModalSimulator._warped  # rtfem.drivers.warping registers it (the package imports it)
        return super().__new__(cls)

    _warped: type | None = None  # the class ModalSimulator(..., warping=True) makes

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
        self._shape_rows: list = []  # (nodes, the shapes there) of the last two batched queries
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
        ``device="gpu"``: the product on a CUDA GPU through CuPy (:mod:`rtfem.drivers.gpu`; the shapes
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

    def trial_displacements(self, forces, nodes: np.ndarray) -> np.ndarray:
        """(k, 3) displacements of ``nodes`` after one step under ``forces`` (an (n, 3) array or a
        {node: f} mapping), the state unchanged: the free step's coordinates (:meth:`predict`) plus
        G1 f, on the nodes' shapes, plus the static correction of those forces."""
        nodes = validate.nodes(nodes, self.n_nodes)
        A = self._as_array(forces)
        q = self._q_free() + self._G1[0] * (A.reshape(-1) @ self._P)
        u = (self._shapes_at(nodes) @ q).reshape(-1, 3)
        if self.static_correction:
            u += self._array_correction(A)[nodes]
        return u

    def _shapes_at(self, nodes: np.ndarray) -> np.ndarray:
        """The mode shapes at ``nodes`` as (3k, r) rows, kept while the same nodes are asked about (a
        contact's candidates: their prediction and displacement each tick, one gather). (A product
        with the (k, 3, r) stack would be numpy's stacked matmul, several times slower.)"""
        kept = self._shape_rows  # the last two sets (a scene asks about its surface and its contacts)
        for hit in kept:
            if hit[0].size == nodes.size and np.array_equal(hit[0], nodes):
                return hit[1]
        P = self._phi[nodes].reshape(3 * nodes.size, -1)
        if P.size <= 1_000_000:
            self._shape_rows = [(nodes.copy(), P), *kept[:1]]
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
