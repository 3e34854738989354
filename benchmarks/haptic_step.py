"""The haptic step from Python, numpy path against the compiled (numba) path, in one run:
``sim.step({p: f}); sim.displacement(p)`` timed per call, one loaded node, 20,000 calls after
2,000 warm-up calls; medians and 99th percentiles; the final states of both paths compared."""

from __future__ import annotations

import argparse
import platform
import sys
import time

import numpy as np

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from _common import print_table  # noqa: E402

import rtfem as rt  # noqa: E402
from rtfem.drivers import kernels  # noqa: E402


def timed(sim, node, f, n):
    for _ in range(2000):
        sim.step({node: f})
        sim.displacement(node)
    ts = np.empty(n)
    for k in range(n):
        t0 = time.perf_counter()
        sim.step({node: f})
        sim.displacement(node)
        ts[k] = time.perf_counter() - t0
    return ts


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--levels", type=int, nargs="+", default=[4, 5])
    ap.add_argument("--modes", type=int, nargs="+", default=[40, 100])
    ap.add_argument("--calls", type=int, default=20000)
    args = ap.parse_args()
    print(f"# rtfem {rt.__version__}, python {platform.python_version()}, numba available: {kernels.HAVE_NUMBA}")
    rows = []
    for level in args.levels:
        mesh = rt.meshes.liver(level)
        model = rt.ShellModel(mesh, rt.Material()).fix("attachment")
        node = int(mesh.groups["probe"][0])
        basis = rt.modal_analysis(model, max(args.modes))
        for r in args.modes:
            modes = basis.truncated(r)
            out = {}
            for compiled in ([False, True] if kernels.HAVE_NUMBA else [False]):
                sim = rt.ModalSimulator(modes, 1e-3, rt.Damping(alpha=4.0))
                sim.compiled = compiled
                ts = timed(sim, node, (0.0, 0.0, -0.1), args.calls)
                out[compiled] = (np.median(ts), np.percentile(ts, 99), sim.get_state())
            same = "-"
            if True in out:
                a, b = out[True][2], out[False][2]
                same = f"{max(np.abs(a[k] - b[k]).max() / max(np.abs(b[k]).max(), 1e-300) for k in ('q', 'qdot')):.1e}"
            med_c = f"{out[True][0] * 1e6:.2f} us" if True in out else "-"
            p99_c = f"{out[True][1] * 1e6:.2f} us" if True in out else "-"
            ratio = f"{out[False][0] / out[True][0]:.1f}x" if True in out else "-"
            rows.append([f"{mesh.n_vertices:,}", r, f"{out[False][0] * 1e6:.2f} us", f"{out[False][1] * 1e6:.2f} us",
                         med_c, p99_c, ratio, same])
            print(f"  level {level}, r = {r} done", file=sys.stderr, flush=True)
    print_table(["vertices", "r", "numpy median", "numpy p99", "compiled median", "compiled p99", "numpy / compiled",
                 "state difference"], rows)


if __name__ == "__main__":
    main()
