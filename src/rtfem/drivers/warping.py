"""Rotation-aware reduced dynamics: modal warping (Choi & Ko, IEEE TVCG 11 (2005) 91-101).

The linear modal displacement of a node, a = Phi_i q, is small-rotation: a part of the organ
that swings by an angle grows and shears. Each mode also carries an infinitesimal rotation
field, w = Psi q (n, 3 per node). Modal warping integrates the displacement along the modal
path in the node's rotating frame: with w growing in proportion to q,

    u_i = Rt(w_i) a_i,   Rt(w) = int_0^1 exp(s [w]x) ds = I + (1 - cos t)/t^2 [w]x + (t - sin t)/t^3 [w]x^2

(t = |w|), which turns a rigid rotation's linear field into the exact rotated one; forces go
back to modal space in each node's frame, Phi_i^T R(w_i)^T f_i. The rotation modes come from
the model (:meth:`FEModel.rotation_field`): a shell's own rotational dofs, recovered through the
condensation (Psi = -K_rr^-1 K_rt Phi), or half the curl of a solid's mode shapes. A step stays
O(k r) for k loaded nodes; a node's displacement O(r); the field O(n r) plus O(n) to warp.
"""

from __future__ import annotations

from typing import Mapping

import numpy as np

from .. import validate
from ..errors import ModelError
from ..fe.rotations import integrated_rotation, rotation
from .base import rows_times, stepped_trial
from .modal import ModalSimulator

__all__ = ["WarpedModalSimulator", "rotation", "integrated_rotation"]


