"""A probe pressed into and dragged over the full-order nonlinear liver at 1 kHz haptics (issue 55): the
haptic ticks of rt.MultiRateProbe (the force against the latest step's linearization; the full-order
step on its own thread) against a synchronous rt.Probe (one full-order step per tick), in one run.

The organ is benchmarks/fullorder.py's: SOFA's liver2 filled at 12 mm (about 2,100 nodes, 9,100 tet4),
E 30 kPa, nu 0.45, held on the tenth of its length at low x; rt.DirectSimulator(model, dt,
Damping(alpha=10), large_deformation=True) (the lagged full-order step). The hand: 5 mm above a
surface vertex at 70 % of the length, pressed 8 mm in along the inward normal over 1 s, dragged 30 mm
along x over 2 s at that depth, held 1 s, lifted over 0.5 s; the spring coupling at 300 N/m; and a
jaw closed on a 10 mm patch there, pulled 20 mm out over 1 s (rt.MultiRateGrasp). Columns: the
ticks' compute time (median, 99th percentile, max; what must stay under 1 ms), the ticks over 1 ms
and missed (a tick started more than a period late), the physics thread's steps per second and
simulated seconds per wall second (dt / step time, at most 1 with pacing), the peak force and the
largest change of force from one tick to the next (a stable surface: no ringing). Then a still hand
8 mm in with the physics unpaced for 1.5 s of simulated time: the settled force against the spring
law on rt.nonlinear.solve_static's state under it (k (n . u_p - g)).

    python benchmarks/haptic_fullorder.py [--busy] [--dt 0.001 0.004] [--sync-seconds 1.5]
"""

from __future__ import annotations

import argparse
import platform
import sys
import time

import numpy as np

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from _common import busy_core, print_table  # noqa: E402
from fullorder import organ  # noqa: E402

import rtfem as rt  # noqa: E402

K, DEPTH, DRAG = 300.0, 0.008, 0.03
PHASES = (1.0, 2.0, 1.0, 0.5)  # press, drag, hold, lift (s)


def path(X0, n):
    """t -> the hand: approach and press along -n, drag along x, hold, lift."""
    a, b, c, d = np.cumsum(PHASES)
    tang = np.array([1.0, 0.0, 0.0]) - n[0] * n
    tang /= np.linalg.norm(tang)

    def at(t):
        if t < a:
            depth, s = -0.005 + (DEPTH + 0.005) * t / a, 0.0
        elif t < b:
            depth, s = DEPTH, DRAG * (t - a) / (b - a)
        elif t < c:
            depth, s = DEPTH, DRAG
        else:
            depth, s = DEPTH - (DEPTH + 0.005) * min(1.0, (t - c) / (d - c)), DRAG
        return X0 - depth * n + s * tang
    return at


def run(model, surface_vertex, dt, multirate: bool, seconds: float):
    sim = rt.DirectSimulator(model, dt, rt.Damping(alpha=10.0), large_deformation=True)
    mesh = model.mesh
    X = np.asarray(mesh.vertices)
    n = mesh.vertex_normals()[surface_vertex]
    device = rt.ScriptedDevice(path(X[surface_vertex], n))
    probe = (rt.MultiRateProbe(mesh, sim, stiffness=K) if multirate else rt.Probe(mesh, sim, stiffness=K))
    probe.prepare(around=X[surface_vertex], radius=0.04) if multirate else None
    stats = rt.HapticLoop(probe, device, rate=1000.0).run(seconds)
    F = np.array(device.forces)
    comp = np.asarray(stats.compute)
    row = {"ticks": len(comp), "missed": stats.missed, "p50": np.median(comp), "p99": np.percentile(comp, 99),
           "max": comp.max(), "over": int((comp > 1e-3).sum()), "finite": bool(np.isfinite(F).all()),
           "peak": float(np.linalg.norm(F, axis=1).max()) if F.size else 0.0}
    row["jump"] = float(np.linalg.norm(np.diff(F, axis=0), axis=1).max()) if len(F) > 1 else 0.0
    if multirate:
        ps = probe.stats()
        probe.close()
        row.update(steps=ps["steps_per_second"], ratio=ps["time_ratio"])
    else:
        row.update(steps=sim.steps / stats.seconds, ratio=sim.time / stats.seconds)
    return row


def settle(model, surface_vertex, dt=4e-3, sim_seconds=1.5):
    """A still hand 8 mm into the vertex, the physics unpaced for ``sim_seconds`` of simulated time: the
    felt force against the spring law on rt.nonlinear.solve_static's state under it (relative)."""
    sim = rt.DirectSimulator(model, dt, rt.Damping(alpha=10.0), large_deformation=True)
    X = np.asarray(model.mesh.vertices)
    n = model.mesh.vertex_normals()[surface_vertex]
    c = X[surface_vertex] - DEPTH * n
    with rt.MultiRateProbe(model.mesh, sim, stiffness=K, pace=False) as probe:
        while sim.time < sim_seconds:
            f = probe.update(c)
            time.sleep(1e-3)
        f, node = probe.update(c), probe.contact_node
    u = rt.nonlinear.solve_static(model, {int(node): tuple(-f)}).displacements
    nn = probe.physics.normals[node]
    law = K * (float(nn @ u[node]) - float(nn @ (c - X[node])))
    return float(np.linalg.norm(f)), abs(np.linalg.norm(f) - law) / law


