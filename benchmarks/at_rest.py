"""The full-order large-deformation step of a solid at rest (no load, nothing moving): what the viewer's
``direct`` method steps until the organ is grasped, and after it has settled.

Before 7e1de8a the lagged step's chord read the roundoff residual of an organ at rest (forces that vanish,
~1e-12 N) as a stalled iteration and took every such step by Newton's method. Rows: the viewer's block of
tests/test_viewer_browser.py's ctrl+drag test (0.1 x 0.02 x 0.02 m, 20 x 4 x 4 cells, tet4, clamped at both
ends, dt 2 ms) and the tet4 liver of benchmarks/fullorder.py (dt 1 ms), ``--steps`` steps from rest, with
the code at ``--baseline`` (a temporary git worktree; default 7938eed, the commit before) and with the
working tree, each in a fresh process, alternating, ``--runs`` times: the step's p50 and p99 (medians over
the runs), the Newton steps and factorizations, the largest displacement (roundoff), the ratio of the
p50s; quiet, and with ``--busy`` another process spinning.

    python benchmarks/at_rest.py [--steps 200] [--runs 2] [--busy] [--baseline 7938eed]
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from _common import baseline_tree, busy_core, child, fmt_s, print_table  # noqa: E402
from fullorder import organ  # noqa: E402

import rtfem as rt  # noqa: E402

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent


def block():
    mesh = rt.meshes.box(0.1, 0.02, 0.02, nx=20, ny=4, nz=4)
    model = rt.SolidModel(mesh, rt.Material(E=3e5, nu=0.45, density=1060.0), element="tet4")
    model.fix(np.concatenate([mesh.groups["x0"], mesh.groups["x1"]]))
    return model, 2e-3, rt.Damping(alpha=8.0)


def liver():
    return organ()[0], 1e-3, rt.Damping(alpha=8.0)


def steps(model, dt, damping, n: int, **options):
    sim = rt.DirectSimulator(model, dt, damping, large_deformation=True, **options)
    sim.step(None)  # the first factorization, not timed
    times = []
    for _ in range(n):
        t0 = time.perf_counter()
        sim.step(None)
        times.append(time.perf_counter() - t0)
    return np.array(times), sim


def one(name: str, n: int) -> None:
    """The child: ``n`` timed steps of the organ ``name`` with the rtfem on PYTHONPATH, as a JSON line."""
    model, dt, damping = {"block": block, "liver": liver}[name]()
    times, sim = steps(model, dt, damping, n)
    print(json.dumps(dict(p50=float(np.median(times)), p99=float(np.percentile(times, 99)), newton=sim.newton_steps,
                          factorizations=sim.refreshes, u=float(np.abs(sim.displacements()).max()),
                          tets=len(model.tetmesh.tets), nodes=model.n_nodes)))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--runs", type=int, default=2)
    ap.add_argument("--busy", action="store_true", help="another process keeps one core busy meanwhile")
    ap.add_argument("--baseline", default="7938eed")
    ap.add_argument("--one", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.one:
        return one(args.one, args.steps)
    print(f"# at rest, {args.steps} steps each, {args.runs} fresh processes per cell; "
          f"{platform.processor() or platform.machine()}, {'one core busy' if args.busy else 'quiet'}", flush=True)
    res: dict = {}
    with baseline_tree(args.baseline) as (base, short):
        trees = {f"baseline {short}": base / "src", "now (working tree)": ROOT / "src"}
        with busy_core(args.busy):
            for _ in range(args.runs):
                for name in ("block", "liver"):
                    for code, src in trees.items():
                        run = child("at_rest.py", src, "--one", name, "--steps", str(args.steps))
                        res.setdefault((name, code), []).append(run)
    rows = []
    for name in ("block", "liver"):
        p50 = {}
        for code in trees:
            rs = res[(name, code)]
            p50[code] = float(np.median([r["p50"] for r in rs]))
            rows.append([name, rs[0]["tets"], rs[0]["nodes"], code, fmt_s(p50[code]),
                         fmt_s(float(np.median([r["p99"] for r in rs]))), max(r["newton"] for r in rs),
                         max(r["factorizations"] for r in rs), f"{max(r['u'] for r in rs):.1e}"])
        rows[-1].append(f"{p50[next(iter(trees))] / p50['now (working tree)']:.0f}x faster")
        rows[-2].append("")
    print_table(["organ", "tets", "nodes", "code", "step p50", "step p99", "Newton steps", "factorizations",
                 "max |u| (m)", "p50 ratio"], rows)


if __name__ == "__main__":
    main()
