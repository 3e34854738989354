"""SLDM (paper section 4) against independent routes.

* the step response against direct Newmark integration of the full system with a small dt,
  and against the exact modal solution with the full basis (dense condensed eigenproblem);
* the frequency response against a direct sparse solve of (K - w^2 M + i w B) u = F;
* a piecewise-constant history (Duhamel) against the exact modal integrator;
* the error estimate against the true error across damping regimes;
* a free body: its centre of mass moves as F t^2 / (2 m_total).
"""

import numpy as np
import pytest
import scipy.linalg as sla
import scipy.sparse as sp
import scipy.sparse.linalg as spla

import rtfem as rt
from conftest import liver_model
from rtfem.reduction.oscillator import step_response


def liver_model_and_node(level):
    model = liver_model(level)
    return model, model.mesh.groups["probe"][0]


def rel_err(U, R):
    return np.abs(U - R).max() / np.abs(R).max()


def modal_reference(model, basis, forces, damping, times):
    """Exact step response from the full modal basis: sum_i phi_i f(w_i^2, a_i, t) phi_i^T F."""
    P = basis.matrix
    F = np.zeros((model.n_nodes, 3))
    for node, f in forces.items():
        F[node] += f
    coef = step_response(basis.omega[:, None] ** 2, damping.modal_alpha(basis.omega)[:, None], times[None, :])
    return (P @ (coef * (P.T @ F.ravel())[:, None])).T.reshape(times.size, -1, 3)


def test_step_response_matches_direct_integration_on_default_liver():
    model, node = liver_model_and_node(4)
    damping = rt.Damping(alpha=4.0)
    forces = {node: (0.0, -0.1, 0.05)}
    dt, n = 2e-5, 2000
    direct = rt.DirectSimulator(model, dt, damping)
    samples = np.arange(200, n + 1, 200)
    U_direct = []
    for k in range(1, n + 1):
        direct.step(forces)
        if k in samples:
            U_direct.append(direct.displacements())
    # Newmark's trapezoid puts half of the first step's load in: a step at t = dt/2
    times = samples * dt - dt / 2
    U = rt.SLDM(model, damping).step_response(forces, times, tol=1e-8)
    assert rel_err(U, np.array(U_direct)) < 1e-4


@pytest.mark.slow
def test_step_response_matches_full_modal_basis_on_default_liver():
    model, node = liver_model_and_node(4)
    t = model.translational_free_dofs()
    Kc = model.condensed_stiffness(allow_large=True)  # dense Eq. 5, ~7,300 x 7,300
    m = model.mass_diagonal[t]
    s = 1 / np.sqrt(m)
    lam, V = sla.eigh(Kc * s[:, None] * s[None, :], overwrite_a=True, driver="evd")
    del Kc
    shapes = np.zeros((model.n_dofs, lam.size))
    shapes[t] = V * s[:, None]
    basis = rt.ModalBasis(np.sqrt(np.clip(lam, 0, None)), shapes.reshape(model.n_nodes, 6, -1)[:, :3], "full")
    times = np.linspace(0.0, 0.1, 26)
    for damping in (rt.Damping(alpha=4.0), rt.Damping(alpha=1.0, beta=2e-4)):
        forces = {node: (0.0, -0.1, 0.05)}
        U = rt.SLDM(model, damping).step_response(forces, times, tol=1e-8)
        assert rel_err(U, modal_reference(model, basis, forces, damping, times)) < 1e-4


@pytest.fixture(scope="module")
def small():
    model, node = liver_model_and_node(2)
    return model, node, rt.modal_analysis(model, "all")


@pytest.mark.parametrize("reorth", ["cgs2", "householder"])
@pytest.mark.parametrize("damping", [rt.Damping(alpha=4.0), rt.Damping(alpha=300.0), rt.Damping(alpha=5000.0),
                                     rt.Damping(alpha=1.0, beta=1e-3), rt.Damping(zeta=0.2)],
                         ids=["light", "medium", "overdamped", "rayleigh", "modal-zeta"])
def test_step_response_exact_against_modal_solution(small, damping, reorth):
    model, node, basis = small
    times = np.linspace(0.0, 0.2, 41)
    forces = {node: (0.0, -0.1, 0.05)}
    sldm = rt.SLDM(model, damping, reorth=reorth)
    U = sldm.step_response(forces, times, tol=1e-9, check_orthogonality=True)
    err = rel_err(U, modal_reference(model, basis, forces, damping, times))
    assert err < 1e-8
    assert sldm.last_info.orthogonality < 1e-13
    assert sldm.last_info.m >= sldm.last_info.m0 // 2


@pytest.mark.parametrize("damping", [rt.Damping(alpha=4.0), rt.Damping(alpha=300.0), rt.Damping(alpha=5000.0),
                                     rt.Damping(alpha=1.0, beta=1e-3), rt.Damping(zeta=0.2)],
                         ids=["light", "medium", "overdamped", "rayleigh", "modal-zeta"])
@pytest.mark.parametrize("tol", [1e-3, 1e-5, 1e-8])
def test_error_estimate_bounds_the_true_error(small, damping, tol):
    model, node, basis = small
    times = np.linspace(0.0, 0.2, 41)
    forces = {node: (0.0, -0.1, 0.05)}
    sldm = rt.SLDM(model, damping)
    U = sldm.step_response(forces, times, tol=tol)
    ref = modal_reference(model, basis, forces, damping, times)
    # the estimate is in the mass-weighted norm of y = M^1/2 u
    mass = model.mass_diagonal.reshape(-1, 6)[:, :3][None]
    true = np.sqrt(((U - ref) ** 2 * mass).sum(axis=(1, 2))).max() / np.sqrt((ref**2 * mass).sum(axis=(1, 2))).max()
    info = sldm.last_info
    assert info.estimate < tol
    assert true <= info.estimate


