"""Organ pulls: linear, warped and reduced-nonlinear (modes + modal derivatives) models against the
corotational full order.

The default liver as a shell (level 4, the attachment fixed). A jaw of radius 1 cm (the nodes
within it held together) or a single vertex on the free edge of the right lobe is pulled 1, 2 or
5 cm along its outward normal. The reference is the geometrically nonlinear static equilibrium
with the held nodes moved there (``rt.nonlinear.solve_static``). The linear and warped modal
models (r modes, static correction) are settled by an ``rt.Grasp`` (1e5 times stiffer than the
organ at the vertex, 2,000 steps at 1 kHz, critical damping); the reduced nonlinear model
(:class:`rtfem.reduced.ReducedNonlinearModel`: the r modes and the modal derivatives of the lowest
d) is solved for its static equilibrium with the held nodes moved exactly. Errors: max and RMS of
the surface displacement error, relative to the pull. Costs, in the same run: the precompute of
the derivatives, the Grasp step of the linear and warped models, one evaluation of the reduced
forces and tangent on all elements (numpy), and the reduced forces on the cubature elements
(An, Kim & James 2008; 16 random training poses, 5 % training error) with the compiled kernel:
the per-step cost of a reduced explicit or semi-implicit step. The static equilibrium is also
solved with the cubature forces, to show what the cubature's error costs in accuracy, and the
:class:`rtfem.ReducedNonlinearSimulator` is settled under the same Grasp (3,000 steps). The grasp
spring is 1e5 times the organ's stiffness at the vertex for every model, so that the
stiffening nonlinear model also reaches the pull. The simulator is settled twice: with every
cubature element each step (spread 1) and multirate (``spread``: one of that many element groups
refreshed per step, the others' nonlinear remainders kept from their last evaluation); both come
to the same equilibrium, the second at a fraction of the step's cost. Last, a probe loop on the
simulator at 250, 500 and 1,000 Hz with spread 1, and at 1,000 Hz with spread 4 and ``spread``.

    python benchmarks/reduced_nonlinear.py [--modes 40] [--derivatives 20] [--spread 8] [--cases jaw2 jaw5 point1 point2]
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
from rtfem.reduced import ReducedNonlinearModel  # noqa: E402
from _common import fmt_s, print_table  # noqa: E402
from large_deformation import errors, grasp_node  # noqa: E402

CASES = {"point1": (0.0, 0.01), "point2": (0.0, 0.02), "point5": (0.0, 0.05),
         "jaw2": (0.01, 0.02), "jaw5": (0.01, 0.05)}


def settle(sim, mesh, node, target, radius, stiffness, steps=2000):
    grasp = rt.Grasp(mesh, sim, stiffness=stiffness, radius=radius)
    held = grasp.grab(node)
    times = []
    for _ in range(steps):
        t0 = time.perf_counter()
        grasp.update(target)
        times.append(time.perf_counter() - t0)
    return sim.displacements(), np.asarray(held), statistics.median(times[steps // 2:])


def run(n_modes: int, n_derivatives: int, cases: list[str], spread: int = 8) -> None:
    mat = rt.Material()
    model = rt.ShellModel(rt.meshes.liver(4), mat).fix("attachment")
    mesh = model.mesh
    X = np.asarray(mesh.vertices)
    surface = mesh.used_vertices()
    node = grasp_node(model)
    normal = mesh.vertex_normals()[node]
    modes = rt.modal_analysis(model, n_modes)
    t0 = time.perf_counter()
    red = ReducedNonlinearModel(model, modes, n_derivatives)
    t_pre = time.perf_counter() - t0
    print(f"shell liver: {model.n_nodes:,} nodes, {n_modes} modes; derivatives of {n_derivatives}: "
          f"{red.size} coordinates in {t_pre:.1f} s", flush=True)
    cub = red.train_cubature(16, tol=0.05)
    print(f"cubature: {cub['elements'].size} of {cub['of']} elements, training error {cub['training_error']:.3f}, "
          f"{cub['seconds']:.1f} s", flush=True)
    q = np.zeros(red.size)
    t_cub, t_cub32 = [], []
    for _ in range(50):  # interleaved, so that both see the same machine
        for single, times in ((False, t_cub), (True, t_cub32)):
            t0 = time.perf_counter()
            red.cubature_forces(q, single=single)
            times.append(time.perf_counter() - t0)
    t_eval = []
    for _ in range(5):
        t0 = time.perf_counter()
        red.reduced_forces(q)
        t_eval.append(time.perf_counter() - t0)
    W_static = np.linalg.norm(np.stack([model.unit_load_response(node, k)[node] for k in range(3)]), 2)
    k_grasp = 1e5 / W_static  # stiff enough to hold the pull against the nonlinear model's stiffening too
    rows, steps_nl, steps_spread = [], [], []
    for case in cases:
        radius, d = CASES[case]
        target = X[node] + d * normal
        out = {}
        for warping in (False, True):
            sim = rt.ModalSimulator(modes, 1e-3, rt.Damping(zeta=1.0), static_correction=True, warping=warping)
            out[warping] = settle(sim, mesh, node, target, radius, k_grasp)
        sim = rt.ReducedNonlinearSimulator(red, 1e-3, rt.Damping(zeta=1.0))
        out["nl"] = settle(sim, mesh, node, target, radius, k_grasp, steps=3000)
        sim = rt.ReducedNonlinearSimulator(red, 1e-3, rt.Damping(zeta=1.0), spread=spread)
        try:
            out["spread"] = settle(sim, mesh, node, target, radius, k_grasp, steps=3000)
        except rt.SolverError as exc:
            out["spread"] = None
            print(f"  spread {spread}: {exc}", flush=True)
        held = out[False][1]
        ref_model = rt.ShellModel(mesh, mat).fix("attachment").fix(held, dofs="xyz")
        P = np.zeros((model.n_nodes, 3))
        P[held] = d * normal
        t0 = time.perf_counter()
        ref = rt.nonlinear.solve_static(ref_model, None, prescribed=P)
        t_ref = time.perf_counter() - t0
        res = red.solve_static(targets={int(h): d * normal for h in held})
        res_c = red.solve_static(targets={int(h): d * normal for h in held}, cubature=True, max_iterations=60)
        e_cub = errors(res_c.displacements, ref.displacements, surface, d)
        e_dyn = errors(out["nl"][0], ref.displacements, surface, d)
        steps_nl.append(out["nl"][2])
        e_spread = None if out["spread"] is None else errors(out["spread"][0], ref.displacements, surface, d)
        if out["spread"] is not None:
            steps_spread.append(out["spread"][2])
        spread_cell = "diverged" if e_spread is None else f"{e_spread[0] * 100:.0f} % / {e_spread[1] * 100:.0f} %"
        e_lin = errors(out[False][0], ref.displacements, surface, d)
        e_warp = errors(out[True][0], ref.displacements, surface, d)
        e_red = errors(res.displacements, ref.displacements, surface, d)
        what = f"jaw r {radius * 100:g} cm ({held.size} nodes)" if radius else "vertex"
        rows.append([what, f"{d * 100:g} cm", f"{t_ref:.0f} s",
                     f"{e_lin[0] * 100:.0f} % / {e_lin[1] * 100:.0f} %",
                     f"{e_warp[0] * 100:.0f} % / {e_warp[1] * 100:.0f} %",
                     f"{e_red[0] * 100:.0f} % / {e_red[1] * 100:.0f} %",
                     f"{e_cub[0] * 100:.0f} % / {e_cub[1] * 100:.0f} %",
                     f"{e_dyn[0] * 100:.0f} % / {e_dyn[1] * 100:.0f} %", spread_cell,
                     f"{e_warp[0] / e_lin[0]:.2f}", f"{e_red[0] / e_lin[0]:.2f}", f"{e_dyn[0] / e_lin[0]:.2f}",
                     "-" if e_spread is None else f"{e_spread[0] / e_lin[0]:.2f}",
                     f"{res.seconds:.1f} s ({res.iterations} its)"])
        print(f"  {what} {d * 100:g} cm: linear {e_lin[0]:.3f}, warped {e_warp[0]:.3f}, reduced nonlinear "
              f"{e_red[0]:.3f}, with cubature {e_cub[0]:.3f}, simulator settled {e_dyn[0]:.3f}", flush=True)
    print()
    if rows:
        print_table(["pulled", "pull", "reference", "linear error max / rms", "warped error max / rms",
                     f"reduced nonlinear static (r {n_modes} + {red.size - n_modes}) max / rms", "same, cubature forces",
                     "ReducedNonlinearSimulator settled", f"same, spread {spread}", "warped / linear",
                     "reduced nl static / linear", "simulator / linear", f"spread {spread} / linear",
                     "reduced static solve"], rows)
        print()
    print_table(["cost", "time"], [
        ["derivatives precompute", f"{t_pre:.1f} s"],
        ["linear Grasp step (median)", fmt_s(out[False][2]) if rows else "-"],
        ["warped Grasp step (median)", fmt_s(out[True][2]) if rows else "-"],
        ["reduced forces + tangent, all elements, numpy (median)", fmt_s(statistics.median(t_eval))],
        [f"reduced forces on the {cub['elements'].size} cubature elements, compiled (median)",
         fmt_s(statistics.median(t_cub[5:]))],
        ["same, basis rows in single precision (median)", fmt_s(statistics.median(t_cub32[5:]))],
        ["ReducedNonlinearSimulator Grasp step (median over the cases)",
         fmt_s(statistics.median(steps_nl)) if steps_nl else "-"],
        [f"same, spread {spread} (median over the cases)",
         fmt_s(statistics.median(steps_spread)) if steps_spread else ("diverged" if rows else "-")]])
    print()
    runs = [(250, 1, "double"), (500, 1, "double"), (1000, 1, "double"), (1000, 1, "single"), (1000, 4, "double"),
            (1000, spread, "double")]
    print_table(["probe loop on the ReducedNonlinearSimulator (Python ticks)", "result"],
                [[f"{rate} Hz, spread {k}, {p}, 3 s", loop_row(red, node, rate, spread=k, precision=p)]
                 for rate, k, p in runs])


def loop_row(red, node: int, rate: int, seconds: float = 3.0, spread: int = 1, precision: str = "double") -> str:
    mesh = red.model.mesh
    X = np.asarray(mesh.vertices)[node]
    n = mesh.vertex_normals()[node]
    sim = rt.ReducedNonlinearSimulator(red, 1.0 / rate, rt.Damping(zeta=1.0), spread=spread, precision=precision)
    probe = rt.Probe(mesh, sim, stiffness=200.0)
    probe.prepare(around=X, radius=0.01)
    device = rt.ScriptedDevice.press(X, n, 0.004, seconds, approach=0.001)
    stats = rt.HapticLoop(probe, device, rate=rate).run(seconds)
    c = np.asarray(stats.compute) * 1e6
    late = np.asarray(stats.lateness) * 1e6
    return (f"{stats.steps} ticks, {stats.missed} skipped, compute p50 {np.median(c):.0f} / p99 "
            f"{np.percentile(c, 99):.0f} us, lateness p99 {np.percentile(late, 99):.0f} us")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--modes", type=int, default=40)
    ap.add_argument("--derivatives", type=int, default=20)
    ap.add_argument("--spread", type=int, default=8, help="element groups of the multirate simulator (default 8)")
    ap.add_argument("--cases", nargs="*", default=["jaw2", "jaw5", "point1", "point2"], choices=sorted(CASES),
                    help="pulls measured against the full-order reference (none: the cost and loop tables only)")
    args = ap.parse_args()
    run(args.modes, args.derivatives, args.cases, args.spread)


if __name__ == "__main__":
    main()
