"""
Static poke
===========

Load the default liver, fix its attachment, push one point, see how far it moves.

    .venv/bin/python examples/01_static_poke.py [MESH]     (default: the embedded liver)
"""

import sys
from pathlib import Path

import numpy as np

import rtfem as rt

mesh = rt.load_mesh(sys.argv[1]) if len(sys.argv) > 1 else rt.meshes.liver()
model = rt.ShellModel(mesh, rt.Material(E=30e3, nu=0.45, thickness=0.003, density=1000.0))
model.fix("attachment")  # or vertex indices, or a boolean mask

node = mesh.groups["probe"][0]
force = -0.2 * mesh.vertex_normals()[node]  # 0.2 N inward along the surface normal
u = model.solve_static({node: force})  # (n, 3) displacements in metres

print(f"{mesh.n_vertices} vertices, {model.n_dofs} dof")
print(f"the poked vertex moved {np.linalg.norm(u[node]) * 1e3:.2f} mm")
print(f"largest displacement {np.linalg.norm(u, axis=1).max() * 1e3:.2f} mm")
# Clapeyron: the strain energy stored is half the work of the load, U = f . u / 2
print(f"strain energy {0.5 * force @ u[node] * 1e3:.4f} mJ")
Path("out/examples").mkdir(parents=True, exist_ok=True)
rt.io.write_vtu("out/examples/static_poke.vtu", mesh, u)
print("wrote out/examples/static_poke.vtu (open in ParaView)")
