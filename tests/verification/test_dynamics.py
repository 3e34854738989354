"""Dynamics against analytic and independent references (paper section 3).

* simply supported square plate: w_mn = pi^2 (m^2/a^2 + n^2/b^2) sqrt(D / (rho t));
* modal analysis equals the dense eigenproblem of the condensed stiffness (Eq. 5);
* modal superposition with all modes equals direct integration of the full system;
* one damped mode under a step force against its closed form, in every damping regime;
* Newmark's period elongation (W/2)/arctan(W/2), W = w dt, and its energy conservation.
"""

import numpy as np
import pytest
import scipy.linalg as sla

import rtfem as rt
from conftest import liver_model
from rtfem.reduction.modal import ModalBasis


def ss_plate_model(divisions, material):
    mesh = rt.meshes.plate(1.0, 1.0, divisions)
    model = rt.ShellModel(mesh, material)
    model.fix("boundary", "z")
    model.fix(np.arange(mesh.n_vertices), "x,y,rz")  # bending modes only
    return model


def ss_plate_reference(material, count=6):
    D, rho_t = material.bending_rigidity, material.density * material.thickness
    w = sorted(np.pi**2 * (m * m + n * n) * np.sqrt(D / rho_t) for m in range(1, 6) for n in range(1, 6))
    return np.array(w[:count])


def test_simply_supported_plate_first_six_frequencies(plate_material):
    ref = ss_plate_reference(plate_material)
    errors = []
    for n in (8, 16, 32):
        omega = rt.modal_analysis(ss_plate_model(n, plate_material), 6).omega
        errors.append(np.abs(omega / ref - 1).max())
        if n == 16:
            assert np.all(np.abs(omega / ref - 1) < 0.02)
    assert errors[0] > errors[1] > errors[2]
    assert errors[2] < errors[1] / 3  # O(h^2)


def test_modes_equal_condensed_eigenproblem_of_eq5():
    model = liver_model(2)
    basis = rt.modal_analysis(model, 12, sigma=0.0)
    assert "Lanczos" in basis.info["method"]
    Kc = model.condensed_stiffness()  # dense Schur complement, paper Eq. 5
    t = model.translational_free_dofs()
    lam = sla.eigh(Kc, np.diag(model.mass_diagonal[t]), eigvals_only=True, subset_by_index=[0, 11])
    assert np.allclose(basis.omega**2, lam, rtol=1e-9)


def test_mass_normalized_and_sorted():
    model = liver_model(3)
    mesh = model.mesh
    basis = rt.modal_analysis(model, 15)
    m = model.mass_diagonal.reshape(-1, 6)[:, :3].ravel()
    P = basis.matrix
    assert np.allclose(P.T @ (m[:, None] * P), np.eye(15), atol=1e-10)
    assert np.all(np.diff(basis.omega) >= 0)
    assert np.allclose(basis.frequencies, basis.omega / (2 * np.pi))
    assert np.all(basis.shapes[mesh.groups["attachment"]] == 0)


def test_unconstrained_model_returns_six_rigid_body_modes_first():
    mesh = rt.meshes.liver(2)
    model = rt.ShellModel(mesh, rt.Material())
    basis = rt.modal_analysis(model, 10)
    assert np.all(basis.omega[:6] < 1e-5 * basis.omega[6])
    # the first six span the rigid-body motions: translations and rotations of the mesh
    X = np.asarray(mesh.vertices)
    c = X - X.mean(axis=0)
    R = np.zeros((mesh.n_vertices, 3, 6))
    for k in range(3):
        e = np.eye(3)[k]
        R[:, k, k] = 1.0
        R[:, :, 3 + k] = np.cross(e, c)
    R = R.reshape(-1, 6)
    Q = np.linalg.qr(basis.matrix[:, :6])[0]
    assert np.linalg.norm(R - Q @ (Q.T @ R)) < 1e-8 * np.linalg.norm(R)


def test_penalty_and_elimination_give_the_same_low_modes():
    mesh = rt.meshes.liver(2)
    a = rt.ShellModel(mesh, rt.Material())
    b = rt.ShellModel(mesh, rt.Material(), constraints="penalty", penalty=1e8)
    a.fix("attachment")
    b.fix("attachment")
    wa, wb = rt.modal_analysis(a, 8).omega, rt.modal_analysis(b, 8).omega
    assert np.allclose(wa, wb, rtol=1e-6)


