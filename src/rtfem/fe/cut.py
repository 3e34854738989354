"""``rt.cut``: a solid model cut along a triangulated surface (issue 57): the same kind of model, element,
material and fixes on the mesh :func:`rtfem.mesh.cut.cut_mesh` separates along the element faces that
lie in the surface."""

from __future__ import annotations

import warnings

import numpy as np

from .. import validate
from ..errors import ModelError, RtfemWarning
from ..mesh.cut import cut_mesh, extend

__all__ = ["cut"]


def cut(model, vertices, triangles, *, snap: bool | str = True, free: str = "warn", held=None):
    """A new model of the same kind, element, material and fixes as ``model`` (an rt.SolidModel),
    its mesh separated along the element faces that lie in the triangulated surface (``vertices``
    (k, 3) in metres, ``triangles`` (m, 3)): :func:`cut_mesh`. A copy of a fixed node is fixed. The
    model given is left as it was; ``new.cut_info`` says what was done.

    Parameters
    ----------
    model : an rt.SolidModel (tet4, tet4-anp or tet10; any material or law, mass and constraints option).
    vertices, triangles : the cut surface.
    snap : where the surface passes through elements, move their nodes onto it first (True; see
        :func:`rtfem.mesh.cut.cut_mesh`), split those elements instead ("split", tet4 and tet10: the geometry
        unchanged, for a solid cut while it runs), or refuse such a surface (False).
    free : what becomes of a part the cut frees with nothing fixed: "warn" (kept, with a warning: it
        would float) or "remove" (dropped, as a scalpel's cut-away piece falls away:
        ``cut_info.removed`` counts its nodes and ``cut_info.removed_mass`` its kg).
    held : nodes of ``model`` that hold the part they end up in as a fix does (a scene's springs and
        grasps on the body): such a part is not free, and their copies are the new model's ``tethered``
        nodes (a piece only they hold is restrained by the springs: it steps, hanging on them).

    Returns
    -------
    the cut model (assembled when first used, like any model).

    Raises
    ------
    ModelError
        A shell (not cut yet); any refusal of :func:`cut_mesh`; free="remove" with nothing fixed at
        all (every part would go).

    Warns
    -----
    RtfemWarning
        free="warn": when the cut frees a part of the solid that nothing holds (fix it, or cut less).
    """
    from .recipe import ModelRecipe

    if not (hasattr(model, "tetmesh") and hasattr(model, "element")):
        raise ModelError(f"model={validate.show(model)}: cutting needs a solid (rt.SolidModel); a shell cannot be "
                         "cut yet")
    free = validate.choice(free, "free", ("warn", "remove"))
    recipe = ModelRecipe.of(model)
    snap = snap if isinstance(snap, str) and snap == "split" else validate.flag(snap, "snap")
    held = np.zeros(0, dtype=np.int64) if held is None else validate.nodes(held, model.n_nodes, "held", allow_empty=True)
    mesh, info = cut_mesh(model.tetmesh, vertices, triangles, snap=snap)
    fixed = extend(np.asarray(recipe.fixed, dtype=bool), info.split)[info.parent]
    holding = fixed.any(axis=1)
    if held.size:  # and the copies of the nodes that hold their part
        holding |= np.isin(info.parent, held)
    kept = np.zeros(info.pieces, dtype=bool)  # the parts something holds
    kept[info.piece[holding]] = True
    info["removed"], info["removed_mass"] = 0, 0.0
    if not kept.all() and free == "remove":
        if not kept.any():
            raise ModelError("free='remove' with nothing fixed or held: every part of the solid would be removed; fix "
                             "the model first")
        mesh, info, fixed = _drop_free(mesh, info, fixed, kept, _densities(recipe.material, mesh.labels))
    elif not kept.all() and fixed.any():
        warnings.warn(f"the cut frees {int((~kept).sum())} of {info.pieces} parts of the solid with nothing fixed: "
                      "they would float; fix a node of each, or cut less (or free='remove')", RtfemWarning, stacklevel=2)
    new = ModelRecipe(mesh, recipe.material, recipe.options, fixed, "", recipe.kind).build()
    new.cut_info = info
    if held.size:  # a piece only they hold is restrained by their springs
        new.tethered = np.flatnonzero(np.isin(info.parent, held))
    return new


def _densities(material, labels: np.ndarray) -> np.ndarray:
    """Each tet's density: the material's, or its region's (a model of several regions)."""
    if not isinstance(material, dict):
        return np.full(labels.shape, float(material.density))
    out = np.zeros(labels.shape)
    for label, law in material.items():
        out[labels == label] = law.density
    return out


def _drop_free(mesh, info, fixed, held, density):
    """The cut mesh without its parts that nothing holds, ``info`` told (``kept``, ``removed``,
    ``removed_mass``; ``parent``, ``piece`` of the nodes kept) and the fixes of the nodes kept."""
    from ..mesh.tetmesh import TetMesh

    keep = np.flatnonzero(held[info.piece])
    new_index = np.full(mesh.n_vertices, -1)
    new_index[keep] = np.arange(keep.size)
    T = np.asarray(mesh.tets)
    inside = (new_index[T] >= 0).all(axis=1)
    lost = float((np.asarray(mesh.volumes()) * density)[~inside].sum())
    groups = {k: new_index[v][new_index[v] >= 0] for k, v in mesh.groups.items()}
    out = TetMesh(np.asarray(mesh.vertices)[keep], new_index[T[inside]], repair=False, merge_tol=0.0, groups=groups,
                  labels=mesh.labels[inside], region_names=mesh.region_names)
    info = type(info)(info)
    pieces = np.unique(info.piece[keep], return_inverse=True)[1]
    info.update(parent=info.parent[keep], piece=pieces.ravel(), pieces=int(held.sum()), kept=keep,
                removed=int(mesh.n_vertices - keep.size), removed_mass=lost)
    return out, info, fixed[keep]
