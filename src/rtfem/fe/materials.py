"""``rt.materials``: the materials in one place (issue 58's name for them): the linear
:class:`~rtfem.Material`, the hyperelastic laws, the Prony series, the sourced tissue sets
(:func:`tissue`, :func:`tissues`: :mod:`rtfem.fe.tissues`) and :func:`fit_material` (a user's own
curve)."""

from __future__ import annotations

from .fitting import fit_material
from .hyperelastic import MooneyRivlin, NeoHookean, Ogden
from .material import Material
from .tissues import TissueSet, tissue, tissues
from .viscoelastic import Prony

__all__ = ["Material", "NeoHookean", "MooneyRivlin", "Ogden", "Prony", "tissue", "tissues", "TissueSet",
           "fit_material"]
