"""Cubature per region or over the whole (issue 58): the reduced nonlinear model of a two-region liver
against its own full order under a pull.

The embedded solid liver (level 3, its shipped tets: 1,152 nodes, 4,903 tet4; the first tables of
benchmarks/results/regions_cubature.txt were measured on a mesh made on this machine, 1,160 nodes,
4,942 tets; E 30 kPa, nu 0.45, held at its attachment) with a ball of other tissue, a soft one
(E 3 kPa, a cyst) or a stiff one (E 300 kPa, a tumour), under two loads scaled so that their
linear answer moves the organ 15 mm (pull) or 20 mm (gravity): ``pull``, a 15 mm ball 12 mm under
the probe point (73 tets) and the probe's surface
patch (radius 20 mm) pulled outward; ``gravity``, a 30 mm ball at the organ's centre (357 tets) and
the organ's weight. Each row: the reduced model's
settled static answer (``solve_static(cubature=True)``) against rt.nonlinear.solve_static's on the
full order (worst node, as a fraction of the largest displacement), and against the reduced model's
own answer without cubature (all elements: what the cubature alone adds), for cubature fitted per
region (``train_cubature(regions=True)``, the default on a model of regions: each region to tol of its
own forces and to tol / 2 of the whole's), over all elements at once to tol, and over all elements to
the training error the per-region fits reached (their cost, about: what the per-region rule buys
beyond a tighter tolerance); medians and ranges over the training seeds (--seeds), with the training
error, the elements chosen and how many lie in the ball, and the training's seconds.

    python benchmarks/regions_cubature.py [--modes 30 80] [--derivatives 15 20] [--tol 0.05] [--poses 16]
        [--load pull gravity] [--seeds 3]
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


def organ(E_ball: float, load: str = "pull"):
    """The two-region liver, the load's nodal forces and the ball's tets: ``pull`` the probe's patch
    outward (a ball under the probe), ``gravity`` the organ's weight (a 30 mm ball at its centre)."""
    liver = rt.meshes.liver(3, solid=True)
    X = np.asarray(liver.vertices)
    c = X[np.asarray(liver.corner_tets)].mean(axis=1)
    top = int(np.argmin(np.linalg.norm(X - np.asarray(rt.meshes.PROBE_POINT), axis=1)))
    inward = X.mean(axis=0) - X[top]
    inward /= np.linalg.norm(inward)
    if load == "pull":
        ball = np.linalg.norm(c - (X[top] + 0.012 * inward), axis=1) < 0.015
    else:
        ball = np.linalg.norm(c - X.mean(axis=0), axis=1) < 0.03
    mesh = rt.TetMesh(liver.vertices, liver.tets, labels=ball.astype(int), groups=liver.groups)
    model = rt.SolidModel(mesh, {0: rt.Material(E=3e4, nu=0.45), 1: rt.Material(E=E_ball, nu=0.45)}).fix("attachment")
    F = np.zeros((model.n_nodes, 3))
    if load == "pull":
        surface = np.unique(mesh.boundary_faces)
        F[surface[np.linalg.norm(X[surface] - X[top], axis=1) < 0.02]] = -inward
    else:  # the weight of the free nodes (the held ones' goes into the supports)
        F[:, 2] = -model.mass_diagonal.reshape(-1, 3)[:, 0] * ~model.held_nodes
    return model, F * (0.015 if load == "pull" else 0.02) / np.abs(model.solve_static(F)).max(), ball


def rows_for(E_ball: float, modes: int, derivatives: int, tol: float, load: str, seeds: int,
             poses: int = 16) -> list[list[object]]:
    model, F, ball = organ(E_ball, load)
    full = rt.nonlinear.solve_static(model, F).displacements
    t0 = time.perf_counter()
    red = ReducedNonlinearModel(model, rt.modal_analysis(model, modes), derivatives)
    built = time.perf_counter() - t0
    exact = red.solve_static(F).displacements
    scale = np.abs(full).max()
    out, reached = [], tol
    for regions, fit_tol, name in ((True, tol, "per region"), (False, tol, "whole"), (False, None, "whole, same train. error")):
        errs, own, counts, inside, secs, trained = [], [], [], [], [], []
        for seed in range(seeds):
            info = red.train_cubature(poses, tol=fit_tol or reached, regions=regions, seed=seed)
            u = red.solve_static(F, cubature=True, max_iterations=60).displacements
            errs.append(np.abs(u - full).max() / scale)
            own.append(np.abs(u - exact).max() / scale)
            counts.append(len(info["elements"]))
            inside.append(int(ball[info["elements"]].sum()))
            secs.append(info["seconds"])
            trained.append(info["training_error"])
        if regions:  # the whole's fit to the training error the regions' fits reached together
            reached = float(np.median(trained))
        out.append([load, f"{E_ball / 1e3:g} kPa", f"{modes}+{derivatives}", f"{built:.1f} s",
                    f"{np.abs(exact - full).max() / scale:.4f}", name, f"{np.median(trained):.3f}",
                    f"{int(np.median(counts))} ({int(np.median(inside))} in ball)", f"{np.median(secs):.1f} s", _span(errs),
                    _span(own)])
    return out


def _span(values) -> str:
    v = np.asarray(values)
    return f"{np.median(v):.4f} ({v.min():.4f}-{v.max():.4f})"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--modes", type=int, nargs="+", default=[30, 80])
    ap.add_argument("--derivatives", type=int, nargs="+", default=[15, 20])
    ap.add_argument("--tol", type=float, default=0.05)
    ap.add_argument("--load", choices=["pull", "gravity"], nargs="+", default=["pull", "gravity"])
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--poses", type=int, default=16, help="training poses per fit")
    args = ap.parse_args()
    rows = []
    for load in args.load:
        for E_ball in (3e3, 3e5):
            for modes, derivatives in zip(args.modes, args.derivatives):
                rows += rows_for(E_ball, modes, derivatives, args.tol, load, args.seeds, args.poses)
    print(f"cubature tol {args.tol}, {args.poses} poses; errors: worst node / largest displacement, "
          f"median (range) of {args.seeds} seeds")
    print_table(["load", "ball", "basis", "build", "no cubature vs full", "cubature", "training error", "elements",
                 "training", "vs full order",
                 "vs no cubature"], rows)


if __name__ == "__main__":
    main()
