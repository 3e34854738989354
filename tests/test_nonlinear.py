"""The corotational element kernels and the nonlinear static solver's interface.

The forces and tangents are checked against central differences of the energy and of the
forces (an independent route: no derivative code involved), the undeformed tangent against the
linear element, and the energy against rotation invariance. The solver's refusals are checked
to name what to do and to change nothing.
"""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import rtfem as rt
from rtfem.fe import shell, solid
from rtfem.mesh.tetmesh import TET10_EDGES

RNG = np.random.default_rng(7)
SHELL_MAT = rt.Material(E=1e5, nu=0.3, thickness=0.01)


def _triangle():
    return np.array([[[0.0, 0.0, 0.0], [1.0, 0.1, 0.0], [0.3, 0.8, 0.1]]])


def _perturbed(x, Q, j, h):
    """Move element dof j (node-major: x, y, z, then a spin about x, y, z) by h."""
    x, Q = x.copy(), None if Q is None else Q.copy()
    i, c = divmod(j, 6 if Q is not None else 3)
    if c < 3:
        x[0, i, c] += h
    else:
        w = np.zeros(3)
        w[c - 3] = h
        Q[0, i] = Rotation.from_rotvec(w).as_matrix() @ Q[0, i]
    return x, Q


def test_shell_kernel_at_rest_is_the_linear_element():
    X = _triangle()
    el = shell.CorotationalTriangles(X, SHELL_MAT)
    f, K, e = el.evaluate(X, np.tile(np.eye(3), (1, 3, 1, 1)))
    Klin = shell.element_stiffness(X, SHELL_MAT)
    assert np.abs(f).max() < 1e-12 * np.abs(Klin).max() and abs(e[0]) < 1e-25
    np.testing.assert_allclose(K, Klin, rtol=0, atol=1e-12 * np.abs(Klin).max())


def test_shell_kernel_forces_and_tangent_against_differences():
    X = _triangle()
    el = shell.CorotationalTriangles(X, SHELL_MAT)
    x = X + 0.2 * RNG.standard_normal(X.shape)
    Q = Rotation.from_rotvec(0.7 * RNG.standard_normal((3, 3))).as_matrix()[None]
    f, K, _ = el.evaluate(x, Q)
    h = 1e-6
    grad = [(el.energy(*_perturbed(x, Q, j, h)) - el.energy(*_perturbed(x, Q, j, -h)))[0] / (2 * h) for j in range(18)]
    np.testing.assert_allclose(grad, f[0], rtol=0, atol=1e-8 * np.abs(f).max())
    # the tangent is the derivative of the force after a multiplicative spin update (not symmetric
    # off equilibrium): columns by central differences of the forces
    cols = [(el.evaluate(*_perturbed(x, Q, j, h), tangent=False)[0] - el.evaluate(*_perturbed(x, Q, j, -h),
                                                                                    tangent=False)[0])[0] / (2 * h)
            for j in range(18)]
    np.testing.assert_allclose(np.array(cols).T, K[0], rtol=0, atol=1e-8 * np.abs(K).max())
    assert np.abs(K[0] - K[0].T).max() > 1e-6 * np.abs(K).max()  # the spin term is really there


@pytest.mark.parametrize("degrees", [5.0, 40.0, 89.0, 120.0, 170.0])
def test_shell_rotation_measure_is_the_rotation_vector(degrees):
    """A corner turned alone (the element undeformed) by theta about an axis: its deformational
    rotation is the rotation vector of R0 Q R0^T (scipy's log map, an independent route), so the
    rotational energy is exactly quadratic in theta up to 170 degrees. The skew part alone
    (sin theta) softened by 10 % at 45 degrees and turned back past 90."""
    X = _triangle()
    el = shell.CorotationalTriangles(X, SHELL_MAT)
    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    Q = np.tile(np.eye(3), (1, 3, 1, 1))
    Q[0, 1] = Rotation.from_rotvec(np.radians(degrees) * axis).as_matrix()
    d = el.deformational(X, Q)[0]
    ref = Rotation.from_matrix(el.R0[0] @ Q[0, 1] @ el.R0[0].T).as_rotvec()
    np.testing.assert_allclose(d[9:12], ref, rtol=0, atol=1e-13)
    assert np.abs(np.delete(d, [9, 10, 11])).max() < 1e-13
    np.testing.assert_allclose(np.degrees(np.linalg.norm(d[9:12])), degrees, rtol=1e-12)
    assert abs(el.local_rotations(X, Q)[0, 1] - degrees) < 1e-6
    e = []  # energy / theta^2 at theta and at 1 degree
    for t in (1.0, degrees):
        Q[0, 1] = Rotation.from_rotvec(np.radians(t) * axis).as_matrix()
        e.append(el.energy(X, Q)[0] / t**2)
    assert abs(e[1] / e[0] - 1.0) < 1e-10


