import numpy as np
import pytest

import rtfem as rt


@pytest.fixture(scope="module")
def organ(liver3_modes):
    model, basis = liver3_modes
    mesh = model.mesh
    node = mesh.groups["probe"][0]
    n = mesh.vertex_normals()[node]
    G = np.stack([model.solve_static({node: e})[node] for e in np.eye(3)], axis=1)  # static point compliance
    return mesh, model, basis, node, n, G


def press(probe, X, n, depth, steps, ramp=200):
    target = X - depth * n
    forces = np.empty(steps)
    for k in range(steps):
        s = min(1.0, (k + 1) / ramp)
        forces[k] = np.linalg.norm(probe.update(X + 0.002 * n * (1 - s) + (target - X) * s))
    return forces


@pytest.mark.parametrize("coupling", ["spring", "constraint"])
def test_held_contact_is_passive_and_settles_to_the_static_force(organ, coupling):
    mesh, model, basis, node, n, G = organ
    sim = rt.ModalSimulator(basis, 1e-3, rt.Damping(alpha=8.0), static_correction=True)
    k = 200.0
    probe = rt.Probe(mesh, sim, coupling=coupling, stiffness=k)
    depth = 0.004
    F = press(probe, np.asarray(mesh.vertices)[node], n, depth, 60_000)  # 60 s of simulated time
    static = depth / (n @ G @ n + (1 / k if coupling == "spring" else 0.0))
    assert F[-1] == pytest.approx(static, rel=1e-6)
    assert F.max() < 1.5 * static  # no blow-up, only the overshoot of the ramp
    assert np.abs(np.diff(F[-1000:])).max() < 1e-9  # settled
    assert probe.contact_node == node


def test_no_contact_no_force(organ):
    mesh, model, basis, node, n, _ = organ
    sim = rt.ModalSimulator(basis, 1e-3)
    probe = rt.Probe(mesh, sim, radius=0.002)
    outside = np.asarray(mesh.vertices)[node] + 0.003 * n
    assert np.all(probe.update(outside) == 0) and probe.contact_node is None
    assert sim.energy() == 0.0


def test_impedance_map_driver_renders_the_static_force(organ):
    mesh, model, _, node, n, G = organ
    imap = rt.ImpedanceMap.build(model, rt.Damping(alpha=8.0), nodes=[node], times=[0.01, 0.1], n_modes=20)
    probe = rt.Probe(mesh, imap, coupling="constraint")
    f = probe.update(np.asarray(mesh.vertices)[node] - 0.003 * n)
    assert np.linalg.norm(f) == pytest.approx(0.003 / (n @ G @ n), rel=1e-9)
    assert np.allclose(f / np.linalg.norm(f), n)  # the probe is pushed back out
    u = probe.displacements()
    assert np.allclose(u, model.solve_static({node: -f}), rtol=0, atol=1e-10 * np.abs(u).max())
    near = np.array([node, 0, 5])
    assert np.allclose(imap.compliance_at(node, near) @ -f, u[near], rtol=0, atol=1e-12)


def test_loop_runs_on_its_own_thread_and_reports(organ):
    mesh, model, basis, node, n, _ = organ
    sim = rt.ModalSimulator(basis, 1e-3, rt.Damping(alpha=8.0), static_correction=True)
    X = np.asarray(mesh.vertices)[node]
    device = rt.ScriptedDevice(lambda t: X - min(t / 0.1, 1.0) * 0.003 * n)
    probe = rt.Probe(mesh, sim)
    assert probe.prepare(around=X, radius=0.01) >= 1
    assert node in probe._W
    loop = rt.HapticLoop(probe, device, rate=1000.0)
    stats = loop.run(0.3)
    # an absolute schedule never runs ahead of the clock
    assert 1 <= stats.steps <= 301 and len(stats.compute) == stats.steps == len(device.forces)
    assert stats.peak_force > 0 and np.isfinite(stats.jitter)
    assert "Hz achieved" in str(stats)
    got = []
    cb = rt.CallbackDevice(lambda: X + 0.01 * n, got.append)
    rt.HapticLoop(rt.Probe(mesh, sim), cb, rate=2000.0).run(0.01)
    assert got and np.all(np.asarray(got) == 0)


def test_loop_surfaces_errors_and_bad_input(organ):
    mesh, model, basis, node, n, _ = organ
    sim = rt.ModalSimulator(basis, 1e-3)
    probe = rt.Probe(mesh, sim)
    with pytest.raises(rt.ModelError, match="finite"):
        probe.update([np.nan, 0, 0])
    bad = rt.ScriptedDevice(lambda t: [np.nan, 0.0, 0.0])
    with pytest.raises(rt.ModelError):
        rt.HapticLoop(probe, bad).run(0.01)
    with pytest.raises(rt.ModelError, match="the probe drives a ModalSimulator"):
        rt.Probe(mesh, model)
    with pytest.raises(rt.ModelError, match="coupling"):
        rt.Probe(mesh, sim, coupling="glue")
    with pytest.raises(rt.ModelError, match="rate"):
        rt.HapticLoop(probe, bad, rate=0)


def test_a_loop_that_cannot_keep_its_rate_skips_ticks_and_says_so():
    """A probe whose update takes 3 ms at 1 kHz: no burst of owed ticks, the skipped ones
    counted, the achieved rate the real one (about 1 / 3 ms), every tick started within a
    period of its slot, and the device's time the wall time."""
    import time as _time

    class SlowProbe:
        driver = None

        def update(self, position):
            _time.sleep(0.003)
            return np.zeros(3)

    device = rt.ScriptedDevice(lambda t: np.zeros(3))
    stats = rt.HapticLoop(SlowProbe(), device, rate=1000.0).run(0.3)
    assert stats.behind and stats.missed >= 150  # ~2 of every 3 slots
    assert 150 <= stats.rate <= 360  # Hz: what was achieved, not the 1 kHz asked for
    assert max(stats.lateness) < 1e-3  # no tick runs on a slot more than a period old
    assert "FELL BEHIND" in str(stats)
    times = np.array(device.times)
    assert np.all(np.diff(times) >= 2e-3 - 1e-12)  # the device saw the skipped time, not a burst
    assert stats.steps + stats.missed == pytest.approx(300, abs=6)
