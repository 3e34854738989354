"""The reduced nonlinear model (modes + modal derivatives, Barbic & James 2005) against
independent references.

- The modal derivative Psi_11 is the second-order term of the full-order corotational static
  response to the load K phi_1: u(h) = h phi_1 + h^2 Psi_11 / 2 + O(h^3), read off by the
  symmetric difference (u(h) + u(-h)) / (2 h^2), whose error must fall as h^2.
- The elastica strip (values in test_large_deformation): the reduced model with the derivatives
  of 6 modes is within 1.5 % of L at P L^2/EI = 1 and at most half the linear model's error at
  1 and 2, while the same modes without derivatives lock (worse than linear: the Galerkin
  projection of a bending mode's stretch).
- A solid whose basis is every mode spans all free dofs: its reduced equilibrium is the
  full-order one to round-off.
"""

import numpy as np
import pytest

import rtfem as rt
from rtfem.reduced import ReducedNonlinearModel
from test_large_deformation import ELASTICA, _edge_load, _tip, _strip


@pytest.fixture(scope="module")
def strip():
    model = _strip(20)
    return model, rt.modal_analysis(model, 12)


def test_derivative_is_the_second_order_static_response(strip):
    model, modes = strip
    red = ReducedNonlinearModel(model, modes, 0)
    n = model.n_nodes
    phi = modes.shapes[:, :, :1]
    full = np.concatenate([phi, model.rotation_field(phi)], axis=1)[:, :, 0]
    load = (model.K @ full.ravel()).reshape(n, 6)
    assert np.abs(load[:, 3:][~model.fixed[:, 3:]]).max() < 1e-10 * np.abs(load).max()  # no moments: a translation load
    load = load[:, :3] * ~model.fixed[:, :3]
    psi = red.system.expand(red.derivatives(full.ravel()[red.free][:, None])[:, 0])[:, :3]
    errors = []
    for h in (0.1, 0.05):
        up = rt.nonlinear.solve_static(model, h * load).displacements
        um = rt.nonlinear.solve_static(model, -h * load).displacements
        errors.append(np.abs((up + um) / (2 * h * h) - 0.5 * psi).max() / np.abs(0.5 * psi).max())
    assert errors[1] < 2e-4
    assert 3.0 < errors[0] / errors[1] < 5.0  # O(h^2)


@pytest.mark.parametrize("k", [1, 2])
def test_reduced_strip_against_the_elastica(strip, k):
    model, modes = strip
    EI = 1.2e6 * 1.0 * 0.1**3 / 12
    F = _edge_load(model, k * EI / 100.0)
    ref = np.array(ELASTICA[k])

    def error(U):
        tip = _tip(model, U)
        return np.hypot(-tip[0] - ref[0], tip[2] - ref[1])

    linear = error(model.solve_static(F))
    red = ReducedNonlinearModel(model, modes, 6)
    assert 12 < red.size <= 12 + 21  # directions the modes already hold are dropped
    res = red.solve_static(F)
    reduced = error(res.displacements)
    assert reduced <= 0.5 * linear
    if k == 1:
        assert reduced < 0.015
        locked = error(ReducedNonlinearModel(model, modes, 0).solve_static(F).displacements)
        assert locked > linear


def test_newton_converges_quadratically(strip):
    model, modes = strip
    red = ReducedNonlinearModel(model, modes, 6)
    EI = 1.2e6 * 1.0 * 0.1**3 / 12
    res = red.solve_static(_edge_load(model, EI / 100.0), steps=1)
    h = np.array(res.residuals[-1])
    near = int(np.argmax(h < 1e-3 * h[0]))  # the first iterate within 1e-3 of the start
    assert h[near] < 1e-3 * h[0] and h[-1] < 1e-10 * h[0]
    assert len(h) - 1 - near <= 3  # then quadratic: 1e-3 -> 1e-6 -> 1e-12 (a linear rate of 0.1 needs 7)


def test_complete_basis_equals_the_full_order_solid():
    model = rt.SolidModel(rt.meshes.box(1.0, 0.1, 0.1, nx=4, ny=1, nz=1), rt.Material(E=1e5, nu=0.3, density=1.0))
    model.fix("x0")
    modes = rt.modal_analysis(model, "all")
    red = ReducedNonlinearModel(model, modes, 0)
    assert red.size == model.free_dofs.size
    F = np.zeros((model.n_nodes, 3))
    tip = model.select_nodes("x1")
    F[tip, 2] = 1.0
    F *= 0.5 / model.solve_static(F)[tip, 2].mean()  # a linear tip deflection of half the length
    full = rt.nonlinear.solve_static(model, F)
    res = red.solve_static(F)
    assert full.displacements[tip, 2].mean() < 0.45  # a large motion: the nonlinear tip lags the linear one
    assert np.abs(res.displacements - full.displacements).max() < 1e-8 * np.abs(full.displacements).max()


def test_pulled_nodes_move_exactly_and_bad_input(strip):
    model, modes = strip
    red = ReducedNonlinearModel(model, modes, 3)
    tip = int(model.select_nodes("x1")[0])
    res = red.solve_static(targets={tip: (0.0, 0.0, 2.0)})
    assert np.allclose(res.displacements[tip], (0.0, 0.0, 2.0), atol=1e-12)
    with pytest.raises(rt.ModelError, match="fixed"):
        red.solve_static(targets={int(model.select_nodes("x0")[0]): (0, 0, 1.0)})
    with pytest.raises(rt.ModelError, match="another mesh"):
        ReducedNonlinearModel(model, rt.modal_analysis(_strip(10), 4), 2)
    with pytest.raises(rt.ModelError, match="derivatives"):
        ReducedNonlinearModel(model, modes, 13)
