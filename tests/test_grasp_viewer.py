"""Grasp (the viewer's pull), the direct simulator's one-step compliance, and the viewer Session."""

from __future__ import annotations

import numpy as np
import pytest

import rtfem as rt
from rtfem.viewer.session import Session, Settings


@pytest.fixture(scope="module")
def cap():
    """A hemispherical cap clamped at its rim: small enough for direct integration in tests."""
    mesh = rt.meshes.hemisphere(radius=0.05, n_rings=8)
    model = rt.ShellModel(mesh, rt.Material(E=1e5, nu=0.45, thickness=0.003, density=1000.0))
    model.fix("rim")
    return model


def test_direct_predict_plus_compliance_is_the_step(cap):
    node = int(cap.mesh.groups["pole"][0])
    a = rt.DirectSimulator(cap, 1e-3, rt.Damping(alpha=5.0))
    b = rt.DirectSimulator(cap, 1e-3, rt.Damping(alpha=5.0))
    f = np.array([0.01, -0.02, -0.05])
    for k in range(30):
        fk = f * (k % 7) / 7
        u_free = a.predict(node)
        W = a.step_compliance(node)
        a.step({node: fk})  # superposed on predict()'s solve
        b.step({node: fk})  # a full solve
        np.testing.assert_allclose(a.displacement(node), u_free + W @ fk, rtol=1e-10, atol=1e-16)
        np.testing.assert_allclose(a.displacements(), b.displacements(), rtol=1e-10, atol=1e-15)
    # W is symmetric positive definite (a block of K_eff^-1)
    assert np.allclose(W, W.T, rtol=1e-10) and np.all(np.linalg.eigvalsh(W) > 0)


@pytest.mark.parametrize("driver", ["modal", "direct", "map"])
def test_held_grasp_settles_at_springs_in_series(cap, driver):
    """Hand held 3 mm off the undeformed vertex: f = k (I + k G)^-1 d, G the static compliance."""
    mesh = cap.mesh
    node = int(mesh.groups["pole"][0])
    d = np.array([0.002, -0.001, 0.003])
    k = 50.0
    G = np.stack([cap.solve_static({node: e})[node] for e in np.eye(3)], axis=1)
    f_ref = np.linalg.solve(np.eye(3) + k * G, k * d)
    damping = rt.Damping(alpha=60.0)
    if driver == "modal":
        sim = rt.ModalSimulator(rt.modal_analysis(cap, 20), 1e-3, damping, static_correction=True)
    elif driver == "direct":
        sim = rt.DirectSimulator(cap, 1e-3, damping)
    else:
        sim = rt.ImpedanceMap.build(cap, damping, nodes=[node], n_modes=20)
    grasp = rt.Grasp(mesh, sim, stiffness=k)
    grasp.grab(node)
    X = np.asarray(mesh.vertices)[node]
    forces = [grasp.update(X + d) for _ in range(1500)]
    np.testing.assert_allclose(forces[-1], f_ref, rtol=1e-6 if driver != "map" else 1e-10)
    if driver != "map":
        # the grabbed vertex sits where the spring law says: x = target - f / k
        np.testing.assert_allclose(sim.displacement(node), d - f_ref / k, rtol=1e-6, atol=1e-12)
        # implicit coupling: a stiff spring stays bounded (no blow-up) and lands at the same law
        g2 = rt.Grasp(mesh, sim, stiffness=1e6)
        g2.grab(node)
        f2 = [np.linalg.norm(g2.update(X + d)) for _ in range(300)]
        assert np.all(np.isfinite(f2)) and max(f2) < 1e6 * np.linalg.norm(d)
    grasp.release()
    assert not np.any(grasp.update(X + d))