def test_fixed_krylov_dimension_and_breakdown():
    mesh = rt.meshes.plate(0.1, 0.1, 2)
    model = rt.ShellModel(mesh, rt.Material())
    model.fix("x0")
    basis = rt.modal_analysis(model, "all")
    node = int(mesh.groups["x1"][1])
    times = np.linspace(0, 5.0, 11)  # a long horizon: m0 exceeds the 18 free translations
    U = rt.SLDM(model, rt.Damping(alpha=2.0)).step_response({node: (0, 0, -1e-3)}, times)
    s = rt.SLDM(model, rt.Damping(alpha=2.0), m=4)
    s.step_response({node: (0, 0, -1e-3)}, times)
    assert s.last_info.m == 4
    ref = modal_reference(model, basis, {node: (0, 0, -1e-3)}, rt.Damping(alpha=2.0), times)
    assert rel_err(U, ref) < 1e-10


def test_frequency_response_matches_direct_sparse_solve(small):
    model, node, _ = small
    damping = rt.Damping(alpha=6.0, beta=1e-4)
    freqs = np.array([0.0, 0.3, 1.0, 2.5, 7.0, 20.0])
    forces = {node: (0.0, -0.1, 0.05)}
    U = rt.SLDM(model, damping).frequency_response(forces, freqs, tol=1e-10)
    K, dofs = model.constrained_stiffness()
    M = sp.diags(model.mass_diagonal[dofs])
    B = damping.matrix(M, K)
    F = model.force_vector(forces)[dofs]
    for k, f in enumerate(freqs):
        w = 2 * np.pi * f
        u = np.zeros(model.n_dofs, complex)
        u[dofs] = spla.spsolve((K - w * w * M + 1j * w * B).tocsc(), F.astype(complex))
        ref = u.reshape(-1, 6)[:, :3]
        assert np.abs(U[k] - ref).max() < 1e-8 * np.abs(ref).max()
    # the static limit is the static solve
    assert np.allclose(U[0].real, model.solve_static(forces), rtol=0, atol=1e-9 * np.abs(U[0]).max())


def test_duhamel_history_matches_exact_modal_integrator(small):
    model, node, basis = small
    damping = rt.Damping(alpha=5.0)
    dt = 1e-3
    history = [(0.0, {node: (0.0, -0.05, 0.0)}), (0.020, {node: (0.0, -0.1, 0.0)}),
               (0.050, {node: (0.0, -0.1, 0.04)}), (0.080, None)]
    sim = rt.ModalSimulator(basis, dt, damping)  # exact for loads held over whole steps
    samples, U_modal = [], []
    for k in range(120):
        t = k * dt
        active = [h for h in history if h[0] <= t + 1e-12][-1][1]
        sim.step(active)
        if (k + 1) % 10 == 0:
            samples.append(sim.time)
            U_modal.append(sim.displacements())
    sldm = rt.SLDM(model, damping)
    U = sldm.response([(t, f if f is not None else {}) for t, f in history], np.array(samples), tol=1e-9)
    assert rel_err(U, np.array(U_modal)) < 1e-8


def test_free_body_moves_with_its_centre_of_mass():
    mesh = rt.meshes.icosphere(0.05, 2)
    model = rt.ShellModel(mesh, rt.Material())
    force = np.zeros((mesh.n_vertices, 3))
    force[:, 0] = 1e-3  # uniform body force along x: no rotation, no deformation
    times = np.array([0.01, 0.05, 0.1])
    U = rt.SLDM(model).step_response(force, times, tol=1e-9)
    total_mass = model.mass_diagonal.reshape(-1, 6)[:, 0].sum()
    m = model.mass_diagonal.reshape(-1, 6)[:, 0]
    com = (U[:, :, 0] * m).sum(axis=1) / total_mass
    assert np.allclose(com, force[:, 0].sum() * times**2 / (2 * total_mass), rtol=1e-8)


def test_bad_input():
    mesh = rt.meshes.liver(2)
    pen = rt.ShellModel(mesh, rt.Material(), constraints="penalty")
    pen.fix("attachment")
    with pytest.raises(rt.ModelError, match="elimination"):
        rt.SLDM(pen)
    model, node = liver_model_and_node(2)
    s = rt.SLDM(model)
    with pytest.raises(rt.ModelError, match="times"):
        s.step_response({node: (1, 0, 0)}, [-1.0])
    with pytest.raises(rt.ModelError, match="non-finite"):
        s.step_response({node: (np.nan, 0, 0)}, [0.1])
    with pytest.raises(rt.ModelError, match="frequencies"):
        s.frequency_response({node: (1, 0, 0)}, [np.inf])
    with pytest.raises(rt.ModelError, match="tol"):
        s.step_response({node: (1, 0, 0)}, [0.1], tol=2.0)
    with pytest.raises(rt.ModelError, match="single modal damping"):
        rt.SLDM(model, rt.Damping(zeta=(0.1, 0.2)))
    with pytest.raises(rt.ModelError, match="strictly increasing"):
        s.response([(0.1, {node: (1, 0, 0)}), (0.05, None)], [0.2])
    assert np.all(s.step_response({}, [0.1]) == 0)
