"""Precompute stages on a Dask cluster (issue 42 item 5): the default liver's impedance map and its
reduced model's modal derivatives, here (serial, as before) and on LocalClusters of 1 and 2 worker
processes on this machine: wall time, speed-up against here, the data a task carries and brings back,
what is sent to each worker once, and each worker's memory (resident set) after the run. Every
cluster result is checked equal to the serial one.

    python benchmarks/cluster.py [--nodes 600] [--modes 40] [--derivatives 20] [--solid] [--busy]
"""

from __future__ import annotations

import argparse
import os
import pickle
import platform
import sys
import time

import numpy as np

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from _common import busy_core, print_table  # noqa: E402

import rtfem as rt  # noqa: E402
from rtfem.cluster import connect  # noqa: E402
from rtfem.fe.recipe import ModelRecipe  # noqa: E402
from rtfem.reduction.reduced import ReducedNonlinearModel  # noqa: E402


def _model(solid: bool):
    mesh = rt.meshes.liver(solid=solid)
    model = rt.SolidModel(mesh, rt.Material(), element="tet10") if solid else rt.ShellModel(mesh, rt.Material())
    return model.fix("attachment")


def _worker_memory(client) -> str:
    import psutil

    rss = client.run(lambda: psutil.Process().memory_info().rss)
    return ", ".join(f"{v / 2**20:.0f}" for v in rss.values())


def run(args) -> list:
    model = _model(args.solid)
    modes = rt.modal_analysis(model, args.modes)
    free = np.flatnonzero(~model.held_nodes[model.mesh.used_vertices()])
    nodes = model.mesh.used_vertices()[free][:: max(1, free.size // args.nodes)][: args.nodes]
    kw = dict(modes=modes, n_modes=args.modes, nodes=nodes, radius=0.03, times=(0.01, 0.05, 0.2))
    recipe = len(pickle.dumps(ModelRecipe.of(model)))
    t0 = time.perf_counter()
    ref = rt.ImpedanceMap.build(model, **kw)
    t_map = time.perf_counter() - t0
    t0 = time.perf_counter()
    red = ReducedNonlinearModel(model, modes, args.derivatives)
    t_der = time.perf_counter() - t0
    per_node = (ref.responses.nbytes + ref.point.nbytes) / ref.loaded.size
    rows = [["map", "here", f"{t_map:.1f}", "1.00", "-", "-", "-"],
            ["derivatives", "here", f"{t_der:.1f}", "1.00", "-", "-", "-"]]
    print(rows[0], rows[1], flush=True)
    for n in (1, 2):
        with connect(f"local:{n}") as client:
            client.run(lambda: None)  # the workers up before the clock starts
            t0 = time.perf_counter()
            imap = rt.ImpedanceMap.build(model, scheduler=client, **kw)
            t1 = time.perf_counter()
            assert np.abs(imap.responses - ref.responses).max() <= 1e-12 * np.abs(ref.responses).max()
            chunk = int(np.clip(np.ceil(nodes.size / (4 * n)), 1, 32))
            once = recipe + modes.shapes.nbytes + modes.omega.nbytes
            rows.append(["map", f"local:{n}", f"{t1 - t0:.1f}", f"{t_map / (t1 - t0):.2f}",
                         f"{chunk} nodes in, {chunk * per_node / 2**20:.1f} MiB back", f"{once / 2**20:.1f} MiB",
                         _worker_memory(client)])
            print(rows[-1], flush=True)
            t0 = time.perf_counter()
            other = ReducedNonlinearModel(model, modes, args.derivatives, scheduler=client)
            t1 = time.perf_counter()
            assert np.abs(other.basis - red.basis).max() <= 1e-12 * np.abs(red.basis).max()
            Phi = red.free.size * args.derivatives * 8
            rows.append(["derivatives", f"local:{n}", f"{t1 - t0:.1f}", f"{t_der / (t1 - t0):.2f}",
                         f"1 mode in, {Phi / 2**20:.1f} MiB back", f"{(recipe + Phi) / 2**20:.1f} MiB",
                         _worker_memory(client)])
            print(rows[-1], flush=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--nodes", type=int, default=600, help="loaded nodes of the map (spread over the free surface)")
    ap.add_argument("--modes", type=int, default=40)
    ap.add_argument("--derivatives", type=int, default=20)
    ap.add_argument("--solid", action="store_true", help="the solid liver (tet10) instead of the shell")
    ap.add_argument("--busy", action="store_true", help="with another process keeping one core busy")
    args = ap.parse_args()
    print(f"# rtfem {rt.__version__}, python {platform.python_version()}, {os.cpu_count()} cores; "
          f"{'solid tet10' if args.solid else 'shell'} liver, {args.nodes} loaded nodes, {args.modes} modes, "
          f"derivatives of {args.derivatives}{', one core busy' if args.busy else ''}")
    with busy_core(args.busy):
        rows = run(args)
    print_table(["stage", "where", "seconds", "speed-up", "a task", "sent once to each worker",
                 "worker RSS (MiB)"], rows)


if __name__ == "__main__":
    main()
