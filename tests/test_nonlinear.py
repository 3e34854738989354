"""The corotational element kernels and the nonlinear static solver's interface.

The forces and tangents are checked against central differences of the energy and of the
forces (an independent route: no derivative code involved), the undeformed tangent against the
linear element, and the energy against rotation invariance. The solver's refusals are checked
to name what to do and to change nothing.
"""

import time

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

    def newton(system, conf, Fk, tol, max_iterations, watch=None):
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


# --- issue 53, section 4: no silent wrong answer ---------------------------------------------------------------


def _jaw_block():
    """A tet10 block (0.1 x 0.04 x 0.04 m, E 4e4) clamped at x = 0, a 15 mm jaw of corner nodes on its
    top at the other end: the corners held by index, so fix() holds the mid-edge nodes between them."""
    model = rt.SolidModel(rt.meshes.box(0.1, 0.04, 0.04, nx=10, ny=4, nz=4), rt.Material(E=4e4, nu=0.45),
                          element="tet10")
    model.fix("x0")
    X = np.asarray(model.tetmesh.vertices)
    corners = np.unique(np.asarray(model.tetmesh.tets)[:, :4])
    jaw = corners[(X[corners, 0] > 0.085 - 1e-9) & (np.abs(X[corners, 2] - 0.04) < 1e-9)]
    model.fix(jaw)
    held_mids = np.setdiff1d(np.flatnonzero(model.held_nodes & (X[:, 0] > 0.085 - 1e-9)), jaw)
    return model, jaw, held_mids


def test_a_jaw_moved_by_its_corners_carries_its_mid_edge_nodes():
    """Moving only the jaw's corners moves the mid-edge nodes fix() held between them with them: the
    same equilibrium as the jaw's every node moved explicitly, and at a small pull the linear solve's
    reaction (a second route). Before, those mid-edge nodes stayed at rest: 6 N for a 2.25 mm pull."""
    model, jaw, mids = _jaw_block()
    assert mids.size >= 9  # the jaw's held mid-edge nodes
    pull = np.zeros((model.n_nodes, 3))
    pull[jaw, 2] = 2.25e-3
    corners_only = rt.nonlinear.solve_static(model, None, prescribed=pull)
    explicit = pull.copy()
    explicit[mids, 2] = 2.25e-3
    every = rt.nonlinear.solve_static(model, None, prescribed=explicit)
    np.testing.assert_allclose(corners_only.displacements, every.displacements, rtol=0, atol=1e-12)
    np.testing.assert_allclose(corners_only.displacements[mids, 2], 2.25e-3, rtol=0, atol=1e-15)
    force = corners_only.reactions[np.union1d(jaw, mids), 2].sum()
    assert 0.05 < force < 0.3  # measured 0.134 N (with the mid-edge nodes at rest the corners alone carried 6 N)
    # the linear solve of the same support motion, at a hundredth of the pull: the same stiffness
    small = rt.nonlinear.solve_static(model, None, prescribed=pull / 100)
    K = model.K.tocsr()
    free, held = model.free_dofs, model.fixed_dofs
    u = model.complete_motion(pull / 100).ravel()
    from scipy.sparse.linalg import spsolve

    u[free] = spsolve(K[free][:, free].tocsc(), -K[free][:, held] @ u[held])
    linear = (K @ u).reshape(-1, 3)[np.union1d(jaw, mids), 2].sum()
    assert abs(small.reactions[np.union1d(jaw, mids), 2].sum() - linear) < 0.01 * abs(linear)


def test_a_mid_edge_node_given_its_own_motion_keeps_it():
    model, jaw, mids = _jaw_block()
    P = np.zeros((model.n_nodes, 3))
    P[jaw, 2] = 1e-3
    P[mids[0], 2] = 2e-3
    done = model.complete_motion(P)
    assert done[mids[0], 2] == 2e-3 and np.all(done[mids[1:], 2] == 1e-3) and P[mids[1], 2] == 0  # P untouched
    tet4 = rt.SolidModel(rt.meshes.box(0.1, 0.04, 0.04, nx=2, ny=1, nz=1), model.material).fix("x1")
    Q = np.zeros((tet4.n_nodes, 3))
    Q[tet4.select_nodes("x1"), 2] = 1e-3
    assert np.array_equal(tet4.complete_motion(Q), Q)  # tet4 has no mid-edge nodes to complete


