"""Why the viewer's reduced nonlinear model keeps the derivatives of 10 modes and spread 1.

The default scene (``default_session``: the liver as a solid of tet10, 40 modes) with the
derivatives of ``d`` modes and ``spread`` cubature groups: the probe vertex grabbed by the 10 mm
jaw (200 N/m) and its hand moved 3 cm along (0.3, -0.5, 0.8) over 0.5 s, then held to 4 s
(4,000 steps at 1 kHz, one BLAS thread). Reported: the step's median and 99th percentile (the
last 3,500 steps), the settled force, the largest displacement, and against the full order's
geometrically nonlinear static equilibrium under the same held forces
(``rt.nonlinear.solve_static``, 2 load steps) the relative error of the field (max norm); the
linear static response's error beside it. A run that diverges says so.

    python benchmarks/viewer_settings.py [--cases 10:1 10:2 10:4 20:1 20:4]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))


def case(d: int, spread: int) -> list:
    import rtfem as rt
    from rtfem.threads import runtime
    from rtfem.viewer.session import Settings, default_session

    t0 = time.perf_counter()
    s = default_session(settings=Settings(method="nonlinear", derivatives=d, spread=spread))
    pre = time.perf_counter() - t0
    node = s.mesh.groups["probe"][0]
    X = s.X[node]
    s.grab(X)
    times = []
    try:
        with runtime():
            for k in range(4000):
                s.drag(X + 0.03 * min(1.0, k / 500) * np.array([0.3, -0.5, 0.8]))
                c0 = time.perf_counter()
                s.step()
                times.append(time.perf_counter() - c0)
    except rt.RtfemError as exc:
        return [d, spread, s.driver.reduced.size, f"{pre:.1f} s", "-", f"diverged: {str(exc)[:60]}", "-", "-", "-"]
    t = np.array(times[500:]) * 1e6
    loads = {int(v): g for v, g in zip(s.grasp.nodes, s.grasp.forces)}
    u = s.displacements()
    ref = rt.nonlinear.solve_static(s.model, loads, steps=2).displacements
    lin = s.model.solve_static(loads)

    def err(a):
        return np.linalg.norm(a - ref, axis=1).max() / np.linalg.norm(ref, axis=1).max()

    return [d, spread, s.driver.reduced.size, f"{pre:.1f} s", f"{np.median(t):,.0f} / {np.percentile(t, 99):,.0f} us",
            f"{np.linalg.norm(s.grasp.forces.sum(axis=0)):.3f} N", f"{np.linalg.norm(u, axis=1).max() * 1e3:.2f} mm",
            f"{err(u) * 100:.1f} %", f"{err(lin) * 100:.1f} %"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", nargs="+", default=["10:1", "10:2", "10:4", "20:1", "20:4"])
    args = ap.parse_args()
    from _common import print_table

    rows = []
    for c in args.cases:
        d, spread = (int(x) for x in c.split(":"))
        rows.append(case(d, spread))
        print(rows[-1], flush=True)
    print()
    print_table(["derivatives of", "spread", "coordinates", "precompute", "step p50 / p99", "force",
                 "largest displacement", "error vs full nonlinear", "linear's error"], rows)


if __name__ == "__main__":
    main()
