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


def cut(model, vertices, triangles, *, snap: bool = True):
    """A new model of the same kind, element, material and fixes as ``model`` (an rt.SolidModel),
    its mesh separated along the element faces that lie in the triangulated surface (``vertices``
    (k, 3) in metres, ``triangles`` (m, 3)): :func:`cut_mesh`. A copy of a fixed node is fixed. The
    model given is left as it was; ``new.cut_info`` says what was done.

    Parameters
    ----------
    model : an rt.SolidModel (tet4, tet4-anp or tet10; any material or law, mass and constraints option).
    vertices, triangles : the cut surface.
    snap : where the surface passes through elements, move their nodes onto it first (see
        :func:`rtfem.mesh.cut.cut_mesh`); False refuses such a surface.

    Returns
    -------
    the cut model (assembled when first used, like any model).

    Raises
    ------
    ModelError
        A shell (not cut yet); any refusal of :func:`cut_mesh`.

    Warns
    -----
    RtfemWarning
        When the cut frees a part of the solid that nothing holds (it would float: fix it, or cut less).
    """
    from .recipe import ModelRecipe

    if not (hasattr(model, "tetmesh") and hasattr(model, "element")):
        raise ModelError(f"model={validate.show(model)}: cutting needs a solid (rt.SolidModel); a shell cannot be "
                         "cut yet")
    recipe = ModelRecipe.of(model)
    mesh, info = cut_mesh(model.tetmesh, vertices, triangles, snap=validate.flag(snap, "snap"))
    fixed = extend(np.asarray(recipe.fixed, dtype=bool), info.split)[info.parent]
    new = ModelRecipe(mesh, recipe.material, recipe.options, fixed, "", recipe.kind).build()
    new.cut_info = info
    if fixed.any():
        held = np.zeros(info.pieces, dtype=bool)
        held[info.piece[fixed.any(axis=1)]] = True
        if not held.all():
            warnings.warn(f"the cut frees {int((~held).sum())} of {info.pieces} parts of the solid with nothing fixed: "
                          "they would float; fix a node of each, or cut less", RtfemWarning, stacklevel=2)
    return new
