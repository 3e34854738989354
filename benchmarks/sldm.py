"""SLDM against the modal route: Krylov dimension, cost and memory for a required accuracy.

For the default liver (level 4) and its refinements, a step load at one node, 1,000 time
samples on [0, T]:

* SLDM for tol = 1e-3 .. 1e-8: the Krylov dimension actually needed (the error of every
  prefix m of one long Lanczos run), the dimension the adaptive rule chose and its lower
  bound m0 = T sqrt(theta_max)/2, the time to build the basis, the time to evaluate the
  1,000 samples, the memory of Q_m, the estimate and the true error;
* the modal route for the same accuracy: modal analysis with r modes and the closed-form
  step response with static correction at the same 1,000 samples; the smallest r of
  (10, 20, 50, 100, 200) that meets tol, its precompute and evaluation times;
* a ramped probe load (Duhamel superposition in SLDM) against the modal route;
* m against the time horizon T (default liver, tol 1e-6).

    .venv/bin/python benchmarks/sldm.py [--levels 4 5 6] [--horizon 0.05] [--samples 1000]
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
from rtfem.reduction.oscillator import step_response  # noqa: E402

DAMPING = rt.Damping(alpha=4.0)
TOLS = (1e-3, 1e-4, 1e-5, 1e-6, 1e-7, 1e-8)
MODES = (10, 20, 50, 100, 200)


def rel(U, R):
    return float(np.abs(U - R).max() / np.abs(R).max())


def modal_step(model, basis, node, force, times, correction=True):
    """Exact modal step response, with the static correction (mode acceleration) by default."""
    P = basis.matrix
    F = np.zeros(P.shape[0])
    F[3 * node : 3 * node + 3] = force
    lam = basis.omega**2
    coef = step_response(lam[:, None], DAMPING.modal_alpha(basis.omega)[:, None], times[None, :])
    fm = P.T @ F
    U = (P @ (coef * fm[:, None])).T
    if correction:
        U = U + (model.solve_static({node: force}).ravel() - P @ (fm / lam))[None, :]
    return U.reshape(times.size, -1, 3)


def prefix_errors(sldm, force_vec, times, m_ref):
    """Error of y_m for every m <= m_ref from one Lanczos run (mass-weighted norm, reduced space)."""
    from rtfem.reduction.lanczos import Lanczos
    from rtfem.reduction.sldm import _eig_tridiagonal

    b = sldm._load(force_vec)
    L = Lanczos(sldm.apply, b)
    L.extend(m_ref)
    a, bt = L.tridiagonal()

    def z_of(m):
        lam, V = _eig_tridiagonal(a[:m], bt[: m - 1])
        c = step_response(lam[:, None], sldm._alpha_of(lam)[:, None], times[None, :]) * V[0][:, None]
        return V @ c

    zr = z_of(L.m)
    scale = np.linalg.norm(zr, axis=0).max()
    errs = {}
    for m in range(10, L.m, max(1, L.m // 200)):
        zm = z_of(m)
        d = zr.copy()
        d[:m] -= zm
        errs[m] = float(np.linalg.norm(d, axis=0).max() / scale)
    return errs, L.m


def ramp_history(node, force, t_ramp=0.02, pieces=20):
    f = np.asarray(force)
    return [(k * t_ramp / pieces, {node: tuple(f * (k + 1) / pieces)}) for k in range(pieces)]


def modal_ramp(model, basis, node, force, times, history, correction=True):
    out = 0.0
    for k, (tk, load) in enumerate(history):
        prev = np.zeros(3) if k == 0 else np.asarray(history[k - 1][1][node])
        jump = np.asarray(load[node]) - prev
        tau = np.clip(times - tk, 0.0, None)
        u = modal_step(model, basis, node, tuple(jump), np.where(tau > 0, tau, 1e-30), correction)
        out = out + u * (times > tk)[:, None, None]
    return out


def run(levels, horizon, samples, tols=TOLS, ramp=True, horizon_table=True):
    print(f"# rtfem {rt.__version__}, numpy {np.__version__}, python {platform.python_version()}; "
          f"load at one node, alpha = {DAMPING.alpha}, horizon T = {horizon} s, {samples} samples")
    times = np.linspace(horizon / samples, horizon, samples)
    rows, rows_ramp = [], []
    for level in levels:
        mesh = rt.meshes.liver(level)
        model = rt.ShellModel(mesh, rt.Material())
        model.fix("attachment")
        node = int(mesh.groups["probe"][0])
        force = tuple(-0.2 * mesh.vertex_normals()[node])
        t0 = time.perf_counter()
        sldm = rt.SLDM(model, DAMPING)
        t_setup = time.perf_counter() - t0
        sldm.step_response({node: force}, times[-1:], tol=1e-6)
        m0 = sldm.last_info.m0
        errs, m_ref = prefix_errors(sldm, {node: force}, times, int(1.5 * m0) + 20)
        hist = ramp_history(node, force)
        ref = sldm.step_response({node: force}, times, m=m_ref)
        mass = model.mass_diagonal.reshape(-1, 6)[:, :3][None]
        mnorm = lambda U: np.sqrt((U**2 * mass).sum(axis=(1, 2))).max()  # noqa: E731
        print(f"  level {level}: m0 = {m0}, reference m = {m_ref}", file=sys.stderr)
        modal = {}
        for r in MODES:
            t0 = time.perf_counter()
            basis = rt.modal_analysis(model, r)
            t_modal = time.perf_counter() - t0
            t0 = time.perf_counter()
            U = modal_step(model, basis, node, force, times)
            t_eval = time.perf_counter() - t0
            e_step = mnorm(U - ref) / mnorm(ref)
            U_ramp = modal_ramp(model, basis, node, force, times, hist) if ramp else None
            modal[r] = (t_modal, t_eval, e_step, U_ramp)
            print(f"    modal r = {r}: {t_modal:.1f} s, step error {e_step:.1e}", file=sys.stderr)
        ref_ramp = rt.SLDM(model, DAMPING, m=m_ref).response(hist, times) if ramp else None
        for tol in tols:
            needed = min((m for m, e in errs.items() if e < tol), default=None)
            U = sldm.step_response({node: force}, times, tol=tol)
            info = sldm.last_info
            err = mnorm(U - ref) / mnorm(ref)
            del U
            q_mb = info.m * model.translational_free_dofs().size * 8 / 2**20
            fit = [r for r in MODES if modal[r][2] < tol]
            best = min(MODES, key=lambda r: modal[r][2])
            mcol = ([str(fit[0]), fmt_s(modal[fit[0]][0] + modal[fit[0]][1])] if fit
                    else [f"none <= {MODES[-1]}", f"best {modal[best][2]:.1e} (r={best})"])
            rows.append([mesh.n_vertices, f"{tol:.0e}", needed if needed else "-", info.m, info.m0,
                         fmt_s(info.lanczos_seconds), fmt_s(info.evaluate_seconds), f"{q_mb:.0f} MB",
                         f"{info.estimate:.1e}", f"{err:.1e}"] + mcol)
            if not ramp:
                print(f"    tol {tol:.0e}: m = {info.m}, {info.lanczos_seconds:.1f} s", file=sys.stderr)
                continue
            Ur = sldm.response(hist, times, tol=tol)
            ir = sldm.last_info
            er = mnorm(Ur - ref_ramp) / mnorm(ref_ramp)
            del Ur
            merr = {r: mnorm(modal[r][3] - ref_ramp) / mnorm(ref_ramp) for r in MODES}
            fit = [r for r in MODES if merr[r] < tol]
            bestr = min(MODES, key=lambda r: merr[r])
            rows_ramp.append([mesh.n_vertices, f"{tol:.0e}", ir.m, f"{er:.1e}",
                              fit[0] if fit else f"none <= {MODES[-1]}",
                              f"{merr[fit[0]]:.1e}" if fit else f"best {merr[bestr]:.1e} (r={bestr})"])
            print(f"    tol {tol:.0e}: m = {info.m}, {info.lanczos_seconds:.1f} s", file=sys.stderr)
        rows.append([f"(setup {fmt_s(t_setup)})"] + [""] * 11)
    print("\nStep load (switched on at t = 0 and held):")
    print_table(["vertices", "tol", "m needed", "m adaptive", "m0", "SLDM basis", f"{samples} samples",
                 "Q_m memory", "estimate", "true error", "modal r for tol", "modal cost / error"], rows)
    print("\nRamped probe load (0 to F in 20 ms, 20 steps, then held): SLDM response() (Duhamel) "
          "against the modal route with static correction:")
    print_table(["vertices", "tol", "SLDM m", "SLDM error", "modal r for tol", "modal error"], rows_ramp)
    print("\nErrors in the mass-weighted norm, max over the samples, relative to the largest response; "
          "reference: SLDM with m = 1.5 m0 + 20 (independently converged).")

    if not horizon_table:
        return
    print("\nKrylov dimension against the time horizon (default liver, tol 1e-6):")
    mesh = rt.meshes.liver(4)
    model = rt.ShellModel(mesh, rt.Material())
    model.fix("attachment")
    node = int(mesh.groups["probe"][0])
    sldm = rt.SLDM(model, DAMPING, m_max=6000)
    rows = []
    for T in (0.005, 0.01, 0.05, 0.1, 0.5, 1.0):
        sldm.step_response({node: (0.0, -0.2, 0.0)}, np.linspace(T / 100, T, 100), tol=1e-6)
        i = sldm.last_info
        rows.append([f"{T:g} s", i.m, i.m0, f"{np.sqrt(i.theta_max):.0f}", fmt_s(i.lanczos_seconds),
                     f"{i.m * model.translational_free_dofs().size * 8 / 2**20:.0f} MB"])
    print_table(["horizon T", "m", "m0 = T sqrt(theta_max)/2", "sqrt(theta_max) (rad/s)", "SLDM basis", "Q_m"], rows)


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--levels", type=int, nargs="+", default=[4, 5, 6])
    ap.add_argument("--horizon", type=float, default=0.05)
    ap.add_argument("--samples", type=int, default=1000)
    ap.add_argument("--tols", type=float, nargs="+", default=list(TOLS))
    ap.add_argument("--no-ramp", action="store_true", help="skip the ramped-load comparison")
    ap.add_argument("--no-horizon", action="store_true", help="skip the m-against-horizon table")
    a = ap.parse_args()
    run(a.levels, a.horizon, a.samples, tuple(a.tols), not a.no_ramp, not a.no_horizon)
