"""A running reduced nonlinear simulator carried over to a cut copy of its model (issue 57): a cut
reduced organ goes full order (its basis cannot open the cut). The state goes through the basis, then
through the cut's interpolation as :mod:`rtfem.drivers.carry` carries a full-order one."""

from __future__ import annotations

import numpy as np

from ..errors import ModelError
from .carry import _check_remesh, _keep_in_place, mass_share, transfer_matrix


def reduced_carry_over(self, model, transfer, *, large_deformation: bool = True, into=None):
    """This reduced nonlinear simulator's state on ``model``, a remesh of its full-order model
    (``rt.cut``'s), as a full-order :class:`rt.DirectSimulator` (issue 57: a cut reduced organ goes
    full order; its basis cannot hold the opened cut). The displacement (with the static correction
    of the current loads), velocity and acceleration through the basis, then node by node through
    the remesh's interpolation (see the module; a node the cut moved is carried at its new place in the
    deformed solid); the loads held, shared among a node's copies by lumped mass. The full order's remembered force is
    the one of the equation of motion at the state (-M a), its first step factorizes at the state.
    Same dt and damping (``into``: one built before by this call on the same model, which then only
    takes the state). This simulator is left as it was.

    Parameters
    ----------
    model : the remeshed model (same kind, element and material as ``self.reduced.model``).
    transfer : the remesh's interpolation (``model.cut_info.transfer()``), or each new node's parent.
    large_deformation : the lagged corotational step (default), or the linear Newmark one.

    Returns
    -------
    DirectSimulator
        The full-order driver, at this simulator's step count and time.

    Raises
    ------
    ModelError
        A model that is not a remesh of this one's (another material, nodes that do not land), a
        transfer of the wrong shape, a Prony law (its history is not carried), an ``into`` of
        another model or dt.
    """
    from .fullorder import DirectSimulator

    old = self.reduced.model
    if self._visc is not None:
        raise ModelError("a Prony law's history lives at the cubature's points and is not carried to a full-order "
                         "cut model yet: use an elastic law")
    P = transfer_matrix(old, model, transfer)
    _check_remesh(old, model, P)
    if into is None:
        into = DirectSimulator(model, self.dt, self.damping, large_deformation=large_deformation)
    elif into.model is not model or into.dt != self.dt or not isinstance(into, DirectSimulator):
        raise ModelError("into= must be a DirectSimulator this call built before on this same model at the same dt")
    red, dpn, solved = self.reduced, model.dofs_per_node, into._solved
    fields = {"u": self.displacements(), "v": red.displacements(self._v), "a": red.displacements(self._a)}
    state = into.get_state()
    for key, X in fields.items():
        state[key] = np.asarray(P @ X.reshape(old.n_nodes, dpn)).ravel()[solved]
    M, _ = model.constrained_mass()
    if "g" in state:  # the equation of motion at the state: M a + g = 0
        state["g"] = -(M @ state["a"])
    if "held" in state:
        loads = self._load_array if self._load_array is not None else old.force_vector(self._loads or np.zeros((old.n_nodes, 3)),
                                                                                          warn=False).reshape(old.n_nodes, dpn)
        held = np.zeros((model.n_nodes, dpn))
        held[:, :3] = (P @ np.asarray(loads, float).reshape(old.n_nodes, -1)[:, :3]) * mass_share(old, model, P)[:, None]
        state["held"] = held.ravel()
    if "ref_u" in state:  # the lagged step's first factor at the state, no predictor history yet
        state["ref_u"], state["ref_step"] = state["u"].copy(), np.array([float(self.steps)])
    state["steps"] = np.array(self.steps)
    _keep_in_place(old, model, P, state, solved)
    into.set_state(state)
    return into


def reduced_take_over(self, driver) -> None:
    """Take over the state of ``driver``, a full-order :class:`rt.DirectSimulator` of this simulator's
    model (a cut organ's full order, once a reduced model of the cut mesh is built: the way back from
    :meth:`carry_over`): the displacement, velocity and acceleration projected on this basis in the
    stiffness inner product (K-orthonormal: exact for a field the basis and the static correction of
    the loads hold), its held loads (the static correction's), its step count and time.

    Raises
    ------
    ModelError
        A driver that is not a full-order one of this simulator's model, or a Prony law.
    """
    from .fullorder import DirectSimulator

    red = self.reduced
    if not isinstance(driver, DirectSimulator) or driver.model is not red.model:
        raise ModelError(f"driver={type(driver).__name__} must be a full-order rt.DirectSimulator of this simulator's "
                         "model (the cut model its reduced model was built on)")
    if self._visc is not None:
        raise ModelError("a Prony law's history is not taken over from the full order yet: use an elastic law")
    state, n, dpn = driver.get_state(), red.model.n_nodes, red.model.dofs_per_node

    def coordinates(values):  # solved-dof values -> this basis's coordinates, U^T K0 u
        full = np.zeros(red.model.n_dofs)
        full[driver._solved] = values
        return self._U.T @ (red._K0 @ full[red.free])

    held = np.asarray(state.get("held", np.zeros(red.model.n_dofs))).reshape(n, dpn)[:, :3]
    loads = {int(i): held[i].copy() for i in np.flatnonzero(np.abs(held).sum(axis=1) > 0)}
    self.set_state({"q": coordinates(state["u"]), "qdot": coordinates(state["v"]), "qddot": coordinates(state["a"]),
                    "steps": int(state["steps"])})
    self._loads, self._load_array = (loads, None) if self.static_correction else ({}, None)
