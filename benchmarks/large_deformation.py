"""Large deformation on organs: linear vs warped reduced models against the corotational full order.

For the default liver as a shell and the solid liver (tet4), a vertex on the free edge of the
right lobe is grasped and pulled 1, 2 and 5 cm along its outward normal, and the lobe is lifted
by an upward load spread over the nodes within 3 cm of it (scaled so that the linear lift of that
vertex is 2 or 5 cm). The reference is the geometrically nonlinear static equilibrium
(``solve_static(large_deformation=True)``, the pulled vertex held at its target). The reduced
models (r modes, static correction, critical modal damping) are run to rest at 1 kHz with an
``rt.Grasp`` (a spring 1,000 times stiffer than the organ at that vertex) or the load; the table
gives the surface displacement error (max and RMS over the surface nodes, relative to the pull),
the median cost of a haptic step (Grasp.update) of each model, and the full-order nonlinear
dynamic step (Newton in HHT, under the viewer's 200 N/m grasp, the hand moving
at 0.5 m/s) measured in the same run. Last, a 1 kHz probe loop on the warped
model (Python ticks: the compiled loop knows no warp).

A reference that has not converged within ``--reference-seconds`` (a thin shell pulled far at one
vertex halves its load steps for a long time) is reported as such and its row left out.

    python benchmarks/large_deformation.py [--modes 40] [--loop-seconds 3] [--organs shell solid]
        [--reference-seconds 900]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import rtfem as rt  # noqa: E402
from _common import fmt_s, print_table  # noqa: E402


def organs(which=("shell", "solid")):
    mat = rt.Material()
    out = []
    if "shell" in which:
        shell = rt.ShellModel(rt.meshes.liver(4), mat).fix("attachment")
        out.append(("shell liver", shell, lambda: rt.ShellModel(shell.mesh, mat)))
    if "solid" in which:
        solid = rt.SolidModel(rt.meshes.liver(solid=True), mat).fix("attachment")
        out.append(("solid liver (tet4)", solid, lambda: rt.SolidModel(solid.tetmesh, mat)))
    return out


class _OverBudget(Exception):
    pass


def _budget(seconds: float):
    """A solve_static progress callback that stops the solve once ``seconds`` have passed."""
    t0 = time.perf_counter()

    def progress(done, total, message):
        if time.perf_counter() - t0 > seconds:
            raise _OverBudget(f"{message} after {time.perf_counter() - t0:.0f} s")
    return progress


def grasp_node(model) -> int:
    mesh = model.mesh
    return int(model.select_nodes("probe")[0]) if "probe" in mesh.groups else model.nearest_free_node(
        rt.meshes.PROBE_POINT)


def settle(sim, mesh, node, target=None, loads=None, steps=2000, stiffness=None, radius=0.0):
    """Run a driver to rest: ``node`` grasped (with the vertices within ``radius``) and held at
    ``target`` (a point, or a function of the step), or stepped under dead ``loads``. Returns the
    field, the held nodes (the node alone under loads), the median step time of the second half
    and the ripple: the largest range of a held node's displacement over the last 500 steps (at
    most half the run), relative to the pull to a fixed target, else to the final displacement."""
    grasp = rt.Grasp(mesh, sim, stiffness=stiffness, radius=radius) if target is not None else None
    held = np.asarray(grasp.grab(node)) if grasp is not None else np.array([node])
    times, tail = [], []
    for k in range(steps):
        t0 = time.perf_counter()
        if grasp is not None:
            grasp.update(target(k) if callable(target) else target)
        else:
            sim.step(loads)
        times.append(time.perf_counter() - t0)
        if k >= steps - min(500, steps // 2):
            tail.append(rt.drivers.base.displacements_at(sim, held))
    tail = np.array(tail)
    fixed = target is not None and not callable(target)
    pull = np.linalg.norm(target - np.asarray(mesh.vertices)[node]) if fixed else np.abs(tail[-1]).max()
    ripple = float((tail.max(axis=0) - tail.min(axis=0)).max() / pull)
    return sim.displacements(), held, statistics.median(times[steps // 2:]), ripple


def errors(U, ref, surface, scale):
    d = np.linalg.norm(U[surface] - ref[surface], axis=1)
    return d.max() / scale, np.sqrt(np.mean(d**2)) / scale


def run(n_modes: int, loop_seconds: float, which=("shell", "solid"), budget: float = 900.0) -> None:
    rows, rows_loop, skipped = [], [], []
    for name, model, fresh in organs(which):
        X = np.asarray(model.mesh.vertices)
        surface = model.mesh.used_vertices()
        node = grasp_node(model)
        normal = model.mesh.vertex_normals()[node]
        t0 = time.perf_counter()
        modes = rt.modal_analysis(model, n_modes)
        print(f"{name}: {model.n_nodes:,} nodes, {n_modes} modes in {time.perf_counter() - t0:.1f} s", flush=True)
        W_static = np.linalg.norm(np.stack([model.unit_load_response(node, k)[node] for k in range(3)]), 2)
        k_grasp = 1e3 / W_static
        near = np.flatnonzero(np.linalg.norm(X - X[node], axis=1) < 0.03)
        near = near[~model.held_nodes[near]]
        lift = np.zeros((model.n_nodes, 3))
        lift[near, 2] = 1.0
        unit_lift = model.solve_static(lift)[node, 2]
        cases = [(f"pull {d * 100:g} cm", d, None) for d in (0.01, 0.02, 0.05)]
        cases += [(f"lobe lift {d * 100:g} cm", d, lift * (d / unit_lift)) for d in (0.02, 0.05)]
        t_full = None
        for label, d, loads in cases:
            ref_model = fresh()
            ref_model.fix("attachment")
            t0 = time.perf_counter()
            try:
                if loads is None:
                    ref_model.fix([node], dofs="xyz")
                    P = np.zeros((model.n_nodes, 3))
                    P[node] = d * normal
                    res = rt.nonlinear.solve_static(ref_model, None, prescribed=P, progress=_budget(budget))
                else:
                    res = rt.nonlinear.solve_static(ref_model, loads, progress=_budget(budget))
            except (_OverBudget, rt.SolverError) as exc:
                skipped.append(f"{name}, {label}: no reference ({exc})")
                print(f"  {label}: no reference ({exc})", flush=True)
                continue
            t_ref = time.perf_counter() - t0
            ref = res.displacements
            target = X[node] + d * normal if loads is None else None
            lin_static = model.solve_static(loads) if loads is not None else None
            out = {}
            for warping in (False, True):
                sim = rt.ModalSimulator(modes, 1e-3, rt.Damping(zeta=1.0), static_correction=True, warping=warping)
                out[warping] = settle(sim, model.mesh, node, target, loads, stiffness=k_grasp)
            if t_full is None:  # the full-order nonlinear dynamic step, same grasp
                full = rt.DirectSimulator(fresh().fix("attachment"), 1e-3, rt.Damping(alpha=5.0), large_deformation=True)
                t_full = settle(full, model.mesh, node, lambda k: X[node] + 0.0005 * (k + 1) * normal, None,
                                   steps=10, stiffness=200.0)[2]  # the hand moving at 0.5 m/s
            e_lin, e_warp = errors(out[False][0], ref, surface, d), errors(out[True][0], ref, surface, d)
            got = ref[node] @ normal if loads is None else ref[node, 2]
            rows.append([name, label, f"{got * 100:.2f} cm", f"{len(res.load_factors)} / {res.iterations} ({t_ref:.1f} s)",
                         f"{e_lin[0] * 100:.1f} % / {e_lin[1] * 100:.1f} %",
                         f"{e_warp[0] * 100:.1f} % / {e_warp[1] * 100:.1f} %",
                         f"{e_warp[0] / e_lin[0]:.2f}", fmt_s(out[False][2]), fmt_s(out[True][2]), fmt_s(t_full)])
            print(f"  {label}: linear {e_lin[0]:.3f}, warped {e_warp[0]:.3f}", flush=True)
            if lin_static is not None:
                assert np.abs(out[False][0] - lin_static).max() < 1e-3 * np.abs(lin_static).max()
        if loop_seconds > 0:
            rows_loop.append([name, loop_row(model, modes, node, loop_seconds)])
    print()
    print_table(["organ", "case", "reference motion", "load steps / Newton its (time)",
                 "linear error max / rms", "warped error max / rms", "warped / linear", "linear step",
                 "warped step", "full nonlinear step"], rows)
    for line in skipped:
        print(line)
    if rows_loop:
        print()
        print_table(["organ", f"1 kHz probe loop on the warped model (r = {n_modes})"], rows_loop)


def loop_row(model, modes, node: int, seconds: float) -> str:
    X = np.asarray(model.mesh.vertices)[node]
    n = model.mesh.vertex_normals()[node]
    sim = rt.ModalSimulator(modes, 1e-3, rt.Damping(alpha=5.0), static_correction=True, warping=True)
    probe = rt.Probe(model.mesh, sim, stiffness=200.0)
    probe.prepare(around=X, radius=0.01)
    device = rt.ScriptedDevice.press(X, n, 0.004, seconds, approach=0.001)
    stats = rt.HapticLoop(probe, device, rate=1000).run(seconds)
    c = np.asarray(stats.compute) * 1e6
    late = np.asarray(stats.lateness) * 1e6
    return (f"{stats.steps} ticks, {stats.missed} skipped, compute p50 {np.median(c):.0f} / p99 "
            f"{np.percentile(c, 99):.0f} us, lateness p99 {np.percentile(late, 99):.0f} us"
            f"{' (compiled)' if stats.compiled else ' (Python ticks)'}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--modes", type=int, default=40)
    ap.add_argument("--loop-seconds", type=float, default=3.0)
    ap.add_argument("--organs", nargs="+", default=["shell", "solid"], choices=["shell", "solid"])
    ap.add_argument("--reference-seconds", type=float, default=900.0,
                    help="stop a full-order reference solve that has not converged after this long (default 900)")
    args = ap.parse_args()
    run(args.modes, args.loop_seconds, args.organs, args.reference_seconds)


if __name__ == "__main__":
    main()