def test_grasp_rejects_bad_input(cap):
    sim = rt.ModalSimulator(rt.modal_analysis(cap, 5), 1e-3)
    with pytest.raises(rt.ModelError, match="stiffness"):
        rt.Grasp(cap.mesh, sim, stiffness=-1)
    g = rt.Grasp(cap.mesh, sim)
    with pytest.raises(rt.ModelError, match="not on the mesh"):
        g.grab(10**6)
    g.grab(0)
    with pytest.raises(rt.ModelError, match="finite"):
        g.update([0.0, np.nan, 0.0])
    with pytest.raises(rt.ModelError, match="grasp drives"):
        rt.Grasp(cap.mesh, object())


@pytest.mark.parametrize("grab_radius", [0.0, 0.01])
def test_session_methods_agree_on_the_held_pull(cap, grab_radius):
    """The viewer's three methods, same pull held (one vertex, or a jaw holding a patch): the same
    settled force and field."""
    mesh = cap.mesh
    node = int(mesh.groups["pole"][0])
    X = np.asarray(mesh.vertices)[node]
    target = X + np.array([0.0, 0.0, 0.004])
    results = {}
    s = Session(mesh, cap.material, fixed="rim", settings=Settings(n_modes=20, alpha=60.0, grasp_stiffness=50.0,
                                                                      grab_radius=grab_radius))
    for method in ("modal", "impedance", "direct"):
        s.configure(method=method)
        assert s.grab(X) == node
        s.drag(target)
        for k in range(1500):
            s.step()
            if k % 20 == 0:
                s.displacements()  # the frame thread's call: feeds the impedance superposition
        results[method] = (s.force, s.displacements())
        s.release()
        for k in range(3000):
            s.step()
            if k % 20 == 0:
                u = s.displacements()
        assert np.abs(u).max() < 1e-3 * np.abs(results[method][1]).max(), method  # let go: it settles back
    f0, u0 = results["direct"]
    for method in ("modal", "impedance"):
        f, u = results[method]
        assert np.abs(f - f0).max() < 1e-5 * np.linalg.norm(f0), method
        assert np.abs(u - u0).max() < 1e-5 * np.abs(u0).max() + 1e-12, method
    if grab_radius:
        assert s.grasp.patch(node).size > 3  # a patch was held


def test_session_rejects_nonsense_settings(cap):
    s = Session(cap.mesh, cap.material, fixed="rim", settings=Settings(n_modes=10))
    for bad, match in ((dict(method="fem"), "method"), (dict(dt=-1.0), "time step"), (dict(alpha=-2.0), "damping"),
                       (dict(E=0.0), "Young")):
        with pytest.raises(rt.ModelError, match=match):
            s.configure(**bad)
    assert s.settings.method == "modal"  # nothing lost
    with pytest.raises(rt.ModelError, match="finite"):
        s.drag([0.0, np.inf, 0.0])
    with pytest.raises(rt.ModelError, match="no nodes"):
        Session(cap.mesh, cap.material, fixed=[])


def test_session_large_deformation_switch(cap):
    """large=True: the modal method warps and the direct method runs the corotational full order;
    a small held pull gives nearly the linear force (to the pull's own small nonlinearity); the
    impedance map, linear by construction, is refused with what to use."""
    mesh = cap.mesh
    node = int(mesh.groups["pole"][0])
    X = np.asarray(mesh.vertices)[node]
    s = Session(mesh, cap.material, fixed="rim", settings=Settings(n_modes=20, alpha=60.0, grasp_stiffness=50.0))
    forces = {}
    for method, large in (("modal", False), ("modal", True), ("direct", True)):
        s.configure(method=method, large=large)
        assert s.settings.label == {False: method, True: {"modal": "modal (warped)",
                                                           "direct": "direct (corotational)"}[method]}[large]
        assert s.driver.compliance_changes == large
        s.grab(X)
        s.drag(X + np.array([0.0, 0.0, 0.001]))
        for _ in range(400 if method == "modal" else 150):
            s.step()
        forces[(method, large)] = np.linalg.norm(s.force)
        s.release()
    assert forces[("modal", True)] == pytest.approx(forces[("modal", False)], rel=0.02)
    assert forces[("direct", True)] == pytest.approx(forces[("modal", False)], rel=0.1)
    with pytest.raises(rt.ModelError, match="impedance map"):
        s.configure(method="impedance", large=True)
    assert s.settings.method == "direct"  # nothing lost