def run_grasp(model, surface_vertex, dt, seconds: float):
    """The jaw closed on a 10 mm patch at the vertex, the hand pulled 20 mm out along the normal over
    1 s and held: the multi-rate grasp's ticks (its physics pays the patch's cross compliances once a
    refresh and two full-order solves a step)."""
    sim = rt.DirectSimulator(model, dt, rt.Damping(alpha=10.0), large_deformation=True)
    mesh = model.mesh
    X = np.asarray(mesh.vertices)
    n = mesh.vertex_normals()[surface_vertex]
    grasp = rt.MultiRateGrasp(mesh, sim, stiffness=K, radius=0.01)
    held = grasp.grab(surface_vertex)
    device = rt.ScriptedDevice(lambda t: X[surface_vertex] + 0.02 * min(1.0, t) * n)
    stats = rt.HapticLoop(grasp, device, rate=1000.0).run(seconds)
    ps = grasp.stats()
    grasp.close()
    F = np.array(device.forces)
    jump = float(np.linalg.norm(np.diff(F, axis=0), axis=1).max())
    comp = np.asarray(stats.compute)
    return {"ticks": len(comp), "missed": stats.missed, "p50": np.median(comp), "p99": np.percentile(comp, 99),
            "max": comp.max(), "over": int((comp > 1e-3).sum()), "finite": bool(np.isfinite(F).all()),
            "peak": float(np.linalg.norm(F, axis=1).max()), "steps": ps["steps_per_second"], "ratio": ps["time_ratio"],
            "held": held.size, "jump": jump}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--busy", action="store_true", help="also with a core kept busy by another process")
    ap.add_argument("--dt", type=float, nargs="+", default=[1e-3, 4e-3])
    ap.add_argument("--sync-seconds", type=float, default=1.5)
    args = ap.parse_args()
    model, held, tip, _ = organ()
    X = np.asarray(model.mesh.vertices)
    lo, hi = X.min(axis=0), X.max(axis=0)
    used = model.mesh.used_vertices()
    top = used[X[used, 2] > np.percentile(X[used, 2], 90)]
    v = int(top[np.argmin(np.abs(X[top, 0] - (lo[0] + 0.7 * (hi[0] - lo[0]))))])
    print(f"liver: {model.n_nodes} nodes, {model.tetmesh.n_tets} tets, "
          f"{held.size} held; the hand at vertex {v}; {platform.processor() or platform.machine()}")
    rows = []
    for busy in ([False, True] if args.busy else [False]):
        with busy_core(busy):
            for dt in args.dt:
                for multirate in (True, False):
                    seconds = sum(PHASES) if multirate else args.sync_seconds
                    r = run(model, v, dt, multirate, seconds)
                    rows.append(["busy" if busy else "quiet", f"{dt * 1e3:g} ms", "multi-rate" if multirate else "sync",
                                 r["ticks"], r["missed"], f"{r['p50'] * 1e6:.0f} us", f"{r['p99'] * 1e6:.0f} us",
                                 f"{r['max'] * 1e3:.2f} ms", r["over"], f"{r['steps']:.0f}", f"{r['ratio']:.2f}",
                                 f"{r['peak']:.3f}", f"{r['jump']:.3f}", "yes" if r["finite"] else "NO"])
            r = run_grasp(model, v, args.dt[-1], 2.0)
            rows.append(["busy" if busy else "quiet", f"{args.dt[-1] * 1e3:g} ms", f"grasp ({r['held']} held)",
                         r["ticks"], r["missed"], f"{r['p50'] * 1e6:.0f} us", f"{r['p99'] * 1e6:.0f} us",
                         f"{r['max'] * 1e3:.2f} ms", r["over"], f"{r['steps']:.0f}", f"{r['ratio']:.2f}",
                         f"{r['peak']:.3f}", f"{r['jump']:.3f}", "yes" if r["finite"] else "NO"])
    print_table(["machine", "dt", "ticks by", "ticks", "missed", "p50", "p99", "max", ">1 ms", "steps/s",
                 "sim s / s", "peak N", "max jump N", "finite"], rows)
    f, err = settle(model, v)
    print(f"settled (a still hand {DEPTH * 1e3:g} mm in, 1.5 s simulated, unpaced): {f:.4f} N, against the spring law on "
          f"rt.nonlinear.solve_static's state under it: {err:.1e}")


if __name__ == "__main__":
    main()
