import numpy as np
import pytest

import rtfem as rt


@pytest.fixture(scope="module")
def setup(liver3_modes):
    model, basis = liver3_modes
    mesh = model.mesh
    node = mesh.nearest_vertex([0.06, 0.05, 0.0])
    return model, basis, node


def test_dict_and_array_forces_agree(setup):
    model, basis, node = setup
    a = rt.ModalSimulator(basis, 1e-3, rt.Damping(alpha=4.0))
    b = rt.ModalSimulator(basis, 1e-3, rt.Damping(alpha=4.0))
    F = np.zeros((model.n_nodes, 3))
    F[node] = (0.0, -0.1, 0.02)
    F[3] = (0.01, 0.0, 0.0)
    for _ in range(20):
        a.step({node: (0.0, -0.1, 0.02), 3: (0.01, 0.0, 0.0)})
        b.step(F)
    # the same sum in another order (3 entries vs a BLAS product over 3n): equal to round-off
    ua, ub = a.displacements(), b.displacements()
    assert np.abs(ua - ub).max() < 1e-12 * np.abs(ub).max()
    assert np.abs(a.displacement(node) - ua[node]).max() < 1e-12 * np.abs(ua).max()


def test_bad_forces_leave_state_untouched(setup):
    model, basis, node = setup
    sim = rt.ModalSimulator(basis, 1e-3)
    sim.run({node: (0.0, -0.1, 0.0)}, 10)
    before = sim.get_state()
    for bad in ({node: (np.nan, 0.0, 0.0)}, {node: (0.0, np.inf, 0.0)}, {10**7: (1, 0, 0)}, {node: (1, 2)},
                np.full((model.n_nodes, 3), np.nan), np.zeros((4, 3)), {"a": (1, 0, 0)}):
        with pytest.raises(rt.ModelError):
            sim.step(bad)
    after = sim.get_state()
    assert all(np.array_equal(before[k], after[k]) for k in before)
    assert sim.steps == 10


def test_reset_and_state_round_trip(setup):
    _, basis, node = setup
    sim = rt.ModalSimulator(basis, 1e-3, rt.Damping(alpha=2.0), integrator="newmark")
    sim.run({node: (0.0, 0.0, 0.1)}, 15)
    state = sim.get_state()
    sim.run({node: (0.0, 0.0, 0.1)}, 10)
    u25 = sim.displacements()
    sim.set_state(state)
    assert sim.steps == 15 and sim.time == pytest.approx(0.015)
    sim.run({node: (0.0, 0.0, 0.1)}, 10)
    assert np.array_equal(sim.displacements(), u25)
    sim.reset()
    assert sim.energy() == 0.0 and sim.time == 0.0
    with pytest.raises(rt.ModelError, match="shape"):
        sim.set_state({"q": np.zeros(3)})


def test_argument_errors(setup):
    model, basis, _ = setup
    for dt in (0.0, -1e-3, np.nan, "x"):
        with pytest.raises(rt.ModelError, match="dt"):
            rt.ModalSimulator(basis, dt)
    with pytest.raises(rt.ModelError, match="integrator"):
        rt.ModalSimulator(basis, 1e-3, integrator="rk4")
    with pytest.raises(rt.ModelError, match="ModalBasis"):
        rt.ModalSimulator(model, 1e-3)
    with pytest.raises(rt.ModelError, match="needs the model"):
        rt.ModalSimulator(rt.ModalBasis(basis.omega, basis.shapes, "x"), 1e-3, static_correction=True)
    with pytest.raises(rt.ModelError, match="zeta"):
        rt.DirectSimulator(model, 1e-3, rt.Damping(zeta=0.02))
    free = rt.ShellModel(model.mesh, rt.Material())
    with pytest.raises(rt.ModelError, match="nothing is fixed"):
        rt.DirectSimulator(free, 1e-3)


def test_static_correction_for_array_loads(setup):
    model, basis, node = setup
    F = np.zeros((model.n_nodes, 3))
    F[node] = (0.0, -0.1, 0.05)
    sim = rt.ModalSimulator(basis.truncated(5), 0.5, rt.Damping(alpha=2 * basis.omega[0]), static_correction=True)
    sim.run(F, 200)
    u = model.solve_static(F)
    assert np.linalg.norm(sim.displacements() - u) < 1e-9 * np.linalg.norm(u)
    # the one-node and batched reads carry the array load's correction too (displacement() once
    # dropped it, reading only the modes' part)
    assert np.abs(sim.displacement(node) - u[node]).max() < 1e-9 * np.abs(u[node]).max()
    assert np.abs(sim.displacements_at([node, 0]) - u[[node, 0]]).max() < 1e-9 * np.abs(u[node]).max()


def test_static_correction_of_a_weight_plus_a_few_changing_loads(setup):
    """A scene body's load: its weight on every node plus contact forces on a few that change each
    step. The correction is then the kept weight's plus the changed nodes' columns: the same field
    as a static solve of the whole load (settled with 5 modes, where the correction is most of it)."""
    model, basis, node = setup
    weight = np.tile([0.0, 0.0, -0.01], (model.n_nodes, 1))
    sim = rt.ModalSimulator(basis.truncated(5), 0.5, rt.Damping(alpha=2 * basis.omega[0]), static_correction=True)
    sim.step(weight)
    sim.displacements()  # the weight's correction: one static solve
    F = weight.copy()
    F[[node, 3, 40]] += [(0.0, -0.1, 0.05), (0.02, 0.0, 0.0), (0.0, 0.0, 0.03)]
    sim.run(F, 200)
    u = model.solve_static(F)
    assert len(sim._D_array) == 1  # the weight's one solve kept; this load from its columns
    assert np.linalg.norm(sim.displacements() - u) < 1e-9 * np.linalg.norm(u)
    assert np.abs(sim.displacements_at([node, 0]) - u[[node, 0]]).max() < 1e-9 * np.abs(u).max()


