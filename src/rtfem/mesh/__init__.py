"""Meshes: surfaces (TriMesh) and tetrahedra (TetMesh), their repairs and reports, mesh files,
generated shapes (plate ... liver), tetrahedralization and node selection. Imports only the core."""
