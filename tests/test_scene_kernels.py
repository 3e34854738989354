"""The scene step's compiled kernels (rtfem.interaction.scene_search, scene_points) against the numpy they replace,
and a driver's trial step (trial_displacements) against the protocol's step, read and restore.

- pair_faces: a body's vertices against another's triangles (nearest triangle, gap, normal,
  barycentric weights, on the face's normal line), compiled against the numpy of
  scene_obstacles.nearest_face_points and on_faces, on random points around a sphere's faces;
- probe_points: a probe's vertex contacts and closest face point, compiled against
  Tool.distance and the numpy face search, for a sphere, a capsule and a jaw;
- assemble: A = G^T P W P^T G, compiled against the dense products with explicit P and G;
- the example scene (two shells, a cystic plate, a grasper and a probe) stepped with the
  kernels and with numpy: the same contact forces and fields to round-off;
- ModalSimulator.trial_displacements (with the static correction, both integrators) and the
  warped simulator's: equal to a step, the displacements read and the state restored, which
  they leave untouched.
"""

from __future__ import annotations

from importlib import resources

import numpy as np
import pytest

import rtfem as rt
from rtfem.drivers.base import displacements_at, stepped_trial, trial_displacements
from rtfem.interaction import scene_points, scene_search
from rtfem.interaction.scene_file import load_scene
from rtfem.interaction.scene_points import assemble
from rtfem.interaction.scene_search import pair_faces, probe_points

compiled = pytest.mark.skipif(scene_search._pair_faces_compiled is None, reason="numba is not installed")


def _sphere(r=0.05, level=2):
    mesh = rt.meshes.icosphere(r, level)
    return np.asarray(mesh.vertices, dtype=float), np.ascontiguousarray(np.asarray(mesh.triangles, dtype=np.int64))


@compiled
def test_pair_faces_compiled_equals_numpy():
    Y, tri = _sphere()
    rng = np.random.default_rng(1)
    x = Y[rng.integers(0, Y.shape[0], 200)] * rng.uniform(0.9, 1.1, (200, 1)) + rng.normal(0, 1e-3, (200, 3))
    tris = rng.integers(0, tri.shape[0], (200, 8))
    valid = rng.random((200, 8)) < 0.8
    valid[:, 0] = True
    a = pair_faces(x, Y, tri, tris, valid, 0.004, 0.01, compiled=True)
    b = pair_faces(x, Y, tri, tris, valid, 0.004, 0.01, compiled=False)
    np.testing.assert_array_equal(a[0], b[0])
    for u, v in zip(a[1:4], b[1:4]):
        np.testing.assert_allclose(u, v, rtol=0, atol=1e-14)
    np.testing.assert_array_equal(a[4], b[4])
    assert 0 < a[4].sum() < 200  # both kinds of answer were compared


@compiled
@pytest.mark.parametrize("tool", [rt.Tool.sphere(0.01), rt.Tool.capsule(0.004, 0.03, axis=(1.0, 1.0, 0.0)),
                                  rt.Tool.jaw(0.01, 0.02, 0.004, normal=(0.0, 0.3, 1.0))])
def test_probe_points_compiled_equals_numpy(tool):
    Y, tri = _sphere()
    O = Y / np.linalg.norm(Y, axis=1)[:, None]
    for position in ([0.0, 0.0, 0.058], [0.01, 0.0, 0.052], [0.0, 0.02, 0.035]):  # beside, touching, through
        a = probe_points(Y, O, tri, tool, np.array(position), 0.03, 0.004, compiled=True)
        b = probe_points(Y, O, tri, tool, np.array(position), 0.03, 0.004, compiled=False)
        np.testing.assert_array_equal(a[0], b[0])
        np.testing.assert_allclose(a[1], b[1], rtol=0, atol=1e-14)
        np.testing.assert_allclose(a[2], b[2], rtol=0, atol=1e-14)
        assert (a[3] is None) == (b[3] is None)
        if a[3] is not None:
            assert a[3][0] == b[3][0]
            for u, v in zip(a[3][1:], b[3][1:]):
                np.testing.assert_allclose(u, v, rtol=0, atol=1e-14)
    assert a[0].size > 0  # the last position is through the surface: points found


