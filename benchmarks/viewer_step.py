"""The viewer's reduced nonlinear step: what a grasped patch costs it, and what holds it back from real
time on a busy machine (issue 54: `rtfem view --benchmark 5` kept 0.66-0.94 of real time with a step
p99 of 5-17 ms under load; the full field cost 26 ms a step on a 9,476-tet liver, the static
correction of a 114-node patch 20 ms).

Part ``patch`` (one process, one driver: the "before" rows replay the replaced code on the same data,
in the same run): the embedded liver meshed at a 11 mm spacing (10,624 tets: tet10, 15,000 nodes),
the viewer's reduced nonlinear model, its probe vertex grasped by a jaw that holds ~114 surface nodes
and pulled 2 cm; then

* the full field with the static correction of the patch's loads: each load's (n, 3, 3) columns by
  numpy's stacked product (before) against one (3n, 3) BLAS product each (now);
* the patch's step compliances after a tangent refresh: the static-correction block gathered again
  (before) against kept (now); and the grasp's (3m + 3) inverse that follows (rt.Grasp, unchanged);
* the viewer's session on that organ and patch for ``--seconds`` (the frame thread drawing at 30/s):
  the surface field computed under the session's lock (before) or beside it (now).

Part ``worker`` (one process): the default scene's session (``rtfem view --benchmark``'s) with the
reduced nonlinear model's background tangent worker at nice 19 (before), at the raised stepping
thread's nice -10, and at the normal priority (now), alternating, quiet and beside ``--busy``
spinning processes.

Part ``view`` (fresh processes): ``rtfem view --benchmark SECONDS`` on the default scene with the code
at ``--baseline`` (a temporary git worktree; default the merge base with main) and with the working
tree, alternately, ``--runs`` times each, quiet and beside ``--busy`` processes spinning (2: both
cores). Medians over the runs of the real-time fraction, the step's p50, p99 and largest.

    python benchmarks/viewer_step.py [--parts patch worker view] [--seconds 5] [--runs 3] [--busy 2] [--baseline REF]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
ROOT = Path(__file__).resolve().parents[1]
SPACING = 0.011  # m: 10,624 tets on this machine's fTetWild (the 9,476-tet liver's size)
PULL = 0.02  # m


def _median_ms(fn, n: int) -> float:
    times = []
    for _ in range(n):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times)) * 1e3


def _old_full_field(d) -> np.ndarray:
    """The full field as the driver drew it before: each load's columns by the stacked product."""
    u = d.reduced.displacements(d._q)
    loads, _ = d._current_loads()
    for node, f in loads.items():
        u += d._correction_column(node) @ f
    return u


def _patch_session(radius: float):
    import rtfem as rt
    from rtfem.viewer.session import Session, Settings

    mesh = rt.meshes.liver(solid=True, spacing=SPACING)
    t0 = time.perf_counter()
    s = Session(mesh, rt.Material(), "attachment", Settings(method="nonlinear", grab_radius=radius), {"element": "tet10"})
    return s, time.perf_counter() - t0, len(mesh.tets)


