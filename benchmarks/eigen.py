"""Precompute speed: r modes through each installed factorization backend against plain
``scipy.sparse.linalg.eigsh(K, r, M, sigma=0)`` on the same matrices, in one run.

Meshes: the liver at the given levels and, when ``../shared/data`` is present, the 15,365-vertex
OpenHELP liver (sofa_env_Liver.stl, scale 1e-3, E 3e4, nu 0.45, t 3 mm, rho 1060, the top 15 %
of its height fixed: the issue's reference case). Columns: factorize, the solves, the rest of
the Lanczos iteration (ARPACK's orthogonalization), the whole modal_analysis, eigsh, and the
ratio eigsh / rtfem; the eigenvalues against eigsh's; the process's peak resident memory so far
(run one mesh per process, e.g. ``--levels 7 --no-openhelp --no-eigsh --backends pardiso``, for
that mesh's own peak). ``--solver`` picks rtfem's eigensolver (default: the block method).
"""

from __future__ import annotations

import argparse
import os
import platform
import resource
import sys
import time
from pathlib import Path

import numpy as np
import scipy.sparse.linalg as spla

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from _common import busy_core, fmt_s, print_table  # noqa: E402

import rtfem as rt  # noqa: E402

OPENHELP = Path(__file__).resolve().parents[2] / "shared" / "data" / "organs" / "sofa_env_Liver.stl"


def geodesic_liver(frequency: int) -> rt.TriMesh:
    """The embedded liver's surface on a geodesic sphere of the given frequency: each
    icosahedron face cut into frequency^2 triangles (10 f^2 + 2 vertices: f = 100 gives
    100,002, between the liver's levels 6 and 7), relaxed on the same map and with the same
    attachment region as ``rt.meshes.liver``."""
    from rtfem.mesh.meshes import _liver_map, _relax_on_map

    ico = rt.meshes.icosphere(1.0, 0)
    V0, T0 = np.asarray(ico.vertices), np.asarray(ico.triangles)
    f = int(frequency)
    i, j = (a.ravel() for a in np.meshgrid(np.arange(f + 1), np.arange(f + 1), indexing="ij"))
    keep = i + j <= f
    i, j = i[keep], j[keep]
    local = -np.ones((f + 1, f + 1), int)
    local[i, j] = np.arange(i.size)
    up = (i + j <= f - 1)
    down = (i + j <= f - 2)
    tri = np.r_[np.column_stack([local[i[up], j[up]], local[i[up] + 1, j[up]], local[i[up], j[up] + 1]]),
                np.column_stack([local[i[down] + 1, j[down]], local[i[down] + 1, j[down] + 1], local[i[down], j[down] + 1]])]
    points, tris = [], []
    for a, b, c in T0:
        A, B, C = V0[a], V0[b], V0[c]
        P = A + np.outer(i / f, B - A) + np.outer(j / f, C - A)
        tris.append(tri + sum(len(p) for p in points))
        points.append(P / np.linalg.norm(P, axis=1)[:, None])
    P = np.concatenate(points)
    _, first, inverse = np.unique(np.round(P, 9), axis=0, return_index=True, return_inverse=True)
    P, T = P[first], inverse.ravel()[np.concatenate(tris)]
    sph = rt.TriMesh(P, T, repair=False)
    P = _relax_on_map(P, sph, _liver_map, iterations=30)
    x, y, z = P[:, 0], P[:, 1], P[:, 2]
    attach = np.flatnonzero((y < -0.55) & (z > 0.05) & (x > -0.55) & (x < 0.25))
    return rt.TriMesh(_liver_map(P), T, repair=False, groups={"attachment": attach})