def test_session_reduced_nonlinear_method(cap):
    """method="nonlinear": the reduced nonlinear driver (the modes, their modal derivatives and
    cubature forces, with the static correction). Held by the grasp, the organ settles to the
    reduced model's own static equilibrium under the forces the jaw applies (dead loads)."""
    from rtfem.drivers.reduced_nonlinear import ReducedNonlinearSimulator

    mesh = cap.mesh
    node = int(mesh.groups["pole"][0])
    X = np.asarray(mesh.vertices)[node]
    s = Session(mesh, cap.material, fixed="rim", settings=Settings(method="nonlinear", n_modes=12, alpha=60.0,
                                                                   grasp_stiffness=50.0, grab_radius=0.0))
    assert s.settings.label.startswith("reduced nonlinear")
    assert isinstance(s.driver, ReducedNonlinearSimulator) and s.driver.spread == 1
    s.grab(X)
    s.drag(X + np.array([0.0, 0.0, 0.01]))
    for _ in range(1500):
        s.step()
    forces = {int(v): f for v, f in zip(s.grasp.nodes, s.grasp.forces)}
    static = s.driver.reduced.solve_static(forces, cubature=True, max_iterations=60, static_correction=True)
    assert s.driver.static_correction
    U = s.driver.displacements()
    assert np.abs(U[node]).max() > 0.003  # pulled a few millimetres
    assert np.abs(U - static.displacements).max() < 1e-4 * np.abs(U).max()


def test_session_reduced_nonlinear_method_on_a_solid():
    """The viewer's nonlinear method on a tet model (the corotated-tet cubature): a cantilever's
    tip grabbed and dragged 10 cm settles to the reduced model's static equilibrium under the
    jaw's forces (measured 2.7e-6 of the motion)."""
    from rtfem.drivers.reduced_nonlinear import ReducedNonlinearSimulator

    mesh = rt.meshes.box(1.0, 0.1, 0.1, nx=10, ny=2, nz=2)
    s = Session(mesh, rt.Material(E=1e5, nu=0.3, density=10.0), fixed="x0",
                settings=Settings(method="nonlinear", n_modes=12, alpha=20.0, grasp_stiffness=50.0, grab_radius=0.0))
    assert isinstance(s.driver, ReducedNonlinearSimulator) and s.driver.reduced.dpn == 3
    X = np.asarray(mesh.vertices)
    node = int(np.flatnonzero(np.isclose(X[:, 0], 1.0))[0])
    s.grab(X[node])
    s.drag(X[node] + np.array([0.0, 0.0, 0.1]))
    for _ in range(3000):
        s.step()
    forces = {int(v): f for v, f in zip(s.grasp.nodes, s.grasp.forces)}
    static = s.driver.reduced.solve_static(forces, cubature=True, max_iterations=60, static_correction=True)
    U = s.driver.displacements()
    assert U[node, 2] > 0.05  # a large motion of the 1 m beam
    assert np.abs(U - static.displacements).max() < 1e-4 * np.abs(U).max()



