"""One node selector for the library, the CLI, the benchmarks and the demo.

A selection is any of: node indices (ints), a boolean mask over the nodes, the name of a mesh
vertex group (``"attachment"``, ``"probe"`` on the default liver), a coordinate slab
``"z<0.01"`` / ``"x>0.1"`` (metres), ``"bottom:0.1"`` (the lowest 10 % of the height) or
``"nodes:3,7,12"``. It works on any mesh with ``vertices``, ``groups`` and ``n_vertices``.
"""

from __future__ import annotations

import numpy as np

from .. import validate
from ..errors import ModelError

__all__ = ["select_nodes", "describe_selection", "probe_vertex", "SELECTION_HELP"]

SELECTION_HELP = "a group name, AXIS<VALUE or AXIS>VALUE (m), bottom:FRACTION or nodes:i,j,k"
_AXES = {"x": 0, "y": 1, "z": 2}


def _parse(mesh, spec, name: str) -> tuple[np.ndarray, str]:
    n = mesh.n_vertices
    if not isinstance(spec, str):
        if isinstance(spec, np.ndarray) and spec.dtype == bool or (
                isinstance(spec, (list, tuple)) and spec and all(isinstance(v, (bool, np.bool_)) for v in spec)):
            arr = np.asarray(spec)
            if arr.shape != (n,):
                raise ModelError(f"a boolean node mask ({name}) must have shape ({n},), got {arr.shape}")
            return np.flatnonzero(arr), f"{int(arr.sum())} nodes of a mask"
        idx = validate.nodes(spec, n, name, allow_empty=True)
        return idx, f"{idx.size} listed nodes"
    s = spec.strip()
    groups = mesh.groups
    X = np.asarray(mesh.vertices)
    if s in groups:
        return np.asarray(groups[s], dtype=np.int64), f"group '{s}'"
    if len(s) > 2 and s[0] in _AXES and s[1] in "<>":
        try:
            value = float(s[2:])
        except ValueError:
            value = float("nan")
        if not np.isfinite(value):
            raise ModelError(f"{name} {validate.show(spec)}: write AXIS<VALUE or AXIS>VALUE in metres, e.g. z<0.01")
        c = X[:, _AXES[s[0]]]
        return np.flatnonzero(c < value if s[1] == "<" else c > value), f"{s} m"
    if s.startswith("bottom:"):
        try:
            frac = float(s.split(":", 1)[1])
        except ValueError:
            frac = -1.0
        if not 0 < frac < 1:
            raise ModelError(f"{name} {validate.show(spec)}: bottom:FRACTION needs 0 < FRACTION < 1, e.g. bottom:0.1")
        z = X[:, 2]
        return np.flatnonzero(z <= z.min() + frac * (z.max() - z.min())), f"the lowest {frac * 100:g} % of the height (z)"
    if s.startswith("nodes:"):
        try:
            idx = np.array([int(v) for v in s[6:].split(",") if v.strip()], dtype=np.int64)
        except ValueError:
            raise ModelError(f"{name} {validate.show(spec)}: nodes:i,j,k takes vertex indices") from None
        if idx.size == 0 or idx.min() < 0 or idx.max() >= n:
            raise ModelError(f"{name} {validate.show(spec)}: vertex indices must be in 0..{n - 1}")
        return np.unique(idx), f"{np.unique(idx).size} listed vertices"
    known = ", ".join(sorted(groups)) or "none in this mesh"
    raise ModelError(f"{name} {validate.show(spec)}: no vertex group of that name and not a selection; give "
                     f"{SELECTION_HELP} (groups: {known})")


def select_nodes(mesh, spec, name: str = "nodes") -> np.ndarray:
    """The node indices ``spec`` selects on ``mesh``.

    Parameters
    ----------
    mesh : any mesh with ``vertices``, ``groups`` and ``n_vertices`` (TriMesh, TetMesh).
    spec : node indices, a boolean mask over the nodes, a vertex group's name, a slab
        ``"z<0.01"`` / ``"x>0.1"`` (m), ``"bottom:0.1"`` (the lowest 10 % of the height) or
        ``"nodes:3,7,12"``.
    name : what the selection is for, in error messages.

    Returns
    -------
    numpy.ndarray
        int64 node indices, sorted for slabs, groups and ``nodes:`` lists (indices given as
        integers keep their order); may be empty.

    Raises
    ------
    ModelError
        An index off the mesh, a mask of the wrong shape, an unknown group or a malformed slab
        (the message lists the groups and the forms).
    """
    return _parse(mesh, spec, name)[0]


def describe_selection(mesh, spec, name: str = "nodes") -> tuple[np.ndarray, str]:
    """:func:`select_nodes` and a few words saying what was selected (for messages)."""
    return _parse(mesh, spec, name)


def probe_vertex(model) -> int:
    """The free surface vertex farthest from the supports: where a load moves the organ most."""
    from scipy.spatial import cKDTree

    held = model.held_nodes
    X = np.asarray(model.mesh.vertices)
    d = cKDTree(X[held]).query(X)[0] if held.any() else np.ones(X.shape[0])
    d[held] = -1.0
    surface = model.mesh.used_vertices()  # a solid's interior nodes cannot be touched
    return int(surface[np.argmax(d[surface])])
