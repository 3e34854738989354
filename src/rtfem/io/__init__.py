"""Exports (VTU, PVD) and load schedules with headless runs. Saved files: rtfem.storage."""

from .vtk import write_pvd, write_vtu

__all__ = ["write_vtu", "write_pvd"]

from ..lazy import submodules  # noqa: E402

__getattr__ = submodules(__name__)  # submodules on first use (rt.mesh.meshing)