@pytest.mark.parametrize("radius", [0.0, 0.06])
def test_a_grasp_carried_to_a_simulator_localized_mid_pull(radius):
    """Grasp.transferred(driver): the same jaw, closed on the same vertices with the same grip
    references, on another driver in the same state; here the reduced nonlinear simulator
    localized around the held vertices mid-pull (ReducedNonlinearSimulator.localized). Settled,
    the beam is where a grasp on the localized model from the start, closed at rest on the same
    vertex and dragged to the same point, settles (re-grabbing at the deformed state instead
    would have moved the jaw's references, and the equilibrium)."""
    from rtfem.drivers.reduced_nonlinear import ReducedNonlinearSimulator, reduced_nonlinear_driver

    mesh = rt.meshes.box(1.0, 0.1, 0.1, nx=10, ny=2, nz=2)
    model = rt.SolidModel(mesh, rt.Material(E=1e5, nu=0.3, density=10.0)).fix("x0")
    sim = reduced_nonlinear_driver(model, rt.modal_analysis(model, 12), 1e-3, rt.Damping(zeta=1.0))
    X = np.asarray(mesh.vertices)
    node = int(np.flatnonzero(np.isclose(X[:, 0], 1.0))[0])
    target = X[node] + np.array([0.0, 0.0, 0.1])
    grasp = rt.Grasp(mesh.surface, sim, stiffness=50.0, radius=radius)
    held = grasp.grab(node)
    for _ in range(100):
        grasp.update(target)
    loc = sim.localized(held, 0.25)
    moved = grasp.transferred(loc)
    assert moved.driver is loc and np.array_equal(moved.nodes, held) and moved.node == node
    assert np.array_equal(moved.force, grasp.force)
    for _ in range(3000):
        moved.update(target)
    ref_sim = ReducedNonlinearSimulator(loc.reduced, 1e-3, rt.Damping(zeta=1.0), static_correction=True)
    ref = rt.Grasp(mesh.surface, ref_sim, stiffness=50.0, radius=radius)
    ref.grab(node)
    for _ in range(3100):
        ref.update(target)
    U, R = loc.displacements(), ref_sim.displacements()
    assert U[node, 2] > 0.05
    assert np.abs(U - R).max() < 1e-6 * np.abs(R).max()
    assert np.abs(moved.force - ref.force).max() < 1e-6 * np.abs(ref.force).max()
    free = rt.Grasp(mesh.surface, loc, stiffness=50.0, radius=radius)
    assert free.transferred(sim).node is None  # an open jaw stays open


def test_session_localizes_the_nonlinear_basis_per_grab():
    """Settings(local=r): each grab localizes the reduced nonlinear basis around the held vertices
    in a background thread and swaps it in mid-pull with the grasp carried over. Settled (the
    patch's modes damped: patch_zeta, under the viewer's alpha), the beam is where a session
    running the localized model from the start settles; a second grab elsewhere localizes again
    from the global basis. The CLI refuses --local without --method nonlinear."""
    from rtfem.drivers.reduced_nonlinear import ReducedNonlinearSimulator

    mesh = rt.meshes.box(1.0, 0.1, 0.1, nx=10, ny=2, nz=2)
    mat = rt.Material(E=1e5, nu=0.3, density=10.0)
    kw = dict(method="nonlinear", n_modes=12, alpha=20.0, grasp_stiffness=50.0, grab_radius=0.0)
    s = Session(mesh, mat, fixed="x0", settings=Settings(local=0.25, **kw))
    assert "localized per grab (250 mm)" in s.settings.label
    X = np.asarray(mesh.vertices)
    node = int(np.flatnonzero(np.isclose(X[:, 0], 1.0))[0])
    target = X[node] + np.array([0.0, 0.0, 0.1])
    plain = s.driver
    s.grab(X[node])
    s.drag(target)
    for _ in range(100):  # the pull goes on while the patch is trained
        s.step()
    s.localizing.join(120)
    assert s.driver is not plain and s.driver.reduced.local is not None
    assert node in s.driver.reduced.local["nodes"] and s.local_status.startswith("localized: ")
    assert s.grasp.driver is s.driver and s.grasp.node == node
    for _ in range(3000):
        s.step()
    ref = Session(mesh, mat, fixed="x0", settings=Settings(**kw))
    ref.use_driver(ReducedNonlinearSimulator(s.driver.reduced, s.driver.dt, s.driver.damping, spread=1,
                                             precision="single", static_correction=True))
    ref.grab(X[node])
    ref.drag(target)
    for _ in range(3100):
        ref.step()
    U, R = s.driver.displacements(), ref.driver.displacements()
    assert U[node, 2] > 0.05
    assert np.abs(U - R).max() < 1e-5 * np.abs(R).max()
    s.release()
    other = int(np.argmin(np.linalg.norm(X - [0.5, 0.1, 0.1], axis=1)))
    s.grab(X[other])
    s.localizing.join(120)
    assert other in s.driver.reduced.local["nodes"] and s.driver.reduced.local["parent"] is plain.reduced
    s.configure(alpha=30.0)  # a rebuild: the patch's status goes with its driver
    assert s.local_status == "" and s.driver.reduced.local is None
    with pytest.raises(rt.ModelError, match="local"):
        Settings(local=-0.01).check()


