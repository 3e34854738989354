"""Finite elements: materials, shell and solid elements (linear and corotational), the models
(the Model protocol, ShellModel, SolidModel), factorizations and full-order nonlinear statics."""

from ..lazy import submodules  # noqa: E402

__getattr__ = submodules(__name__)  # submodules on first use (rt.mesh.meshing)
