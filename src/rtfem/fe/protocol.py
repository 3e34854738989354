"""The Model protocol (what drivers and tools need of a model), its checks, and the dof names."""

from __future__ import annotations

import re
from typing import Protocol, Sequence, runtime_checkable

import numpy as np
import scipy.sparse as sp

from .. import validate
from ..errors import ModelError

__all__ = ["Model", "MODEL_MEMBERS", "check_model", "check_supports", "DOF_NAMES", "parse_dofs",
           "require_lumped_mass", "is_diagonal"]

DOF_NAMES = ("x", "y", "z", "rx", "ry", "rz")


@runtime_checkable
class Model(Protocol):
    """What ``modal_analysis``, ``SLDM``, ``ImpedanceMap``, the full-order simulators, the viewer and
    the CLI ask of a model, and nothing more (DESIGN.md, "The two seams").

    Dofs: each node has ``dofs_per_node`` dofs whose first three are the translations (x, y, z);
    dof ``d`` of node ``i`` is global dof ``i * dofs_per_node + d``. ``constrained_stiffness()`` and
    ``constrained_mass()`` are sparse on the same dofs (the free ones with elimination, all with
    a penalty) and return those dofs, the map back to nodes (:meth:`nodal_translations`).
    ``solve_static`` and ``unit_load_response`` go through the cached ``factorization()``; the
    latter is the one copy of the unit-load loop (static correction, impedance map).
    ``condensation()`` gives K_c = K_tt - K_tr K_rr^-1 K_rt on the free translations t (for a
    model without rotations, K_tt). Satisfied by :class:`ShellModel` and :class:`~rtfem.SolidModel`.
    """

    mesh: object  # the surface that is drawn and touched: triangles over model nodes
    material: object
    n_nodes: int
    n_dofs: int
    dofs_per_node: int
    constraints: str  # "elimination" or "penalty"
    fixed: np.ndarray  # (n_nodes, dofs_per_node) bool
    held_nodes: np.ndarray  # (n_nodes,) bool: all three translations fixed
    mass_diagonal: np.ndarray  # (n_dofs,) lumped mass
    metadata: dict  # what a saved result records about the model (kind, element, ...)

    def select_nodes(self, nodes) -> np.ndarray: ...
    def fix(self, nodes, dofs="all"): ...
    def release(self, nodes=None, dofs="all"): ...
    def nearest_free_node(self, point, displacements=None) -> int: ...
    def check_not_all_fixed(self) -> None: ...
    def check_restrained(self) -> None: ...
    def constrained_stiffness(self) -> tuple: ...
    def constrained_mass(self) -> tuple: ...
    def nodal_translations(self, values, dofs) -> np.ndarray: ...
    def translation_dofs(self, node: int) -> np.ndarray: ...
    def dof_order(self, dofs) -> np.ndarray: ...
    def factorization(self): ...
    def force_vector(self, forces, *, warn: bool = True) -> np.ndarray: ...
    def solve_static(self, forces, *, warn: bool = True) -> np.ndarray: ...
    def unit_load_response(self, node: int, direction: int) -> np.ndarray: ...
    def condensation(self): ...


MODEL_MEMBERS = ("mesh", "material", "n_nodes", "n_dofs", "dofs_per_node", "constraints", "fixed", "held_nodes",
                 "mass_diagonal", "metadata", "select_nodes", "fix", "release", "nearest_free_node",
                 "check_not_all_fixed", "check_restrained", "constrained_stiffness", "constrained_mass",
                 "nodal_translations", "translation_dofs", "dof_order", "factorization", "force_vector",
                 "solve_static", "unit_load_response", "condensation")


def check_model(model, what: str = "model"):
    """``model`` if it satisfies the Model protocol; otherwise a ModelError naming what it lacks."""
    missing = [m for m in MODEL_MEMBERS if not hasattr(type(model), m) and not hasattr(model, m)]
    if missing:
        raise ModelError(f"{what}={validate.show(model)} is not a model: rtfem needs a ShellModel, a SolidModel "
                         "or any class with "
                         f"the Model protocol's members; it lacks {', '.join(missing[:6])}"
                         f"{' ...' if len(missing) > 6 else ''}")
    return model


def check_supports(model, version: int, what: str) -> None:
    """Refuse to go on with ``what`` (a driver) built on ``model`` when its ``supports_version``
    was ``version``: it would answer for the old supports (a user's model without the counter:
    nothing to check)."""
    if getattr(model, "supports_version", 0) != version:
        raise ModelError(f"the model's supports changed (model.fix or release) since this {what} was built on it: "
                         "build a new one for the new supports")


def is_diagonal(M: sp.spmatrix) -> bool:
    """Whether the sparse matrix has no nonzero entry off its diagonal (a lumped mass)."""
    C = M.tocoo()
    return bool(np.all((C.row == C.col) | (C.data == 0)))


def require_lumped_mass(model, what: str) -> None:
    """Refuse a model whose constrained mass is not diagonal: ``what`` works with M^-1/2 or M^-1
    of the diagonal (lumped) mass."""
    if not is_diagonal(model.constrained_mass()[0]):
        raise ModelError(f"{what} needs a diagonal (lumped) mass; this model's is consistent: build it with "
                         "mass='lumped', or use the modal route (modal_analysis takes a consistent mass)")


def parse_dofs(dofs: str | Sequence[str] | Sequence[int]) -> np.ndarray:
    """Turn a dof specification into a boolean mask over ``(x, y, z, rx, ry, rz)``.

    Accepts "all", "xyz" (translations), "rxyz" or "rotations", single components ("z",
    "rx"), concatenations ("xy", "z,rx") or a sequence of names or indices 0..5.
    """
    mask = np.zeros(6, bool)
    if not isinstance(dofs, (str, Sequence, np.ndarray)):
        raise ModelError(f"dofs={validate.show(dofs)} not understood; use 'all', 'xyz', 'rotations', or components "
                         f"from {DOF_NAMES}")
    if isinstance(dofs, str):
        s = dofs.strip().lower()
        if s == "all":
            return np.ones(6, bool)
        if s in ("rotations", "rot", "r"):
            mask[3:] = True
            return mask
        if s in ("translations", "trans", "t"):
            mask[:3] = True
            return mask
        s = s.replace("rxyz", "rx,ry,rz")
        compact = re.sub(r"[\s,;+]", "", s)
        tokens = re.findall(r"r?[xyz]", compact)
        if not tokens or "".join(tokens) != compact:
            raise ModelError(
                f"dofs={dofs!r} not understood; use 'all', 'xyz', 'rotations', or components from {DOF_NAMES}"
            )
        for t in tokens:
            mask[DOF_NAMES.index(t)] = True
        return mask
    for d in dofs:
        if isinstance(d, str):
            mask |= parse_dofs(d)
        elif isinstance(d, (int, np.integer)) and not isinstance(d, (bool, np.bool_)) and 0 <= d < 6:
            mask[int(d)] = True
        else:
            raise ModelError(f"dof {validate.show(d)} not understood; use names from {DOF_NAMES} or indices 0..5")
    if not mask.any():
        raise ModelError(f"dofs={validate.show(dofs)} names no dof; use 'all', 'xyz', 'rotations', ...")
    return mask