@pytest.mark.parametrize("use_compiled", [True, False])
def test_assemble_equals_the_dense_products(use_compiled):
    if use_compiled and scene_points._assemble_compiled is None:
        pytest.skip("numba is not installed")
    rng = np.random.default_rng(2)
    m, u = 7, 9
    Q, _ = np.linalg.qr(rng.normal(size=(m, 3, 3)))
    slot = rng.integers(-1, u, (m, 2, 3))
    slot[:, 0, 0] = rng.integers(0, u, m)
    sw = np.where(slot >= 0, rng.normal(size=(m, 2, 3)), 0.0)
    R = rng.normal(size=(3 * u, 3 * u))
    W = R @ R.T
    P = np.zeros((3 * m, 3 * u))  # point c's world displacement per node displacement
    for c, s, i in zip(*np.nonzero(slot >= 0)):
        P[3 * c:3 * c + 3, 3 * slot[c, s, i]:3 * slot[c, s, i] + 3] += sw[c, s, i] * np.eye(3)
    G = np.zeros((3 * m, 3 * m))
    for c in range(m):
        G[3 * c:3 * c + 3, 3 * c:3 * c + 3] = Q[c]
    tool = np.array([-1, 0, 1, 0, -1, 1, 0])  # points of two probes on springs of 1/0.5 and 1/0.25 N/m
    inv_k = np.array([0.5, 0.25])
    C = np.zeros((3 * m, 3 * m))  # a probe's proxy moves by the sum of its points' forces / k
    for c in range(m):
        for d in range(m):
            if tool[c] >= 0 and tool[c] == tool[d]:
                C[3 * c:3 * c + 3, 3 * d:3 * d + 3] = inv_k[tool[c]] * np.eye(3)
    np.testing.assert_allclose(assemble(Q, slot, sw, W, tool, inv_k, use_compiled), G.T @ (P @ W @ P.T + C) @ G,
                               rtol=1e-12, atol=1e-12)


def _same_steps(scenes, n):
    """Step both scenes n times; their contact forces agree every step; the pairs that carried force."""
    scenes[1].compiled = False
    touched = set()
    for _ in range(n):
        for sc in scenes:
            sc.step()
        for key, f in scenes[0].contacts.items():
            np.testing.assert_allclose(f, scenes[1].contacts[key], rtol=0, atol=1e-9 * max(1.0, np.abs(f).max()))
            if np.any(f != 0):
                touched.add(key)
    for a, b in zip(*(sc.bodies for sc in scenes)):
        np.testing.assert_allclose(displacements_at(a.driver, a.surface), displacements_at(b.driver, b.surface),
                                   rtol=0, atol=1e-12)
    return touched


def test_the_example_scene_steps_the_same_with_the_kernels_and_with_numpy():
    scenes = [load_scene(resources.files("rtfem") / "scenes" / "gallbladder.toml") for _ in range(2)]
    touched = _same_steps(scenes, 1000)  # the grasper holds from 0.28 s, the probe presses from 0.89 s
    assert {("liver", "probe"), ("gallbladder", "grasper")} <= touched


def test_a_box_dropped_on_a_box_steps_the_same_with_the_kernels_and_with_numpy():
    scenes = []
    for _ in range(2):
        scene = rt.Scene()
        for name, mesh in (("A", rt.meshes.box(0.1, 0.1, 0.05, nx=4, ny=4, nz=2)),
                           ("B", rt.TetMesh(np.asarray(rt.meshes.box(0.06, 0.06, 0.03, nx=3, ny=3, nz=2).vertices)
                                            + (0.02, 0.02, 0.0505), rt.meshes.box(0.06, 0.06, 0.03, nx=3, ny=3,
                                                                                   nz=2).tets))):
            model = rt.SolidModel(mesh, rt.Material(E=3e4, nu=0.3, density=1000.0))
            sim = rt.ModalSimulator(rt.modal_analysis(model, 12), dt=1e-3, damping=rt.Damping(alpha=20.0))
            scene.add_body(name, sim, model.mesh)
        scene.add_plane("table", (0.0, 0.0, -0.0005), (0.0, 0.0, 1.0), friction=0.3)
        scene.friction = 0.2
        scenes.append(scene)
    assert {("A", "B"), ("B", "A"), ("A", "table")} <= _same_steps(scenes, 200)


@pytest.fixture(scope="module")
def modes():
    model = rt.ShellModel(rt.meshes.liver(2), rt.Material(E=3e4, nu=0.45, thickness=4e-3, density=1060.0))
    model.fix(rt.select_nodes(model.mesh, "attachment"))
    return rt.modal_analysis(model, 12)


@pytest.mark.parametrize("kind", ["exact", "newmark", "warped"])
def test_a_trial_step_equals_a_step_read_and_restored(modes, kind):
    options = dict(static_correction=True) if kind != "warped" else dict(warping=True)
    if kind == "newmark":
        options["integrator"] = "newmark"
    sim = rt.ModalSimulator(modes, dt=1e-3, damping=rt.Damping(alpha=4.0), **options)
    rng = np.random.default_rng(3)
    n = sim.n_nodes
    for _ in range(5):
        sim.step(rng.normal(0, 0.05, (n, 3)))
    before = (sim.get_state(), sim.displacements().copy())
    F = rng.normal(0, 0.05, (n, 3))
    nodes = rng.choice(n, 40, replace=False)
    a = trial_displacements(sim, F, nodes)
    np.testing.assert_array_equal(sim.displacements(), before[1])  # the state left as it was
    b = stepped_trial(sim, F, nodes)
    np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-15 * np.abs(b).max())
    assert np.abs(a - displacements_at(sim, nodes)).max() > 1e-3 * np.abs(a).max()  # the step moved them
    for key, value in before[0].items():
        np.testing.assert_array_equal(sim.get_state()[key], value)