class WarpedModalSimulator(ModalSimulator):
    """A :class:`ModalSimulator` whose displacements are warped by each node's rotation and
    whose loads act in each node's rotated frame (modal warping). Made by
    ``rt.ModalSimulator(modes, dt, damping, warping=True)``; needs ``modes.model``.

    The Driver members keep their meaning: ``predict(node)`` is the warped no-load step and
    ``step_compliance(node)`` its linearization in the force (the warp's derivative included),
    recomputed each call (``compliance_changes``): the contact of a Probe or Grasp follows the
    rotation. The static correction acts in the rotated frame (R_i D (R_j^T f)).
    """

    compliance_changes = True
    warping = True

    def __init__(self, modes, dt, damping=None, *, integrator: str = "exact", static_correction: bool = False,
                 warping: bool = True) -> None:
        if warping is not True:
            raise ModelError("WarpedModalSimulator is the warped simulator: use rt.ModalSimulator(..., warping=False) "
                             "for the linear one")
        super().__init__(modes, dt, damping, integrator=integrator, static_correction=static_correction)
        model = modes.model
        if model is None:
            raise ModelError("warping needs the model for the rotation modes: load the basis with "
                             "ModalBasis.load(path, model=...)")
        self.compiled = False  # the compiled point step knows no warp
        self._psi = np.ascontiguousarray(model.rotation_field(self._phi))  # (n, 3, r)

    # ---------------------------------------------------------------- loads in the rotated frame
    def _rotations(self, nodes: np.ndarray, q: np.ndarray | None = None) -> np.ndarray:
        """R(w_i) (k, 3, 3) of ``nodes`` at modal coordinates ``q`` (default: now)."""
        return rotation(rows_times(self._psi[nodes], self._S[0] if q is None else q))

    def _local_forces(self, forces):
        """The loads turned into each node's rest frame, R(w_i)^T f_i (same format)."""
        if forces is None:
            return None
        if isinstance(forces, Mapping):
            items = [(self._node(k), self._vec(k, f)) for k, f in forces.items()]
            if not items:
                return {}
            nodes = np.array([i for i, _ in items])
            R = self._rotations(nodes)
            return {i: R[k].T @ f for k, (i, f) in enumerate(items)}
        A = self._as_array(forces).copy()
        loaded = np.flatnonzero(np.any(A != 0, axis=1))
        if loaded.size:
            A[loaded] = np.einsum("kji,kj->ki", self._rotations(loaded), A[loaded])
        return A

    def step(self, forces=None) -> None:
        """Advance one step; each load acts in its node's frame at the start of the step."""
        super().step(self._local_forces(forces))

    # ---------------------------------------------------------------- warped outputs
    def _warp(self, nodes: np.ndarray, q: np.ndarray, linear: np.ndarray, correction: np.ndarray | None):
        w = rows_times(self._psi[nodes], q)
        u = np.einsum("kij,kj->ki", integrated_rotation(w), linear)
        if correction is not None:
            u += np.einsum("kij,kj->ki", rotation(w), correction)
        return u

    def _corrections(self, nodes: np.ndarray) -> np.ndarray | None:
        if not self.static_correction or (not self._loads and self._load_array is None):
            return None
        if self._load_array is not None:
            return self._array_correction(self._load_array)[nodes]
        return sum(self._correction_column(j)[nodes] @ f for j, f in self._loads.items())

    def displacements(self, out: np.ndarray | None = None, *, dtype=np.float64, device: str = "cpu") -> np.ndarray:
        """The warped (n, 3) field: Rt(w_i) Phi_i q (+ R(w_i) times the static correction), on
        the CPU (each node's rotation is its own: no single product to hand a GPU)."""
        if device != "cpu":
            validate.choice(device, "device", ("cpu", "gpu"))
            raise ModelError("the warped field is computed on the CPU (device='cpu'): its per-node rotations are not "
                             "one product")
        if np.dtype(dtype) not in (np.dtype(np.float64), np.dtype(np.float32)):
            raise ModelError(f"dtype={validate.show(dtype)}: displacements come as float64 or float32")
        q = self._S[0]
        nodes = np.arange(self.n_nodes)
        u = self._warp(nodes, q, rows_times(self._phi, q), self._corrections(nodes))
        if out is not None:
            out[...] = u
            return out
        return u.astype(dtype, copy=False)

    def trial_displacements(self, forces, nodes: np.ndarray) -> np.ndarray:
        """(k, 3) displacements of ``nodes`` after one step under ``forces``, the state unchanged
        (the warped step rotates the loads: a step, read, and the state restored, the static
        correction's loads with it)."""
        loads = self._current_loads()
        try:
            return stepped_trial(self, forces, nodes)
        finally:
            self._loads, self._load_array = loads

    def displacements_at(self, nodes: np.ndarray) -> np.ndarray:
        nodes = validate.nodes(nodes, self.n_nodes)
        q = self._S[0]
        return self._warp(nodes, q, rows_times(self._phi[nodes], q), self._corrections(nodes))

    def displacement(self, node: int) -> np.ndarray:
        return self.displacements_at(np.array([self._node(node)]))[0]

    def velocities(self) -> np.ndarray:
        """Rt(w_i) Phi_i q' (the warp's own rate neglected)."""
        q = self._S[0]
        return np.einsum("kij,kj->ki", integrated_rotation(rows_times(self._psi, q)), rows_times(self._phi, self._S[1]))

    # ---------------------------------------------------------------- the one-step contract
    def predict(self, node: int) -> np.ndarray:
        """The warped displacement (3,) of ``node`` after one more step with no new load."""
        return self.predict_at(np.array([self._node(node)]))[0]

    def predict_at(self, nodes) -> np.ndarray:
        """(k, 3) :meth:`predict` of ``nodes``."""
        nodes = validate.nodes(nodes, self.n_nodes)
        q = self._q_free()
        return self._warp(nodes, q, rows_times(self._phi[nodes], q), None)

    def _jacobians(self, nodes: np.ndarray, q: np.ndarray) -> np.ndarray:
        """d u_i / d q (k, 3, r) of the warped displacement at ``q``: Rt(w_i) Phi_i plus the warp's
        derivative (central differences of Rt in w, which is smooth)."""
        P, Ps = self._phi[nodes], self._psi[nodes]
        a, w = rows_times(P, q), rows_times(Ps, q)
        J = integrated_rotation(w) @ P
        h = 1e-6
        for k in range(3):
            e = np.zeros(3)
            e[k] = h
            dR = (integrated_rotation(w + e) - integrated_rotation(w - e)) / (2 * h)
            J += np.einsum("ki,kr->kir", np.einsum("kij,kj->ki", dR, a), Ps[:, k])
        return J

    def step_compliance(self, node: int) -> np.ndarray:
        """d u_i(k+1) / d f_i at the no-load step: the warp's Jacobian times the modal gain times
        the force's turn into the node's frame (plus R D_ii R^T with the static correction)."""
        i = self._node(node)
        return self.step_compliances(np.array([i]))

    def step_compliances(self, nodes, loaded=None) -> np.ndarray:
        """The cross compliances (3k, 3l) of a contact set at the no-load step: J_a diag(Gamma)
        Phi_b^T R_b^T, plus R_a D_ab R_b^T with the static correction."""
        nodes = validate.nodes(nodes, self.n_nodes)
        loaded = nodes if loaded is None else validate.nodes(loaded, self.n_nodes)
        q = self._q_free()
        r = self._phi.shape[2]
        J = self._jacobians(nodes, q).reshape(-1, r)
        Rn = self._rotations(loaded)  # the frames the forces are turned into (now)
        Pb = np.einsum("kij,kjr->kir", Rn, self._phi[loaded]).reshape(-1, r)  # R_b Phi_b
        W = (J * self._G1[0]) @ Pb.T
        if self.static_correction and loaded.size:
            Ra = rotation(rows_times(self._psi[nodes], q))
            for b, j in enumerate(loaded.tolist()):
                D = self._correction_column(j)[nodes]  # (k, 3, 3)
                W[:, 3 * b:3 * b + 3] += np.einsum("kij,kjl,ml->kim", Ra, D, Rn[b]).reshape(-1, 3)
        return W


ModalSimulator._warped = WarpedModalSimulator
