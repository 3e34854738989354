"""rt.StaticDriver: the Driver protocol on the static solve, for quasi-static contact."""

import numpy as np
import pytest

import rtfem as rt


@pytest.fixture(scope="module")
def beam():
    model = rt.SolidModel(rt.meshes.box(1.0, 0.1, 0.1, nx=12, ny=2, nz=2), rt.Material(E=1e5, nu=0.3, density=10.0))
    model.fix("x0")
    return model


def test_each_step_is_the_static_solve_of_the_held_and_the_steps_loads(beam):
    """Every step equals model.solve_static of the held loads plus the step's, for dict and array
    loads, few or many loaded nodes (the columns or one solve); predict is the held loads'
    equilibrium and u = predict + W f exactly (the static compliance)."""
    model = beam
    tip = model.select_nodes("x1")
    held = np.zeros((model.n_nodes, 3))
    held[tip, 2] = 0.01
    d = rt.StaticDriver(model, held)
    np.testing.assert_allclose(d.displacements(), model.solve_static(held), rtol=1e-12, atol=1e-15)
    node = int(tip[0])
    f = np.array([0.02, -0.01, 0.03])
    u = d.predict(node) + d.step_compliance(node) @ f
    d.step({node: f})
    F = held.copy()
    F[node] += f
    ref = model.solve_static(F)
    scale = np.abs(ref).max()
    assert np.abs(d.displacements() - ref).max() < 1e-12 * scale
    assert np.abs(d.displacement(node) - u).max() < 1e-12 * scale
    many = np.zeros((model.n_nodes, 3))
    many[:, 1] = 1e-3  # every free node loaded: one solve
    many[model.select_nodes("x0")] = 0.0
    d.step(many)
    assert np.abs(d.displacements() - model.solve_static(held + many)).max() < 1e-12 * scale
    W = d.step_compliances(tip[:3], tip[3:5])
    assert W.shape == (9, 6) and np.allclose(W[:3, :3], d.step_compliances(tip[:1], tip[3:4]))
    d.reset()
    assert d.steps == 0 and np.array_equal(d.displacements(), d.predict_at(np.arange(model.n_nodes)))


def test_a_rigid_tool_on_the_static_driver_gives_the_static_contact_force():
    """A 1 cm sphere lowered 2 mm by the constraint coupling onto a block's top through the static
    driver equals the quasi-static route the tests used before (a modal simulator with the static
    correction and a 100 s critically damped step) to 1e-6, and friction can be set mid-contact
    (checked; a bad value is refused and the old one kept)."""
    model = rt.SolidModel(rt.meshes.box(0.2, 0.1, 0.1, nx=16, ny=8, nz=8), rt.Material(E=1e5, nu=0.3, density=10.0))
    model.fix("x0")
    top = np.array([0.12, 0.05, 0.1])
    forces = []
    for d in (rt.StaticDriver(model),
              rt.ModalSimulator(rt.modal_analysis(model, 6), 100.0, rt.Damping(zeta=1.0), static_correction=True)):
        tc = rt.ToolContact(model.mesh, d, rt.Tool.sphere(0.01), coupling="constraint")
        for k in range(14):
            f = tc.update(top + [0.0, 0.0, 0.01 - 0.0002 * min(k + 1, 10)])
        forces.append(f.copy())
        tc.friction = 0.3
        assert tc.friction == 0.3
        for bad in (-0.1, float("nan"), "x", 11.0):
            with pytest.raises(rt.ModelError, match="friction"):
                tc.friction = bad
        assert tc.friction == 0.3
        g = tc.update(top + [0.0005, 0.0, 0.008])  # dragged with friction: it holds the tissue back
        assert g[0] < -0.01 * g[2]
    assert forces[0][2] > 0.5  # measured 1.51 N
    assert np.abs(forces[0] - forces[1]).max() < 1e-6 * np.abs(forces[1]).max()


def test_bad_input_and_changed_supports_are_refused(beam):
    model = rt.SolidModel(beam.tetmesh, beam.material).fix("x0")
    d = rt.StaticDriver(model)
    d.step({0: (0.0, 0.0, 1.0)})
    state = d.get_state()
    for bad in ({10**6: (0, 0, 1)}, {3: (0.0, float("nan"), 0.0)}, np.ones((2, 3)), {3: (1.0, 2.0)}):
        with pytest.raises(rt.ModelError):
            d.step(bad)
    assert all(np.array_equal(v, state[k]) for k, v in d.get_state().items())  # nothing changed
    for bad in ({"u": np.zeros(3)}, "state", {"x": 1}):
        with pytest.raises(rt.ModelError):
            d.set_state(bad)
    with pytest.raises(rt.ModelError):
        rt.StaticDriver("model")
    with pytest.raises(rt.ModelError):
        rt.StaticDriver(model, dt=-1.0)
    free = rt.SolidModel(beam.tetmesh, beam.material)
    with pytest.raises(rt.ModelError):
        rt.StaticDriver(free)  # nothing fixed
    model.fix("x1")
    with pytest.raises(rt.ModelError, match="supports changed"):
        d.step(None)
