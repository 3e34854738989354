"""The Driver protocol (issue 11): a driver written here, knowing nothing of rtfem's simulators,
works with Probe, Grasp and HapticLoop, and the forces match the closed form.

The driver is a Winkler bed: every node sits on its own spring of stiffness k in each
direction, massless (quasi-static), so u = f / k at the loaded node, predict(node) = 0 and
W = I / k. A probe coupled through a spring k_s pressed a depth d into the surface then
feels the series stiffness: |F| = d k k_s / (k + k_s); a grasp pulling its vertex by a
distance s feels the same series law.
"""

from __future__ import annotations

import numpy as np
import pytest

import rtfem as rt
from rtfem.drivers.base import DRIVER_MEMBERS, Driver


class WinklerBed:
    """Independent massless springs, one per node: the smallest thing that is a Driver."""

    def __init__(self, n_nodes: int, k: float, dt: float = 1e-3) -> None:
        self.n_nodes, self.k, self.dt = n_nodes, k, dt
        self.time, self.steps = 0.0, 0
        self.u = np.zeros((n_nodes, 3))

    def step(self, forces=None) -> None:
        u = np.zeros_like(self.u)
        for node, f in (forces or {}).items():
            u[node] += np.asarray(f, float) / self.k
        self.u = u
        self.steps += 1
        self.time = self.steps * self.dt

    def predict(self, node):
        return np.zeros(3)

    def step_compliance(self, node):
        return np.eye(3) / self.k

    def displacement(self, node):
        return self.u[node].copy()

    def displacements(self):
        return self.u.copy()

    def reset(self) -> None:
        self.u[:] = 0.0
        self.time, self.steps = 0.0, 0

    def get_state(self):
        return {"u": self.u.copy(), "steps": self.steps}

    def set_state(self, state) -> None:
        self.u, self.steps = state["u"].copy(), state["steps"]
        self.time = self.steps * self.dt


K_BED, K_TOOL, DEPTH = 300.0, 200.0, 0.004
SERIES = K_BED * K_TOOL / (K_BED + K_TOOL)


@pytest.fixture(scope="module")
def organ():
    mesh = rt.meshes.liver(2)
    node = int(np.argmax(np.asarray(mesh.vertices)[:, 2]))  # the top of the dome: normal nearly +z
    return mesh, node


def test_the_simulators_and_the_map_driver_satisfy_the_protocol(organ):
    mesh, node = organ
    model = rt.ShellModel(mesh, rt.Material()).fix("attachment")
    modes = rt.modal_analysis(model, 6)
    imap = rt.ImpedanceMap.build(model, nodes=[node], modes=modes)
    for d in (rt.ModalSimulator(modes, 1e-3), rt.DirectSimulator(model, 1e-3), imap.as_driver(), WinklerBed(3, 1.0)):
        assert isinstance(d, Driver), type(d).__name__
        assert all(hasattr(d, m) for m in DRIVER_MEMBERS)


def test_a_probe_on_a_users_driver_feels_the_series_stiffness(organ):
    mesh, node = organ
    bed = WinklerBed(mesh.n_vertices, K_BED)
    probe = rt.Probe(mesh, bed, stiffness=K_TOOL)
    X, n = np.asarray(mesh.vertices)[node], mesh.vertex_normals()[node]
    f = probe.update(X - DEPTH * n)
    assert probe.contact_node == node
    np.testing.assert_allclose(f, DEPTH * SERIES * n, rtol=1e-12)
    # the organ moved by f / k at the contact, nowhere else
    u = bed.displacements()
    np.testing.assert_allclose(u[node], -f / K_BED, rtol=1e-12)
    assert np.count_nonzero(np.abs(u).sum(axis=1)) == 1


def test_a_grasp_on_a_users_driver_pulls_with_the_series_stiffness(organ):
    mesh, node = organ
    bed = WinklerBed(mesh.n_vertices, K_BED)
    grasp = rt.Grasp(mesh, bed, stiffness=K_TOOL)
    grasp.grab(node)
    pull = np.array([0.003, -0.002, 0.005])
    f = grasp.update(np.asarray(mesh.vertices)[node] + pull)
    np.testing.assert_allclose(f, SERIES * pull, rtol=1e-12)
    np.testing.assert_allclose(bed.displacement(node), f / K_BED, rtol=1e-12)


