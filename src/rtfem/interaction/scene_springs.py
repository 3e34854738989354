"""A scene's springs (attachments and graspers' holds, :class:`rtfem.interaction.scene.Scene`): each set's key,
the last step's forces as the next step's start (:func:`warm_springs`), and the spring system
(I / k + A) f = rhs of their implicit forces (:func:`spring_system`)."""

from __future__ import annotations

import numpy as np
from scipy.linalg import cho_factor, cho_solve, lu_factor, lu_solve

from ..drivers.base import step_compliances

__all__ = ["spring_key", "spring_system", "warm_springs"]


def spring_key(att) -> tuple:
    """What a spring set's forces are kept against: its nodes and stiffness."""
    return att.nodes_a.tobytes(), None if att.b is None else att.nodes_b.tobytes(), att.stiffness


def warm_springs(scene, springs, weights) -> list[np.ndarray]:
    """Each spring set's forces (S, 3) in the last step (zero for a set new or changed since), added to
    the bodies' ``weights``: a step's spring forces are these and a correction (the scene's ``_attachment_loads``),
    which vanishes at rest, so that a spring at rest holds k times its stretch on a body whose step is not
    affine in its loads (a nonlinear one: from the weights alone the correction was the whole force,
    taken through the compliance of a step far from the one made, and the clamped beam's tip springs of
    500 N/m held 0.20 N where their stretch said 0.15 N)."""
    index = {b.name: k for k, b in enumerate(scene.bodies)}
    out = []
    for att in springs:
        kept = scene._spring_forces.get(att.name)
        f = kept[1] if kept is not None and kept[0] == spring_key(att) else np.zeros((att.nodes_a.size, 3))
        np.add.at(weights[index[att.a.name]], att.nodes_a, f)
        if att.b is not None:
            np.add.at(weights[index[att.b.name]], att.nodes_b, -f)
        out.append(f)
    return out


def spring_system(scene, springs, index, start, sizes, spring_nodes):
    """The springs' Jacobians {body: (its spring nodes, J_k)} (``spring_nodes``: the scene's ``_spring_nodes``)
    and the solve of (I / k + A) f = rhs, kept while the springs are the same and no body's one-step
    compliances change with its motion."""
    key = tuple((att.name, att.nodes_a.tobytes(), att.stiffness) for att in springs)
    kept = getattr(scene, "_springs_kept", None)
    if kept is not None and kept[0] == key:
        return kept[1], kept[2]
    n_springs = int(start[-1])
    J = {}  # body -> (its attached nodes, (3 S, 3 n) Jacobian)
    for k in sorted(spring_nodes):
        J[k] = (spring_nodes[k], np.zeros((3 * n_springs, 3 * spring_nodes[k].size)))
    for a_index, att in enumerate(springs):
        for k, nodes, sign in ((index[att.a.name], att.nodes_a, 1.0),
                               *(((index[att.b.name], att.nodes_b, -1.0),) if att.b is not None else ())):
            all_nodes, Jk = J[k]
            slots = np.searchsorted(all_nodes, nodes)
            for s_local, slot in enumerate(slots.tolist()):
                row = 3 * (start[a_index] + s_local)
                Jk[row:row + 3, 3 * slot:3 * slot + 3] += sign * np.eye(3)
    A = np.zeros((3 * n_springs, 3 * n_springs))
    for k, (nodes, Jk) in J.items():
        A += Jk @ step_compliances(scene.bodies[k].driver, nodes) @ Jk.T
    A += np.diag(np.repeat([1.0 / att.stiffness for att in springs], np.asarray(sizes) * 3))
    constant = not any(getattr(scene.bodies[k].driver, "compliance_changes", True) for k in J)
    try:  # symmetric positive definite: the compliances and 1/k
        factor, apply = cho_factor(A), cho_solve
    except np.linalg.LinAlgError:  # a user's driver with compliances that are not
        factor, apply = lu_factor(A), lu_solve
    inverse = apply(factor, np.eye(A.shape[0])) if constant else None

    def solve(rhs):  # kept: the inverse (one product a step); else this step's factor
        return inverse @ rhs if inverse is not None else apply(factor, rhs)

    if constant:
        scene._springs_kept = (key, J, solve)
    return J, solve
