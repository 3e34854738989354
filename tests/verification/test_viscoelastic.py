"""Viscoelastic tissue (issue 41, item 3): rt.Prony, a Prony series on a hyperelastic law's
isochoric stress, against the hereditary integral's closed forms and invariants.

- Relaxation: a unit cube's homogeneous deformation (stretch and volume change) applied over one
  time step and held: the face reactions equal P_vol + F (S_iso - sum_i Q_i(t)) with
  Q_i(t) = g_i S_iso [1 - (e^x - 1) / x e^(-t / tau_i)], x = dt / tau_i, the convolution integral
  of an S_iso ramped linearly over [0, dt] and held (written here from the relaxation function,
  not from the update the kernel uses); the volumetric part does not relax.
- Rate: simple shear ramped at two rates to the same small strain: the shear reaction equals the
  linear viscoelastic closed form mu gamma_dot [g_inf t + sum_i g_i tau_i (1 - e^(-t / tau_i))]
  (to the law's O(gamma^2)), the fast press the stiffer.
- The step's consistent tangent against central differences of the forces, mid-history.
- A column under a held load creeps from the instantaneous law's static answer to the long-term
  law's (rt.nonlinear.solve_static with the Prony law: the relaxed equilibrium), in the full-order
  Newmark simulator; a saved state (the internal variables with it) replays the same steps.
"""

from __future__ import annotations

import numpy as np
import pytest

import rtfem as rt
from rtfem.errors import ModelError

LAW = rt.NeoHookean(mu=2000.0, kappa=100000.0, density=1000.0)
G, TAU = np.array([0.3, 0.2]), np.array([0.05, 0.5])


def _cube(law):
    mesh = rt.meshes.box(1.0, 1.0, 1.0, nx=2, ny=2, nz=2)
    T, X = np.asarray(mesh.tets), np.asarray(mesh.vertices)
    return law.tets(X[T], "tet4"), T, X


def _face_force(kernel, T, X, F, history, axis):
    """The internal forces' resultant on the face X[axis] = 1 with every node at F X."""
    x = (X @ F.T)[T]
    fe = kernel.evaluate(x, False, history)[0].reshape(T.shape[0], -1, 3)
    f = np.zeros_like(X)
    np.add.at(f, T, fe)
    return f[np.isclose(X[:, axis], 1.0)].sum(axis=0)


def test_a_held_deformation_relaxes_as_the_hereditary_integral_says():
    law = rt.Prony(LAW, g=G, tau=TAU)
    kernel, T, X = _cube(law)
    F = np.diag([1.2, 0.95, 0.9])  # stretched and compressed (J = 1.026): both parts in play
    J, Finv = np.linalg.det(F), np.linalg.inv(F)
    P_vol = LAW.kappa * (J - 1.0) * J * Finv.T
    P = LAW.stress(F[None], False)[0][0]
    S_iso = Finv @ (P - P_vol)
    dt = 0.01
    h = np.zeros(kernel.history_size)
    x = (X @ F.T)[T]
    for n in range(1, 201):
        t = n * dt
        got = _face_force(kernel, T, X, F, (h, dt), 0)
        Q = sum(g * S_iso * (1.0 - np.expm1(dt / tau) / (dt / tau) * np.exp(-t / tau)) for g, tau in zip(G, TAU))
        expect = (P_vol + F @ (S_iso - Q))[:, 0]  # the nominal stress on the face x = 1, area 1
        np.testing.assert_allclose(got, expect, rtol=1e-10, atol=1e-10 * np.abs(P).max())
        h = kernel.committed(x, (h, dt))
    relaxed = LAW.scaled(law.g_inf)
    relaxed.kappa = LAW.kappa
    np.testing.assert_allclose(law.relaxation(2.0), law.g_inf + np.sum(G * np.exp(-2.0 / TAU)))
    long_term = relaxed.stress(F[None], False)[0][0][:, 0]
    np.testing.assert_allclose(got, long_term, rtol=2e-3, atol=1e-9 * np.abs(P).max())  # t = 2 s = 4 tau_2
    assert abs(got[0] - long_term[0]) > 5e-4 * abs(long_term[0])  # but not all of it yet


@pytest.mark.parametrize("rate", [0.01, 0.1])
def test_simple_shear_at_two_rates_follows_the_linear_closed_form(rate):
    law = rt.Prony(LAW, g=G, tau=TAU)
    kernel, T, X = _cube(law)
    gamma_end, dt = 1e-3, 0.002
    steps = int(round(gamma_end / rate / dt))
    h = np.zeros(kernel.history_size)
    for n in range(1, steps + 1):
        F = np.eye(3)
        F[0, 1] = rate * n * dt
        got = _face_force(kernel, T, X, F, (h, dt), 1)[0]  # the shear force on the face y = 1
        h = kernel.committed((X @ F.T)[T], (h, dt))
    t = steps * dt
    expect = LAW.mu * rate * (law.g_inf * t + np.sum(G * TAU * (1.0 - np.exp(-t / TAU))))
    np.testing.assert_allclose(got, expect, rtol=2e-6)  # the law's own nonlinearity: gamma^2 / 3
    instantaneous = LAW.mu * gamma_end
    assert law.g_inf * instantaneous < got < instantaneous
    if rate == 0.1:  # stiffer than the slow press at the same strain (the closed form at 0.01)
        t_slow = gamma_end / 0.01
        slow = LAW.mu * 0.01 * (law.g_inf * t_slow + np.sum(G * TAU * (1.0 - np.exp(-t_slow / TAU))))
        assert got > 1.15 * slow


