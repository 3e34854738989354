"""Tissue laws on the default liver (issue 41 item 6): what a law costs at run time and how it changes
the force a probe feels.

1. The viewer's step (``rtfem view --benchmark``: the solid liver of tet10, the reduced nonlinear model,
   a 3 cm scripted pull) with the corotated linear material (the default) and each hyperelastic law of
   the same initial moduli (mu, kappa of E = 30 kPa, nu = 0.45): p50 / p99 and the ratio to the
   corotated step measured in the same run.
   A Prony law (neo-Hookean + Prony, g 0.5, tau 0.5 s) steps its cubature elements' history too.
2. The indentation curve: the full-order static force (rt.nonlinear.solve_static) of a flat punch, the
   surface nodes within 6 mm of the default probe vertex moved together along its inward normal, at
   depths of 1, 2, 4 and 8 mm, per law, next to the linear model's (force proportional to depth).

The Mooney-Rivlin and Ogden parameters below are illustrative shapes of the same initial shear
modulus (C01 = 0.3 mu / 2; Ogden alpha = 8 and -2), not a fit to liver data.

    python benchmarks/materials.py [--seconds 5] [--depths 1 2 4 8] [--skip-steps | --skip-indentation]
                                   [--laws WORD ...] [--busy]
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time

import numpy as np

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from _common import busy_core, print_table  # noqa: E402

import rtfem as rt  # noqa: E402


def laws(material: rt.Material) -> dict:
    mu, kappa = material.G, material.E / (3 * (1 - 2 * material.nu))
    rho = material.density
    return {"corotated (linear)": material,
            "neo-Hookean": rt.NeoHookean(mu, kappa, rho),
            "Mooney-Rivlin (C01 = 0.3 mu/2)": rt.MooneyRivlin(0.35 * mu, 0.15 * mu, kappa, rho),
            "Ogden (alpha 8, -2)": rt.Ogden([0.8 * mu, 0.2 * mu], [8.0, -2.0], kappa, rho),
            "neo-Hookean + Prony (g 0.5, tau 0.5 s)": rt.Prony(rt.NeoHookean(mu, kappa, rho), [0.5], [0.5])}


def step_costs(seconds: float, only=None, busy: bool = False) -> list:
    from rtfem.viewer.benchmark import run
    from rtfem.viewer.session import Session, Settings

    mesh = rt.meshes.liver(solid=True)
    rows, base = [], None
    for name, law in laws(rt.Material()).items():
        if only and not name.startswith("corotated") and not any(w.lower() in name.lower() for w in only):
            continue
        session = Session(mesh, law, "attachment", Settings(method="nonlinear"), {"element": "tet10"})
        with busy_core(busy):
            r = run(session, seconds)
        base = base or r["step_p50_us"]
        rows.append([name, f"{r['step_p50_us']:,.0f} / {r['step_p99_us']:,.0f}", f"{r['step_p50_us'] / base:.2f}",
                     f"{r['realtime']:.2f}", f"{r['max_force_N']:.3f}", f"{r['peak_mm']:.1f}", r["error"] or "-"])
        print(rows[-1], flush=True)
    return rows


def indentation(depths: list[float]) -> tuple[list, list]:
    mesh = rt.meshes.liver(solid=True)
    material = rt.Material()
    probe = int(mesh.surface.groups["probe"][0]) if "probe" in (mesh.surface.groups or {}) else None
    curves, seconds = {}, {}
    for name, law in laws(material).items():
        if isinstance(law, rt.Prony):  # without time it is its long-term law: the neo-Hookean at g_inf mu
            continue
        model = rt.SolidModel(mesh, law, element="tet10")
        model.fix("attachment")
        X = np.asarray(model.tetmesh.vertices)
        node = probe if probe is not None else rt.mesh.selection.probe_vertex(model)
        normal = model.mesh.vertex_normals()[node]
        surface = model.mesh.used_vertices()
        punch = surface[np.linalg.norm(X[surface] - X[node], axis=1) <= 0.006]
        model.fix(punch)
        forces, t0 = [], time.perf_counter()
        for d in ([0.01] if name.startswith("corotated") else []) + list(depths):
            prescribed = np.zeros((model.n_nodes, 3))
            prescribed[punch] = -d * 1e-3 * normal
            r = rt.nonlinear.solve_static(model, prescribed=prescribed, steps=4)
            forces.append(-float(r.reactions[punch].sum(axis=0) @ normal))  # the punch pushing the organ inward (N)
        if name.startswith("corotated"):  # its 0.01 mm slope: the linear model's stiffness
            curves["linear"], forces = [forces[0] / 0.01 * d for d in depths], forces[1:]
        curves[name], seconds[name] = forces, time.perf_counter() - t0
        print(name, [f"{v:.3f}" for v in forces], f"{seconds[name]:.0f} s", flush=True)
    rows = [[f"{d:g}"] + [f"{curves[n][i]:.3f}" for n in curves] for i, d in enumerate(depths)]
    return list(curves), rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--depths", type=float, nargs="+", default=[1.0, 2.0, 4.0, 8.0])
    ap.add_argument("--skip-steps", action="store_true", help="only the indentation curves")
    ap.add_argument("--skip-indentation", action="store_true", help="only the step costs")
    ap.add_argument("--busy", action="store_true", help="the step costs with another process keeping one core busy")
    ap.add_argument("--laws", nargs="+", default=None, metavar="WORD",
                    help="only the laws whose name contains one of these words (the corotated row is always measured: "
                         "the ratios' baseline)")
    args = ap.parse_args()
    print(f"# rtfem {rt.__version__}, python {platform.python_version()}, {os.cpu_count()} cores")
    if not args.skip_steps:
        print_table(["law", "step p50 / p99 (us)", "p50 / corotated", "real time", "max force (N)", "peak (mm)", "error"],
                    step_costs(args.seconds, args.laws, args.busy))
    if not args.skip_indentation:
        names, rows = indentation(args.depths)
        print_table(["depth (mm)"] + [f"{n} (N)" for n in names], rows)


if __name__ == "__main__":
    main()