def models(levels, openhelp=True, geodesic=()):
    for level in levels:
        model = rt.ShellModel(rt.meshes.liver(level), rt.Material())
        yield f"liver level {level}", lambda m=model: m.fix("attachment")
    for f in geodesic:
        model = rt.ShellModel(geodesic_liver(f), rt.Material())
        yield f"liver, geodesic f = {f}", lambda m=model: m.fix("attachment")
    if not openhelp:
        return
    if OPENHELP.exists():
        mesh = rt.load_mesh(OPENHELP, scale=1e-3)
        model = rt.ShellModel(mesh, rt.Material(E=3e4, nu=0.45, thickness=3e-3, density=1060.0))
        z = np.asarray(mesh.vertices)[:, 2]
        yield "OpenHELP liver", lambda m=model: m.fix(z >= z.max() - 0.15 * (z.max() - z.min()))
    else:
        print(f"(skipped the OpenHELP liver: {OPENHELP} is absent)", file=sys.stderr)


def peak_gb() -> float:
    """The process's peak resident memory (GB; Linux reports KiB, macOS bytes)."""
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / (2**30 if platform.system() == "Darwin" else 2**20)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--levels", type=int, nargs="*", default=[5])
    ap.add_argument("--geodesic", type=int, nargs="*", default=[],
                    help="also the liver on a geodesic sphere of these frequencies (10 f^2 + 2 vertices; 100: 100,002)")
    ap.add_argument("--modes", type=int, default=100)
    ap.add_argument("--no-eigsh", action="store_true", help="skip the plain eigsh baseline")
    ap.add_argument("--eigsh-max-dof", type=int, default=300_000, help="skip eigsh above this many dofs")
    ap.add_argument("--no-openhelp", action="store_true", help="only the embedded livers")
    ap.add_argument("--backends", nargs="+", default=None, help="factorization backends (default: all installed)")
    ap.add_argument("--solver", default="auto", choices=["auto", "block", "arpack"])
    ap.add_argument("--busy", action="store_true", help="with another process keeping one core busy throughout")
    args = ap.parse_args()
    with busy_core(args.busy):
        run(args)


def run(args) -> None:
    print(f"# rtfem {rt.__version__}, python {platform.python_version()}, {platform.machine()}, "
          f"{os.cpu_count()} cores, backends: {', '.join(rt.available_backends())}; r = {args.modes}; "
          f"solver {args.solver}{'; one core busy' if args.busy else ''}")
    rows = []
    for name, make in models(args.levels, not args.no_openhelp, args.geodesic):
        model = make()
        K, dofs = model.constrained_stiffness()
        M, _ = model.constrained_mass()
        t_eigsh = lam_ref = None
        if not args.no_eigsh and K.shape[0] <= args.eigsh_max_dof:
            t0 = time.perf_counter()
            lam_ref = np.sort(spla.eigsh(K, args.modes, M, sigma=0, return_eigenvectors=False))
            t_eigsh = time.perf_counter() - t0
        for backend in args.backends or rt.available_backends():
            os.environ["RTFEM_BACKEND"] = backend
            model.release()
            make()  # the same fixes again: a fresh factorization
            t0 = time.perf_counter()
            basis = rt.modal_analysis(model, args.modes, solver=args.solver)
            total = time.perf_counter() - t0
            i = basis.info
            diff = "-" if lam_ref is None else f"{np.abs(basis.omega**2 - lam_ref).max() / lam_ref.max():.1e}"
            rows.append([name, f"{model.n_nodes:,}", f"{K.shape[0]:,}", backend, fmt_s(i["factorize_seconds"]),
                         f"{fmt_s(i['solve_seconds'])} ({i['solves']})", fmt_s(i["lanczos_other_seconds"]), fmt_s(total),
                         fmt_s(t_eigsh), "-" if t_eigsh is None else f"{t_eigsh / total:.1f}x", diff,
                         i["method"].split(" (")[0].replace("shift-invert ", ""), f"{peak_gb():.1f} GB"])
            print(f"  {name}, {backend}: {total:.1f} s", file=sys.stderr, flush=True)
        os.environ.pop("RTFEM_BACKEND", None)
    print_table(["mesh", "vertices", "dof", "backend", "factorize", "solves (right-hand sides)", "Lanczos other",
                 "modal_analysis",
                 "plain eigsh", "eigsh / rtfem", "max |dw^2|/w_r^2", "eigensolver", "peak RSS so far"], rows)


if __name__ == "__main__":
    main()