def push_release(sim, node, steps_on, steps_off, force):
    out = []
    for k in range(steps_on + steps_off):
        sim.step({node: force} if k < steps_on else None)
        out.append(sim.displacements())
    return np.array(out)


@pytest.mark.parametrize("damping", [rt.Damping(alpha=3.0), rt.Damping(alpha=1.0, beta=2e-4), rt.Damping()])
def test_modal_with_all_modes_equals_direct_integration(damping):
    mesh = rt.meshes.plate(0.1, 0.05, 6, 3)
    model = rt.ShellModel(mesh, rt.Material(E=1e5, thickness=2e-3))
    model.fix("x0")
    basis = rt.modal_analysis(model, "all")
    node = int(mesh.groups["x1"][1])
    dt = 2e-3
    U_modal = push_release(rt.ModalSimulator(basis, dt, damping, integrator="newmark"), node, 40, 60, (0.01, 0.02, -0.05))
    U_direct = push_release(rt.DirectSimulator(model, dt, damping), node, 40, 60, (0.01, 0.02, -0.05))
    assert np.abs(U_modal - U_direct).max() < 1e-9 * np.abs(U_direct).max()


def test_truncation_error_falls_with_r_and_static_correction_converges():
    model = liver_model(3)
    mesh = model.mesh
    full = rt.modal_analysis(model, 80)
    node = mesh.nearest_vertex([0.06, 0.05, 0.0])
    f = {node: (0.0, -0.1, 0.05)}
    u_static = model.solve_static(f)
    errs, errs_corr = [], []
    for r in (5, 10, 20, 40, 80):
        for corr, store in ((False, errs), (True, errs_corr)):
            # the exact integrator takes any dt: 200 steps of 0.5 s with damping critical for the
            # lowest mode (every mode then decays at least as e^{-w1 t}) reach the static state
            damping = rt.Damping(alpha=2 * full.omega[0])
            sim = rt.ModalSimulator(full.truncated(r), 0.5, damping, static_correction=corr)
            sim.run(f, 200)
            store.append(np.linalg.norm(sim.displacements() - u_static) / np.linalg.norm(u_static))
    assert all(b < a for a, b in zip(errs, errs[1:])), errs
    assert errs[0] > 0.05  # few modes alone miss the static deflection
    assert max(errs_corr) < 1e-9  # mode acceleration: exact in the static limit for any r


def single_mode(omega):
    return ModalBasis(np.array([omega]), np.array([[[1.0], [0.0], [0.0]]]), "single")


def closed_form_step(w, a, t):
    """Unit step response of x'' + a x' + w^2 x = 1 from rest, written out per regime."""
    d = a / 2
    if d < w:
        wd = np.sqrt(w * w - d * d)
        return (1 - np.exp(-d * t) * (np.cos(wd * t) + d / wd * np.sin(wd * t))) / w**2
    if d == w:
        return (1 - np.exp(-d * t) * (1 + d * t)) / w**2
    mu = np.sqrt(d * d - w * w)
    # e^{-dt} (cosh(mu t) + d/mu sinh(mu t)) with the exponentials combined (no overflow)
    slow, fast = np.exp(-(d - mu) * t), np.exp(-(d + mu) * t)
    return (1 - 0.5 * ((1 + d / mu) * slow + (1 - d / mu) * fast)) / w**2


REGIMES = {"undamped": 0.0, "under": 0.2, "critical": 1.0, "over": 3.0}


@pytest.mark.parametrize("regime", REGIMES)
def test_single_mode_exact_integrator_matches_closed_form(regime):
    w = 2 * np.pi * 30.0
    a = 2 * REGIMES[regime] * w
    for dt in (1e-3, 7e-3):  # exact at any dt
        sim = rt.ModalSimulator(single_mode(w), dt, rt.Damping(alpha=a))
        x = []
        for _ in range(300):
            sim.step({0: (1.0, 0.0, 0.0)})
            x.append(sim.q[0])
        t = dt * np.arange(1, 301)
        ref = closed_form_step(w, a, t)
        assert np.abs(np.array(x) - ref).max() < 1e-12 / w**2


