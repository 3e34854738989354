"""The reduced model's a posteriori error indicator (issue 56: rtfem.reduction.indicator.error_estimate)
against the true error, the reduced static state's distance from the full order's equilibrium under
the same loads (rt.nonlinear.solve_static: Newton with load steps, another algorithm), on the
issue's three cases, each on a mesh built here: the tet10 block pulled 2.25 cm at a jaw on its end,
a grasp on the solid liver (a patch of its top pulled up by 3 and 5.5 N), the tet10 cantilever at
30 % of its length. The reduced state is the reduced model's static equilibrium under those loads
(40 modes and the derivatives of 10, the viewer's default basis; the cantilever 20 and 20; the
static correction on). The issue asks for a factor of 2; measured 0.999-1.017 (Newton's correction
and two chord steps), 0.93-1.22 with Newton's correction alone, 0.91-1.00 on the linear model's
8-770 times larger error, and each time the worst node itself."""

import numpy as np
import pytest

import rtfem as rt
from rtfem.reduction.indicator import error_estimate
from rtfem.reduction.reduced import ReducedNonlinearModel


def _jaw(model):
    """The nodes of the block's end face under a 15 mm jaw at its centre (corner and mid-edge nodes)."""
    X = np.asarray(model.mesh.vertices)
    end = np.flatnonzero(np.isclose(X[:, 0], 0.1))
    return end[np.linalg.norm(X[end] - [0.1, 0.02, 0.02], axis=1) < 0.0075]


def _case(name):
    if name == "block":  # 0.1 x 0.04 x 0.04 m tet10, E 4e4, clamped at x = 0; the viewer's default basis
        model = rt.SolidModel(rt.meshes.box(0.1, 0.04, 0.04, nx=10, ny=4, nz=4),
                              rt.Material(E=4e4, nu=0.45, density=1000.0), element="tet10")
        model.fix("x0")
        jaw = _jaw(model)
        F = np.zeros((model.n_nodes, 3))
        F[jaw, 2] = 0.5 / jaw.size  # 0.5 N: the end moves 2.1 cm
        return model, ReducedNonlinearModel(model, rt.modal_analysis(model, 40), 10), [F], 0.02
    if name == "liver":  # the solid liver (tet4, 12 mm), held at its attachment, a 15 mm patch of its top
        model = rt.SolidModel(rt.meshes.liver(solid=True, spacing=0.012), rt.Material(E=3e4, nu=0.45), element="tet4")
        model.fix("attachment")
        X, used = np.asarray(model.mesh.vertices), model.mesh.used_vertices()
        free = used[~model.held_nodes[used]]
        v = free[np.argmax(X[free, 2])]
        patch = free[np.linalg.norm(X[free] - X[v], axis=1) < 0.015]
        n = model.mesh.vertex_normals()[v]
        loads = []
        for P in (3.0, 5.5):  # N: the top moves 2.4 and 4.1 cm
            F = np.zeros((model.n_nodes, 3))
            F[patch] = P * n / patch.size
            loads.append(F)
        return model, ReducedNonlinearModel(model, rt.modal_analysis(model, 40), 10), loads, 0.02
    # the tet10 cantilever 1 x 0.1 x 0.1 m, P L^2 / EI = 1 at the tip: the elastica lifts it 30 %
    model = rt.SolidModel(rt.meshes.box(1.0, 0.1, 0.1, nx=10, ny=1, nz=1), rt.Material(E=1e5, nu=0.3, density=10.0),
                          element="tet10")
    model.fix("x0")
    tip = model.select_nodes("x1")
    F = np.zeros((model.n_nodes, 3))
    F[tip, 2] = 1e5 * 0.1**4 / 12 / tip.size
    return model, ReducedNonlinearModel(model, rt.modal_analysis(model, 20), 20), [F], 0.25


@pytest.mark.parametrize("name", ["block", "liver", "cantilever"])
def test_the_indicator_predicts_the_reduced_models_error_within_a_factor_of_2(name):
    model, red, loads, motion = _case(name)
    for F in loads:
        full = rt.nonlinear.solve_static(model, F, steps=8).displacements
        assert np.linalg.norm(full, axis=1).max() > motion  # m: the large motions the issue names
        reduced = red.solve_static(F, steps=8, max_iterations=100, static_correction=True).displacements
        true = np.linalg.norm(full - reduced, axis=1)
        est = error_estimate(model, reduced, F)
        assert 0.5 < est.max_error / true.max() < 2.0, (est.max_error, true.max())
        # and where: the estimate's field is the error's (its worst node is among the truly worst)
        assert true[est.worst_node] > 0.5 * true.max()
        first = error_estimate(model, reduced, F, iterations=1)  # Newton's correction alone
        assert 0.5 < first.max_error / true.max() < 2.0, (first.max_error, true.max())
        # the linear model's error, ten times larger, is read as well: the indicator is not tuned to one size
        linear = model.solve_static(F)
        lin_true = np.linalg.norm(full - linear, axis=1).max()
        assert lin_true > 5 * true.max()
        assert 0.5 < error_estimate(model, linear, F).max_error / lin_true < 2.0
        # at the full order's own equilibrium there is nothing left to estimate (its residual's tolerance)
        assert error_estimate(model, full, F).max_error < 1e-3 * true.max()


def test_held_nodes_are_prescribed_and_labels_report_regions():
    """With the jaw's vertices held where the state has them, the estimate is the correction of the
    prescribed-displacement problem: zero at those vertices, and against rt.nonlinear.solve_static with
    those motions prescribed (the vertices fixed on a copy of the model) within a factor of 2 (measured
    1.000); a labelled region's figure is the largest estimate in it."""
    model, red, (F,), _ = _case("block")
    reduced = red.solve_static(F, steps=8, max_iterations=100, static_correction=True).displacements
    jaw = _jaw(model)
    X = np.asarray(model.mesh.vertices)
    labels = (X[:, 0] > 0.05).astype(int)
    est = error_estimate(model, reduced, None, held=jaw, labels=labels)
    assert np.all(est.node_error[jaw] == 0.0)
    held_model = rt.SolidModel(rt.meshes.box(0.1, 0.04, 0.04, nx=10, ny=4, nz=4),
                               rt.Material(E=4e4, nu=0.45, density=1000.0), element="tet10")
    held_model.fix("x0")
    held_model.fix(jaw)
    prescribed = np.zeros((model.n_nodes, 3))
    prescribed[jaw] = reduced[jaw]
    full = rt.nonlinear.solve_static(held_model, None, prescribed=prescribed, steps=8).displacements
    true = np.linalg.norm(full - reduced, axis=1).max()
    assert 0.5 < est.max_error / true < 2.0, (est.max_error, true)
    assert est.regions[1] == est.max_error and est.regions[0] == est.node_error[labels == 0].max()
    with pytest.raises(rt.ModelError, match="finite"):
        error_estimate(model, np.full((model.n_nodes, 3), np.nan), F)