def test_shell_kernel_energy_is_rotation_invariant():
    X = _triangle()
    el = shell.CorotationalTriangles(X, SHELL_MAT)
    x = X + 0.05 * RNG.standard_normal(X.shape)
    Q = Rotation.from_rotvec(0.1 * RNG.standard_normal((3, 3))).as_matrix()[None]
    R = Rotation.from_rotvec([0.4, -1.3, 2.0]).as_matrix()
    e0 = el.energy(x, Q)[0]
    e1 = el.energy(x @ R.T + 3.0, R @ Q)[0]
    assert e0 > 0 and abs(e1 - e0) < 1e-12 * e0
    f0, _, _ = el.evaluate(x, Q, tangent=False)
    f1, _, _ = el.evaluate(x @ R.T, R @ Q, tangent=False)
    np.testing.assert_allclose(f1[0].reshape(6, 3), f0[0].reshape(6, 3) @ R.T, atol=1e-10 * np.abs(f0).max())


def _tet(element):
    X = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float)
    if element == "tet10":
        X = np.vstack([X, [(X[i] + X[j]) / 2 for i, j in TET10_EDGES]])
    return X[None]


@pytest.mark.parametrize("element", ["tet4", "tet10"])
def test_tet_kernel_against_differences_and_linear(element):
    mat = rt.Material(E=1e5, nu=0.3)
    X = _tet(element)
    el = solid.CorotationalTets(X, mat, element)
    f, K, e = el.evaluate(X)
    Klin, _ = solid.element_matrices(X, mat, element, "lumped")
    np.testing.assert_allclose(K, Klin, rtol=0, atol=1e-12 * np.abs(Klin).max())
    assert np.abs(f).max() < 1e-9 and abs(e[0]) < 1e-20
    R = Rotation.from_rotvec([0.5, 1.0, -0.3]).as_matrix()
    x = (X + 0.15 * RNG.standard_normal(X.shape)) @ R.T
    f, K, _ = el.evaluate(x)
    n, h = x.shape[1] * 3, 1e-6
    grad = [(el.evaluate(_perturbed(x, None, j, h)[0], False)[2] - el.evaluate(_perturbed(x, None, j, -h)[0], False)[2])[0]
            / (2 * h) for j in range(n)]
    np.testing.assert_allclose(grad, f[0], rtol=0, atol=1e-8 * np.abs(f).max())
    cols = [(el.evaluate(_perturbed(x, None, j, h)[0], False)[0] - el.evaluate(_perturbed(x, None, j, -h)[0], False)[0])[0]
            / (2 * h) for j in range(n)]
    np.testing.assert_allclose(np.array(cols).T, K[0], rtol=0, atol=1e-8 * np.abs(K).max())
    np.testing.assert_allclose(K[0], K[0].T, atol=1e-12 * np.abs(K).max())  # a hyperelastic energy's Hessian
    f_rigid, _, e_rigid = el.evaluate(X @ R.T + 1.0)
    assert np.abs(f_rigid).max() < 1e-10 and abs(e_rigid[0]) < 1e-20


def test_polar_decomposition_of_an_inverted_element():
    F = np.diag([1.0, 1.0, -0.5])[None]
    R, S = solid.polar(F)
    assert np.linalg.det(R[0]) == pytest.approx(1.0)
    np.testing.assert_allclose(R @ S, F, atol=1e-14)


def _strip():
    m = rt.meshes.plate(1.0, 0.2, nx=6, ny=1)
    model = rt.ShellModel(m, rt.Material(E=1e5, nu=0.3, thickness=0.01))
    return model.fix("x0")