@pytest.mark.parametrize("regime", REGIMES)
def test_single_mode_newmark_converges_at_second_order(regime):
    w = 2 * np.pi * 30.0
    a = 2 * REGIMES[regime] * w
    T = 0.2
    errors = []
    for dt in (2e-4, 1e-4, 5e-5):
        sim = rt.ModalSimulator(single_mode(w), dt, rt.Damping(alpha=a), integrator="newmark")
        n = int(round(T / dt))
        x = np.empty(n)
        for k in range(n):
            sim.step({0: (1.0, 0.0, 0.0)})
            x[k] = sim.q[0]
        # Newmark takes the force at the end of each step: the step starts at t = 0 as in the
        # closed form, with the trapezoid of f over the first step being f/2 (a half-step lag)
        t = dt * np.arange(1, n + 1)
        errors.append(np.abs(x - closed_form_step(w, a, t - dt / 2)).max() * w**2)
    assert errors[-1] < 1e-3
    assert 3.5 < errors[0] / errors[1] < 4.5 and 3.5 < errors[1] / errors[2] < 4.5


@pytest.mark.parametrize("freq,expected", [(50.0, 0.008), (160.0, 0.079), (500.0, 0.56)])
def test_newmark_period_elongation(freq, expected):
    w, dt = 2 * np.pi * freq, 1e-3
    sim = rt.ModalSimulator(single_mode(w), dt, integrator="newmark")
    sim.set_state({"q": np.array([1.0]), "qdot": np.array([0.0])})
    x = np.empty(400)
    for k in range(400):
        sim.step()
        x[k] = sim.q[0]
    W = w * dt
    w_num = 2 / dt * np.arctan(W / 2)  # trapezoidal rule: exact phase per step
    assert np.abs(x - np.cos(w_num * dt * np.arange(1, 401))).max() < 1e-10
    elongation = (W / 2) / np.arctan(W / 2) - 1
    assert elongation == pytest.approx(expected, abs=0.005)
    # the exact integrator has no period error
    ex = rt.ModalSimulator(single_mode(w), dt)
    ex.set_state({"q": np.array([1.0]), "qdot": np.array([0.0])})
    ex.run(None, 400)
    assert ex.q[0] == pytest.approx(np.cos(w * 0.4), abs=1e-10)


@pytest.mark.slow
def test_undamped_newmark_conserves_modal_energy_over_a_million_steps():
    model = liver_model(2)
    basis = rt.modal_analysis(model, 20)
    for integrator in ("newmark", "exact"):
        sim = rt.ModalSimulator(basis, 1e-3, integrator=integrator)
        rng = np.random.default_rng(0)
        sim.set_state({"q": rng.normal(size=20) * 1e-3, "qdot": rng.normal(size=20) * 1e-2})
        e0 = sim.energy()
        sim.run(None, 1_000_000)
        assert sim.energy() == pytest.approx(e0, rel=1e-9)


def test_linear_hht_equals_the_corotational_hht_at_a_small_load():
    """The linear Newmark with numerical damping d (Hilber-Hughes-Taylor, alpha = -d) against a second
    implementation of the same rule, the corotational simulator's, at a load whose rotations are
    1e-5 rad: the same trajectory to 1e-6 (measured 3e-8), while the average-acceleration rule
    (d = 0) differs by 2 % after the load is released (HHT damps the modes 10 ms does not resolve)."""
    mesh = rt.meshes.plate(0.2, 0.2, 16, 16)
    model = rt.ShellModel(mesh, rt.Material(E=3e4, nu=0.3, thickness=4e-3))
    model.fix(mesh.boundary_vertices(), dofs="xyz")
    node, damping = int(mesh.groups["center"][0]), rt.Damping(alpha=1.0, beta=1e-4)
    sims = [rt.DirectSimulator(model, 0.01, damping, numerical_damping=0.1),
            rt.DirectSimulator(model, 0.01, damping, large_deformation=True, numerical_damping=0.1, tol=1e-12),
            rt.DirectSimulator(model, 0.01, damping)]
    z = np.zeros((3, 100))
    for k in range(100):
        for s, sim in enumerate(sims):
            sim.step({node: (0.0, 0.0, -1e-6 if k < 10 else 0.0)})
            z[s, k] = sim.displacement(node)[2]
    scale = np.abs(z[1]).max()
    assert scale > 1e-7
    assert np.abs(z[0] - z[1]).max() < 1e-6 * scale
    assert np.abs(z[2] - z[1]).max() > 0.005 * scale
