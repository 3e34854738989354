"""Organ pulls: linear, warped and reduced-nonlinear (modes + modal derivatives) models against the
corotational full order.

The default liver as a shell (level 4, the attachment fixed; ``--organ solid``: the solid liver
of tet4, meshed once per machine). A jaw of radius 1 cm (the nodes within it held together) or a
single vertex on the free edge of the right lobe is pulled 1, 2 or 5 cm along its outward
normal, or the lobe is lifted by an upward dead load on the nodes within 3 cm of that vertex,
scaled so that its linear lift is 2 or 5 cm (as in large_deformation.py; the models then step
under the load instead of a grasp). The reference is the geometrically nonlinear static
equilibrium with the held nodes moved there (``rt.nonlinear.solve_static`` in 8 load steps, Newton
and, where it stalls, the trust region; a case with no reference, as a shell vertex pulled 5 cm
whose apex would turn past the shell's 90-degree limit, is reported and left out). The linear and
warped modal models (r modes, static correction) are settled by an ``rt.Grasp`` (1e5 times
stiffer than the organ at the vertex, 2,000 steps at 1 kHz, critical damping); the reduced
nonlinear model (:class:`rtfem.reduction.reduced.ReducedNonlinearModel`: the r modes and the modal
derivatives of the lowest d) is solved for its static equilibrium with the held nodes moved
exactly, without and with the static correction (the static response D f, D = K^-1 - U U^T,
that the basis cannot hold, for the held nodes' reactions f: ``static_correction=True``).
Errors: max and RMS of the surface displacement error, relative to the pull. Costs, in the same
run: the precompute of the derivatives, the Grasp step of the linear and warped models, one
evaluation of the reduced forces and tangent on all elements (numpy), and the reduced forces on
the cubature elements (An, Kim & James 2008; 16 random training poses, ``--tol`` training error)
with the compiled kernel: the per-step cost of a reduced explicit or semi-implicit step. The
:class:`rtfem.ReducedNonlinearSimulator` is settled under the same Grasp (3,000 steps; 8,000
under the lift, where it creeps to rest with a time constant of ~0.65 s), three ways: with
every cubature element each step (spread 1) and no correction; with the static correction and
spread 1; with the static correction, ``spread`` (one of that many element groups refreshed per
step, the others' nonlinear remainders kept from their last evaluation) and the basis rows in
single precision, the setting for a 1 kHz loop. ``--local RADIUS``: also the localized model
(``red.localize(held nodes, RADIUS)``: every dof within RADIUS of the held nodes added to the
basis, its cubature keeping the patch's elements exact; ``--local-remainder``: a cubature of the
nonlinear remainder only), its static solve and its
simulator in the 1 kHz setting, built per case. The grasp spring is 1e5 times the organ's
stiffness at the vertex for every model, so that the stiffening nonlinear model also reaches
the pull. Last, a probe loop on the simulator: at 500 Hz and 1 kHz with spread 1 and no
correction (the previous setting), and at 1 kHz with the correction, single precision and
spread 1, 2, 4 and ``spread`` (with ``--local``: the localized model around the vertex at
spread 4, 8 and ``spread``).

    python benchmarks/reduced_nonlinear.py [--organ shell|solid] [--modes 40] [--derivatives 20] [--spread 4]
        [--tol 0.05] [--local RADIUS [--local-remainder]] [--cases jaw2 jaw5 point1 point2 point5 lift2 lift5]
        [--reference-seconds 600]
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
from rtfem.reduction.reduced import ReducedNonlinearModel  # noqa: E402
from _common import fmt_s, print_table  # noqa: E402
from large_deformation import _budget, _OverBudget, errors, grasp_node, organs, settle  # noqa: E402

# the step as a real-time loop runs it: linearized about the cubature's tangent, refreshed on a
# background thread (--tangent rest: the step before, linearized about the rest tangent)
STEP = {"tangent": "current", "background": True}

CASES = {"point1": (0.0, 0.01), "point2": (0.0, 0.02), "point5": (0.0, 0.05),
         "jaw2": (0.01, 0.02), "jaw5": (0.01, 0.05), "lift2": (None, 0.02), "lift5": (None, 0.05)}


def run(n_modes: int, n_derivatives: int, cases: list[str], spread: int = 4, organ: str = "shell",  # noqa: C901
        tol: float = 0.05, local: float | None = None, local_remainder: bool = False,
        reference_seconds: float = 600.0) -> None:
    name, model, fresh = organs([organ])[0]
    mesh = model.mesh
    X = np.asarray(mesh.vertices)
    surface = mesh.used_vertices()
    node = grasp_node(model)
    normal = mesh.vertex_normals()[node]
    modes = rt.modal_analysis(model, n_modes)
    t0 = time.perf_counter()
    red = ReducedNonlinearModel(model, modes, n_derivatives)
    t_pre = time.perf_counter() - t0
    print(f"{name}: {model.n_nodes:,} nodes, {n_modes} modes; derivatives of {n_derivatives}: "
          f"{red.size} coordinates in {t_pre:.1f} s", flush=True)
    cub = red.train_cubature(16, tol=tol)
    print(f"cubature: {cub['elements'].size} of {cub['of']} elements, training error {cub['training_error']:.3f}, "
          f"{cub['seconds']:.1f} s", flush=True)
    loc_info = []
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
    near = np.flatnonzero(np.linalg.norm(X - X[node], axis=1) < 0.03)  # the lobe lift: upward loads on the nodes
    near = near[~model.held_nodes[near]]                                # within 3 cm, as in large_deformation.py
    lift = np.zeros((model.n_nodes, 3))
    lift[near, 2] = 1.0
    lift /= model.solve_static(lift)[node, 2]  # the linear lift of the vertex: 1 m
    rows, steps_nl, steps_sc, steps_spread, steps_loc, ref_info = [], [], [], [], [], []
    for case in cases:
        radius, d = CASES[case]
        loads = None if radius is not None else d * lift
        target = X[node] + d * normal if loads is None else None
        out = {}
        for warping in (False, True):
            sim = rt.ModalSimulator(modes, 1e-3, rt.Damping(zeta=1.0), static_correction=True, warping=warping)
            out[warping] = settle(sim, mesh, node, target, loads, stiffness=k_grasp, radius=radius)
        for key, kwargs in (("nl", {}), ("sc", {"static_correction": True}),
                            ("spread", {"static_correction": True, "spread": spread, "precision": "single"})):
            sim = rt.ReducedNonlinearSimulator(red, 1e-3, rt.Damping(zeta=1.0), **kwargs, **STEP)
            try:
                # under the lift's dead load the reduced model creeps to rest (time constant ~0.65 s)
                out[key] = settle(sim, mesh, node, target, loads, 3000 if loads is None else 8000, k_grasp, radius)
            except rt.SolverError as exc:
                out[key] = None
                print(f"  {kwargs}: {exc}", flush=True)
        held = out[False][1]
        loc = None
        if local:  # the patch: every node within `local` of the held ones (the lift: of the vertex)
            t1 = time.perf_counter()
            loc = red.localize(held, local)
            c = loc.train_cubature(16, tol=tol, remainder=local_remainder)
            loc_info.append(f"{case}: {loc.info['local']['nodes']} nodes within {local * 100:g} cm of the "
                            f"{held.size} held, {loc.size} coordinates; {'remainder ' if local_remainder else ''}cubature "
                            f"{c['elements'].size} elements "
                            f"({c['pinned']} of the patch), {time.perf_counter() - t1:.1f} s")
            print("  " + loc_info[-1], flush=True)
            sim = rt.ReducedNonlinearSimulator(loc, 1e-3, rt.Damping(zeta=1.0), static_correction=True, spread=spread,
                                               precision="single", **STEP)
            try:
                out["loc"] = settle(sim, mesh, node, target, loads, 3000 if loads is None else 8000, k_grasp, radius)
            except rt.SolverError as exc:
                out["loc"] = None
                print(f"  localized: {exc}", flush=True)
        t0 = time.perf_counter()
        # 8 load steps: the quasi-static path (one step from rest can end on another equilibrium);
        # 15 Newton iterations (75 of the trust region) and 6 halvings a step, and a time budget
        options = dict(steps=8, max_iterations=15, max_cuts=6, progress=_budget(reference_seconds))
        try:
            ref = rt.nonlinear.solve_static(fresh().fix("attachment").fix(held, dofs="xyz"), None,
                                            prescribed=np.where(np.isin(np.arange(model.n_nodes), held)[:, None],
                                                                d * normal, 0.0), **options) \
                if loads is None else rt.nonlinear.solve_static(fresh().fix("attachment"), loads, **options)
        except (rt.SolverError, _OverBudget) as exc:
            print(f"  {case}: no full-order reference, {time.perf_counter() - t0:.0f} s: {exc}", flush=True)
            continue
        ref_info.append(f"{case}: reference in {len(ref.load_factors)} load steps ({', '.join(sorted(set(ref.methods)))}), "
                        f"{ref.iterations} iterations, largest local rotation {ref.local_rotation:.0f} degrees")
        print("  " + ref_info[-1], flush=True)
        if loads is None:
            pulls = {int(h): d * normal for h in held}
            res = red.solve_static(targets=pulls)
            res_sc = red.solve_static(targets=pulls, static_correction=True)
            res_loc = loc.solve_static(targets=pulls, static_correction=True) if loc is not None else None
        else:
            res = red.solve_static(loads)
            res_sc = red.solve_static(loads, static_correction=True)
            res_loc = loc.solve_static(loads, static_correction=True) if loc is not None else None
        t_ref = time.perf_counter() - t0 - res.seconds - res_sc.seconds - (res_loc.seconds if res_loc else 0.0)
        e = {key: errors(u, ref.displacements, surface, d) for key, u in
             (("linear", out[False][0]), ("warped", out[True][0]), ("static", res.displacements),
              ("static sc", res_sc.displacements))}
        if res_loc is not None:
            e["loc static"] = errors(res_loc.displacements, ref.displacements, surface, d)
        for key, times in (("nl", steps_nl), ("sc", steps_sc), ("spread", steps_spread), ("loc", steps_loc)):
            if out.get(key) is not None:
                e[key] = errors(out[key][0], ref.displacements, surface, d)
                times.append(out[key][2])

        def cell(key):
            if key not in e:
                return "-" if key.startswith("loc") and not local else "diverged"
            ripple = f" (ripple {out[key][3]:.0e})" if key in ("nl", "sc", "spread", "loc") else ""
            return f"{e[key][0] * 100:.0f} % / {e[key][1] * 100:.0f} %{ripple}"

        def ratio(key):
            return f"{e[key][0] / e['linear'][0]:.2f}" if key in e else "-"

        what = "lobe lift (3 cm)" if loads is not None else f"jaw r {radius * 100:g} cm ({held.size} nodes)" \
            if radius else "vertex"
        rows.append([what, f"{d * 100:g} cm", f"{t_ref:.0f} s", *map(cell, ("linear", "warped", "static", "static sc",
                                                                            "nl", "sc", "spread", "loc static", "loc")),
                     *map(ratio, ("warped", "static", "static sc", "nl", "spread", "loc")),
                     f"{res_sc.seconds:.1f} s ({res_sc.iterations} its)"])
        print(f"  {what} {d * 100:g} cm: " + ", ".join(f"{k} {v[0]:.3f}" for k, v in e.items()), flush=True)
    print()
    if rows:
        print_table(["pulled", "pull", "reference", "linear error max / rms", "warped error max / rms",
                     f"reduced nonlinear static (r {n_modes} + {red.size - n_modes}) max / rms",
                     "same + static correction", "ReducedNonlinearSimulator settled (spread 1)",
                     "same + static correction", f"same, spread {spread}, single",
                     f"localized ({local * 100 if local else 0:g} cm patch) static, corrected",
                     f"localized simulator, corrected, spread {spread}, single", "warped / linear",
                     "reduced nl static / linear", "+ static correction / linear", "simulator / linear",
                     f"simulator, correction, spread {spread} / linear", "localized simulator / linear",
                     "reduced static solve (corrected)"], rows)
        print()
    print_table(["cost", "time"], [
        ["derivatives precompute", f"{t_pre:.1f} s"],
        ["linear Grasp step (median)", fmt_s(out[False][2]) if rows else "-"],
        ["warped Grasp step (median)", fmt_s(out[True][2]) if rows else "-"],
        ["reduced forces + tangent, all elements, numpy (median)", fmt_s(statistics.median(t_eval))],
        [f"reduced forces on the {cub['elements'].size} cubature elements, compiled (median)",
         fmt_s(statistics.median(t_cub[5:]))],
        ["same, basis rows in single precision (median)", fmt_s(statistics.median(t_cub32[5:]))],
        ["ReducedNonlinearSimulator Grasp step, spread 1 (median over the cases)",
         fmt_s(statistics.median(steps_nl)) if steps_nl else "-"],
        ["same, static correction", fmt_s(statistics.median(steps_sc)) if steps_sc else ("diverged" if rows else "-")],
        [f"same, static correction, spread {spread}, single",
         fmt_s(statistics.median(steps_spread)) if steps_spread else ("diverged" if rows else "-")],
        [f"localized, static correction, spread {spread}, single",
         fmt_s(statistics.median(steps_loc)) if steps_loc else ("diverged" if rows and local else "-")]])
    print()
    runs = [(500, 1, "double", False), (1000, 1, "double", False)] + \
        [(1000, k, "single", True) for k in sorted({1, 2, 4, spread})]
    loops = [[f"{rate} Hz, spread {k}, {p}{', static correction' if sc else ''}, 3 s",
              loop_row(red, node, rate, spread=k, precision=p, static_correction=sc)] for rate, k, p, sc in runs]
    if STEP["tangent"] == "current":  # the baseline in the same run: the step about the rest tangent
        loops += [[f"1000 Hz, spread {k}, single, static correction, 3 s, tangent 'rest' (the step before)",
                   loop_row(red, node, 1000, spread=k, precision="single", static_correction=True, tangent="rest")]
                  for k in sorted({1, spread})]
    if local:
        loc = red.localize([node], local)
        loc.train_cubature(16, tol=tol, remainder=local_remainder)
        loops += [[f"localized ({loc.info['local']['nodes']} nodes), 1000 Hz, spread {k}, single, static correction, 3 s",
                   loop_row(loc, node, 1000, spread=k, precision="single", static_correction=True)]
                  for k in sorted({4, 8, spread})]
    for line in ref_info + loc_info:
        print(line)
    print_table(["probe loop on the ReducedNonlinearSimulator (Python ticks)", "result"], loops)


def loop_row(red, node: int, rate: int, seconds: float = 3.0, spread: int = 1, precision: str = "double",
             static_correction: bool = False, tangent: str | None = None) -> str:
    mesh = red.model.mesh
    X = np.asarray(mesh.vertices)[node]
    n = mesh.vertex_normals()[node]
    step = STEP if tangent is None else {"tangent": tangent, "background": tangent == "current"}
    sim = rt.ReducedNonlinearSimulator(red, 1.0 / rate, rt.Damping(zeta=1.0), spread=spread, precision=precision,
                                       static_correction=static_correction, **step)
    probe = rt.Probe(mesh, sim, stiffness=200.0)
    probe.prepare(around=X, radius=0.01)
    device = rt.ScriptedDevice.press(X, n, 0.004, seconds, approach=0.001)
    stats = rt.HapticLoop(probe, device, rate=rate).run(seconds)
    c = np.asarray(stats.compute) * 1e6
    late = np.asarray(stats.lateness) * 1e6
    done = sim._worker.done if getattr(sim, "_worker", None) is not None else 0
    return (f"{stats.steps} ticks, {stats.missed} skipped, compute p50 {np.median(c):.0f} / p99 "
            f"{np.percentile(c, 99):.0f} us, lateness p99 {np.percentile(late, 99):.0f} us"
            + (f", {done} tangents" if done else ""))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--modes", type=int, default=40)
    ap.add_argument("--derivatives", type=int, default=20)
    ap.add_argument("--spread", type=int, default=4, help="element groups of the multirate simulator (default 4)")
    ap.add_argument("--cases", nargs="*", default=["jaw2", "jaw5", "point1", "point2", "point5", "lift2", "lift5"],
                    choices=sorted(CASES),
                    help="pulls measured against the full-order reference (none: the cost and loop tables only)")
    ap.add_argument("--organ", choices=["shell", "solid"], default="shell",
                    help="the default liver as a shell (level 4, default) or the solid liver (tet4)")
    ap.add_argument("--tol", type=float, default=0.05, help="the cubature's training error (default 0.05)")
    ap.add_argument("--local", type=float, default=None, metavar="RADIUS",
                    help="also the localized model: every dof within RADIUS m of each case's held nodes added to the basis")
    ap.add_argument("--local-remainder", action="store_true",
                    help="the localized models' cubature fits the nonlinear remainder only (train_cubature(remainder=True))")
    ap.add_argument("--reference-seconds", type=float, default=600.0,
                    help="a full-order reference not converged in this long is reported and its row left out (600)")
    ap.add_argument("--tangent", choices=["current", "rest"], default="current",
                    help="the simulator's step: linearized about the cubature's tangent refreshed in the background "
                         "(default) or about the rest tangent (the step before)")
    args = ap.parse_args()
    STEP.update(tangent=args.tangent, background=args.tangent == "current")
    run(args.modes, args.derivatives, args.cases, args.spread, args.organ, args.tol, args.local, args.local_remainder,
        args.reference_seconds)


if __name__ == "__main__":
    main()
