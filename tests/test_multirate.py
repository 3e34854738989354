"""rt.MultiRateProbe (issue 55): the haptic tick against the last full-order step's linearization, the
full-order nonlinear step on its own thread. Checked against the full order's own answers: a still hand
settles where rt.nonlinear.solve_static under the felt force puts the surface (the spring law), the
force a tick renders is the force the next physics step is taken with, between steps it follows the
hand through the step's compliance (computed here independently from the driver), and a failing
physics step ends in zero force with a reason."""

import time

import numpy as np
import pytest

import rtfem as rt

K = 300.0


def _block(dt=2e-3, alpha=30.0):
    mesh = rt.meshes.box(0.1, 0.04, 0.04, nx=10, ny=4, nz=4)
    model = rt.SolidModel(mesh, rt.Material(E=3e4, nu=0.45, density=1000.0), element="tet4")
    model.fix("x0")
    X = np.asarray(model.mesh.vertices)
    top = np.flatnonzero(np.isclose(X[:, 2], X[:, 2].max()))
    p = int(top[np.argmin(np.linalg.norm(X[top, :2] - [0.07, 0.02], axis=1))])
    sim = rt.DirectSimulator(model, dt, rt.Damping(alpha=alpha), large_deformation=True)
    return model, sim, X, p


def test_a_still_hand_settles_on_the_full_orders_static_equilibrium():
    """The physics thread (unpaced) settles the block under a hand 6 mm into its top; the force the hand
    feels then, put on the vertex as a dead load in rt.nonlinear.solve_static (another algorithm: Newton
    on the static equations), moves the vertex to where the spring law k (n . u_p - g) gives that force
    back (measured to 2.5e-9 of it; the linear model is 14 % off, so the check sees the nonlinearity)."""
    model, sim, X, p = _block()
    n = model.mesh.vertex_normals()[p]
    c = X[p] - 0.006 * n
    with rt.MultiRateProbe(model.mesh, sim, stiffness=K, pace=False) as probe:
        t0 = time.perf_counter()
        while sim.time < 1.5 and time.perf_counter() - t0 < 120:  # 1.5 s of simulated time: 22 decay times
            f = probe.update(c)
            time.sleep(1e-3)
        assert probe.error is None and probe.contact_node == p
        f = probe.update(c)
    lam = float(np.linalg.norm(f))
    assert lam > 0.1 and np.allclose(f / lam, n, atol=1e-12)  # N: pushed back along the outward normal
    g = float(n @ (c - X[p]))
    u = rt.nonlinear.solve_static(model, {p: tuple(-f)}).displacements
    assert abs(K * (float(n @ u[p]) - g) - lam) < 1e-6 * lam
    linear = model.solve_static({p: tuple(-f)})
    assert abs(K * (float(n @ linear[p]) - g) - lam) > 0.05 * lam


def test_a_tick_renders_the_force_the_next_physics_step_takes_and_follows_the_hand_between_steps():
    """thread=False: the physics advances only when called, so a tick's snapshot is known. At a still
    hand the force of a tick equals the force the next physics step is stepped with (both the Probe's
    implicit formula at the same linearization; measured equal to the bit); a hand moved by d along the normal between
    two steps changes the tick's force by d / (n^T W n + 1/k), W the driver's step compliance at the
    vertex, asked of the driver itself here (measured to 7e-15; the stiff surface the hand feels between
    steps)."""
    model, sim, X, p = _block(dt=1e-3, alpha=10.0)
    n = model.mesh.vertex_normals()[p]
    probe = rt.MultiRateProbe(model.mesh, sim, stiffness=K, thread=False)
    for k in range(40):  # a press 4 mm in over 40 steps, two ticks a step
        c = X[p] - 1e-4 * (k + 1) * n
        probe.update(c)
        f_tick = probe.update(c)
        probe.physics_step()
        if k > 2:
            assert np.allclose(probe.physics.force, f_tick, rtol=1e-9, atol=1e-12), (k, probe.physics.force, f_tick)
    assert probe.contact_node == p and np.linalg.norm(f_tick) > 0.05
    W = np.asarray(sim.step_compliance(p))
    d = 2e-4
    f0, f1 = probe.update(c), probe.update(c - d * n)
    expected = d / (float(n @ W @ n) + 1.0 / K)
    assert abs(float(n @ (f1 - f0)) - expected) < 1e-9 * expected
    assert float(n @ W @ n) > 0.01 / K  # the organ's compliance matters: it is not the spring alone
    probe.close()


def test_in_a_haptic_loop_the_force_is_finite_and_the_ticks_outrun_the_physics():
    """A 1 kHz HapticLoop (Python ticks) presses and drags the block; the physics thread steps at its
    own rate. What is asserted is what the rate cannot change: finite forces, contact made, more ticks
    than physics steps (benchmarks/haptic_fullorder.py measures the times)."""
    model, sim, X, p = _block(dt=5e-3)  # paced: at most 240 physics steps in the 1.2 s, against ~1,200 ticks
    n = model.mesh.vertex_normals()[p]

    def hand(t):
        return X[p] + (0.002 - 0.006 * min(1.0, t / 0.5)) * n + [0.01 * max(0.0, t - 0.5), 0.0, 0.0]
    device = rt.ScriptedDevice(hand)
    probe = rt.MultiRateProbe(model.mesh, sim, stiffness=K)
    stats = rt.HapticLoop(probe, device, rate=1000.0).run(1.2)
    probe.close()
    F = np.array(device.forces)
    assert np.isfinite(F).all() and np.linalg.norm(F, axis=1).max() > 0.05
    assert probe.physics_steps > 0 and stats.steps > probe.physics_steps
    assert probe.stats()["time_ratio"] <= 1.0 + 0.05  # paced: the simulated time never ahead of the wall's