def test_a_haptic_loop_runs_a_users_driver(organ):
    mesh, node = organ
    X, n = np.asarray(mesh.vertices)[node], mesh.vertex_normals()[node]
    probe = rt.Probe(mesh, WinklerBed(mesh.n_vertices, K_BED), stiffness=K_TOOL)
    device = rt.ScriptedDevice(lambda t: X - DEPTH * n)
    stats = rt.HapticLoop(probe, device, rate=1000).run(0.05)
    assert stats.steps >= 10
    np.testing.assert_allclose(np.linalg.norm(device.forces, axis=1), DEPTH * SERIES, rtol=1e-12)


def test_an_object_that_is_not_a_driver_is_refused_naming_what_it_lacks(organ):
    mesh, _ = organ

    class Half:
        n_nodes, dt, time = mesh.n_vertices, 1e-3, 0.0

        def step(self, forces=None):
            pass

    with pytest.raises(rt.RtfemError, match="lacks predict"):
        rt.Probe(mesh, Half())


def test_the_viewer_session_runs_a_users_driver(organ):
    """The Session grabs, steps and draws through the protocol only: the grasp force on the
    bed is the series law and the drawn field is the bed's."""
    from rtfem.viewer.session import Session, Settings

    mesh, node = organ
    session = Session(mesh, settings=Settings(n_modes=4, grasp_stiffness=K_TOOL, max_force=100.0))
    bed = WinklerBed(mesh.n_vertices, K_BED)
    session.use_driver(bed)
    X = np.asarray(mesh.vertices)[node]
    assert session.grab(X) == node
    pull = np.array([0.002, 0.001, 0.004])
    session.drag(X + pull)
    for _ in range(3):
        session.step()
    np.testing.assert_allclose(session.force, SERIES * pull, rtol=1e-12)
    U = session.displacements()
    np.testing.assert_allclose(U[node], SERIES * pull / K_BED, rtol=1e-12)
    assert np.count_nonzero(np.abs(U).sum(axis=1)) == 1
    session.release()
    session.step()
    assert not np.any(session.displacements())


def test_the_dynamic_map_driver_superposes_the_force_history_and_settles_to_the_static_field(organ):
    """ImpedanceDriver(dynamic=True) against ImpedanceMap.displacements of the same history
    written out by hand (Duhamel), and against the static columns once the load has settled."""
    mesh, node = organ
    model = rt.ShellModel(mesh, rt.Material()).fix("attachment")
    imap = rt.ImpedanceMap.build(model, rt.Damping(alpha=8.0), nodes=[node], n_modes=20,
                                 times=(0.002, 0.005, 0.01, 0.02, 0.05, 0.1))
    dt = 1e-3
    drv = imap.as_driver(dt, dynamic=True)
    drv.resolution = dt  # no merging: the history is exactly the steps' load changes
    f1, f2 = np.array([0.0, 0.0, 0.2]), np.array([0.1, 0.0, -0.1])
    schedule = [f1] * 7 + [f2] * 5 + [None] * 4
    history = []
    current = np.zeros(3)
    for k, f in enumerate(schedule):
        drv.step(None if f is None else {node: f})
        new = np.zeros(3) if f is None else f
        if np.any(new != current):
            history.append((node, new - current, k * dt))
            current = new
        np.testing.assert_allclose(drv.displacements(), imap.displacements(history, drv.time), rtol=1e-12, atol=1e-18)
        np.testing.assert_allclose(drv.displacement(node), imap.displacements(history, drv.time)[node], rtol=1e-12,
                                   atol=1e-18)
    # a held load settles: past the last sample the field is the static one, and the history
    # has merged into one settled entry
    for _ in range(150):
        drv.step({node: f1})
    static = imap.displacements([(node, f1, 0.0)], np.inf)
    np.testing.assert_allclose(drv.displacements(), static, rtol=1e-12, atol=1e-18)
    assert len(drv.get_state()["history"]) == 1
    # the contact stays the paper's quasi-static one
    np.testing.assert_allclose(drv.step_compliance(node), imap.point_compliance(node), rtol=0)
    assert not np.any(drv.predict(node))


