"""The reduced nonlinear step's tangent refresh on the default liver (the viewer's model: solid of tet10,
40 modes + derivatives of 10, cubature, single-precision rows), pulled 3 cm: the closed-form element
tangents (tet_kernels) against forward differences of the force kernel (31 force evaluations an
element, the way it was computed before session 49), measured in the same run, and the projection
U_e^T dK_e U_e in float64 and float32. Medians of --repeat calls.

    python benchmarks/tangent_refresh.py [--repeat 20]
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time

import numpy as np

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from _common import print_table  # noqa: E402

import rtfem as rt  # noqa: E402


def _median_ms(fn, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times)) * 1e3


def _differences(red, V, data):
    """The element tangents by forward differences of the force kernel (the earlier method)."""
    E, nd = V.shape
    h = 1e-7 * red.system.size
    P = np.array(V, dtype=float)
    F0 = red._kernel_forces(P, data)
    K = np.empty((E, nd, nd))
    for j in range(nd):
        P[:, j] = V[:, j] + h
        K[:, :, j] = (red._kernel_forces(P, data) - F0) / h
        P[:, j] = V[:, j]
    return 0.5 * (K + K.transpose(0, 2, 1))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeat", type=int, default=20)
    args = ap.parse_args()
    from rtfem.threads import runtime
    from rtfem.viewer.benchmark import default_vertex
    from rtfem.viewer.session import default_session

    print(f"# rtfem {rt.__version__}, python {platform.python_version()}, {os.cpu_count()} cores")
    s = default_session()
    d, red = s.driver, s.driver.reduced
    node = default_vertex(s)
    X, n = s.X[node], s.mesh.vertex_normals()[node]
    s.grab(X)
    with runtime():
        for i in range(300):
            s.drag(X + 0.03 * min(1.0, i / 150) * n)
            s.step()
        q = d._q.copy()
        data, w = red._cubature
        Ue = data[0]
        E, nd, r = Ue.shape
        V = (Ue.reshape(-1, r) @ q).reshape(E, nd)
        Ke, _ = red.cubature_rest()
        closed = red._element_tangents(V, data)
        diff = _differences(red, V, data)
        dK = (closed - Ke) * w[:, None, None]
        U32, UT32 = red.cubature_rows(True)
        U3 = U32.reshape(E, nd, r)
        parts = [
            ("element tangents, closed form (compiled)", lambda: red._element_tangents(V, data)),
            ("element tangents, forward differences", lambda: _differences(red, V, data)),
            ("projection U^T dK U, float64", lambda: Ue.reshape(-1, r).T @ np.matmul(dK, Ue).reshape(-1, r)),
            ("projection, float32 rows", lambda: UT32 @ np.matmul(dK.astype(np.float32), U3).reshape(-1, r)),
            ("the whole refresh (_linearization), as the step takes it", lambda: d._linearization(q)),
        ]
        rows = [[name, f"{_median_ms(fn, args.repeat):.2f}"] for name, fn in parts]
    print(f"{E} cubature tets of {red.info['cubature']['of']}, {r} coordinates; closed form against differences: "
          f"{np.abs(closed - diff).max() / np.abs(closed).max():.1e} of the largest entry")
    print_table(["part", "median (ms)"], rows)


if __name__ == "__main__":
    main()