class _Failing:
    """A Driver (the protocol, delegated) whose step raises from its 5th call."""

    def __init__(self, inner):
        self.inner, self.calls = inner, 0

    def __getattr__(self, name):
        return getattr(self.inner, name)

    def step(self, forces=None):
        self.calls += 1
        if self.calls >= 5:
            raise rt.SolverError("step refused: an element turned inside out")
        self.inner.step(forces)


def test_a_failing_physics_step_ends_in_zero_force_with_the_reason():
    model, sim, X, p = _block()
    n = model.mesh.vertex_normals()[p]
    probe = rt.MultiRateProbe(model.mesh, _Failing(sim), stiffness=K, pace=False)
    with pytest.raises(rt.ModelError, match="physics step failed.*inside out"):
        t0 = time.perf_counter()
        while time.perf_counter() - t0 < 30:
            probe.update(X[p] - 0.003 * n)
            time.sleep(1e-3)
    assert np.all(probe.force == 0.0) and "inside out" in probe.stop_reason
    with pytest.raises(rt.ModelError, match="inside out"):  # and stays stopped
        probe.update(X[p] - 0.003 * n)
    assert np.all(probe.force == 0.0)


def test_a_grasp_ticks_the_jaws_force_of_the_next_physics_step_and_settles_on_the_static_equilibrium():
    """rt.MultiRateGrasp, thread=False: a jaw closed on a 12 mm patch of the block's top pulled 8 mm up.
    Each tick's force is the force the next physics step takes (the jaw's implicit formula at the same
    free step and cross compliances; equal to the bit). Settled, the held vertices' forces put as dead
    loads in rt.nonlinear.solve_static give displacements for which every grip spring's jaw translation
    f_i / grip + (u_i - u_i at the grab) is the same, and the grasp spring pulls the total force
    (k (target - jaw - translation)): the tool's own equations, on the static state of another algorithm
    (the translations agree to 7e-10, the pull to 1e-8; with the linear model's displacements 1.4 % and 21 %)."""
    model, sim, X, p = _block()
    grasp = rt.MultiRateGrasp(model.mesh, sim, stiffness=K, radius=0.012, thread=False)
    held = grasp.grab(p)
    assert held.size > 3 and grasp.node == p
    jaw = X[p].copy()
    z = np.array([0.0, 0.0, 1.0])
    for k in range(700):
        c = jaw + 0.008 * min(1.0, (k + 1) / 100) * z
        f_tick = grasp.update(c)
        grasp.physics_step()
        if k > 2:
            assert np.allclose(grasp.physics.force, f_tick, rtol=1e-9, atol=1e-12), (k, grasp.physics.force, f_tick)
    f = grasp.update(c)
    forces = grasp.physics.forces
    assert f[2] > 0.5 and np.allclose(forces.sum(axis=0), f, rtol=1e-9)  # N: upwards, the jaw's total
    u = rt.nonlinear.solve_static(model, {int(v): tuple(g) for v, g in zip(held.tolist(), forces)}).displacements
    hold = grasp.physics._hold.reshape(-1, 3)
    delta = forces / grasp.physics.grip + (u[held] - hold)
    assert np.abs(delta - delta.mean(axis=0)).max() < 1e-6 * np.linalg.norm(delta.mean(axis=0))
    assert np.allclose(K * (c - jaw - delta.mean(axis=0)), f, rtol=1e-6, atol=1e-9)
    grasp.release()
    assert grasp.node is None and np.all(grasp.update(c) == 0.0)


def test_bad_arguments_are_refused_in_words_and_change_nothing():
    """The multi-rate tools and the error estimate refuse nonsense with an RtfemError that names it; the
    driver is not stepped by a refused call."""
    model, sim, X, p = _block()
    for bad in (dict(rate=0.0), dict(rate=float("nan")), dict(stiffness=-1.0), dict(pace="yes"), dict(thread=2)):
        with pytest.raises(rt.ModelError):
            rt.MultiRateProbe(model.mesh, sim, **bad)
    with pytest.raises(rt.ModelError, match="radius"):
        rt.MultiRateGrasp(model.mesh, sim, radius=-0.01)
    with pytest.raises(rt.ModelError):
        rt.MultiRateProbe(model.mesh, object())
    probe = rt.MultiRateProbe(model.mesh, sim, thread=False)
    with pytest.raises(rt.ModelError, match="no hand position"):
        probe.physics_step()
    with pytest.raises(rt.ModelError):
        probe.update([np.nan, 0.0, 0.0])
    assert sim.steps == 0 and np.all(probe.force == 0.0)
    U = np.zeros((model.n_nodes, 3))
    for args, kw in (((U[:-1],), {}), ((U, np.full((model.n_nodes, 3), np.inf)), {}), ((U,), dict(iterations=0)),
                     ((U,), dict(held=[model.n_nodes])), ((U,), dict(inertia=np.zeros(3)))):
        with pytest.raises(rt.ModelError):
            rt.error_estimate(model, *args, **kw)
    with pytest.raises(rt.ModelError, match="nonlinear"):
        rt.error_estimate(object(), U)
