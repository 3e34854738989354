"""The compiled haptic loop (issue 12): every probe tick in compiled code without the GIL.

Its ticks are checked against the Python Probe.update tick by tick (same forces and states to
round-off), on the positions the loop actually ran; the schedule bookkeeping (slots, skipped
ticks, period errors) against hand-made records. No assertion here is about speed: the rates
and percentiles are measured by benchmarks/haptic_loop.py."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

import rtfem as rt
from rtfem.interaction.ticks import _compiled_loop

needs_loop = pytest.mark.skipif(_compiled_loop() is None, reason="the compiled loop needs numba (rtfem[fast])")


@pytest.fixture(scope="module")
def organ(liver3_modes):
    model, basis = liver3_modes
    mesh = model.mesh
    node = int(mesh.groups["probe"][0])
    return mesh, basis, node, np.asarray(mesh.vertices), mesh.vertex_normals()


def press_and_slide(X, N, node, steps=1500, depth=0.004):
    """Press at the probe vertex, slide 1 cm sideways, back out and come down elsewhere."""
    t = np.arange(steps) / steps
    tang = np.cross(N[node], [0.0, 0.0, 1.0])
    tang /= np.linalg.norm(tang)
    d = depth * np.clip(np.minimum(t / 0.1, (0.8 - t) / 0.1), -0.5, 1.0)
    slide = 0.01 * np.clip((t - 0.2) / 0.5, 0.0, 1.0)
    return X[node] - d[:, None] * N[node] + slide[:, None] * tang


def sim_for(basis, **kw):
    return rt.ModalSimulator(basis, 1e-3, rt.Damping(alpha=8.0), static_correction=True, **kw)


@needs_loop
@pytest.mark.parametrize("integrator", ["exact", "newmark"])
@pytest.mark.parametrize("coupling", ["spring", "constraint"])
def test_compiled_ticks_are_the_python_ticks(organ, integrator, coupling):
    mesh, basis, node, X, N = organ
    P = press_and_slide(X, N, node)
    runs = {}
    for compiled in (True, False):
        sim = sim_for(basis, integrator=integrator)
        probe = rt.Probe(mesh, sim, coupling=coupling, radius=0.0005)
        F = probe.replay(P, compiled=compiled)
        runs[compiled] = (F, sim.get_state(), sim.displacements(), probe.contact_node, sim.steps, sorted(probe._W))
    (Fc, Sc, Uc, pc, kc, Wc), (Fp, Sp, Up, pp, kp, Wp) = runs[True], runs[False]
    assert np.abs(Fp).max() > 0.05  # the press made contact
    assert np.abs(Fc - Fp).max() <= 1e-12 * np.abs(Fp).max()
    for key in Sp:
        assert np.allclose(Sc[key], Sp[key], rtol=0, atol=1e-12 * max(np.abs(Sp[key]).max(), 1e-300))
    assert np.abs(Uc - Up).max() <= 1e-12 * np.abs(Up).max() + 1e-300
    assert pc == pp and kc == kp == len(P)
    assert Wc == Wp and len(Wc) >= 1  # vertices first touched were prepared on the way (no prepare call)


@needs_loop
def test_the_compiled_loop_runs_what_it_records(organ):
    """A compiled 1 kHz loop: the forces it handed the device are those of Python ticks at the
    slots it ran (whatever the machine skipped), and slots + skipped cover the schedule."""
    mesh, basis, node, X, N = organ
    P = press_and_slide(X, N, node, steps=300)
    device = rt.ScriptedDevice(lambda t: P[min(int(round(t * 1000)), len(P) - 1)])
    sim = sim_for(basis)
    probe = rt.Probe(mesh, sim)
    probe.prepare(around=X[node], radius=0.01)
    loop = rt.HapticLoop(probe, device, rate=1000.0)
    assert loop.compiled
    stats = loop.run(0.3)
    assert stats.compiled and "compiled loop" in str(stats)
    assert stats.steps == len(stats.compute) == len(stats.lateness) == len(stats.slots) == len(device.forces)
    assert stats.steps + stats.missed == 300 and np.all(np.diff(stats.slots) >= 1)
    assert np.allclose(device.times, np.array(stats.slots) * 1e-3, rtol=0, atol=1e-15)
    assert sim.steps == stats.steps
    twin = rt.Probe(mesh, sim_for(basis))
    expected = twin.replay(P[np.array(stats.slots)], compiled=False)
    assert np.abs(np.array(device.forces) - expected).max() <= 1e-12 * np.abs(expected).max()
    assert stats.peak_force == pytest.approx(np.linalg.norm(expected, axis=1).max(), rel=1e-12)
    np.testing.assert_allclose(probe.force, expected[-1], rtol=0, atol=1e-12 * np.abs(expected).max())


@needs_loop
def test_a_shared_device_is_read_without_the_gil(organ):
    """Another Python thread moves a SharedDevice while the compiled loop runs and a third
    keeps the GIL busy: the loop still sees the moves (it reads the shared array each tick)
    and hands back the contact force through it."""
    mesh, basis, node, X, N = organ
    device = rt.SharedDevice(X[node] + 0.002 * N[node])
    probe = rt.Probe(mesh, sim_for(basis))
    probe.prepare([node])
    loop = rt.HapticLoop(probe, device, rate=2000.0).start()
    # the loop thread prepares in Python (and compiles in a fresh process) before its first tick:
    # let it get there before another thread takes the GIL (under the hog a cold start took 0.2 s)
    time.sleep(0.5)
    stop = threading.Event()

    def hog():  # pure-Python work: holds the GIL between switch intervals
        x = 0
        while not stop.is_set():
            x += 1

    hogger = threading.Thread(target=hog)
    hogger.start()
    try:
        time.sleep(0.05)
        assert np.all(device.force == 0)
        device.move_to(X[node] - 0.003 * N[node])
        time.sleep(0.2)
        pressed = device.force
    finally:
        stop.set()
        hogger.join()
        stats = loop.stop()
    assert pressed @ N[node] > 0.01  # pushed back out along the normal
    assert stats.compiled and stats.steps > 100 and probe.contact_node == node
    with pytest.raises(rt.ModelError, match="device position"):
        device.move_to([np.nan, 0, 0])


def pull(X, N, node, steps=600):
    """The hand pulls the grabbed vertex 2 cm out along its normal and 1 cm sideways, then back."""
    t = np.arange(steps) / steps
    tang = np.cross(N[node], [0.0, 0.0, 1.0])
    tang /= np.linalg.norm(tang)
    s = np.sin(np.pi * t)[:, None]
    return X[node] + s * (0.02 * N[node] + 0.01 * tang)


@needs_loop
@pytest.mark.parametrize("integrator", ["exact", "newmark"])
@pytest.mark.parametrize("radius", [0.0, 0.02])
def test_compiled_grasp_ticks_are_the_python_ticks(organ, integrator, radius):
    """Grasp ticks in the compiled loop (the jaw's system inverted once) against Grasp.update, for
    one vertex and a patch, with a force cap reached on the way."""
    mesh, basis, node, X, N = organ
    P = pull(X, N, node)
    runs = {}
    for compiled in (True, False):
        sim = sim_for(basis, integrator=integrator)
        grasp = rt.Grasp(mesh, sim, stiffness=300.0, radius=radius, max_force=0.4)
        held = grasp.grab(node)
        F = grasp.replay(P, compiled=compiled)
        runs[compiled] = (F, sim.get_state(), sim.displacements(), grasp.forces.copy(), sim.steps, held.size)
    (Fc, Sc, Uc, fc, kc, mc), (Fp, Sp, Up, fp, kp, mp) = runs[True], runs[False]
    assert mc == mp and (mc > 2) == (radius > 0)
    norms = np.linalg.norm(Fp, axis=1)
    assert norms.max() == pytest.approx(0.4) and np.median(norms) > 0.1  # pulled hard enough to reach the cap
    assert np.abs(Fc - Fp).max() <= 1e-10 * norms.max()
    for key in Sp:
        assert np.allclose(Sc[key], Sp[key], rtol=0, atol=1e-10 * max(np.abs(Sp[key]).max(), 1e-300))
    assert np.abs(Uc - Up).max() <= 1e-10 * np.abs(Up).max() and np.abs(fc - fp).max() <= 1e-10 * norms.max()
    assert kc == kp == len(P)


@needs_loop
def test_a_grab_during_a_compiled_loop_pauses_its_ticks(organ):
    """grab() and release() from another thread while a compiled loop runs a Grasp: its ticks stop
    for the new grip and go on with it (the slots meanwhile are skipped, not burst through)."""
    mesh, basis, node, X, N = organ
    sim = sim_for(basis)
    grasp = rt.Grasp(mesh, sim, stiffness=300.0)
    device = rt.SharedDevice(X[node] + 0.01 * N[node])
    loop = rt.HapticLoop(grasp, device, rate=2000.0)
    assert loop.compiled
    loop.start()
    try:
        time.sleep(0.05)
        assert np.all(device.force == 0)  # nothing held: no force
        grasp.grab(node)
        time.sleep(0.1)
        pulling = device.force.copy()
        grasp.release()
        time.sleep(0.05)
        after = device.force.copy()
    finally:
        stats = loop.stop()
    assert stats.compiled and stats.steps > 100
    assert pulling @ N[node] > 0.05  # the organ is pulled out along the normal
    assert np.all(after == 0) and np.all(grasp.force == 0) and grasp.node is None
    assert sim.steps == stats.steps


@pytest.fixture(scope="module")
def organ_map(liver3_modes, organ):
    """A quasi-static impedance map of the vertices within 3 cm of the probe vertex (the press
    and slide stay on them), from the same modes."""
    model, basis = liver3_modes
    mesh, _, node, X, N = organ
    near = np.flatnonzero(np.linalg.norm(X - X[node], axis=1) < 0.03)
    return rt.ImpedanceMap.build(model, rt.Damping(alpha=8.0), nodes=near, radius=0.04, modes=basis, times=(0.01,))


@needs_loop
def test_compiled_impedance_ticks_are_the_python_ticks(organ, organ_map):
    """The impedance-map driver (quasi-static) in the compiled loop: its ticks are the modal ones
    with no modes. Probe (both couplings, stopped in contact and after release) and Grasp (one
    vertex and a patch) against the Python ticks: forces, the driver's loads and field, steps."""
    mesh, _, node, X, N = organ
    P = press_and_slide(X, N, node, steps=600)
    H = pull(X, N, node, steps=300) * 0.5 + 0.5 * X[node]  # a 1 cm pull: the map's static responses
    cases = [("probe", c, P[:n]) for c in ("spring", "constraint") for n in (300, 600)]
    cases += [("grasp", r, H) for r in (0.0, 0.01)]
    for tool, option, path in cases:
        runs = {}
        for compiled in (True, False):
            driver = organ_map.as_driver(1e-3)
            if tool == "probe":
                obj = rt.Probe(mesh, driver, coupling=option, radius=0.0005)
            else:
                obj = rt.Grasp(mesh, driver, stiffness=300.0, radius=option, max_force=0.12)
                obj.grab(node)
            F = obj.replay(path, compiled=compiled)
            runs[compiled] = (F, driver.displacements(), driver.steps, dict(driver._loads), obj.force.copy())
        (Fc, Uc, kc, Lc, fc), (Fp, Up, kp, Lp, fp) = runs[True], runs[False]
        scale = np.abs(Fp).max()
        assert scale > 0.05, (tool, option)  # pressed or pulled for real
        assert np.abs(Fc - Fp).max() <= 1e-12 * scale and np.abs(fc - fp).max() <= 1e-12 * scale
        assert kc == kp == len(path) and sorted(Lc) == sorted(Lp)
        assert all(np.abs(Lc[v] - Lp[v]).max() <= 1e-12 * scale for v in Lp)
        assert np.abs(Uc - Up).max() <= 1e-12 * max(np.abs(Up).max(), 1e-300)
        if tool == "probe":
            assert (len(path) == 300) == bool(Lp)  # in contact mid-slide, released at the end


@needs_loop
def test_a_compiled_impedance_loop_shows_its_load_while_it_runs(organ, organ_map):
    """A drawing thread reads the impedance driver's field while the compiled ticks run: it is the
    static response G_pp f to the force the loop hands the device (quasi-static: constant under a
    held press). Stopped, the driver keeps that load."""
    mesh, _, node, X, N = organ
    driver = organ_map.as_driver(1e-3)
    device = rt.SharedDevice(X[node] - 0.003 * N[node])
    probe = rt.Probe(mesh, driver)
    probe.prepare([node])
    loop = rt.HapticLoop(probe, device, rate=2000.0)
    assert loop.compiled
    loop.start()
    try:
        time.sleep(0.3)
        u, f = driver.displacement(node), device.force.copy()
    finally:
        stats = loop.stop()
    assert stats.compiled and stats.steps > 100 and f @ N[node] > 0.05
    expected = organ_map.point_compliance(node) @ -f
    assert np.abs(u - expected).max() <= 1e-12 * np.abs(expected).max()
    assert list(driver._loads) == [node] and np.abs(driver._loads[node] + f).max() <= 1e-15
    assert driver.steps == stats.steps


def test_compiled_impedance_refusals_say_why(organ, organ_map):
    """A dynamic map's force history is Python: its ticks run in Python (refused when compiled=True
    is asked). A driver holding loads the probe did not apply: Python ticks too (the compiled
    search takes the surface at rest)."""
    mesh, _, node, X, N = organ
    dynamic = rt.Probe(mesh, organ_map.as_driver(1e-3, dynamic=True))
    assert not rt.HapticLoop(dynamic, rt.SharedDevice()).compiled
    with pytest.raises(rt.ModelError, match="dynamic"):
        rt.HapticLoop(dynamic, rt.SharedDevice(), compiled=True)
    if _compiled_loop() is None:
        return
    driver = organ_map.as_driver(1e-3)
    probe = rt.Probe(mesh, driver)
    other = int(organ_map.loaded[organ_map.loaded != node][0])
    driver.step({other: (0.0, 0.0, -0.05)})
    with pytest.raises(rt.ModelError, match="loads the probe did not apply"):
        probe.replay(np.tile(X[node] + 0.01 * N[node], (3, 1)), compiled=True)
    assert driver.steps == 1  # refused before any tick
    with pytest.raises(rt.ModelError, match="loads the probe did not apply"):
        rt.HapticLoop(probe, rt.SharedDevice(), compiled=True).start()
    stats = rt.HapticLoop(probe, rt.SharedDevice(X[node] + 0.01 * N[node])).run(0.02)
    assert not stats.compiled and stats.steps >= 1 and not driver._loads  # Python ticks; the probe's own loads now


def test_compiled_refusals_say_why(organ):
    mesh, basis, node, X, N = organ
    sim = sim_for(basis)
    grasp = rt.Grasp(mesh, rt.ModalSimulator(basis, 1e-3, warping=True))  # compliances follow the motion
    with pytest.raises(rt.ModelError, match="compiled=True"):
        rt.HapticLoop(grasp, rt.SharedDevice(), compiled=True)
    assert not rt.HapticLoop(grasp, rt.SharedDevice()).compiled  # auto: the Python loop
    with pytest.raises(rt.ModelError, match=r"\(k, 3\) array of hand"):
        grasp.replay(np.zeros((4, 2)))
    with pytest.raises(rt.ModelError, match="compiled=True"):
        grasp.replay(np.zeros((4, 3)), compiled=True)
    assert grasp.driver.steps == 0  # refused before any tick
    slow = rt.ModalSimulator(basis, 1e-3)
    slow.compiled = False
    assert not rt.HapticLoop(rt.Probe(mesh, slow), rt.SharedDevice()).compiled
    if _compiled_loop() is not None:
        scripted = rt.ScriptedDevice(lambda t: X[node] + 0.01 * N[node])
        with pytest.raises(rt.ModelError, match="seconds="):
            rt.HapticLoop(rt.Probe(mesh, sim), scripted, compiled=True).start(max_steps=10)
        auto = rt.HapticLoop(rt.Probe(mesh, sim), scripted)  # open-ended and scripted: Python ticks
        assert auto.compiled
        stats = auto.start(max_steps=5).stop()
        assert not stats.compiled
    with pytest.raises(rt.ModelError, match=r"\(k, 3\)"):
        rt.Probe(mesh, sim).replay(np.zeros((4, 2)))


def test_period_errors_use_adjacent_slots_only():
    from rtfem.interaction.loop import LoopStats

    st = LoopStats(lateness=[0.0, 2e-6, 1e-6, 9e-6, 5e-6], slots=[0, 1, 2, 5, 6], compute=[1e-6] * 5, steps=5)
    assert np.allclose(st.period_errors(), [2e-6, 1e-6, 4e-6], rtol=0, atol=1e-18)  # 2 -> 5 is a gap
    assert st.period_error(100) == pytest.approx(4e-6)
    assert np.isnan(LoopStats().period_error(99))


def test_a_compiled_loop_leaves_blas_a_core_fewer():
    threadpoolctl = pytest.importorskip("threadpoolctl")
    import os

    from rtfem.interaction.loop import _spare_core

    np.ones((64, 64)) @ np.ones((64, 64))  # numpy's BLAS is loaded
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    before = {p["filepath"]: p["num_threads"] for p in threadpoolctl.threadpool_info()}
    with _spare_core():
        inside = threadpoolctl.threadpool_info()
        assert inside and all(p["num_threads"] <= max(1, cores - 1) for p in inside)
    assert {p["filepath"]: p["num_threads"] for p in threadpoolctl.threadpool_info()} == before  # restored


def test_a_tick_that_overruns_the_end_leaves_no_slot_uncounted():
    """A Python-tick loop whose 40th tick takes 30 ms: the loop wakes after its 50 ms end with slots
    still due; they are skipped and counted, so steps + skipped cover the schedule (they were lost)."""
    mesh = rt.meshes.plate(0.2, 0.2, 4, 4)
    model = rt.ShellModel(mesh, rt.Material())
    model.fix(mesh.boundary_vertices())
    tc = rt.ToolContact(mesh, rt.ModalSimulator(rt.modal_analysis(model, 4), 1e-3, rt.Damping(alpha=5.0)))
    update, calls = tc.update, []

    def slow(p):
        calls.append(p)
        if len(calls) == 40:
            time.sleep(0.03)
        return update(p)

    tc.update = slow
    stats = rt.HapticLoop(tc, rt.ScriptedDevice(lambda t: np.array([0.1, 0.1, 0.05])), rate=1000.0).run(0.05)
    assert not stats.compiled and stats.missed >= 1
    assert stats.steps + stats.missed == 50 and stats.steps == len(calls)
