"""A running full-order driver carried over to a remeshed copy of its model (issue 57: a cut).

The state goes through the remesh's interpolation P (n_new, n_old) (``cut_info.transfer()``; an
integer array ``parent`` stands for the rows that pick node ``parent[i]``): a cut gives each node on a
cut face one copy per side (a row picking it), a node added on a split edge is the interpolation of
the edge's ends. Displacements, velocities and accelerations go through P (the fields are the same
piecewise polynomials, so where the cut follows element faces the kinetic and strain energies are
exactly the old ones); the loads a step remembers (HHT's last forces) go through P scaled by each new
node's lumped mass over that of what it interpolates (a node's load shared among its copies by mass:
the total kept where only copies are made). A node the cut moved onto its surface (``cut_info.max_move``;
a running scalpel cuts with ``snap="split"``: moves under a fifth of an edge) is carried at its new
reference point: rt.cut's transfer interpolates there in the uncut tet it lies in, so the old nodes land
on the new and the elements about it keep their strains (the node slides within the deformed solid).
Given a transfer that does not land them (a parent array after a cut that moved nodes), a moved node
keeps its place in the world instead, its displacement taking the move back, its elements strained by
the move over their size.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from ..errors import ModelError

#: the state vectors that are loads (extensive: shared among a node's copies); the rest are fields
EXTENSIVE = frozenset({"_g", "_held", "_f"})


def lumped_nodal_masses(model) -> np.ndarray:
    """Each node's lumped mass (n,): ``model.mass_diagonal`` at its x dof."""
    return np.asarray(model.mass_diagonal, dtype=float).reshape(model.n_nodes, model.dofs_per_node)[:, 0]


def mass_share(old, new, P: sp.csr_matrix) -> np.ndarray:
    """(new.n_nodes,) each new node's lumped mass over that of what it interpolates (|P| of the old
    nodes' masses): a load carried through P times this is shared among a node's copies by mass.
    The weights' magnitudes, not the weights: a node the cut moved onto its surface is interpolated in
    the uncut tet it lies in, and where that is a little outside it (a weight of -0.1 is seen on a
    scalpel's cuts) P's masses can sum to nearly nothing, which made the share 1e301 and the loads the
    step remembers as large (the next step then turned half the organ inside out). With |P| a node's
    load per unit mass never exceeds the largest the old nodes had; rows of non-negative weights (a
    copy, a node on a split edge) are as before."""
    return lumped_nodal_masses(new) / np.maximum(abs(P) @ lumped_nodal_masses(old), np.finfo(float).tiny)


def transfer_matrix(old, new, transfer) -> sp.csr_matrix:
    """``transfer`` checked, as a sparse (new.n_nodes, old.n_nodes) interpolation."""
    if old.dofs_per_node != new.dofs_per_node:
        raise ModelError(f"the new model has {new.dofs_per_node} dofs a node and the old one {old.dofs_per_node}: "
                         "carry a state only to a remeshed copy of the same kind of model")
    if sp.issparse(transfer):
        P = sp.csr_matrix(transfer, dtype=float)
        if P.shape != (new.n_nodes, old.n_nodes) or not np.isfinite(P.data).all():
            raise ModelError(f"transfer of shape {P.shape}: give the interpolation ({new.n_nodes}, {old.n_nodes}) from "
                             "the old model's nodes to the new's (cut_info.transfer()), finite")
        return P
    p = np.asarray(transfer)
    if p.shape != (new.n_nodes,) or not np.issubdtype(p.dtype, np.integer):
        raise ModelError(f"transfer of shape {p.shape} and type {p.dtype}: give one old node index for each of the new "
                         f"model's {new.n_nodes} nodes, or the sparse interpolation cut_info.transfer()")
    if p.size and (p.min() < 0 or p.max() >= old.n_nodes):
        raise ModelError(f"transfer indexes nodes {int(p.min())}..{int(p.max())}, but the old model has {old.n_nodes}: "
                         "a cut that split edges needs cut_info.transfer(), not cut_info.parent")
    return sp.csr_matrix((np.ones(p.size), (np.arange(p.size), p)), shape=(new.n_nodes, old.n_nodes))


