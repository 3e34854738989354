"""A Driver whose every step is the linear static equilibrium: quasi-static contact.

A tool pressed or dragged slowly (a Hertz or Coulomb check, an indentation protocol, a
quasi-static retraction) needs no dynamics: each step is K u = F_held + f, with f the step's
loads (a ToolContact's contact forces, a Grasp's jaw) and F_held loads held throughout (a weight,
a retractor's pull). Its one-step compliance is the static one, W = K^-1 restricted to the
loaded nodes, so the contact solve of :class:`~rtfem.ToolContact` is then exactly the static
frictional contact problem at every step. Each loaded node's three columns of K^-1 are solved
once (``prepare``) and kept; a step then costs O(n k) for k loaded nodes, no solve.
"""

from __future__ import annotations

from typing import Mapping

import numpy as np

from .. import validate
from ..errors import ModelError
from .base import ForceInput, check_dt

__all__ = ["StaticDriver"]


class StaticDriver(ForceInput):
    """The Driver protocol on a model's static solve: ``step(forces)`` sets the displacements to
    K^-1 (F_held + forces).

    Parameters
    ----------
    model : ShellModel or SolidModel
        The model with its supports (they are read now: a later ``model.fix`` or ``release``
        makes this driver refuse to step, instead of answering for the old supports).
    loads : array_like or dict, optional
        Loads held at every step ((n, 3) or {node: f}; None for none); change them with
        :meth:`hold`.
    dt : float
        The time a step stands for (s; only ``time`` uses it).

    Notes
    -----
    ``predict(node)`` is the equilibrium under the held loads alone and ``step_compliance(node)``
    the static 3x3 compliance (K^-1)_pp, so ``rt.ToolContact(mesh, rt.StaticDriver(model), ...)``
    solves the static contact problem each step (its ``coupling="constraint"``: a rigid tool).

    Raises
    ------
    ModelError
        A model that is not one, loads off the mesh or not finite, a bad dt; at run time, a
        step after the model's supports changed.
    SolverError
        The stiffness cannot be factorized (nothing fixed: a mechanism).
    """

    compliance_changes = False
    warping = False

    def __init__(self, model, loads=None, dt: float = 1e-3) -> None:
        from ..fe.protocol import check_model

        check_model(model, "static driver")
        if not hasattr(model, "unit_load_responses"):
            raise ModelError(f"model={validate.show(model)} must be an rt.ShellModel or rt.SolidModel")
        self.model = model
        self.n_nodes = int(model.n_nodes)
        self.dt = check_dt(dt)
        self._supports = getattr(model, "supports_version", 0)
        model.check_restrained()
        self._columns: dict[int, np.ndarray] = {}  # node -> (n, 3, 3): [displaced node, axis, load axis]
        self.hold(loads)

    # ---------------------------------------------------------------- loads and columns
    def hold(self, loads=None) -> None:
        """Hold ``loads`` ((n, 3), {node: f} or None) from now on and go to their equilibrium (the
        step's own loads of the last step are dropped, as after reset)."""
        self._check_supports()
        if isinstance(loads, Mapping):
            nodes, P = self._parse_loads(loads)
            F = np.zeros((self.n_nodes, 3))
            np.add.at(F, nodes, P)
        else:
            F = self._as_array(loads)
        self._held = self.model.solve_static(F) if F.any() else np.zeros((self.n_nodes, 3))
        self.reset()

    def _check_supports(self) -> None:
        from ..fe.protocol import check_supports

        check_supports(self.model, self._supports, "StaticDriver")

    def prepare(self, nodes) -> None:
        """Solve the three columns of K^-1 of each of ``nodes`` not yet solved (multi-column solves)."""
        nodes = validate.nodes(nodes, self.n_nodes)
        self._check_supports()
        todo = np.array([i for i in dict.fromkeys(nodes.tolist()) if i not in self._columns], dtype=np.int64)
        if todo.size:
            for i, G in zip(todo.tolist(), self.model.unit_load_responses(todo)):
                self._columns[i] = G

    # ---------------------------------------------------------------- stepping
    def step(self, forces=None) -> None:
        """One step: the equilibrium under the held loads and ``forces`` ({node: f}, (n, 3) or None)."""
        self._check_supports()
        if forces is None:
            nodes, P = np.zeros(0, np.int64), np.zeros((0, 3))
        elif isinstance(forces, Mapping):
            nodes, P = self._parse_loads(forces)
        else:
            A = self._as_array(forces)
            nodes = np.flatnonzero(A.any(axis=1))
            P = A[nodes]
        if nodes.size > 64:  # many loaded nodes (a pressure, a weight): one solve
            F = np.zeros((self.n_nodes, 3))
            np.add.at(F, nodes, P)
            u = self._held + self.model.solve_static(F, warn=False)  # as the columns: a held dof takes its share
        else:
            if nodes.size:
                self.prepare(nodes)
            u = self._held.copy()
            for i, f in zip(nodes.tolist(), P):
                u += self._columns[i] @ f
        self._u = u
        self.steps += 1
        self.time = self.steps * self.dt

    def run(self, forces, n_steps: int) -> None:
        for _ in range(self._n_steps(n_steps)):
            self.step(forces)

    # ---------------------------------------------------------------- the one-step contract
    def predict(self, node: int) -> np.ndarray:
        return self._held[self._node(node)].copy()

    def predict_at(self, nodes) -> np.ndarray:
        return self._held[validate.nodes(nodes, self.n_nodes)].copy()

    def step_compliance(self, node: int) -> np.ndarray:
        return self.step_compliances(np.array([self._node(node)]))

    def step_compliances(self, nodes, loaded=None) -> np.ndarray:
        nodes = validate.nodes(nodes, self.n_nodes)
        loaded = nodes if loaded is None else validate.nodes(loaded, self.n_nodes)
        self.prepare(loaded)
        W = np.empty((3 * nodes.size, 3 * loaded.size))
        for b, j in enumerate(loaded.tolist()):
            W[:, 3 * b:3 * b + 3] = self._columns[j][nodes].reshape(-1, 3)
        return W

    def displacement(self, node: int) -> np.ndarray:
        return self._u[self._node(node)].copy()

    def displacements_at(self, nodes) -> np.ndarray:
        return self._u[validate.nodes(nodes, self.n_nodes)].copy()

    def displacements(self) -> np.ndarray:
        return self._u.copy()

    # ---------------------------------------------------------------- state
    def reset(self) -> None:
        self._u = self._held.copy()
        self.steps = 0
        self.time = 0.0

    def get_state(self) -> dict:
        return {"u": self._u.copy(), "steps": np.array(self.steps)}

    def set_state(self, state) -> None:
        if not isinstance(state, Mapping) or "u" not in state:
            raise ModelError(f"state={validate.show(state)} must be a mapping with 'u' (and 'steps'), as get_state() "
                             "returns")
        u = validate.real_array(state["u"], "state['u']", 2)
        if u.shape != (self.n_nodes, 3):
            raise ModelError(f"state['u'] must have shape ({self.n_nodes}, 3), got {u.shape}")
        steps = state.get("steps", 0)
        steps = validate.count(steps[()] if isinstance(steps, np.ndarray) else steps, "state['steps']", 0)
        self._u, self.steps, self.time = u.copy(), steps, steps * self.dt

    @property
    def fingerprint(self) -> str:
        from ..reduction.modal import mesh_fingerprint

        return mesh_fingerprint(self.model.mesh)
