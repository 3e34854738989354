"""The error indicator while the model runs (issue 56): rtfem.reduction.indicator.ErrorMonitor in the
viewer's session. The issue's block (tet10 0.1 x 0.04 x 0.04 m, E 4e4, clamped at one end) driven by
the viewer's own session and settings (the reduced nonlinear model, 40 modes and the derivatives of
10, cubature, 1 ms steps), a jaw on its free end dragged 2.25 cm: the estimate the session's monitor
reports of the settled state against the true error of that state, its distance from the full
order's equilibrium under the jaw's forces (rt.nonlinear.solve_static): measured 0.99 of it (0.95
with Newton's correction alone), the state's error 0.29 of the linear model's, 0.15 s an estimate."""

import time

import numpy as np
import pytest

import rtfem as rt
import rtfem.viewer.session as session_module
from rtfem.viewer.session import Session, Settings


def test_the_sessions_monitor_estimates_the_settled_grasps_error_within_a_factor_of_2(monkeypatch):
    mesh = rt.meshes.box(0.1, 0.04, 0.04, nx=10, ny=4, nz=4)
    s = Session(mesh, rt.Material(E=4e4, nu=0.45, density=1000.0), fixed="x0",
                settings=Settings(method="nonlinear", alpha=30.0, grab_radius=0.0075),
                model_options={"element": "tet10"})
    assert s.monitor is not None and s.monitor.period == Session.indicator_period
    X = np.asarray(s.mesh.vertices)
    centre = np.array([0.1, 0.02, 0.02])
    node = s.grab(centre)
    assert np.linalg.norm(X[node] - centre) < 1e-9
    s.drag(centre + [0.0, 0.0, 0.0225])
    for _ in range(2500):  # 2.5 s at 1 ms: alpha 30 settles it
        s.step()
    U, loads, _ = s._error_state()
    est = s.monitor.estimate()
    model = s.model
    full = rt.nonlinear.solve_static(model, loads, steps=8).displacements
    true = np.linalg.norm(full - U, axis=1)
    assert np.linalg.norm(U[node]) > 0.01  # m: a large pull
    assert 0.5 < est.max_error / true.max() < 2.0, (est.max_error, true.max())
    linear = np.linalg.norm(full - model.solve_static(loads), axis=1).max()
    assert true.max() < linear  # the reduced model is better than the linear one here, and the indicator says by how much
    # on its thread: an estimate arrives without a step waiting for it; above the panel's tolerance
    # (Settings.adapt, 0.5 mm) the model adapts: the basis is localized around the jaw in the
    # background and swapped in while the clock runs; the monitor stops with the session
    # (the cubature's greedy fit moves this error: 0.77 mm with 150 elements, 0.30 mm with 143 after
    # last-bit differences in its training, BLAS on one thread or two; the tolerance is set under it)
    s.configure(adapt=0.5 * est.max_error)
    s.monitor.latest = None
    # the patch's step is timed before it is swapped in, and one over 0.9 dt keeps the running basis: on a slow
    # or loaded machine (0.93-1.26 ms measured in session 70's fresh clones) that decided this test, not the
    # monitor; the step's cost is pinned under the budget here, the refusal being the machine's, not the model's
    monkeypatch.setattr(session_module, "_step_cost", lambda driver: 0.5 * driver.dt)
    s.start()
    try:
        t0 = time.perf_counter()
        while "localized" not in s.local_status and time.perf_counter() - t0 < 120:
            time.sleep(0.05)
        assert s.monitor.latest is not None and s.monitor.error is None
        assert s.monitor.latest.max_error > 0 and np.isfinite(s.monitor.latest.max_error)
        assert s.local_status.startswith("the error estimate") and "mm: localized" in s.local_status, s.local_status
    finally:
        s.stop()
    assert s.monitor._thread is None
    assert s.driver.reduced.info["local"]["radius"] == s.settings.adapt_radius
    localizing = s.localizing
    s._adapt(est)  # once per grab: a second estimate above the tolerance does not localize again
    assert s.localizing is localizing
    for _ in range(2500):  # settled on the localized basis, the jaw held where it was
        s.step()
    U2, loads2, _ = s._error_state()
    full2 = rt.nonlinear.solve_static(model, loads2, steps=8).displacements
    true2 = np.linalg.norm(full2 - U2, axis=1).max()
    linear2 = np.linalg.norm(full2 - model.solve_static(loads2), axis=1).max()
    # the goal, 0.2 of the linear model's error: measured 0.10 and 0.16 (0.27 and 0.43 mm, the
    # localized cubature's fit moving it as above; 0.29 and 0.12 of it before)
    assert true2 < 0.2 * linear2, (true.max(), true2, linear2)
    assert 0.5 < s.monitor.estimate().max_error / true2 < 2.0
    s.configure(adapt=0.0)  # the tolerance changes without a rebuild
    assert s.driver.reduced.info.get("local") and s.settings.adapt == 0.0


