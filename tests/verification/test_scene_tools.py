"""Tools in scenes (rt.Scene.add_tool): probes and graspers on their own devices, against a second
algorithm and the balance of forces.

- A probe pressed into a block fixed at its base settles at the force ToolContact (the single-organ
  tool contact, its own contact set and solve; verified against Hertz) gives for the same press.
- A probe pressing a free box on a table: the table carries the box's weight plus the probe's push.
- A probe started inside a free box's top pushes it down by its coupling spring, k d.
- A grasper closing on a box resting on a table and lifting it carries the box's weight, and the
  table nothing; the hand feels the weight.
"""

from __future__ import annotations

import numpy as np
import pytest

import rtfem as rt
from rtfem.interaction.scene_tools import Keyframes


def _box(lx, ly, lz, n, fix=None, modes=20):
    model = rt.SolidModel(rt.meshes.box(lx, ly, lz, nx=n[0], ny=n[1], nz=n[2]),
                          rt.Material(E=3e4, nu=0.3, density=1000.0), element="tet4")
    if fix:
        model.fix(fix)
    return model, rt.modal_analysis(model, modes)


@pytest.mark.parametrize("stiffness, tol", [(None, 0.02), (300.0, 0.005)])
def test_a_probe_presses_a_fixed_block_as_tool_contact_does(stiffness, tol):
    """A 4 mm sphere 2 mm into a 3 cm block fixed at its base, off its vertices (30 modes, static
    correction: the settled state is the static one). The two solvers take different contact sets
    (ToolContact also the vertices the tool's surface is about to reach, with predictions), so the
    settled forces agree to the discretization: measured 1.3 % with the tool at the device, 0.12 %
    on a 300 N/m coupling (which carries part of the compliance)."""
    model, modes = _box(0.1, 0.1, 0.03, (8, 8, 2), fix="z<1e-9", modes=30)
    top = np.array([0.047, 0.052, 0.03])

    def path(t):
        return top + np.array([0.0, 0.0, 0.008 - 0.006 * min(t / 0.4, 1.0)])

    def sim():
        return rt.ModalSimulator(modes, dt=1e-3, damping=rt.Damping(alpha=20.0), static_correction=True)

    scene = rt.Scene(gravity=(0.0, 0.0, 0.0))
    scene.add_body("block", sim(), model.mesh)
    device = rt.ScriptedDevice(path)
    scene.add_tool("probe", device, radius=0.004, stiffness=stiffness)
    scene.run(1000)
    reference = rt.ToolContact(model.mesh, sim(), rt.Tool.sphere(0.004),
                               coupling="constraint" if stiffness is None else "spring", stiffness=stiffness or 200.0)
    for i in range(1000):
        f = reference.update(path((i + 1) * 1e-3))
    assert f[2] > 0.3  # pressed, not grazing
    assert abs(device.forces[-1][2] - f[2]) < tol * f[2]
    assert np.allclose(scene.contacts[("block", "probe")], -device.forces[-1])  # the hand feels the push on the body


def test_a_probe_started_inside_a_box_pushes_it_down_by_its_coupling():
    """A 1 cm sphere on a 500 N/m coupling put 5 mm into the top of a free 5 cm box at t = 0: the first
    step's push is down, k d = 2.5 N less the box's give (the trial step's) within 1 %. The box's bottom
    vertices under the probe, within its search (its reach, the margin and the longest edge) but 5.5 cm
    from its centre, are not taken for vertices it has passed (they once were: the push came out up,
    15 N, and the box flew off up)."""
    model, modes = _box(0.1, 0.1, 0.05, (4, 4, 2))
    scene = rt.Scene(gravity=(0.0, 0.0, 0.0))
    scene.add_body("box", rt.ModalSimulator(modes, dt=1e-3, damping=rt.Damping(alpha=20.0)), model.mesh)
    device = rt.ScriptedDevice(lambda t: np.array([0.05, 0.05, 0.055]))
    scene.add_tool("probe", device, radius=0.01, stiffness=500.0)
    scene.step()
    f = scene.contacts[("box", "probe")]
    assert f[2] < 0 and abs(f[2] + 2.5) < 0.01 * 2.5 and np.abs(f[:2]).max() < 1e-6 * 2.5
    for _ in range(20):
        scene.step()
    body = scene.body("box")
    drift = body.masses @ body.driver.displacements() / body.mass  # the free box's centre of mass moved
    assert drift[2] < 0 and np.abs(drift[:2]).max() < 1e-3 * abs(drift[2])  # down, away from the probe


def test_a_probe_pressing_a_box_on_a_table_the_table_carries_both():
    model, modes = _box(0.1, 0.1, 0.05, (4, 4, 2))
    scene = rt.Scene()
    scene.add_body("box", rt.ModalSimulator(modes, dt=1e-3, damping=rt.Damping(alpha=20.0)), model.mesh)
    scene.add_plane("table", (0.0, 0.0, -0.001), (0.0, 0.0, 1.0), friction=0.5)
    top = np.array([0.05, 0.05, 0.05])  # a vertex: the push is along z
    scene.add_tool("probe", rt.ScriptedDevice(lambda t: top + [0.0, 0.0, 0.006 - 0.0075 * min(t / 0.5, 1.0)]),
                   radius=0.005, stiffness=200.0)
    scene.run(2000)
    weight = scene.body("box").mass * 9.81
    push, table = scene.contacts[("box", "probe")], scene.contacts[("box", "table")]
    assert push[2] < -0.5  # pressing down about a newton
    assert np.abs(table + push - [0.0, 0.0, weight]).max() < 1e-4 * weight


