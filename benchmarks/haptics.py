"""Haptic update cost, loop rate and jitter, and the impedance map's cost against its radius.

For the default liver (level 4) and its refinements:

* per-step compute time of ``Probe.update`` (contact search, force, organ step) for the
  modal route (r modes, static correction) and the impedance-map route (quasi-static),
  median and 99th percentile over a scripted press;
* the real-time HapticLoop at 1 kHz over ``--seconds`` of wall time: achieved rate,
  compute-time percentiles and jitter of the tick start times;
* the impedance map: precompute time and memory per loaded node against the radius of
  influence (Euclidean), and against a magnitude threshold.

    .venv/bin/python benchmarks/haptics.py [--levels 4 5 6] [--seconds 10] [--modes 40]
"""

from __future__ import annotations

import argparse
import platform
import sys
import time

import numpy as np

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from _common import fmt_s, print_table  # noqa: E402

import rtfem as rt  # noqa: E402

DAMPING = rt.Damping(alpha=8.0)


def press_trajectory(X, n, depth=0.004, period=2.0):
    """In 0.2 s from 2 mm outside to ``depth`` inside, hold, release; repeat every ``period``."""
    return rt.ScriptedDevice.press(X, n, depth, period, ramp=0.1, release=0.5, repeat=True).trajectory


def offline(probe, traj, steps):
    times = np.empty(steps)
    for k in range(steps):
        p = traj(k * 1e-3)
        t0 = time.perf_counter()
        probe.update(p)
        times[k] = time.perf_counter() - t0
    return times


def run(levels, seconds, n_modes):
    print(f"# rtfem {rt.__version__}, numpy {np.__version__}, python {platform.python_version()}; "
          f"{n_modes} modes, static correction, alpha = {DAMPING.alpha}, spring coupling 200 N/m")
    rows, loop_rows, map_rows = [], [], []
    for level in levels:
        mesh = rt.meshes.liver(level)
        model = rt.ShellModel(mesh, rt.Material())
        model.fix("attachment")
        node = int(mesh.groups["probe"][0])
        X, n = np.asarray(mesh.vertices)[node], mesh.vertex_normals()[node]
        traj = press_trajectory(X, n)
        t0 = time.perf_counter()
        basis = rt.modal_analysis(model, n_modes)
        t_modal = time.perf_counter() - t0
        sim = rt.ModalSimulator(basis, 1e-3, DAMPING, static_correction=True)
        probe = rt.Probe(mesh, sim)
        probe.prepare(around=X, radius=0.01)
        c = offline(probe, traj, 4000)
        # impedance map over the nodes the probe can touch
        near = np.flatnonzero(np.linalg.norm(np.asarray(mesh.vertices) - X, axis=1) < 0.01)
        t0 = time.perf_counter()
        imap = rt.ImpedanceMap.build(model, DAMPING, nodes=near, times=[0.01, 0.05, 0.2], n_modes=n_modes, threshold=0.01)
        t_map = time.perf_counter() - t0
        cm = offline(rt.Probe(mesh, imap), traj, 4000)
        rows.append([mesh.n_vertices, fmt_s(t_modal), f"{np.median(c) * 1e6:.1f} us", f"{np.percentile(c, 99) * 1e6:.1f} us",
                     f"{near.size} nodes, {fmt_s(t_map)}", f"{np.median(cm) * 1e6:.1f} us",
                     f"{np.percentile(cm, 99) * 1e6:.1f} us"])
        # the real-time loop
        sim.reset()
        probe = rt.Probe(mesh, sim)
        probe.prepare(around=X, radius=0.01)
        loop = rt.HapticLoop(probe, rt.ScriptedDevice(traj), rate=1000.0)
        st = loop.run(seconds)
        late = np.abs(np.array(st.lateness))
        loop_rows.append([mesh.n_vertices, st.steps, f"{st.rate:.1f} Hz", f"{st.percentile(50) * 1e6:.1f} us",
                          f"{st.percentile(99) * 1e6:.1f} us", f"{max(st.compute) * 1e6:.0f} us",
                          f"{st.jitter * 1e6:.1f} us", f"{np.percentile(late, 99) * 1e6:.1f} us",
                          f"{np.mean(np.array(st.compute) > 1e-3) * 100:.2f} %", f"{st.peak_force:.3f} N"])
        print(f"  level {level}: {st}", file=sys.stderr)
        if level == levels[0]:
            # spread the loaded nodes over the organ: near the attachment and far from it
            sample = np.linspace(0, mesh.n_vertices - 1, 12).astype(int)
            sample = sample[~model.fixed[sample, :3].all(axis=1)][:10]
            full = rt.ImpedanceMap.build(model, DAMPING, nodes=sample, times=[0.01, 0.05, 0.2], n_modes=n_modes)

            def err(m):  # L2 error of each truncated static column against the full one, worst node
                e = []
                for j in sample:
                    for d in np.eye(3):
                        ref = full.displacements([(j, d, 0.0)], np.inf)
                        e.append(np.linalg.norm(m.displacements([(j, d, 0.0)], np.inf) - ref) / np.linalg.norm(ref))
                return max(e)

            variants = [("radius", f"{R:g} m", dict(radius=R)) for R in (0.01, 0.02, 0.05, 0.1, 0.2)]
            variants += [("threshold", f"{th:g}", dict(threshold=th)) for th in (0.1, 0.01, 0.001)]
            variants += [("none", "-", {}), ("none, 2 workers", "-", dict(workers=2))]
            for kind, value, kw in variants:
                t0 = time.perf_counter()
                m = rt.ImpedanceMap.build(model, DAMPING, nodes=sample, times=[0.01, 0.05, 0.2], n_modes=n_modes, **kw)
                dt = time.perf_counter() - t0
                map_rows.append([mesh.n_vertices, kind, value, f"{np.diff(m.offsets).mean():.0f}", fmt_s(dt / sample.size),
                                 f"{m.bytes_per_node / 1024:.0f} KiB", f"{err(m):.1e}"])
    print("\nPer-step compute of Probe.update (offline, 4,000 steps of a press-hold-release):")
    print_table(["vertices", "modal analysis", "modal median", "modal p99", "map precompute", "map median", "map p99"], rows)
    print(f"\nReal-time HapticLoop at 1 kHz for {seconds} s (modal route):")
    print_table(["vertices", "steps", "achieved", "compute median", "compute p99", "compute max", "jitter (std)",
                 "|lateness| p99", "steps over 1 ms", "peak force"], loop_rows)
    print("\nImpedance map cost and accuracy against truncation (10 loaded nodes spread over the organ, "
          "3 samples + static; error: worst relative L2 error of a static column):")
    print_table(["vertices", "truncation", "value", "kept nodes", "precompute per node", "memory per node", "error"], map_rows)


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--levels", type=int, nargs="+", default=[4, 5, 6])
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--modes", type=int, default=40)
    a = ap.parse_args()
    run(a.levels, a.seconds, a.modes)
