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
from rtfem.simulate import DRIVER_MEMBERS, Driver


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