def test_the_static_correction_of_a_few_nodes_equals_the_whole_fields_rows(modes):
    """ModalSimulator.displacements_at on a few nodes under an (n, 3) load that differs from a kept
    one at a few nodes (a scene body's weight and its contacts) computes those rows only: equal to the
    whole field's rows, and to a correction solved from scratch."""
    sim = rt.ModalSimulator(modes, dt=1e-3, damping=rt.Damping(alpha=4.0), static_correction=True)
    n = sim.n_nodes
    weight = np.zeros((n, 3))
    weight[:, 2] = -0.01
    sim.step(weight)
    sim.displacements()  # the weight's correction solved and kept
    F = weight.copy()
    F[[3, 50, 51, 90]] += np.array([[0.2, 0.0, -0.1], [0.0, 0.3, 0.0], [0.1, 0.1, 0.1], [-0.2, 0.0, 0.4]])
    sim.step(F)
    few = np.array([3, 7, 50, 120])
    rows = displacements_at(sim, few)
    sim._D_last = None
    whole = sim.displacements()[few]
    np.testing.assert_allclose(rows, whole, rtol=1e-12, atol=1e-14 * np.abs(whole).max())
    fresh = rt.ModalSimulator(modes, dt=1e-3, damping=rt.Damping(alpha=4.0), static_correction=True)
    fresh.set_state(sim.get_state())
    fresh._loads, fresh._load_array = sim._loads, sim._load_array  # the same loads, no kept correction
    np.testing.assert_allclose(fresh.displacements()[few], whole, rtol=1e-9, atol=1e-12 * np.abs(whole).max())


def test_points_on_held_nodes_are_left_out_the_same_way_compiled_and_in_numpy():
    """A block fixed at its base standing on a plane there (those points move nothing: the supports take
    them, they are left out of the solve) with a probe pressing its top (points that are solved)."""
    scenes = []
    for _ in range(2):
        model = rt.SolidModel(rt.meshes.box(0.1, 0.1, 0.03, nx=4, ny=4, nz=2), rt.Material(E=3e4, nu=0.3, density=1000.0),
                              element="tet4")
        model.fix("z<1e-9")
        sim = rt.ModalSimulator(rt.modal_analysis(model, 12), dt=1e-3, damping=rt.Damping(alpha=20.0),
                                static_correction=True)
        scene = rt.Scene()
        scene.add_body("block", sim, model.mesh)
        scene.add_plane("floor", (0.0, 0.0, -0.0005), (0.0, 0.0, 1.0), friction=0.3)
        # off the block's diagonals: at its centre the probe stands on a tie between mirror-image contacts, which
        # round-off breaks one way compiled and the other in numpy (with MKL_CBWR=COMPATIBLE: lateral forces
        # swapped, 3.34e-5 against 3.42e-5 N), a choice and not an error of either path
        scene.add_tool("probe", rt.ScriptedDevice(lambda t: np.array([0.043, 0.058, 0.034 - 0.01 * min(t / 0.1, 1.0)])),
                       radius=0.005, stiffness=300.0)
        scenes.append(scene)
    touched = _same_steps(scenes, 150)
    assert ("block", "probe") in touched and ("block", "floor") not in touched  # the floor's points: on held nodes


def test_a_trial_step_refuses_bad_nodes_and_forces_and_leaves_the_state(modes):
    """trial_displacements with a node off the mesh or a non-finite force raises a ModelError (exit 2
    in the CLI) and changes nothing: the state and the displacements are as before."""
    sim = rt.ModalSimulator(modes, dt=1e-3, damping=rt.Damping(alpha=4.0), static_correction=True)
    n = sim.n_nodes
    sim.step(np.full((n, 3), 0.01))
    state, field = sim.get_state(), sim.displacements().copy()
    bad_force = np.zeros((n, 3))
    bad_force[3, 1] = np.nan
    for forces, nodes in ((np.zeros((n, 3)), np.array([0, n])), (bad_force, np.array([0, 1]))):
        with pytest.raises(rt.ModelError):
            trial_displacements(sim, forces, nodes)
        np.testing.assert_array_equal(sim.displacements(), field)
        for key, value in state.items():
            np.testing.assert_array_equal(sim.get_state()[key], value)
    with pytest.raises(rt.ModelError, match="choose one of 'openhaptics', 'forcedimension', 'haply', 'igtl'"):
        rt.devices.open_device("mouse")
