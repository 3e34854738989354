"""Modal reduction against direct integration: precompute, time per step, accuracy.

For the default liver (level 4) and its refinements, and r in (10, 20, 50, 100, 200):

* precompute: the sparse factorization (once) and the shift-invert Lanczos for r modes;
* haptic step: one loaded node, its own displacement read back (ModalSimulator, exact
  integrator), median over batches of steps;
* full-field step: a step plus the whole (n, 3) displacement field;
* direct step: implicit Newmark on the full sparse system (DirectSimulator, effective
  stiffness factorized once), and the ratios direct / modal measured in the same run;
* error: a probe pushes a node for 100 ms and releases it for 100 ms; the largest L2 error
  of the modal field (Newmark integrator, so only the truncation differs) against the direct
  solution over samples every 10 ms, relative to the largest direct field; without and with
  the static correction (mode acceleration), and the haptic step time with it.

    .venv/bin/python benchmarks/dynamics.py [--levels 4 5 6] [--modes 10 20 50 100 200]
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
from rtfem.cli.bench import per_step as _per_step  # noqa: E402

DT = 1e-3
DAMPING = rt.Damping(alpha=4.0)
PUSH, RELEASE, SAMPLE = 100, 100, 10


def per_step(fn, batch: int, batches: int = 7) -> float:
    return _per_step(fn, batch, batches)


def history(sim, node, force):
    out = []
    for k in range(PUSH + RELEASE):
        sim.step({node: force} if k < PUSH else None)
        if (k + 1) % SAMPLE == 0:
            out.append(sim.displacements())
    return np.array(out)


def run(levels, modes_list):
    print(f"# rtfem {rt.__version__}, numpy {np.__version__}, python {platform.python_version()}, "
          f"backends: {', '.join(rt.linalg.available_backends())}; dt = {DT * 1e3:g} ms, alpha = {DAMPING.alpha}")
    rows = []
    for level in levels:
        mesh = rt.meshes.liver(level)
        model = rt.ShellModel(mesh, rt.Material())
        model.fix("attachment")
        model.K  # noqa: B018
        t0 = time.perf_counter()
        model.factorization()
        t_fac = time.perf_counter() - t0
        node = int(mesh.groups["probe"][0])
        force = tuple(-0.2 * mesh.vertex_normals()[node])
        # the direct baseline
        t0 = time.perf_counter()
        direct = rt.DirectSimulator(model, DT, DAMPING)
        t_dsetup = time.perf_counter() - t0
        t0 = time.perf_counter()
        U_ref = history(direct, node, force)
        t_direct = (time.perf_counter() - t0) / (PUSH + RELEASE)
        print(f"  level {level}: {mesh.n_vertices} vertices, direct {t_direct * 1e3:.1f} ms/step", file=sys.stderr)
        out = np.empty((mesh.n_vertices, 3))
        basis_max = None
        for r in sorted(modes_list):
            t0 = time.perf_counter()
            basis = rt.modal_analysis(model, r)
            t_modal = time.perf_counter() - t0
            basis_max = basis
            sim = rt.ModalSimulator(basis, DT, DAMPING)
            f = {node: force}
            t_hap = per_step(lambda: (sim.step(f), sim.displacement(node)), 2000)
            t_full = per_step(lambda: (sim.step(f), sim.displacements(out=out)), max(5, int(2e7 / (mesh.n_vertices * r))))
            scale = max(np.linalg.norm(u) for u in U_ref)
            errs = []
            for corr in (False, True):
                s2 = rt.ModalSimulator(basis, DT, DAMPING, integrator="newmark", static_correction=corr)
                s2.prepare([node])
                U = history(s2, node, force)
                errs.append(max(np.linalg.norm(U[k] - U_ref[k]) for k in range(len(U))) / scale)
            sc = rt.ModalSimulator(basis, DT, DAMPING, static_correction=True)
            sc.prepare([node])
            t_hap_c = per_step(lambda: (sc.step(f), sc.displacement(node)), 2000)
            rows.append([mesh.n_vertices, model.n_dofs, r, fmt_s(t_fac), fmt_s(t_modal), f"{t_hap * 1e6:.2f} us",
                         f"{t_hap_c * 1e6:.2f} us", fmt_s(t_full), fmt_s(t_direct), f"{t_direct / t_hap:,.0f}x",
                         f"{t_direct / t_full:,.0f}x", f"{errs[0]:.1e}", f"{errs[1]:.1e}", f"{basis.frequencies[-1]:.0f}"])
            print(f"    r = {r}: modal {t_modal:.1f} s, haptic {t_hap * 1e6:.2f} us", file=sys.stderr)
        del basis_max
        rows.append([""] * 14)
        rows[-1][0] = f"(direct setup {fmt_s(t_dsetup)})"
    print_table(["vertices", "dof", "r", "factorize", "Lanczos r modes", "haptic step", "haptic + correction",
                 "full-field step", "direct step", "direct/haptic", "direct/full", "error", "error corrected",
                 "f_r (Hz)"], rows)
    print("\nhaptic step: ModalSimulator.step({node: f}) + displacement(node); full-field: step + "
          "displacements(); direct: DirectSimulator (Newmark) step + nothing else. Medians of batches.")


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--levels", type=int, nargs="+", default=[4, 5, 6])
    ap.add_argument("--modes", type=int, nargs="+", default=[10, 20, 50, 100, 200])
    a = ap.parse_args()
    run(a.levels, a.modes)