def test_solve_static_refusals_change_nothing():
    model = _strip()
    with pytest.raises(rt.ModelError, match="large_deformation=True"):
        model.solve_static(np.zeros((model.n_nodes, 3)), steps=3)
    P = np.zeros((model.n_nodes, 3))
    P[model.select_nodes("x1")[0], 2] = 0.1
    with pytest.raises(rt.ModelError, match="not fixed"):
        model.solve_static(None, large_deformation=True, prescribed=P)
    with pytest.raises(rt.ModelError, match="non-finite"):
        model.solve_static({3: (np.nan, 0, 0)}, large_deformation=True)
    with pytest.raises(rt.ModelError, match="steps"):
        model.solve_static(None, large_deformation=True, steps=0)
    for bad, match in ((dict(max_iterations=0), "max_iterations"), (dict(max_cuts=-1), "max_cuts"),
                       (dict(tol=-1.0), "tol")):
        with pytest.raises(rt.ModelError, match=match):
            model.solve_static(None, large_deformation=True, **bad)
    with pytest.raises(rt.ModelError, match="method='newmark'"):
        rt.DirectSimulator(model, 1e-3, method="central", large_deformation=True)
    with pytest.raises(rt.ModelError, match="large_deformation=True"):
        rt.DirectSimulator(model, 1e-3, tol=1e-6)
    for bad, match in ((dict(numerical_damping=0.5), "numerical_damping"), (dict(tol=0.0), "tol"),
                       (dict(max_iterations=0), "max_iterations")):
        with pytest.raises(rt.ModelError, match=match):
            rt.DirectSimulator(model, 1e-3, large_deformation=True, **bad)
    sim = rt.DirectSimulator(model, 1e-3, large_deformation=True)
    sim.step({int(model.select_nodes("x1")[0]): (0.0, 0.0, 0.1)})
    before = sim.get_state()
    with pytest.raises(rt.ModelError, match="non-finite"):
        sim.step({3: (0.0, np.inf, 0.0)})
    with pytest.raises(rt.ModelError, match="rotations"):
        sim.set_state({k: v for k, v in before.items() if k != "rotations"})
    after = sim.get_state()
    assert all(np.array_equal(before[k], after[k]) for k in before)
    assert not model.fixed[model.select_nodes("x1")].any()


def test_a_failed_solve_keeps_the_last_equilibrium():
    model = _strip()
    F = np.zeros((model.n_nodes, 3))
    F[model.select_nodes("x1"), 0] = -1e5  # far past buckling in compression
    with pytest.raises(rt.SolverError) as info:
        rt.nonlinear.solve_static(model, F, max_iterations=4, max_cuts=2, method="newton")
    res = info.value.result
    assert not res.converged and res.displacements.shape == (model.n_nodes, 3)
    assert "load factor" in str(info.value)


def test_a_solve_stalling_in_ever_shorter_steps_ends_with_the_solver_error(monkeypatch):
    """Newton that converges only below 60 % of the load (a snap there): each short step near it
    converges, so the cuts in a row never reach max_cuts while the step halves towards zero. The
    solve ends with a SolverError holding the last equilibrium (once a ZeroDivisionError from the
    secant predictor, when the step fell below the load factor's round-off)."""
    import rtfem.fe.nonlinear as nl

    model = _strip()
    F = np.zeros((model.n_nodes, 3))
    F[model.select_nodes("x1"), 2] = 1.0
    full = np.linalg.norm(model.force_vector(F))
    calls = []

    def newton(system, conf, Fk, tol, max_iterations):
        calls.append(np.linalg.norm(Fk) / full)
        return [1.0] * 8, calls[-1] <= 0.6  # 8 residuals: no doubling of the next step

    monkeypatch.setattr(nl, "_newton", newton)
    with pytest.raises(rt.SolverError, match="load factor 0.6") as info:
        nl.solve_static(model, F, method="newton")
    assert not info.value.result.converged
    assert 0.6 - 1e-8 < max(c for c in calls if c <= 0.6) <= 0.6 and len(calls) < 500


def test_the_system_follows_the_fixes():
    model = _strip()
    s1 = model.nonlinear()
    assert model.nonlinear() is s1
    model.fix("y0", dofs="z")
    assert model.nonlinear() is not s1