def test_central_difference_refuses_unstable_dt_and_agrees_below(setup):
    mesh = rt.meshes.plate(0.1, 0.05, 6, 3)
    model = rt.ShellModel(mesh, rt.Material(E=1e5, thickness=2e-3))
    model.fix("x0")
    probe = rt.DirectSimulator(model, 1e-9, rt.Damping(alpha=3.0), method="central")
    limit = probe.critical_dt
    # the limit is T_n / pi of the highest mode of the condensed system
    w_max = rt.modal_analysis(model, "all").omega.max()
    assert limit == pytest.approx(2 / w_max, rel=1e-4)
    with pytest.raises(rt.ModelError, match=r"T_n/pi = .*Use dt <="):
        rt.DirectSimulator(model, 1.01 * limit, rt.Damping(alpha=3.0), method="central")
    dt = 0.5 * limit
    cd = rt.DirectSimulator(model, dt, rt.Damping(alpha=3.0), method="central")
    nm = rt.DirectSimulator(model, dt, rt.Damping(alpha=3.0))
    node = int(mesh.groups["x1"][1])
    exact = rt.ModalSimulator(rt.modal_analysis(model, "all"), dt, rt.Damping(alpha=3.0))
    n = int(0.5 / dt)
    for _ in range(n):
        for sim in (cd, nm, exact):
            sim.step({node: (0.0, 0.0, -0.01)})
    # the three take the step force at the start, the middle (trapezoid) and over the whole
    # first step; after many steps they differ by their O(dt^2) errors only
    ref = exact.displacements()
    assert np.abs(cd.displacements() - ref).max() < 2e-3 * np.abs(ref).max()
    assert np.abs(nm.displacements() - ref).max() < 2e-3 * np.abs(ref).max()
    with pytest.raises(rt.ModelError, match="diagonal damping"):
        rt.DirectSimulator(model, dt, rt.Damping(alpha=1.0, beta=1e-3), method="central")


def test_single_precision_field_for_drawing():
    """displacements(dtype=float32) (the viewer's): the float64 field to single precision, with
    the static correction of point and array loads, into a given out array too."""
    model = rt.ShellModel(rt.meshes.liver(3), rt.Material()).fix("attachment")
    basis = rt.modal_analysis(model, 12)
    sim = rt.ModalSimulator(basis, 1e-3, rt.Damping(alpha=8.0), static_correction=True)
    node = int(model.mesh.groups["probe"][0])
    for load in ({node: (0.0, 0.0, -0.2)}, np.full((model.mesh.n_vertices, 3), 1e-3)):
        for _ in range(5):
            sim.step(load)
        u64, u32 = sim.displacements(), sim.displacements(dtype=np.float32)
        assert u32.dtype == np.float32 and u32.shape == u64.shape
        assert np.abs(u32 - u64).max() <= 1e-6 * np.abs(u64).max()
        out = np.empty(u64.shape, np.float32)
        got = sim.displacements(out, dtype=np.float32)
        assert np.shares_memory(got, out) and np.array_equal(out, u32)
    with pytest.raises(rt.ModelError, match="float64 or float32"):
        sim.displacements(dtype=np.int32)


def test_newmark_numerical_damping_is_checked_and_kept_in_the_state():
    mesh = rt.meshes.plate(0.2, 0.2, 4, 4)
    model = rt.ShellModel(mesh, rt.Material())
    model.fix(mesh.boundary_vertices())
    for bad, match in ((dict(method="central", numerical_damping=0.1), "Newmark's"),
                       (dict(numerical_damping=0.5), r"\[0, 1/3\]"), (dict(numerical_damping="x"), "number")):
        with pytest.raises(rt.ModelError, match=match):
            rt.DirectSimulator(model, 1e-5, **bad)
    with pytest.raises(rt.ModelError, match="Newmark's"):
        rt.CentralDifferenceSimulator(model, 1e-5, numerical_damping=0.1)
    sim = rt.DirectSimulator(model, 1e-3, numerical_damping=0.1)
    sim.step({12: (0.0, 0.0, 1.0)})
    state = sim.get_state()
    assert np.abs(state["f"]).max() == 1.0  # HHT weighs the last step's forces into the next
    sim.step(None)
    after = sim.displacements()
    sim.set_state(state)
    sim.step(None)
    assert np.array_equal(sim.displacements(), after)


def test_unit_load_responses_equal_the_single_ones_and_refuse_bad_nodes():
    """The batched static columns (multi-column solves, here two nodes per solve) equal the single
    ones to round-off, with fixes by elimination and by penalty; bad nodes or a bad memory bound
    are refused before anything is solved."""
    mesh = rt.meshes.plate(0.2, 0.2, 6, 6)
    for constraints in ("elimination", "penalty"):
        model = rt.ShellModel(mesh, rt.Material(), constraints=constraints)
        model.fix(mesh.boundary_vertices())
        nodes = np.array([10, 24, 0, 10])  # a held node and a repeat among them
        A = model.unit_load_responses(nodes, memory=8 * 3 * model.n_dofs * 2)
        B = np.stack([np.stack([model.unit_load_response(int(n), k) for k in range(3)], axis=2) for n in nodes])
        assert np.abs(A - B).max() <= 1e-12 * np.abs(B).max()
    for bad, kw in (([10**6], {}), ([1.5], {}), ([10], {"memory": 0.0})):
        with pytest.raises(rt.ModelError):
            model.unit_load_responses(bad, **kw)