def _crushed_block(element="tet4"):
    model = rt.SolidModel(rt.meshes.box(0.04, 0.04, 0.02, nx=2, ny=2, nz=2), rt.Material(E=1e4, nu=0.3, density=1000.0),
                          element=element)
    model.fix("z<1e-9")
    top = model.select_nodes("z>0.0199999")
    model.fix(top)
    return model, top


def _inverted_count(model, u):
    """Tets with a non-positive signed volume of their corners: counted from the coordinates alone."""
    T = np.asarray(model.tetmesh.tets)[:, :4]
    x = np.asarray(model.tetmesh.vertices) + u
    a, b, c, d = (x[T[:, i]] for i in range(4))
    return int(np.count_nonzero(np.einsum("ij,ij->i", np.cross(b - a, c - a), d - a) <= 0))


@pytest.mark.parametrize("push, side", [(1.5, 0.003), (1.2, 0.01), (3.0, 0.0)])
def test_no_solve_converges_onto_inverted_elements(push, side):
    """The top of a block pushed down through its clamped base: the middle layer has nowhere to go but
    inside out. The corotated law gives such a state finite forces (its polar decomposition keeps a
    proper rotation), and Newton converged there: 25-36 inverted tets with converged=True (and at the
    symmetric push, a LinAlgError from a singular polar derivative). Now each ends in a SolverError that
    says so, holding the last equilibrium, which has no inverted element."""
    model, top = _crushed_block()
    P = np.zeros((model.n_nodes, 3))
    P[top, 2] = -push * 0.02
    P[top, 0] = side
    with pytest.raises(rt.SolverError, match="turned inside out") as info:
        rt.nonlinear.solve_static(model, None, prescribed=P, method="newton")
    last = info.value.result
    assert not last.converged and 0 < last.load_factors[-1] < 1.0
    assert _inverted_count(model, last.displacements) == 0
    # a push the block can take is solved (every tet keeps its orientation)
    res = rt.nonlinear.solve_static(model, None, prescribed=P * 0.5 / push)
    assert res.converged and _inverted_count(model, res.displacements) == 0


@pytest.mark.parametrize("push, side", [(1.5, 0.003), (1.2, 0.01), (3.0, 0.0)])
def test_no_tet10_solve_converges_onto_inverted_elements(push, side):
    """The crushed block in 10-node tets, where a curved element can fold at a corner while its
    quadrature points do not: each push is refused (Newton and method="auto" alike, at 19-39 % of it),
    and the equilibrium the error holds has no element inverted at a quadrature point or a corner."""
    model, top = _crushed_block("tet10")
    P = np.zeros((model.n_nodes, 3))
    P[top, 2] = -push * 0.02
    P[top, 0] = side
    kernel, cells = model._corotational()
    x0 = np.asarray(model.tetmesh.vertices)
    for method in ("newton", "auto"):
        with pytest.raises(rt.SolverError, match="turned inside out") as info:
            rt.nonlinear.solve_static(model, None, prescribed=P, method=method)
        last = info.value.result
        assert not last.converged and 0 < last.load_factors[-1] < 1.0
        assert not kernel.inverted((x0 + last.displacements)[cells]).any()


def test_the_dynamic_newton_refuses_inverted_elements():
    """A 50 N point load on a small soft block's top: the step that would turn elements inside out is
    refused with the reason and the simulator keeps the last accepted state."""
    model, _ = _crushed_block()
    model.release()
    model.fix("z<1e-9")
    X = np.asarray(model.tetmesh.vertices)
    node = int(np.argmin(np.linalg.norm(X - [0.02, 0.02, 0.02], axis=1)))
    sim = rt.DirectSimulator(model, 1e-3, rt.Damping(alpha=50.0), large_deformation=True)
    F = np.zeros((model.n_nodes, 3))
    F[node, 2] = -50.0
    with pytest.raises(rt.SolverError, match="step [0-9]+ was refused: [0-9]+ elements? turned inside out"):
        for _ in range(200):
            before, steps = sim.displacements().copy(), sim.steps
            sim.step(F)
    assert sim.steps == steps and np.array_equal(sim.displacements(), before)
    assert _inverted_count(model, before) == 0


