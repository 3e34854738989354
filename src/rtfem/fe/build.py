"""Building the model of a mesh: one place where a new kind of model is added."""

from __future__ import annotations

from ..mesh.tetmesh import TetMesh
from .material import Material
from .shellmodel import ShellModel
from .solidmodel import SolidModel

__all__ = ["make_model"]


def make_model(mesh, material: Material, **options):
    """The model of ``mesh``: where the CLI and the viewer build models, so that a new kind is
    added in one place.

    Parameters
    ----------
    mesh : a :class:`~rtfem.TriMesh` (a shell) or a :class:`~rtfem.TetMesh` (a solid).
    material : the :class:`~rtfem.Material`.
    options : the model's keyword arguments (a solid's ``element``, ``mass``; a shell's
        ``membrane``, ...).

    Returns
    -------
    ShellModel or SolidModel

    Raises
    ------
    ModelError, MeshError
        What the model's constructor raises (an unknown option, a degenerate mesh).
    """
    if isinstance(mesh, TetMesh):
        return SolidModel(mesh, material, **options)
    return ShellModel(mesh, material, **options)