def test_the_steps_tangent_equals_differences_of_its_forces():
    law = rt.Prony(rt.MooneyRivlin(c10=700.0, c01=300.0, kappa=50000.0, density=1000.0), g=G, tau=TAU)
    kernel, T, X = _cube(law)
    rng = np.random.default_rng(4)
    x0 = (X + 0.05 * rng.normal(size=X.shape))[T]
    h = np.zeros(kernel.history_size)
    for _ in range(3):  # a history that is not zero
        h = kernel.committed(x0 + 0.02 * rng.normal(size=x0.shape), (h, 0.01))
    f, K, _ = kernel.evaluate(x0, True, (h, 0.01))
    eps = 1e-6
    m, k = x0.shape[:2]
    for j in range(0, 3 * k, 5):
        dx = np.zeros((m, 3 * k))
        dx[:, j] = eps
        fp = kernel.evaluate(x0 + dx.reshape(m, k, 3), False, (h, 0.01))[0]
        fm = kernel.evaluate(x0 - dx.reshape(m, k, 3), False, (h, 0.01))[0]
        np.testing.assert_allclose((fp - fm) / (2 * eps), K[:, :, j], rtol=1e-6, atol=1e-6 * np.abs(K).max())
    # the forces are the step's potential's gradient
    e = lambda y: kernel.evaluate(y, False, (h, 0.01))[2].sum()  # noqa: E731
    d = rng.normal(size=x0.shape) * 1e-6
    np.testing.assert_allclose((e(x0 + d) - e(x0 - d)) / 2, np.sum(f.reshape(x0.shape) * d), rtol=1e-6)


def _column(law):
    mesh = rt.meshes.box(0.02, 0.02, 0.06, nx=2, ny=2, nz=4)
    model = rt.SolidModel(mesh, law)
    X = np.asarray(model.tetmesh.vertices)
    model.fix(np.flatnonzero(X[:, 2] == 0.0))
    top = np.flatnonzero(np.isclose(X[:, 2], 0.06))
    forces = np.zeros_like(X)
    forces[top, 0] = 0.02 / top.size  # 20 mN sideways on the top
    return model, forces


def test_a_held_load_creeps_from_the_instantaneous_to_the_long_term_answer():
    law = rt.Prony(LAW, g=np.array([0.5]), tau=np.array([0.2]))
    model, forces = _column(law)
    sim = rt.DirectSimulator(model, dt=0.005, damping=rt.Damping(alpha=50.0), large_deformation=True)
    tip = np.flatnonzero(np.isclose(np.asarray(model.tetmesh.vertices)[:, 2], 0.06))
    relaxed = rt.nonlinear.solve_static(model, forces).displacements[tip, 0].mean()
    instant = rt.nonlinear.solve_static(_column(LAW)[0], forces).displacements[tip, 0].mean()
    assert relaxed > 1.5 * instant  # g_inf = 0.5 on the shear modulus (the bulk does not relax)
    track = []
    for n in range(600):
        sim.step(forces)
        track.append(sim.displacements()[tip, 0].mean())
        if n == 49:
            state = sim.get_state()
    track = np.array(track)
    assert np.all(np.diff(track[60:]) > 0)  # creeping, past the first transient
    assert abs(track[-1] - relaxed) < 1e-3 * relaxed  # 3 s = 15 tau: relaxed
    assert track[8] < 1.15 * instant  # the first 40 ms (0.2 tau): still near the instantaneous
    sim.set_state(state)  # the internal variables come back with the state
    for n in range(50, 80):
        sim.step(forces)
    np.testing.assert_allclose(sim.displacements()[tip, 0].mean(), track[79], rtol=1e-12)


def test_prony_refusals():
    with pytest.raises(ModelError, match="hyperelastic law"):
        rt.Prony(rt.Material(E=1e4, nu=0.3, density=1000.0), g=[0.2], tau=[1.0])
    with pytest.raises(ModelError, match="sum < 1"):
        rt.Prony(LAW, g=[0.6, 0.5], tau=[1.0, 2.0])
    with pytest.raises(ModelError, match="> 0"):
        rt.Prony(LAW, g=[0.2], tau=[0.0])
    with pytest.raises(ModelError, match="one relaxation fraction per relaxation time"):
        rt.Prony(LAW, g=[0.2, 0.1], tau=[1.0])


def test_a_history_of_the_wrong_size_is_refused():
    law = rt.Prony(LAW, g=G, tau=TAU)
    kernel, T, X = _cube(law)
    with pytest.raises(ModelError, match="viscoelastic history of 9 values"):
        kernel.evaluate(X[T], True, (np.zeros(9), 0.01))
    with pytest.raises(ModelError, match="dt"):
        law.coefficients(0.0)
