"""Precompute speed: r modes through each installed factorization backend against plain
``scipy.sparse.linalg.eigsh(K, r, M, sigma=0)`` on the same matrices, in one run.

Meshes: the liver at the given levels and, when ``../shared/data`` is present, the 15,365-vertex
OpenHELP liver (sofa_env_Liver.stl, scale 1e-3, E 3e4, nu 0.45, t 3 mm, rho 1060, the top 15 %
of its height fixed: the issue's reference case). Columns: factorize, the solves, the rest of
the Lanczos iteration (ARPACK's orthogonalization), the whole modal_analysis, eigsh, and the
ratio eigsh / rtfem; the last column checks the eigenvalues against eigsh's.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
import scipy.sparse.linalg as spla

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from _common import fmt_s, print_table  # noqa: E402

import rtfem as rt  # noqa: E402

OPENHELP = Path(__file__).resolve().parents[2] / "shared" / "data" / "organs" / "sofa_env_Liver.stl"


def models(levels):
    for level in levels:
        model = rt.ShellModel(rt.meshes.liver(level), rt.Material())
        yield f"liver level {level}", lambda m=model: m.fix("attachment")
    if OPENHELP.exists():
        mesh = rt.load_mesh(OPENHELP, scale=1e-3)
        model = rt.ShellModel(mesh, rt.Material(E=3e4, nu=0.45, thickness=3e-3, density=1060.0))
        z = np.asarray(mesh.vertices)[:, 2]
        yield "OpenHELP liver", lambda m=model: m.fix(z >= z.max() - 0.15 * (z.max() - z.min()))
    else:
        print(f"(skipped the OpenHELP liver: {OPENHELP} is absent)", file=sys.stderr)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--levels", type=int, nargs="*", default=[5])
    ap.add_argument("--modes", type=int, default=100)
    ap.add_argument("--no-eigsh", action="store_true", help="skip the plain eigsh baseline")
    args = ap.parse_args()
    print(f"# rtfem {rt.__version__}, python {platform.python_version()}, {platform.machine()}, "
          f"{os.cpu_count()} cores, backends: {', '.join(rt.available_backends())}; r = {args.modes}")
    rows = []
    for name, make in models(args.levels):
        model = make()
        K, dofs = model.constrained_stiffness()
        M, _ = model.constrained_mass()
        t_eigsh = lam_ref = None
        if not args.no_eigsh:
            t0 = time.perf_counter()
            lam_ref = np.sort(spla.eigsh(K, args.modes, M, sigma=0, return_eigenvectors=False))
            t_eigsh = time.perf_counter() - t0
        for backend in rt.available_backends():
            os.environ["RTFEM_BACKEND"] = backend
            model.release()
            make()  # the same fixes again: a fresh factorization
            t0 = time.perf_counter()
            basis = rt.modal_analysis(model, args.modes)
            total = time.perf_counter() - t0
            i = basis.info
            diff = "-" if lam_ref is None else f"{np.abs(basis.omega**2 - lam_ref).max() / lam_ref.max():.1e}"
            rows.append([name, f"{model.n_nodes:,}", f"{K.shape[0]:,}", backend, fmt_s(i["factorize_seconds"]),
                         f"{fmt_s(i['solve_seconds'])} ({i['solves']})", fmt_s(i["lanczos_other_seconds"]), fmt_s(total),
                         fmt_s(t_eigsh), "-" if t_eigsh is None else f"{t_eigsh / total:.1f}x", diff])
            print(f"  {name}, {backend}: {total:.1f} s", file=sys.stderr, flush=True)
        os.environ.pop("RTFEM_BACKEND", None)
    print_table(["mesh", "vertices", "dof", "backend", "factorize", "solves (count)", "Lanczos other", "modal_analysis",
                 "plain eigsh", "eigsh / rtfem", "max |dw^2|/w_r^2"], rows)


if __name__ == "__main__":
    main()
