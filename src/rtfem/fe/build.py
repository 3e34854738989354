"""Building the model of a mesh: one place where a new kind of model is added."""

from __future__ import annotations

from ..mesh.tetmesh import TetMesh
from .material import Material
from .shellmodel import ShellModel
from .solidmodel import SolidModel

__all__ = ["make_model"]


def make_model(mesh, material: Material, **options):
    """The model of ``mesh``: a :class:`ShellModel` for a triangle surface, a
    :class:`~rtfem.SolidModel` for a :class:`~rtfem.TetMesh` (``element``, ``mass`` among the
    options). Where the CLI and the viewer build models, so that a new kind is added in one place."""
    if isinstance(mesh, TetMesh):
        return SolidModel(mesh, material, **options)
    return ShellModel(mesh, material, **options)