def test_a_grasper_lifts_a_box_and_carries_its_weight():
    """The grasper closes on the top of a box resting on a table at 0.2 s, lifts 3 cm over 0.5 s
    and holds it: the table is left with nothing, the grasper carries m g, the hand feels it."""
    model, modes = _box(0.1, 0.1, 0.05, (4, 4, 2))
    scene = rt.Scene()
    scene.add_body("box", rt.ModalSimulator(modes, dt=1e-3, damping=rt.Damping(alpha=20.0)), model.mesh)
    scene.add_plane("table", (0.0, 0.0, -0.001), (0.0, 0.0, 1.0), friction=0.5)
    hand = Keyframes([[0.0, 0.05, 0.05, 0.049], [0.3, 0.05, 0.05, 0.049], [0.8, 0.05, 0.05, 0.079]], closed=[[0.2, 9.0]])
    device = hand.device()
    grasper = scene.add_tool("grasper", device, kind="grasper", radius=0.015, stiffness=2000.0)
    scene.run(150)
    assert grasper.held is None and scene.contacts[("box", "table")][2] > 0  # open: resting on the table
    scene.run(1850)
    weight = scene.body("box").mass * 9.81
    assert grasper.held is not None and grasper.held.a.name == "box"
    assert np.abs(scene.contacts[("box", "table")]).max() == 0.0  # lifted off
    assert np.abs(scene.contacts[("box", "grasper")] - [0.0, 0.0, weight]).max() < 1e-3 * weight
    assert np.allclose(device.forces[-1], -scene.contacts[("box", "grasper")])
    x = np.asarray(model.mesh.vertices) + scene.body("box").driver.displacements()
    assert x[:, 2].min() > 0.02  # off the table by about the lift


def _incline_mesh(theta, size=3.0, n=5):
    """A square of the plane through the origin tilted by theta about y (rising toward -x), in n x n
    squares of two triangles (60 cm): far coarser than the box, its vertices nowhere near the box's."""
    s = np.linspace(-size / 2, size / 2, n + 1) + 0.013
    X, Y = np.meshgrid(s, s, indexing="ij")
    P = np.column_stack([X.ravel() * np.cos(theta), Y.ravel(), -X.ravel() * np.sin(theta)])
    ids = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = ids[:-1, :-1].ravel(), ids[1:, :-1].ravel(), ids[1:, 1:].ravel(), ids[:-1, 1:].ravel()
    return rt.TriMesh(P, np.concatenate([np.column_stack([a, b, c]), np.column_stack([a, c, d])]))


@pytest.mark.parametrize("mu, sticks", [(0.5, True), (0.1, False)])
def test_a_box_on_a_tilted_mesh_obstacle_sticks_or_slides_by_coulomb(mu, sticks):
    """A free box on a triangulated incline (a mesh obstacle, not a plane; 15 degrees): with
    mu > tan 15 it sticks, the obstacle's force is the weight (1 %), along -g; with mu < tan 15 it
    slides with |F_t| = mu F_n (1 %) along the face."""
    theta = np.radians(15.0)
    R = np.array([[np.cos(theta), 0.0, np.sin(theta)], [0.0, 1.0, 0.0], [-np.sin(theta), 0.0, np.cos(theta)]])
    mesh = rt.meshes.box(0.1, 0.1, 0.05, nx=4, ny=4, nz=2)
    lifted = (np.asarray(mesh.vertices) - [0.05, 0.05, -1e-4]) @ R.T  # resting on the tilted face
    model = rt.SolidModel(rt.TetMesh(lifted, np.asarray(mesh.tets)), rt.Material(E=1e5, nu=0.3, density=1000.0),
                          element="tet4")
    scene = rt.Scene()
    scene.add_body("box", rt.ModalSimulator(rt.modal_analysis(model, 20), dt=1e-3, damping=rt.Damping(alpha=20.0)),
                   model.mesh)
    incline = _incline_mesh(theta)
    scene.add_obstacle("incline", incline, friction=mu)
    scene.run(1200 if sticks else 800)  # sliding at 1.6 m/s^2: 0.5 m down the 3 m incline by 0.8 s
    f = scene.contacts[("box", "incline")]
    weight = scene.body("box").mass * 9.81
    normal = R @ [0.0, 0.0, 1.0]
    fn = f @ normal
    ft = np.linalg.norm(f - fn * normal)
    assert abs(fn - weight * np.cos(theta)) < 0.01 * weight
    if sticks:
        assert np.abs(f - [0.0, 0.0, weight]).max() < 0.01 * weight
    else:
        assert abs(ft - mu * fn) < 0.01 * fn