def patch_part(seconds: float, target: int = 114) -> None:
    import rtfem as rt
    from _common import print_table
    from rtfem.drivers.base import prepare, step_compliances
    from rtfem.interaction.contact import patch_system
    from rtfem.threads import runtime
    from rtfem.viewer import benchmark as vb

    s, build, tets = _patch_session(0.02)
    node = vb.default_vertex(s)
    radius = next(r for r in np.arange(0.010, 0.080, 0.001) if s.grasp.patch(node, r).size >= target)
    s.configure(grab_radius=float(radius))
    d, g = s.driver, rt.Grasp(s.mesh, s.driver, stiffness=200.0, radius=float(radius))
    held = g.patch(node)
    t0 = time.perf_counter()
    prepare(d, held)
    t_prepare = time.perf_counter() - t0
    g.grab(node)
    X, n = s.X[node], s.mesh.vertex_normals()[node]
    with runtime():
        for k in range(300):
            g.update(X + PULL * min(1.0, k / 150) * n)
        np.testing.assert_allclose(d.displacements(), _old_full_field(d), rtol=1e-10, atol=1e-15)
        old_field, new_field = _median_ms(lambda: _old_full_field(d), 15), _median_ms(d.displacements, 15)

        def compliances(keep: bool):
            d._last_compliances = None  # as after a tangent refresh
            if not keep:
                d.__dict__.pop("_block_kept", None)
            return step_compliances(d, g.nodes)

        old_w, new_w = _median_ms(lambda: compliances(False), 15), _median_ms(lambda: compliances(True), 15)
        W = compliances(True)
        inv = _median_ms(lambda: np.linalg.inv(patch_system(W, g.stiffness, g.grip)), 15)
    size = 3 * g.nodes.size + 3
    g.release()
    d.reset()
    print(f"\nthe liver at spacing {SPACING * 1e3:g} mm: {tets:,} tets, {s.model.n_nodes:,} nodes (tet10), "
          f"{s.drawn.size:,} drawn; precompute {build:.0f} s; the jaw's radius {radius * 1e3:.0f} mm holds {held.size} "
          f"nodes (prepared in {t_prepare:.2f} s, on the grab's thread)\n")
    print_table(["operation", "before (ms, p50)", "now (ms, p50)", "now / before"], [
        ["full field + the patch's static correction", f"{old_field:.2f}", f"{new_field:.2f}", f"{new_field / old_field:.2f}"],
        ["step compliances after a tangent refresh", f"{old_w:.2f}", f"{new_w:.2f}", f"{new_w / old_w:.2f}"],
        [f"the grasp's {size} x {size} inverse that follows (rt.Grasp, unchanged)", f"{inv:.2f}", f"{inv:.2f}", "1.00"],
    ])
    rows = []
    for label, concurrent in (("surface field under the session lock (before)", False),
                              ("surface field beside it (now)", True)):
        d.concurrent_reads = concurrent
        s.release()
        d.reset()
        rep = vb.run(s, seconds, pull=PULL)
        rows.append([label, f"{rep['realtime']:.3f}", f"{rep['step_p50_us']:,.0f}", f"{rep['step_p99_us']:,.0f}",
                     f"{max(s.stats.computes) * 1e6:,.0f}", f"{rep['frames_per_s']:.0f}"])
    print(f"\nthe viewer's session on it, {seconds:g} s, the {held.size}-node jaw pulled {PULL * 1e2:g} cm "
          "(rtfem.viewer.benchmark.run):\n")
    print_table(["frames' field", "real time", "step p50 (us)", "p99 (us)", "max (us)", "frames/s"], rows)


def worker_part(seconds: float, runs: int, busy: int) -> None:
    """The default scene's session (one process, one precompute) with its background tangent worker
    at nice 19 (before), at the stepping thread's raised priority, and at the normal priority (now),
    alternating, quiet and beside ``busy`` spinning processes."""
    import rtfem.drivers.tangent as tangent
    from _common import print_table
    from rtfem.viewer import benchmark as vb
    from rtfem.viewer.session import default_session

    s = default_session()
    nice = {"value": 0}

    class _Os:  # drivers.tangent's os: its worker's setpriority gives the variant's value
        PRIO_PROCESS = os.PRIO_PROCESS
        getpriority = staticmethod(os.getpriority)

        @staticmethod
        def setpriority(which, who, value) -> None:
            os.setpriority(which, who, nice["value"])

    tangent.os = _Os
    variants = {"nice 19 (before)": 19, "the stepping thread's (nice -10)": -10, "normal, nice 0 (now)": 0}
    res: dict = {}
    for k in range(runs):
        for b in (0, busy):
            for name, value in variants.items():
                nice["value"] = value
                s.release()
                s.driver.reset()
                if s.driver._worker is not None:  # a new worker thread for the new priority
                    s.driver._worker.close()
                    s.driver._worker = None
                spinners = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(b)]
                try:
                    rep = vb.run(s, seconds)
                finally:
                    for p in spinners:
                        p.kill()
                        p.wait()
                res.setdefault((name, b), []).append((rep["realtime"], rep["step_p99_us"], max(s.stats.computes) * 1e6,
                                                      rep["sync_refreshes"], rep["frames_per_s"]))
    tangent.os = os
    rows = []
    for (name, b), v in res.items():
        v = np.array(v, dtype=float)
        rows.append([name, f"{b} busy" if b else "quiet", f"{np.median(v[:, 0]):.3f} ({v[:, 0].min():.2f}-{v[:, 0].max():.2f})",
                     f"{np.median(v[:, 1]):,.0f}", f"{np.median(v[:, 2]):,.0f}", f"{np.median(v[:, 3]):.0f}",
                     f"{np.median(v[:, 4]):.0f}"])
    print(f"\nthe default scene's session, {seconds:g} s runs of rtfem.viewer.benchmark.run, {runs} per cell, alternating "
          f"(one process); the tangent worker's priority; 'busy': {busy} processes spinning; medians over the runs:\n")
    print_table(["tangent worker", "machine", "real time (range)", "step p99 (us)", "longest step (us)", "sync refreshes",
                 "frames/s"], rows)