def test_the_polar_derivative_of_a_flattened_element_is_finite():
    """Two principal stretches summing to zero (a tet squashed through itself symmetrically) made the
    corotated tangent's linear solve singular (LinAlgError): it is finite now."""
    F = np.diag([1.0, 0.5, -0.5])[None]
    P, psi, dP = solid.corotated_stress(F, 1e4, 5e3)
    assert np.all(np.isfinite(P)) and np.all(np.isfinite(dP)) and np.isfinite(psi).all()


@pytest.mark.parametrize("kind", ["solid", "shell"])
@pytest.mark.parametrize("distance", [1e3, 1e6])
def test_a_model_carried_a_kilometre_by_its_supports(kind, distance):
    """A rigid motion of every support moves the whole model with no strain, however far: before, 1 km
    was a LinAlgError (solid) or a NaN residual refused as a turned triad (shell)."""
    if kind == "solid":
        model = rt.SolidModel(rt.meshes.box(1.0, 0.1, 0.1, 10, 1, 1), rt.Material(E=1e5, nu=0.3))
    else:
        model = rt.ShellModel(rt.meshes.plate(1.0, 0.2, 8, 2), rt.Material(E=1e5, nu=0.3, thickness=0.01))
    model.fix("x0")
    P = np.zeros((model.n_nodes, model.dofs_per_node))
    P[model.select_nodes("x0"), :2] = distance
    res = rt.nonlinear.solve_static(model, None, prescribed=P)
    assert res.converged
    # every node carried exactly (to the coordinates' resolution: 8 ulp of the distance)
    np.testing.assert_allclose(res.displacements, np.tile([distance, distance, 0.0], (model.n_nodes, 1)), rtol=0,
                               atol=8 * np.finfo(float).eps * distance)
    assert np.abs(res.reactions).max() < 1e-6


def test_a_long_solve_reports_progress_and_stops_at_its_time_limit():
    model = _strip()
    F = np.zeros((model.n_nodes, 3))
    F[model.select_nodes("x1"), 2] = 2.0
    seen = []
    res = rt.nonlinear.solve_static(model, F, progress=lambda done, total, message: seen.append((done, message)))
    iterations = [m for _, m in seen if "iteration" in m]
    # every iteration is reported (those of refused attempts too), the load factor reached never falls
    assert len(iterations) >= res.iterations + len(res.load_factors) and "residual" in iterations[0]
    done = [d for d, _ in seen]
    assert done == sorted(done) and done[-1] == 1.0
    with pytest.raises(rt.SolverError, match="time limit of 1e-06 s") as info:
        rt.nonlinear.solve_static(model, F, time_limit=1e-6)
    assert not info.value.result.converged and info.value.result.load_factors == []


def test_a_solve_stopped_partway_by_its_time_limit_keeps_an_equilibrium():
    """method='auto' stopped by time_limit after its first load step (the callback holds it 2.5 s
    there): the error's result is the equilibrium at the load factor it reached, the same as a solve
    of that fraction of the load (1e-8; measured 8e-12)."""
    model = _strip()
    F = np.zeros((model.n_nodes, 3))
    F[model.select_nodes("x1"), 2] = 2.0

    def hold(done, total, message):
        if done > 0 and not hold.held:
            hold.held = True
            time.sleep(2.5)

    hold.held = False
    with pytest.raises(rt.SolverError, match="time limit of 2 s .* holds the last equilibrium") as info:
        rt.nonlinear.solve_static(model, F, progress=hold, time_limit=2.0)
    part = info.value.result
    assert not part.converged and len(part.load_factors) >= 1 and 0 < part.load_factors[-1] < 1
    ref = rt.nonlinear.solve_static(model, F * part.load_factors[-1], tol=1e-10)
    assert np.abs(part.displacements - ref.displacements).max() <= 1e-8 * np.abs(ref.displacements).max()


@pytest.mark.parametrize("bad", [dict(progress=5), dict(time_limit=-1.0), dict(time_limit="soon")])
def test_solve_static_refuses_bad_options(bad):
    model = _strip()
    with pytest.raises(rt.ModelError):
        rt.nonlinear.solve_static(model, None, **bad)


def test_solve_static_refuses_what_is_not_a_model():
    for model in ("liver", 5, None):
        with pytest.raises(rt.ModelError, match="is not a model"):
            rt.nonlinear.solve_static(model)
        with pytest.raises(rt.ModelError, match="is not a model"):
            rt.nonlinear.NonlinearSystem(model)
