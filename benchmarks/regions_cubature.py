"""Cubature per region or over the whole (issue 58): the reduced nonlinear model of a two-region liver
against its own full order under a pull.

The embedded solid liver (level 3: 1,160 nodes, 4,942 tet4; E 30 kPa, nu 0.45, held at its
attachment) with a 15 mm ball of other tissue 12 mm under the probe point (73 tets): a soft one (E 3
kPa, a cyst) and a stiff one (E 300 kPa, a tumour). The probe's surface patch (radius 20 mm) is
pulled outward with a load whose linear answer moves the organ 15 mm. Each row: the reduced model's
settled static answer (``solve_static(cubature=True)``) against rt.nonlinear.solve_static's on the
full order (worst node, as a fraction of the largest displacement), and against the reduced model's
own answer without cubature (all elements: what the cubature alone adds), for cubature fitted per
region (``train_cubature(regions=True)``, the default on a model of regions) and over all elements
at once; medians and ranges over three training seeds, with the elements chosen (of 4,942) and how
many lie in the ball.

    python benchmarks/regions_cubature.py [--modes 30 80] [--derivatives 15 20] [--tol 0.05]
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from _common import print_table  # noqa: E402

import rtfem as rt  # noqa: E402
from rtfem.reduction.reduced import ReducedNonlinearModel  # noqa: E402


def organ(E_ball: float):
    """The two-region liver, the pull's nodal forces and the ball's tets."""
    liver = rt.meshes.liver(3, solid=True)
    X = np.asarray(liver.vertices)
    c = X[np.asarray(liver.corner_tets)].mean(axis=1)
    top = int(np.argmin(np.linalg.norm(X - np.asarray(rt.meshes.PROBE_POINT), axis=1)))
    inward = X.mean(axis=0) - X[top]
    inward /= np.linalg.norm(inward)
    ball = np.linalg.norm(c - (X[top] + 0.012 * inward), axis=1) < 0.015
    mesh = rt.TetMesh(liver.vertices, liver.tets, labels=ball.astype(int), groups=liver.groups)
    model = rt.SolidModel(mesh, {0: rt.Material(E=3e4, nu=0.45), 1: rt.Material(E=E_ball, nu=0.45)}).fix("attachment")
    surface = np.unique(mesh.boundary_faces)
    patch = surface[np.linalg.norm(X[surface] - X[top], axis=1) < 0.02]
    F = np.zeros((model.n_nodes, 3))
    F[patch] = -inward
    return model, F * 0.015 / np.abs(model.solve_static(F)).max(), ball


def rows_for(E_ball: float, modes: int, derivatives: int, tol: float) -> list[list[object]]:
    model, F, ball = organ(E_ball)
    full = rt.nonlinear.solve_static(model, F).displacements
    t0 = time.perf_counter()
    red = ReducedNonlinearModel(model, rt.modal_analysis(model, modes), derivatives)
    built = time.perf_counter() - t0
    exact = red.solve_static(F).displacements
    scale = np.abs(full).max()
    out = []
    for regions in (True, False):
        errs, own, counts, inside = [], [], [], []
        for seed in range(3):
            info = red.train_cubature(16, tol=tol, regions=regions, seed=seed)
            u = red.solve_static(F, cubature=True, max_iterations=60).displacements
            errs.append(np.abs(u - full).max() / scale)
            own.append(np.abs(u - exact).max() / scale)
            counts.append(len(info["elements"]))
            inside.append(int(ball[info["elements"]].sum()))
        out.append([f"{E_ball / 1e3:g} kPa", f"{modes}+{derivatives}", f"{built:.1f} s",
                    f"{np.abs(exact - full).max() / scale:.4f}", "per region" if regions else "whole",
                    f"{int(np.median(counts))} ({int(np.median(inside))} in ball)", _span(errs), _span(own)])
    return out


def _span(values) -> str:
    v = np.asarray(values)
    return f"{np.median(v):.4f} ({v.min():.4f}-{v.max():.4f})"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--modes", type=int, nargs="+", default=[30, 80])
    ap.add_argument("--derivatives", type=int, nargs="+", default=[15, 20])
    ap.add_argument("--tol", type=float, default=0.05)
    args = ap.parse_args()
    rows = []
    for E_ball in (3e3, 3e5):
        for modes, derivatives in zip(args.modes, args.derivatives):
            rows += rows_for(E_ball, modes, derivatives, args.tol)
    print(f"cubature tol {args.tol}; errors: worst node / largest displacement, median (range) of 3 seeds")
    print_table(["ball", "basis", "build", "no cubature vs full", "cubature", "elements", "vs full order",
                 "vs no cubature"], rows)


if __name__ == "__main__":
    main()