def test_the_viewer_impedance_method_holds_the_static_field_of_the_grasp_force(organ):
    """The Session's impedance route is the dynamic map driver: a held grasp settles to the
    map's static field of the force the grasp applies."""
    from rtfem.viewer.session import Session, Settings

    mesh, node = organ
    session = Session(mesh, settings=Settings(method="impedance", n_modes=12, max_force=100.0))
    X = np.asarray(mesh.vertices)[node]
    assert session.grab(X) == node
    session.drag(X + np.array([0.0, 0.0, 0.004]))
    for _ in range(1300):  # past the last sample (1 s)
        session.step()
    f = session.force
    imap = session.driver.maps[0]
    np.testing.assert_allclose(session.displacements(), imap.displacements([(node, f, 0.0)], np.inf), rtol=1e-12,
                               atol=1e-18)
    # and the spring law holds with the static compliance: f = k (target - X - G f)
    G = imap.point_compliance(node)
    np.testing.assert_allclose(f, 200.0 * (np.array([0.0, 0.0, 0.004]) - G @ f), rtol=1e-9)


@pytest.mark.parametrize("kind", ["modal", "modal-corrected", "newmark", "central", "map", "large", "warped",
                                  "warped-corrected", "reduced-nonlinear", "reduced-nonlinear-corrected", "static"])
def test_every_driver_keeps_its_one_step_contract(organ, kind):
    """u(k+1) = predict(node) + W f for a force f on that node, for every driver rtfem ships
    (mid-motion, after a few loaded steps), and get_state/set_state replays a step exactly."""
    mesh, node = organ
    model = rt.ShellModel(mesh, rt.Material()).fix("attachment")
    damping = rt.Damping(alpha=5.0)
    if kind.startswith("modal") or kind.startswith("warped"):
        d = rt.ModalSimulator(rt.modal_analysis(model, 10), 1e-3, damping, static_correction=kind.endswith("corrected"),
                              warping=kind.startswith("warped"))
        assert d.warping == kind.startswith("warped")
    elif kind == "newmark":
        d = rt.DirectSimulator(model, 1e-3, damping)
        assert isinstance(d, rt.NewmarkSimulator)
    elif kind == "central":
        d = rt.DirectSimulator(model, 2e-6, damping, method="central")
        assert isinstance(d, rt.CentralDifferenceSimulator) and isinstance(d, rt.DirectSimulator)
    elif kind == "large":
        d = rt.DirectSimulator(model, 1e-3, damping, large_deformation=True, tol=1e-12)
        assert isinstance(d, rt.NonlinearNewmarkSimulator) and isinstance(d, rt.DirectSimulator)
    elif kind.startswith("reduced-nonlinear"):
        red = rt.ReducedNonlinearModel(model, rt.modal_analysis(model, 10), 3)
        red.train_cubature(8, tol=0.1)
        d = rt.ReducedNonlinearSimulator(red, 1e-3, damping, static_correction=kind.endswith("corrected"))
    elif kind == "static":
        d = rt.StaticDriver(model, {node: (0.0, 0.0, 0.05)})
    else:
        d = rt.ImpedanceMap.build(model, damping, nodes=[node], n_modes=10).as_driver()
    other = int(np.argmin(np.asarray(mesh.vertices)[:, 2])) if kind != "map" else node
    for _ in range(4):
        d.step({other: (0.05, -0.02, 0.1)})
    f = np.array([0.03, 0.04, -0.08])
    before = d.get_state()
    u_pred = d.predict(node) + d.step_compliance(node) @ f
    d.step({node: f})
    after = d.displacement(node)
    scale = np.abs(after).max()
    # the nonlinear and warped steps are linear in f only to first order: their error is the
    # curvature's, O(f^2) (measured 1e-6 .. 1e-5 of the motion here); every linear driver is exact to round-off
    tol = 1e-5 if kind == "large" else 1e-4 if kind.startswith("warped") else 1e-9
    np.testing.assert_allclose(after, u_pred, rtol=tol, atol=tol * scale)
    d.set_state(before)
    d.step({node: f})  # (Newmark replays by a full solve where the first step superposed: round-off apart)
    np.testing.assert_allclose(d.displacement(node), after, rtol=1e-12, atol=1e-12 * scale)