def test_a_patch_that_arrives_after_the_release_or_too_slow_is_not_swapped_in(monkeypatch):
    """A patch still training when the hand lets go is dropped (it was for that grab: swapped in
    after the release it left a bigger model stepping at 1 % of real time); a patch whose free
    step would take more than 0.9 of the time step is not swapped in either, and the panel says
    why."""
    import rtfem.viewer.session as session_module

    mesh = rt.meshes.box(1.0, 0.1, 0.1, nx=10, ny=2, nz=2)
    mat = rt.Material(E=1e5, nu=0.3, density=10.0)
    kw = dict(method="nonlinear", n_modes=12, alpha=20.0, grasp_stiffness=50.0, grab_radius=0.0, local=0.25)
    s = Session(mesh, mat, fixed="x0", settings=Settings(**kw))
    X = np.asarray(mesh.vertices)
    node = int(np.flatnonzero(np.isclose(X[:, 0], 1.0))[0])
    plain = s.driver
    s.grab(X[node])
    s.release()  # before the patch (seconds of training) is ready
    assert "dropped" in s.local_status
    s.localizing.join(120)
    assert s.driver is plain and s.grasp.driver is plain
    monkeypatch.setattr(session_module, "_step_cost", lambda driver: 5e-3)  # a 5 ms step against dt = 1 ms
    s.grab(X[node])
    s.localizing.join(120)
    assert s.driver is plain and "kept the running basis" in s.local_status and "5.00 ms" in s.local_status


def test_new_viewer_settings_and_entry_points_refuse_bad_values():
    """The derivatives, spread and force limit of the viewer, and the benchmark's arguments: a
    bad value is an RtfemError that changes nothing."""
    from rtfem.viewer import benchmark

    for bad in (dict(derivatives=-1), dict(spread=0), dict(spread=2.5), dict(max_force=0.0),
                dict(max_force=float("nan"))):
        with pytest.raises(rt.RtfemError):
            Settings(**bad).check()
    mesh = rt.meshes.box(1.0, 0.1, 0.1, nx=6, ny=2, nz=2)
    s = Session(mesh, rt.Material(E=1e5, nu=0.3, density=10.0), fixed="x0", settings=Settings(n_modes=6))
    assert s.settings.max_force == 10.0 and s.grasp.max_force == 10.0  # a desktop device's range, not 2 N
    for bad in (-1.0, 0.0, float("inf"), "ten"):
        with pytest.raises(rt.RtfemError):
            s.set_force_limit(bad)
    assert s.settings.max_force == 10.0 and s.grasp.max_force == 10.0
    s.set_force_limit(3.0)
    assert s.settings.max_force == 3.0 and s.grasp.max_force == 3.0
    driver = s.driver
    s.configure(grab_radius=0.0, grasp_stiffness=80.0)  # the hand only: no new precompute
    assert s.driver is driver and s.grasp.stiffness == 80.0 and s.grasp.max_force == 3.0
    for kw in (dict(seconds=0.0), dict(seconds=-1.0), dict(seconds=float("nan")), dict(seconds=1.0, pull=-0.01)):
        with pytest.raises(rt.RtfemError):
            benchmark.run(s, **kw)
    with pytest.raises(rt.RtfemError):
        benchmark.run("session", 1.0)
    assert s.stats.steps == 0 and s.node is None  # nothing ran
