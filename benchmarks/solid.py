"""Solid (tetrahedral) organs: the reduced model against the full-order one on a liver of the
size of SOFA's ModelOrderReduction scene (4,293 nodes, 22,019 tets: 0.62 frames/s full order,
262.6 reduced, about 420x), and every shared organ file through the mesher.

Scene: ``rt.meshes.liver(solid=True, spacing=--spacing)`` (default 7 mm: about 4,300 nodes),
E 3e4, nu 0.45, rho 1060, fixed at its attachment; tet4 and tet10 rows, lumped mass.
Columns: assembly, factorization (the constrained stiffness, the model's backend), r modes, the
modal haptic step (one loaded node and its displacement, static correction on), the modal
full-field step (a step plus the (n, 3) field), the full-order implicit Newmark step (one sparse
solve with the factorized effective stiffness, the field included) and their ratios, measured in
the same run; and the compiled 1 kHz probe loop (a probe pressing 4 mm into the "probe" vertex)
for --loop-seconds. ``--organs`` meshes every file of ../shared/data/organs (fTetWild, default
edge length) and prints nodes, tets, quality and seconds, or the refusal.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from _common import fmt_s, print_table  # noqa: E402

import rtfem as rt  # noqa: E402
from rtfem.cli.bench import per_step  # noqa: E402

ORGANS = Path(__file__).resolve().parents[2] / "shared" / "data" / "organs"
SCALES = {".stl": 1e-3, ".vtk": 1e-3}  # the OpenHELP/sofa_env and GCA files are in millimetres


def dynamics_rows(mesh, element: str, modes_list, loop_seconds: float) -> list[list]:
    mat = rt.Material(E=3e4, nu=0.45, density=1060.0)
    model = rt.SolidModel(mesh, mat, element=element).fix("attachment")
    t0 = time.perf_counter()
    model.K  # noqa: B018 - assembly
    t_asm = time.perf_counter() - t0
    t0 = time.perf_counter()
    fac = model.factorization()
    t_fac = time.perf_counter() - t0
    node = int(mesh.groups["probe"][0])
    damping = rt.Damping(alpha=8.0)
    f = (0.0, 0.0, -0.1)
    direct = rt.DirectSimulator(model, 1e-3, damping)

    def full_step():
        direct.step({node: f})
        direct.displacements()

    t_direct = per_step(full_step, 3)
    rows = []
    for r in modes_list:
        t0 = time.perf_counter()
        basis = rt.modal_analysis(model, r)
        t_modes = time.perf_counter() - t0
        sim = rt.ModalSimulator(basis, 1e-3, damping, static_correction=True)

        def haptic():
            sim.step({node: f})
            sim.displacement(node)

        def field():
            sim.step({node: f})
            sim.displacements()

        t_h, t_f = per_step(haptic, 20), per_step(field, 5)
        loop = loop_row(mesh, model, sim, node, loop_seconds) if r == modes_list[-1] and loop_seconds > 0 else "-"
        rows.append([element, f"{model.n_nodes:,}", f"{mesh.n_tets:,}", f"{model.n_dofs:,}", fmt_s(t_asm),
                     f"{fmt_s(t_fac)} ({fac.backend})", r, fmt_s(t_modes), fmt_s(t_h), fmt_s(t_f), fmt_s(t_direct),
                     f"{t_direct / t_h:,.0f}x", f"{t_direct / t_f:,.0f}x", loop])
    return rows


def loop_row(mesh, model, sim, node: int, seconds: float) -> str:
    X = np.asarray(model.mesh.vertices)[node]
    n = model.mesh.vertex_normals()[node]
    probe = rt.Probe(model.mesh, sim, stiffness=200.0)
    probe.prepare(around=X, radius=0.01)
    device = rt.ScriptedDevice.press(X, n, 0.004, seconds, approach=0.001)
    stats = rt.HapticLoop(probe, device, rate=1000).run(seconds)
    c = np.asarray(stats.compute) * 1e6
    return (f"{stats.steps} ticks, {stats.missed} skipped, compute p50 {np.median(c):.1f} / p99 "
            f"{np.percentile(c, 99):.1f} us, period err p99 {stats.period_error(0.99) * 1e6:.1f} us"
            f"{' (compiled)' if stats.compiled else ''}")


def organ_rows() -> list[list]:
    rows = []
    for path in sorted(ORGANS.glob("*.*")):
        if path.suffix == ".md":
            continue
        surface = rt.load_mesh(path, scale=SCALES.get(path.suffix, 1.0))
        t0 = time.perf_counter()
        try:
            tets = rt.tetrahedralize(surface)
        except rt.RtfemError as exc:
            rows.append([path.name, f"{surface.n_vertices:,}", "refused", str(exc)[:80], "-", "-", "-"])
            continue
        dt = time.perf_counter() - t0
        q = tets.quality()
        rows.append([path.name, f"{surface.n_vertices:,}", f"{tets.n_vertices:,}", f"{tets.n_tets:,}",
                     f"{q.radius_ratio.min():.3f} / {np.median(q.radius_ratio):.3f}",
                     f"{tets.volume() / surface.volume():.4f}", f"{dt:.1f} s"])
        print(f"  {path.name}: {dt:.1f} s", flush=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--spacing", type=float, default=0.007, help="tet edge length of the solid liver (m)")
    ap.add_argument("--modes", type=int, nargs="+", default=[20, 40, 100])
    ap.add_argument("--elements", nargs="+", default=["tet4", "tet10"])
    ap.add_argument("--loop-seconds", type=float, default=5.0)
    ap.add_argument("--organs", action="store_true", help="also mesh every shared organ file")
    args = ap.parse_args()
    print(f"# {' '.join(['python', *sys.argv])}")
    print(f"# {platform.processor() or platform.machine()}, {os.cpu_count()} cores, backends "
          f"{', '.join(rt.available_backends())}")
    t0 = time.perf_counter()
    mesh = rt.meshes.liver(solid=True, spacing=args.spacing)
    print(f"# solid liver: {mesh.n_vertices:,} nodes, {mesh.n_tets:,} tets, {mesh.surface.n_triangles:,} surface "
          f"triangles ({time.perf_counter() - t0:.1f} s, from the mesh cache when it was made before); quality: "
          f"{mesh.quality()}")
    rows = []
    for element in args.elements:
        rows += dynamics_rows(mesh, element, args.modes, args.loop_seconds)
    print()
    print_table(["element", "nodes", "tets", "dof", "assembly", "factorize", "r", "modes", "haptic step",
                 "field step", "full Newmark step", "full / haptic", "full / field", "1 kHz probe loop"], rows)
    if args.organs:
        print("\n# every shared organ through rt.tetrahedralize (fTetWild, 5 % of the diagonal, 1 thread)")
        print_table(["organ file", "surface vertices", "nodes", "tets", "radius ratio min / median",
                     "volume / surface volume", "meshing"], organ_rows())


if __name__ == "__main__":
    main()