def test_the_model_adapts_only_above_the_tolerance_while_a_grasp_is_held():
    from rtfem.reduction.indicator import ErrorEstimate

    s = Session(rt.meshes.box(0.1, 0.04, 0.04, nx=5, ny=2, nz=2), rt.Material(E=4e4, nu=0.45, density=1000.0),
                fixed="x0", settings=Settings(method="nonlinear", n_modes=10, derivatives=3, alpha=30.0))
    n = s.model.n_nodes

    def est(mm):
        return ErrorEstimate(np.zeros((n, 3)), np.zeros(n), mm * 1e-3, 0, 0.0, 1.0, {})

    def adapt(mm):  # what the monitor does: the state (and the grab it is of) read, then the estimate
        s._error_state()
        s._adapt(est(mm))

    adapt(5.0)  # nothing held: nothing to localize around
    assert s.localizing is None
    s.grab([0.1, 0.02, 0.02])
    adapt(0.4)  # below the tolerance
    assert s.localizing is None
    s.configure(adapt=0.0)
    adapt(5.0)  # adapt 0: never
    assert s.localizing is None
    s.configure(adapt=3e-3, adapt_radius=0.03)
    s.error = "SolverError: the step diverged"  # the stepping thread ended on a failure: nothing adapts, the error stays
    adapt(5.0)
    assert s.localizing is None and s.error == "SolverError: the step diverged"
    s.error = None
    s._error_state()  # an estimate of this grab ...
    s.release()
    s.grab([0.1, 0.0, 0.0])
    s._adapt(est(5.0))  # ... arriving after another grab: not this one's
    assert s.localizing is None
    plain = s.driver
    adapt(5.0)
    s.grab([0.1, 0.04, 0.04])  # a grab elsewhere while the patch trains (no release between): it is dropped
    s.localizing.join(60)
    assert s.driver is plain and s.grasp.driver is plain
    adapt(5.0)
    s.localizing.join(60)
    assert "the error estimate 5.00 mm is above 3 mm: localized" in s.local_status, s.local_status
    assert s.driver.reduced.info["local"]["radius"] == 0.03 and s.driver._patch_margin is not None
    s.configure()  # the panel's reset: the same settings rebuild, the patch and the grasp gone
    assert s.node is None and s.driver.reduced.local is None
    with pytest.raises(rt.ModelError, match="adapt"):
        Settings(adapt=-1.0).check()
    for bad in (0.0, 0.06):
        with pytest.raises(rt.ModelError, match="adapt_radius"):
            Settings(adapt_radius=bad).check()


def test_no_monitor_for_the_linear_methods_and_bad_arguments_are_refused():
    from rtfem.reduction.indicator import ErrorMonitor

    s = Session(rt.meshes.liver(2), fixed="attachment", settings=Settings(method="modal", n_modes=10))
    assert s.monitor is None
    with pytest.raises(rt.ModelError, match="callable"):
        ErrorMonitor(s.model, None)
    with pytest.raises(rt.ModelError, match="period"):
        ErrorMonitor(s.model, lambda: (None, None), period=0.0)
    for bad in ([0, 1], {"a": [s.model.n_nodes]}, {"a": [-1]}, {"a": [0.5]}):
        with pytest.raises(rt.ModelError):
            ErrorMonitor(s.model, lambda: (None, None), regions=bad)


