"""Meshes: surfaces (TriMesh) and tetrahedra (TetMesh), their repairs and reports, mesh files,
generated shapes (plate ... liver), tetrahedralization and node selection. Imports only the core."""

from ..lazy import submodules  # noqa: E402

__getattr__ = submodules(__name__)  # submodules on first use (rt.mesh.meshing)