def _view_once(src: Path, seconds: float, busy: int) -> dict:
    env = dict(os.environ, PYTHONPATH=str(src))
    spinners = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(busy)]
    try:
        out = subprocess.run([sys.executable, "-m", "rtfem.cli.main", "view", "--benchmark", str(seconds)], env=env,
                             capture_output=True, text=True, timeout=900, cwd=tempfile.gettempdir())
    finally:
        for p in spinners:
            p.kill()
            p.wait()
    line = [x for x in out.stdout.splitlines() if x.startswith("{")]
    if not line:
        raise RuntimeError(f"rtfem view --benchmark failed: {out.stderr[-2000:]}")
    return json.loads(line[-1])


def view_part(seconds: float, runs: int, busy: int, ref: str) -> None:
    from _common import baseline_tree, print_table

    with baseline_tree(ref) as (base, short):
        trees = {f"baseline {short}": base / "src", "now (working tree)": ROOT / "src"}
        res = {(name, b): [] for name in trees for b in (0, busy)}
        for k in range(runs):
            for b in (0, busy):
                for name, src in trees.items():
                    r = _view_once(src, seconds, b)
                    res[(name, b)].append(r)
                    print(f"  run {k + 1}: {name}, busy {b}: real time {r['realtime']:.3f}, p50 / p99 {r['step_p50_us']:.0f} / "
                          f"{r['step_p99_us']:.0f} us, sync refreshes {r['sync_refreshes']}", flush=True)
    rows = []
    for (name, b), rs in res.items():
        real = [r["realtime"] for r in rs]
        rows.append([name, f"{b} busy" if b else "quiet", f"{np.median(real):.3f} ({min(real):.2f}-{max(real):.2f})",
                     f"{np.median([r['step_p50_us'] for r in rs]):,.0f}", f"{np.median([r['step_p99_us'] for r in rs]):,.0f}",
                     f"{np.median([r['sync_refreshes'] for r in rs]):.0f}", f"{np.median([r['frames_per_s'] for r in rs]):.0f}"])
    print(f"\nrtfem view --benchmark {seconds:g} (the default scene), {runs} fresh processes per cell, alternating; "
          f"'busy': {busy} processes spinning beside it; medians (real time: median (range)):\n")
    print_table(["code", "machine", "real time", "step p50 (us)", "step p99 (us)", "sync refreshes", "frames/s"], rows)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--parts", nargs="+", choices=("patch", "worker", "view"), default=["patch", "worker", "view"])
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--busy", type=int, default=2, help="processes spinning beside the busy runs (default 2)")
    ap.add_argument("--baseline", default="merge-base", help="git ref of the code compared against (default: the "
                    "merge base of HEAD and main)")
    args = ap.parse_args()
    print(f"load average before: {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores")
    if "patch" in args.parts:
        patch_part(args.seconds)
    if "worker" in args.parts:
        worker_part(args.seconds, args.runs, args.busy)
    if "view" in args.parts:
        view_part(args.seconds, args.runs, args.busy, args.baseline)
    print(f"load average after: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