def test_a_haptic_loops_statistics_carry_the_error_estimate():
    """HapticLoop(..., monitor=probe_monitor(grasp)): the monitor runs beside the loop's ticks and
    stats.error_estimate is its latest estimate (said by str(stats)). A grasp on a reduced nonlinear
    beam (12 modes + derivatives, no localization) lifts its tip 15 % of the length and holds: the
    estimate shown at the end is within a factor of 2 of the true error of the state, its distance
    from the full order's equilibrium under the grasp's forces (rt.nonlinear.solve_static): measured
    0.99 (without the grasp's loads the estimate reads 21 times the error)."""
    from rtfem.drivers.reduced_nonlinear import reduced_nonlinear_driver
    from rtfem.reduction.indicator import probe_monitor

    mesh = rt.meshes.box(1.0, 0.1, 0.1, nx=10, ny=2, nz=2)
    model = rt.SolidModel(mesh, rt.Material(E=1e5, nu=0.3, density=10.0)).fix("x0")
    sim = reduced_nonlinear_driver(model, rt.modal_analysis(model, 12), 1e-3, rt.Damping(zeta=1.0), derivatives=4)
    X = np.asarray(mesh.vertices)
    node = int(np.flatnonzero(np.isclose(X[:, 0], 1.0))[0])
    grasp = rt.Grasp(mesh.surface, sim, stiffness=50.0, radius=0.0)
    grasp.grab(node)
    device = rt.ScriptedDevice(lambda t: X[node] + [0.0, 0.0, 0.15 * min(1.0, t / 0.5)])
    monitor = probe_monitor(grasp, period=0.2)
    loop = rt.HapticLoop(grasp, device, monitor=monitor)
    stats = loop.run(3.0)
    est = stats.error_estimate
    assert est is not None and monitor._thread is None and monitor.error is None
    assert f"error estimate {est.max_error * 1e3:.3g} mm at node {est.worst_node}" in str(stats)
    U = sim.displacements()
    loads = {int(v): f for v, f in zip(grasp.nodes.tolist(), grasp.forces)}
    full = rt.nonlinear.solve_static(model, loads, steps=8).displacements
    true = np.linalg.norm(full - U, axis=1).max()
    assert U[node, 2] > 0.05 and true > 1e-3  # a large lift, and an error worth telling
    assert 0.5 < est.max_error / true < 2.0, (est.max_error, true)
    assert rt.HapticLoop(grasp, device).stats.error_estimate is None
    assert not loop.compiled  # the monitor reads the tool's loads in Python
    modal = rt.ModalSimulator(rt.modal_analysis(model, 6), 1e-3)
    on_modal = rt.Grasp(mesh.surface, modal, stiffness=50.0, radius=0.0)
    assert probe_monitor(on_modal).model is model
    with pytest.raises(rt.ModelError, match="compiled=False"):
        rt.HapticLoop(on_modal, device, monitor=probe_monitor(on_modal), compiled=True)
    assert not rt.HapticLoop(on_modal, device, monitor=probe_monitor(on_modal)).compiled
    with pytest.raises(rt.ModelError, match="ErrorMonitor"):
        rt.HapticLoop(grasp, device, monitor="yes")
    with pytest.raises(rt.ModelError, match="no driver"):
        probe_monitor(object())


def test_a_labelled_solids_estimate_is_given_per_region():
    """On a solid of two regions the monitor's estimate carries each region's largest value (over its
    elements' nodes, an interface's in both): the worst node's region has the whole estimate, and each
    equals the largest of the estimate's field over that region's nodes taken from the elements."""
    box = rt.meshes.box(0.1, 0.04, 0.04, nx=6, ny=2, nz=2)
    V, T = np.asarray(box.vertices), np.asarray(box.tets)
    labels = np.where(V[T].mean(axis=1)[:, 0] < 0.05, 1, 2)
    mesh = rt.TetMesh(V, T, groups=box.groups, labels=labels, region_names={"base": 1, "tip": 2})
    s = Session(mesh, rt.Material(E=4e4, nu=0.45, density=1000.0), fixed="x0",
                settings=Settings(method="nonlinear", n_modes=10, derivatives=3, alpha=30.0, grab_radius=0.0, adapt=0.0),
                model_options={"element": "tet10"})
    node = s.grab([0.1, 0.02, 0.02])
    s.drag(s.X[node] + [0.0, 0.0, 0.02])
    for _ in range(300):
        s.step()
    est = s.monitor.estimate()
    assert set(est.regions) == {"base", "tip"}
    Tq, lab = np.asarray(s.volume.tets), np.asarray(s.volume.labels)
    assert Tq.shape[1] == 10  # the model's own (quadratic) elements
    for name, k in (("base", 1), ("tip", 2)):
        assert est.regions[name] == est.node_error[np.unique(Tq[lab == k])].max()
    assert est.regions["tip"] == est.max_error > est.regions["base"] > 0