def carried_state(old, new, P: sp.csr_matrix) -> dict:
    """``old``'s state (a DirectSimulator) as ``new``'s (the same class on the remeshed model): see the
    module."""
    state = old.get_state()
    if "visc" in state:
        raise ModelError("a viscoelastic law's history lives at the elements' quadrature points and is not carried "
                         "to a cut mesh yet: cut the model before running it, or use an elastic law")
    target = new.get_state()
    n_old, n_new, dpn = old.model.n_dofs, new.model.n_dofs, old.model.dofs_per_node
    share = None
    out = {}
    for key, value in state.items():
        value, like = np.asarray(value), np.asarray(target[key])
        if value.shape == (old._solved.size,) and like.shape == (new._solved.size,):
            full, pick = np.zeros(n_old), new._solved
            full[old._solved] = value
        elif value.shape == (n_old,) and like.shape == (n_new,):
            full, pick = value, slice(None)
        elif value.shape == like.shape:
            out[key] = value.copy()  # a step count: not nodal
            continue
        else:
            raise ModelError(f"state[{key!r}] has shape {value.shape}, not a nodal vector of the old model; carry over "
                             "only between drivers of one class")
        nodal = P @ full.reshape(-1, dpn)
        if f"_{key}" in EXTENSIVE:
            if share is None:
                share = mass_share(old.model, new.model, P)
            nodal = nodal * share[:, None]
        out[key] = np.asarray(nodal).ravel()[pick].copy()
    return out


def carry_over(old, model, transfer, into=None):
    """A driver of ``old``'s class and settings on ``model`` (``into``: one built before by this call on
    the same model, which then only takes the state), holding ``old``'s state carried through
    ``transfer``; ``old`` is left as it was."""
    P = transfer_matrix(old.model, model, transfer)
    _check_remesh(old.model, model, P)
    prepared = into is not None
    if into is None:
        into = type(old)(model, old.dt, old.damping, **getattr(old, "_settings", {}))
    elif into.model is not model or type(into) is not type(old) or into.dt != old.dt:
        raise ModelError("into= must be a driver carry_over built before from this driver on this same model (the "
                         f"same class and dt): got a {type(into).__name__} at dt {into.dt:g} on "
                         f"{'this' if into.model is model else 'another'} model")
    state = carried_state(old, into, P)
    _keep_in_place(old.model, model, P, state, into._solved)
    if prepared and "ref_u" in state and getattr(into, "_factor", None) is not None:
        # the lagged step's factor ``into`` made already (factorize(), on the cutter's thread) is kept: the
        # state takes its reference (else the new driver factorizes at the reference carried)
        state["ref_u"], state["ref_step"] = into._ref_u.copy(), into._ref_step.copy()
    into.set_state(state)
    return into


def _material_of(model):
    """A model's material, or its regions' {label: material or law}."""
    return getattr(model, "materials", None) or model.material


def _check_remesh(old, new, P) -> None:
    """``new`` must be a remesh of ``old`` (rt.cut's) through ``P``: the same material, and the old
    nodes interpolated land on the new ones (within half the median element edge: a cut moves nodes
    by at most that); else the state would be carried onto the wrong nodes."""
    a, b = _material_of(old), _material_of(new)
    if type(a) is not type(b) or a != b:
        raise ModelError(f"the new model's material {b} is not the old one's {a}: carry a state only to a remesh of "
                         "the same model (rt.cut's)")
    if getattr(old, "law", None) is not None and type(old.law) is not type(getattr(new, "law", None)):
        raise ModelError("the new model's law is not the old one's: carry a state only to a remesh of the same model")
    if not (hasattr(old, "tetmesh") and hasattr(new, "tetmesh")):
        return
    X_old, X_new = np.asarray(old.tetmesh.vertices, dtype=float), np.asarray(new.tetmesh.vertices, dtype=float)
    E = X_new[np.asarray(new.tetmesh.tets)[:, :2]]
    half = 0.5 * float(np.median(np.linalg.norm(E[:, 1] - E[:, 0], axis=1)))
    off = float(np.abs(P @ X_old - X_new).max(initial=0.0))
    if off > half:
        raise ModelError(f"the transfer does not map the old model's nodes onto the new model's (off by {off:.3g} m, more "
                         "than half an element edge): pass the new model's own cut_info.transfer()")


def _keep_in_place(old, new, P, state: dict, solved: np.ndarray) -> None:
    """A node whose reference point the remesh moved and the transfer does not land (P X != X': a parent
    array for a cut that moved nodes; rt.cut's own transfer lands them) keeps its place in the world: its
    displacement takes the move back (u' = P(X + u) - X'), so the solid is where it was at the swap and
    no element can turn inside out there; its elements' strains change by the move over their size."""
    if not (hasattr(old, "tetmesh") and hasattr(new, "tetmesh")) or "u" not in state:
        return
    shift = P @ np.asarray(old.tetmesh.vertices, dtype=float) - np.asarray(new.tetmesh.vertices, dtype=float)
    if not np.abs(shift).max(initial=0.0) > 0:
        return
    full = shift.ravel()[solved]
    for key in ("u", "ref_u", "u_1", "u_2"):  # (the lagged step's factor point and its predictor's history)
        if key in state:
            state[key] = state[key] + full
