"""Which model when, measured (issue 56): on the issue's three cases, through the viewer's own session
and settings, the settled worst-node error of the linear modal model and of the reduced nonlinear
model (the viewer's default: 40 modes + derivatives of 10, cubature, 1 ms steps) against the full
order's equilibrium under the same grasp forces (rt.nonlinear.solve_static), as a fraction of the linear
static solution's error under those loads and of the linear model's error in the same drag, the error
estimate the session's monitor reports (rt.error_estimate) and each model's step time (median of the
last 500 steps, stepped synchronously on this thread).

Cases: the tet10 block 0.1 x 0.04 x 0.04 m (E 40 kPa, clamped at x = 0) with a 15 mm jaw on its free
end dragged 22.5 mm up; the default organ (the solid tet10 liver) grabbed at its top vertex (10 mm
jaw) and dragged 20 mm up; the tet10 cantilever 1 x 0.1 x 0.1 m (E 100 kPa) grabbed on its tip face (a
jaw of 11 cm: its four corners; on one node a solid takes a point load, singular) and dragged 30 cm up
(30 % of its length). The hand moves over the first second, then holds.

With ``--realtime SECONDS`` each case runs instead as the viewer runs it (issue 56's done-when): the
session's own thread keeps the 1 ms clock, a frame thread does the viewer's per-frame work at 30
frames/s, the error monitor runs beside them and the model adapts where its estimate exceeds the
panel's tolerance (``Settings.adapt``, 0.5 mm: the basis localized 10 mm around the grasp). The hand
moves over the first second by the wall clock and holds; the table gives the settled error, the
estimate the panel showed, what adapted, and the real-time share and step percentiles of the run.

    python benchmarks/model_errors.py [--steps 2500]
    python benchmarks/model_errors.py --realtime 12 [--busy]
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from _common import busy_core, print_table  # noqa: E402

import rtfem as rt  # noqa: E402
from rtfem.viewer.session import Session, Settings, default_session  # noqa: E402


def cases():
    block = dict(mesh=rt.meshes.box(0.1, 0.04, 0.04, nx=10, ny=4, nz=4),
                 material=rt.Material(E=4e4, nu=0.45, density=1000.0), fixed="x0", model_options={"element": "tet10"})
    beam = dict(mesh=rt.meshes.box(1.0, 0.1, 0.1, nx=10, ny=1, nz=1), material=rt.Material(E=1e5, nu=0.3, density=10.0),
                fixed="x0", model_options={"element": "tet10"})
    return [("block, 15 mm jaw, 22.5 mm", block, 0.0075, 30.0, lambda X: np.array([0.1, 0.02, 0.02]), 0.0225),
            ("liver (default organ), 20 mm", None, None, None, None, 0.02),
            ("cantilever, tip face, 30 % of L", beam, 0.11, 20.0, lambda X: np.array([1.0, 0.05, 0.05]), 0.3)]


def settle(s, point, lift, steps):
    node = s.grab(point)
    start = s.X[node] + s.driver.displacement(node)
    times = []
    for k in range(steps):
        s.drag(start + [0.0, 0.0, lift * min(1.0, (k + 1) / 1000)])  # the hand moves over the first second
        t = time.perf_counter()
        s.step()
        times.append(time.perf_counter() - t)
    U, loads, _ = s._error_state()
    return node, U, loads, float(np.median(times[-500:]))


def realtime(s, point, lift, seconds, fps=30.0):
    """The case as the viewer runs it: the session's clock thread, the frames, the monitor; the hand
    moved by the wall clock over the first second, then held until ``seconds``."""
    from rtfem.viewer.benchmark import _Drawer

    drawer = _Drawer(s, fps)
    s.stats.computes.clear()
    s.start()
    drawer.start()
    try:
        node = s.grab(point)
        start = s.X[node] + s.driver.displacement(node)
        t0, steps0 = time.perf_counter(), s.stats.steps
        while (t := time.perf_counter() - t0) < seconds:
            s.drag(start + [0.0, 0.0, lift * min(1.0, t)])
            time.sleep(0.005)
        wall, steps = time.perf_counter() - t0, s.stats.steps - steps0
    finally:
        drawer.stop()
        s.stop()
    U, loads, _ = s._error_state()
    computes = np.array(s.stats.computes) * 1e6
    shown = s.monitor.latest.max_error * 1e3 if getattr(s, "monitor", None) is not None and s.monitor.latest else None
    return node, U, loads, dict(realtime=steps * s.driver.dt / wall, p50=np.median(computes), p99=np.percentile(computes, 99),
                                shown=shown, adapted=s.local_status or "-")


def session_for(kw, method, alpha, radius, adapt):
    """The case's session with the viewer's settings (``adapt``: its tolerance, or 0 where no monitor
    runs: the synchronous table, the model as it starts)."""
    if kw is None:
        s = default_session(settings=Settings(method=method, adapt=adapt))
        return s, s.X[s.drawn[np.argmax(s.X[s.drawn, 2])]]
    s = Session(kw["mesh"], kw["material"], fixed=kw["fixed"], model_options=kw["model_options"],
                settings=Settings(method=method, alpha=alpha, grab_radius=radius, adapt=adapt))
    return s, None


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=3000)
    ap.add_argument("--realtime", type=float, metavar="SECONDS", help="run each case on the viewer's clock this long")
    ap.add_argument("--busy", action="store_true", help="another process keeps a core busy meanwhile")
    args = ap.parse_args()
    with busy_core(args.busy):
        run(args)


def run(args) -> None:
    rows, extra = [], []
    for name, kw, radius, alpha, where, lift in cases():
        for method in ("modal", "nonlinear"):
            s, point = session_for(kw, method, alpha, radius, Settings.adapt if args.realtime else 0.0)
            point = where(s.X) if point is None else point
            if args.realtime:
                node, U, loads, rt_stats = realtime(s, point, lift, args.realtime)
                step = rt_stats["p50"] * 1e-6
            else:
                node, U, loads, step = settle(s, point, lift, args.steps)
            model = s.model
            full = rt.nonlinear.solve_static(model, loads, steps=8).displacements
            linear = np.linalg.norm(model.solve_static(loads) - full, axis=1).max()
            err = np.linalg.norm(U - full, axis=1).max()
            est = rt.error_estimate(model, U, loads).max_error
            if method == "modal":
                modal_err = err
            rows.append([name, s.settings.label, f"{np.linalg.norm(U[node]) * 1e3:.1f}", f"{err * 1e3:.3f}",
                         f"{err / linear:.2f}", f"{err / modal_err:.2f}", f"{est * 1e3:.3f}", f"{est / err:.2f}",
                         f"{step * 1e6:.0f} us"])
            if args.realtime:
                shown = "-" if rt_stats["shown"] is None else f"{rt_stats['shown']:.3f}"
                extra.append([name, method, shown, f"{rt_stats['realtime']:.3f}",
                              f"{rt_stats['p50']:.0f} / {rt_stats['p99']:.0f}", rt_stats["adapted"]])
            print(rows[-1], extra[-1:] or "", flush=True)
    print_table(["case", "model", "jaw moved (mm)", "worst-node error (mm)", "/ linear, same loads",
                 "/ linear model, same drag", "estimate (mm)", "estimate / error", "step (median)"], rows)
    if extra:
        print_table(["case", "method", "estimate shown (mm)", "real time", "step p50 / p99 (us)", "adapted"], extra)


if __name__ == "__main__":
    main()
