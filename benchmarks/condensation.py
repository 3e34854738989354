"""Bro-Nielsen & Cotin's surface condensation against solves: where the static surface compliance
of a solid organ comes from.

A volumetric organ is drawn and touched on its surface, so what a static (or impedance-map) route
needs is the block C of K^-1 between the surface nodes' translations. Three ways to get it, timed in
the same run on the solid liver (``rt.meshes.liver(solid=True, spacing=...)``, tet4, fixed at its
attachment; the factorization of K is made before and not counted):
- one by one: three single sparse solves per surface node (what the impedance map's static limits
  cost node after node; timed on ``--sample`` nodes, scaled to the surface);
- batched solves: ``model.surface_compliance()``, multi-column solves with the same factorization;
- condensation: ``model.surface_compliance(method="condensation")``, the Schur complement
  K* = K_SS - K_SI K_II^-1 K_IS (a factorization of the interior block, solves with K_IS's columns)
  and its dense Cholesky inverse, Bro-Nielsen & Cotin's route.
Then the impedance map (modal route, 40 modes, radius 3 cm) over ``--map-nodes`` surface nodes and
over the whole surface, with the static limits from solves and from the condensation.

    python benchmarks/condensation.py [--spacing 0.007 0.01] [--map-nodes 200]
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from _common import fmt_s, print_table  # noqa: E402

import rtfem as rt  # noqa: E402


def row(spacing: float, sample: int, map_nodes: int) -> tuple[list, list]:
    model = rt.SolidModel(rt.meshes.liver(solid=True, spacing=spacing), rt.Material()).fix("attachment")
    model.factorization()
    used = model.mesh.used_vertices()
    surface = used[~model.fixed[used, :3].all(axis=1)]
    t0 = time.perf_counter()
    for j in surface[np.linspace(0, surface.size - 1, sample).astype(int)].tolist():
        for k in range(3):
            model.unit_load_response(j, k)
    one = (time.perf_counter() - t0) / sample * surface.size
    t0 = time.perf_counter()
    _, C = model.surface_compliance()
    solves = time.perf_counter() - t0
    t0 = time.perf_counter()
    _, C_c = model.surface_compliance(method="condensation")
    cond = time.perf_counter() - t0
    err = np.abs(C - C_c).max() / np.abs(C).max()
    rows = [[f"{model.n_nodes:,}", f"{surface.size:,}", f"{C.shape[0]:,}^2 ({C.nbytes / 2**20:.0f} MiB)", fmt_s(one),
             fmt_s(solves), fmt_s(cond), f"{one / cond:.1f}x", f"{solves / cond:.2f}x", f"{err:.0e}"]]
    modes = rt.modal_analysis(model, 40)
    maps = []
    for count in (map_nodes, surface.size):
        nodes = surface[np.linspace(0, surface.size - 1, min(count, surface.size)).astype(int)]
        times = {}
        for static in ("solves", "condensation"):
            t0 = time.perf_counter()
            m = rt.ImpedanceMap.build(model, rt.Damping(alpha=5.0), nodes=nodes, radius=0.03, modes=modes,
                                      static=static)
            times[static] = (time.perf_counter() - t0, m.neighbours.size / nodes.size)
        maps.append([f"{model.n_nodes:,}", f"{nodes.size:,} of {surface.size:,}", fmt_s(times["solves"][0]),
                     f"{times['solves'][1]:.0f}", fmt_s(times["condensation"][0]), f"{times['condensation'][1]:.0f}",
                     f"{times['solves'][0] / times['condensation'][0]:.2f}x"])
    return rows, maps


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--spacing", type=float, nargs="+", default=[0.01, 0.007], help="tet edge lengths (m)")
    ap.add_argument("--sample", type=int, default=100, help="surface nodes timed one by one")
    ap.add_argument("--map-nodes", type=int, default=200, help="loaded nodes of the smaller map")
    args = ap.parse_args()
    print(f"# {' '.join(['python', *sys.argv])}; backends {', '.join(rt.available_backends())}")
    rows, maps = [], []
    for spacing in args.spacing:
        r, m = row(spacing, args.sample, args.map_nodes)
        rows += r
        maps += m
    print_table(["nodes", "surface nodes", "surface compliance", "one by one (3 solves per node)", "batched solves",
                 "condensation (Schur + dense inverse)", "one by one / condensation", "batched / condensation",
                 "condensation vs solves"], rows)
    print()
    print_table(["nodes", "loaded surface nodes", "map, static by solves", "kept per node",
                 "map, static by condensation", "kept per node", "solves / condensation"], maps)


if __name__ == "__main__":
    main()
