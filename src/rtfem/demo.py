"""`make demo`: the default liver, fixed at its attachment, poked at one surface node.

Run with ``python -m rtfem.demo [--out DIR]``.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

import rtfem as rt
from rtfem.io import write_vtu


def static_poke(out: Path, force: float = 0.2) -> dict:
    t0 = time.perf_counter()
    mesh = rt.meshes.liver()
    t_mesh = time.perf_counter() - t0
    material = rt.Material()
    model = rt.ShellModel(mesh, material)
    model.fix("attachment")
    # poke the anterior edge of the left lobe, inward along the surface normal
    node = mesh.nearest_vertex([0.055, 0.05, 0.0])
    normal = mesh.vertex_normals()[node]
    t0 = time.perf_counter()
    K = model.K
    t_assemble = time.perf_counter() - t0
    t0 = time.perf_counter()
    model.factorization()
    t_factor = time.perf_counter() - t0
    t0 = time.perf_counter()
    u = model.solve_static({node: -force * normal})
    t_solve = time.perf_counter() - t0
    mag = np.linalg.norm(u, axis=1)
    path = write_vtu(out / "liver_static.vtu", mesh, u)

    print("rtfem demo: static poke of the default liver")
    print(f"  mesh        {mesh.n_vertices} vertices, {mesh.n_triangles} triangles, "
          f"extent {np.array2string((mesh.bounds()[1] - mesh.bounds()[0]) * 1e3, precision=0)} mm "
          f"(generated in {t_mesh * 1e3:.0f} ms)")
    print(f"  material    E = {material.E:.3g} Pa, nu = {material.nu}, t = {material.thickness * 1e3:.1f} mm, "
          f"rho = {material.density:.0f} kg/m^3")
    print(f"  model       {model.n_dofs} dof, K with {K.nnz} nonzeros, "
          f"{mesh.groups['attachment'].size} nodes fixed at the attachment")
    print(f"  timings     assemble {t_assemble * 1e3:.0f} ms, factorize {t_factor * 1e3:.0f} ms "
          f"({model.factorization().backend}), solve {t_solve * 1e3:.1f} ms")
    print(f"  load        {force} N at node {node}, inward along the surface normal")
    print(f"  result      contact node moved {mag[node] * 1e3:.2f} mm; peak displacement "
          f"{mag.max() * 1e3:.2f} mm at node {int(mag.argmax())}")
    print(f"  wrote       {path}  (open in ParaView; colour by displacement_magnitude)")
    return {"node": node, "u": u}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m rtfem.demo", description=__doc__)
    ap.add_argument("--out", default="out/demo", help="folder for the output files (default: out/demo)")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    static_poke(out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
