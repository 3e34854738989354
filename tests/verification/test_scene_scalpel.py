"""A scalpel in a scene (issue 57): a [[tool]] of kind "scalpel" cuts its body as the scene steps it.

The reference is the slit beam of test_cut (built by index arithmetic, not by rt.cut): the beam clamped at
both ends, cut from below at mid-length as it sags, settles to the static equilibrium of the slit beam
under the same weights, as rt.Scalpel alone does (test_scalpel)."""

from __future__ import annotations

import csv
import glob

import meshio
import numpy as np
import pytest

import rtfem as rt
from rtfem.cli.main import main
from rtfem.errors import ModelError
from rtfem.interaction.scene_file import load_scene
from rtfem.interaction.scene_tools import Keyframes

from test_cut import _slit_box
from test_scalpel import MAT, L, W, _block, _same_mesh, slit_beam

# the blade upright at mid-length from 10 mm below the beam to half its height: held 0.3 s while the sag
# settles, drawn across the width in 0.3 s, then out beside the beam while the cut beam settles
PATH = [[0.0, L / 2, -0.005, -0.01], [0.3, L / 2, -0.005, -0.01], [0.605, L / 2, W + 0.005, -0.01],
        [0.61, L / 2, W + 0.01, -0.01]]
BLADE = (0.0, 0.0, W / 2 + 0.01)


def _scene_file(folder, extra: str = "") -> str:
    model = _block(ends=True)
    rt.save_mesh(model.tetmesh, folder / "beam.vtu")
    ends = ",".join(map(str, np.flatnonzero(model.fixed.any(axis=1)).tolist()))
    path = folder / "cut.toml"
    path.write_text(f"""dt = 0.005
[[body]]
name = "beam"
mesh = "beam.vtu"
element = "tet4"
material = {{ E = {MAT.E}, nu = {MAT.nu}, density = {MAT.density} }}
fix = "nodes:{ends}"
alpha = 60.0

[[tool]]
name = "knife"
kind = "scalpel"
body = "beam"
blade = {list(BLADE)}
toughness = 0
path = {PATH}
{extra}""")
    return path


def _slit_reference():
    """The slit beam (index arithmetic) and its static displacements under its nodal weights."""
    ref = _slit_box(below=True)
    slit, weights, _ = slit_beam(ref)
    return ref, slit.solve_static(weights, large_deformation=True)


def test_a_scene_files_scalpel_cuts_its_beam_as_it_sags_and_the_beam_settles_to_the_slit_beam(tmp_path, capsys):
    """A scene file's scalpel on a scripted path: the body's mesh is the slit beam node for node (its cut
    nodes within 0.1 mm of the swept plane), its settled displacements the slit beam's static ones within
    0.5 % of the largest (measured 0.14 %, as rt.Scalpel alone), the cut's lips parted as theirs (1 %);
    the contact record has the scalpel's force on the beam; `rtfem simulate` writes the cut mesh's frames."""
    scene = load_scene(_scene_file(tmp_path))
    knife = scene.scalpels[0]
    scene.run(421)
    assert knife.cuts >= 1 and knife.cutter.refused is None
    ref, U_ref = _slit_reference()
    beam = scene.body("beam")
    assert beam.driver.model is knife.model and beam.model is knife.model
    assert _same_mesh(knife.model.tetmesh, ref, tol=1e-4)
    mine = np.zeros(ref.n_vertices, dtype=np.int64)  # the scene's node at each of the slit beam's
    mine[np.asarray(ref.tets).ravel()] = np.asarray(knife.model.tetmesh.tets).ravel()
    U = np.asarray(beam.driver.displacements())[mine]
    scale = np.abs(U_ref).max()
    assert 3e-3 < scale < 4e-3
    assert np.abs(U - U_ref).max() < 0.005 * scale, np.abs(U - U_ref).max() / scale
    lips = [(250 + 5 * j, 525 + 2 * j) for j in range(5)]  # the slit's bottom edge, left lip and right
    gap = np.array([U[b, 0] - U[a, 0] for a, b in lips])
    assert (gap > 1e-3).all()
    np.testing.assert_allclose(gap, [U_ref[b, 0] - U_ref[a, 0] for a, b in lips], rtol=0.01)
    # the surface the scene touches is the cut mesh's: the slit's faces are on it
    assert beam.surface.size == knife.model.mesh.used_vertices().size and beam.X.shape == (ref.n_vertices, 3)
    assert ("beam", "knife") in scene.contacts and np.all(scene.contacts[("beam", "knife")] == 0.0)  # toughness 0

    rc = main(["simulate", str(tmp_path / "cut.toml"), "--duration", "0.7", "--fps", "5", "--out", str(tmp_path / "out")])
    out = capsys.readouterr().out
    assert rc == 0 and "scalpel     knife: 4 cut(s) of beam, now 535 nodes" in out and "on its modes" not in out, out
    frames = sorted(glob.glob(str(tmp_path / "out" / "beam" / "frame_*.vtu")))
    first, last = meshio.read(frames[0]), meshio.read(frames[-1])
    assert first.points.shape[0] == ref.n_vertices - 10 and last.points.shape[0] == ref.n_vertices


def test_a_scalpel_moves_the_springs_on_the_nodes_it_copies_and_the_scene_steps_on():
    """An attachment holding the beam's bottom nodes at mid-length, where the blade cuts: after the cut each
    copy of those nodes is held at the node's anchor (the lips both hang from it), the cut's new nodes
    are not, and the scene steps on; a grasper holding the beam lets go at the cut and takes hold again."""
    model = _block(ends=True)
    scene = rt.Scene(gravity=(0.0, 0.0, 0.0))
    scene.add_body("beam", rt.DirectSimulator(model, 5e-3, rt.Damping(alpha=60.0), large_deformation=True), model.mesh)
    X = np.asarray(model.tetmesh.vertices)
    bottom = np.flatnonzero((np.abs(X[:, 0] - L / 2) < 1e-9) & (X[:, 2] < 1e-9))
    att = scene.attach("hold", "beam", bottom, stiffness=100.0)
    grip = rt.ScriptedDevice(lambda t: np.array([L / 4, W / 2, W]), buttons=lambda t: 1)
    grasper = scene.add_tool("grip", grip, kind="grasper", radius=0.004)
    path = [[0.0, L / 2, -0.005, -0.01], [0.3, L / 2, W + 0.005, -0.01]]
    knife = scene.add_scalpel("knife", "beam", Keyframes(path).device(), blade=BLADE, toughness=0.0)
    scene.run(70)
    assert knife.cuts >= 1
    assert scene.attachments[0] is not att and att.nodes_a.size == bottom.size  # replaced, not changed
    att = scene.attachments[0]
    P = knife.cutter.transfer
    parents = np.asarray(P[att.nodes_a].argmax(axis=1)).ravel()
    assert np.array_equal(np.unique(parents), bottom) and att.nodes_a.size == 2 * bottom.size  # both lips held
    np.testing.assert_array_equal(att.anchor, X[parents])
    assert grasper.held is not None and grasper.held.a is scene.body("beam")
    assert np.isfinite(scene.body("beam").driver.displacements()).all()


@pytest.mark.parametrize("change, said", [
    ('element = "tet4"', "must be element = 'tet4'"),
    ('alpha = 60.0', "leave modes out"),
    ('body = "beam"', "no body named 'liver'"),
    ('toughness = 0', "is for a probe or a grasper"),
    ('blade = [', "key 'blade'.*of some length"),
    ('fix = "nodes:', "key 'fix': missing"),
])
def test_what_a_scene_files_scalpel_refuses_is_said(tmp_path, change, said):
    text = _scene_file(tmp_path).read_text()
    new = {"element": 'element = "tet10"', "alpha": 'alpha = 60.0\nmodes = 10', "body": 'body = "liver"',
           "toughness": 'toughness = 0\nradius = 0.01', "blade": 'blade = [0, 0, 0]\n# [',
           "fix": '# fix = "nodes:'}[change.split()[0]]
    (tmp_path / "cut.toml").write_text(text.replace(change, new, 1))
    with pytest.raises(ModelError, match=said):
        load_scene(tmp_path / "cut.toml")


def _surfaces(scene):
    return [np.asarray(b.driver.displacements()) for b in scene.bodies]


def test_the_scene_viewers_clock_goes_back_before_a_cut_and_steps_through_it_to_the_same_cut(tmp_path):
    """The scene viewer's session keeps the scene's state every 0.1 s: a seek back to before the cut puts
    the uncut beam back (its model, driver and attachments; the scalpel as it was), and stepping on
    cuts it again the same way, node for node, to the same field (measured: equal to the bit); a restart is the uncut beam
    at rest."""
    from rtfem.viewer.scene_session import SceneSession

    scene = load_scene(_scene_file(tmp_path))
    knife = scene.scalpels[0]
    uncut = scene.bodies[0]
    session = SceneSession(scene, playing=False)
    for _ in range(140):  # 0.7 s: the blade has crossed the beam (0.3 - 0.6 s)
        session.step()
    assert knife.cuts >= 1 and scene.bodies[0] is not uncut
    cut_model, field = knife.model, _surfaces(scene)
    session.seek(0.2)
    assert scene.steps == 40 and scene.bodies[0] is uncut and knife.cuts == 0 and knife.model is uncut.driver.model
    assert knife.cutter.driver is uncut.driver and knife.cutter.triangles.shape[0] == 0
    session.seek(0.7)
    assert knife.model is not cut_model and _same_mesh(knife.model.tetmesh, cut_model.tetmesh, tol=1e-15)
    for u, v in zip(_surfaces(scene), field):
        np.testing.assert_allclose(u, v, rtol=0, atol=1e-12)
    session.restart()
    assert scene.bodies[0] is uncut and np.abs(_surfaces(scene)[0]).max() == 0.0


def test_the_scene_viewer_draws_the_cut_body_and_the_blade(tmp_path):
    """Served (no browser): after the cut the viewer draws the cut body's surface (its grabbable copy
    too), the blade is drawn from its tip to its heel, and no frame fails."""
    pytest.importorskip("viser")
    from conftest import free_port, wait_until
    from rtfem.viewer.scene_session import SceneSession
    from rtfem.viewer.scene_view import SceneViewer

    scene = load_scene(_scene_file(tmp_path))
    knife = scene.scalpels[0]
    viewer = SceneViewer(SceneSession(scene), port=free_port(), wait_for_client=False).start()
    try:
        wait_until(lambda: knife.cuts >= 1 and viewer._bodies[0] is scene.bodies[0], 60, "a cut drawn")
        frames = viewer.frames
        wait_until(lambda: viewer.frames > frames + 3, 20, "frames after the cut")

        def drawn():  # (the scene steps on meanwhile: a later cut is drawn by a later frame)
            size = scene.bodies[0].surface.size
            return size > 0 and viewer._glbs[0][2].shape == (size, 3) and \
                np.asarray(viewer.picks[0].vertices).shape == (size, 3)

        wait_until(drawn, 30, lambda: f"the cut body surface drawn ({scene.bodies[0].surface.size} vertices; "
                                      f"drawn {viewer._glbs[0][2].shape}, picks {np.asarray(viewer.picks[0].vertices).shape})")
        blade = np.asarray(viewer.glyphs.blades[0][1].points)
        np.testing.assert_allclose(blade[0, 1] - blade[0, 0], BLADE, atol=1e-6)
        assert viewer.state()["error"] is None
    finally:
        viewer.stop()


def test_the_cut_example_runs_headless_and_no_element_of_the_cut_liver_turns_inside_out(tmp_path, capsys):
    """`rtfem simulate --example cut`: the scalpel cuts the hanging solid liver (nodes added, the frames on
    the cut mesh), the hand feels the cutting resistance while the blade is in the tissue (contacts.csv),
    and every tet of the cut liver, deformed as the last frame has it, keeps a positive volume."""
    out = tmp_path / "out"
    rc = main(["simulate", "--example", "cut", "--duration", "1.8", "--fps", "5", "--out", str(out)])
    assert rc == 0, capsys.readouterr()
    frames = sorted(glob.glob(str(out / "liver" / "frame_*.vtu")))
    first, last = meshio.read(frames[0]), meshio.read(frames[-1])
    assert first.points.shape[0] == 1152 and last.points.shape[0] > 1152 + 20
    T = last.cells_dict["tetra"]

    def volumes(x):
        return np.einsum("ij,ij->i", np.cross(x[T[:, 1]] - x[T[:, 0]], x[T[:, 2]] - x[T[:, 0]]), x[T[:, 3]] - x[T[:, 0]])
    volumes, rest = volumes(last.points + last.point_data["displacement"]), volumes(last.points)
    assert (np.sign(volumes) == np.sign(rest)).all() and np.abs(volumes).min() > 0
    rows = [r for r in csv.DictReader(open(out / "contacts.csv")) if r["b"] == "scalpel"]
    force = np.array([[float(r[k]) for k in ("fx", "fy", "fz")] for r in rows])
    assert np.linalg.norm(force, axis=1).max() > 1.0  # N: J = 164 J/m^2 times centimetres of lobe


def test_rtfem_view_example_cut_serves_and_stops_on_ctrl_c():
    pytest.importorskip("viser")
    from conftest import serves_and_stops_on_ctrl_c

    serves_and_stops_on_ctrl_c("--example", "cut")


def _beam_scene(gravity=(0.0, 0.0, 0.0), x=L / 2, **scalpel):
    """The beam clamped at both ends in a scene, and a scalpel drawn across it from below at ``x`` in 0.1 s
    (its lower half cut; toughness 0)."""
    model = _block(ends=True)
    scene = rt.Scene(gravity=gravity)
    scene.add_body("beam", rt.DirectSimulator(model, 5e-3, rt.Damping(alpha=60.0), large_deformation=True), model.mesh)
    path = [[0.0, x, -0.005, -0.01], [0.1, x, W + 0.005, -0.01], [0.11, x, W + 0.01, -0.01]]
    knife = scene.add_scalpel("knife", "beam", Keyframes(path).device(), blade=BLADE, toughness=0.0, **scalpel)
    return model, scene, knife


def test_springs_loads_masses_and_grasps_go_to_the_copies_of_their_nodes_not_to_the_nodes_a_split_adds():
    """A cut 1.5 mm beside the beam's bottom nodes at mid-length (elements split, nodes added on their
    edges): the attachment on those nodes keeps five springs at rest (none on a new node: they are 1.5-2.6
    mm off, and with them the beam turned elements inside out), the loads held there stay there with their
    sum, a weightless body stays weightless; an attachment from another body whose pairs share nodes of the
    beam keeps every pair through a cut elsewhere; two scalpels on one body are refused."""
    model, scene, knife = _beam_scene(x=0.0515)
    X = np.asarray(model.tetmesh.vertices)
    bottom = np.flatnonzero(np.isclose(X[:, 0], L / 2) & (X[:, 2] < 1e-9))
    scene.attach("hold", "beam", bottom, stiffness=100.0)
    scene.body("beam").loads[bottom] = [0.0, 0.0, -5e-4]
    scene.bodies[0].masses = np.zeros(model.n_nodes)  # weightless (no gravity either: nothing moves it)
    scene.run(40)
    beam, att = scene.body("beam"), scene.attachments[0]
    assert knife.cuts >= 1 and beam.driver.n_nodes > model.n_nodes
    assert att.nodes_a.size == bottom.size and np.abs(beam.X[att.nodes_a] - att.anchor).max() == 0.0
    loaded = np.flatnonzero(beam.loads[:, 2])
    assert np.allclose(beam.X[loaded, 0], L / 2) and beam.loads.sum(axis=0) == pytest.approx([0.0, 0.0, -2.5e-3])
    assert beam.mass == 0.0 and np.abs(beam.driver.displacements()).max() < 1e-3  # the loads' sag only
    with pytest.raises(ModelError, match="cut by scalpel knife already"):
        scene.add_scalpel("other", "beam", Keyframes([[0.0, 0.0, 0.0, 1.0]]).device())

    model, scene, knife = _beam_scene(x=L / 2)
    pad = rt.meshes.box(0.01, 0.01, 0.005, nx=4, ny=4, nz=2)
    pad = rt.SolidModel(rt.TetMesh(np.asarray(pad.vertices) + [0.02, 0.005, 0.0205], pad.tets), MAT, element="tet4")
    Xp = np.asarray(pad.tetmesh.vertices)
    pad.fix(np.flatnonzero(Xp[:, 2] > 0.0255 - 1e-9))
    scene.add_body("pad", rt.DirectSimulator(pad, 5e-3, rt.Damping(alpha=60.0)), pad.mesh)
    underside = np.flatnonzero(Xp[:, 2] < 0.0205 + 1e-9)
    scene.attach("lig", "pad", underside, "beam", stiffness=200.0)
    shared = np.unique(scene.attachments[0].nodes_b).size
    scene.run(40)
    lig = scene.attachments[0]
    assert knife.cuts >= 1 and lig.b is scene.body("beam") and shared < underside.size
    assert lig.nodes_a.size == underside.size and np.unique(lig.nodes_b).size == shared


def test_a_grasp_holds_on_through_a_cut_and_keeps_the_piece_it_holds_and_a_relaxing_law_is_refused():
    """A grasper holding the beam's far quarter while the scalpel cuts across its near quarter holds on
    (its springs on the same nodes' copies; its force through the cuts within 5 % of the uncut beam's: it
    dropped by half, and let go at the second cut); cut through, a cantilever's tip piece held by a spring
    to the world is kept, not removed as cut free, and parted: it hangs on the spring alone, whose force is
    the piece's weight (before, the cut that parts it was refused); a body of a relaxing (Prony) law is
    refused (its cuts all were, silently)."""
    model = _block(ends=True)
    scene = rt.Scene(gravity=(0.0, 0.0, 0.0))
    scene.add_body("beam", rt.DirectSimulator(model, 5e-3, rt.Damping(alpha=60.0), large_deformation=True), model.mesh)
    lift = [[0.0, 0.75 * L, W / 2, W], [0.05, 0.75 * L, W / 2, W + 0.004]]  # takes the top and lifts it 4 mm
    grasper = scene.add_tool("grip", Keyframes(lift, [[0.0, 10.0]]).device(), kind="grasper", radius=0.004)
    cut = [[0.0, L / 4, -0.005, -0.01], [0.3, L / 4, -0.005, -0.01], [0.4, L / 4, W + 0.005, -0.01]]
    knife = scene.add_scalpel("knife", "beam", Keyframes(cut).device(), blade=BLADE, toughness=0.0)
    forces = []
    for _ in range(100):
        scene.step()
        forces.append((knife.cuts, np.linalg.norm(grasper.force)))
    uncut = [f for c, f in forces if c == 0][-1]
    assert knife.cuts >= 1 and grasper.held is not None and grasper.held.a is scene.body("beam")
    assert uncut > 0.1 and forces[-1][1] == pytest.approx(uncut, rel=0.05)  # N; the cut beam a little softer
    assert all(abs(f - uncut) < 0.05 * uncut for c, f in forces if c >= 1)  # no drop at a cut

    model = rt.SolidModel(rt.meshes.box(L, W, W, nx=20, ny=4, nz=4), MAT, element="tet4").fix("x0")
    scene = rt.Scene(gravity=(0.0, 0.0, -9.81))
    scene.add_body("beam", rt.DirectSimulator(model, 5e-3, rt.Damping(alpha=60.0), large_deformation=True), model.mesh)
    X = np.asarray(model.tetmesh.vertices)
    scene.attach("tip", "beam", np.flatnonzero(X[:, 0] > L - 1e-9), stiffness=50.0)
    path = [[0.0, 0.0705, -0.005, -0.01], [0.1, 0.0705, W + 0.005, -0.01]]
    knife = scene.add_scalpel("knife", "beam", Keyframes(path).device(), blade=(0.0, 0.0, W + 0.02), toughness=0.0)
    scene.run(40)
    # kept, not removed, and parted: the tip piece hangs on its spring alone (its copies of the held nodes are
    # the cut model's tethered ones, which restrain it for the step)
    body = scene.body("beam")
    assert knife.cuts >= 1 and knife.cutter.removed_mass == 0.0 and knife.cutter.refused is None
    assert body.mass == pytest.approx(model.tetmesh.volume() * 1060.0, rel=1e-4)  # (1.5e-6: nodes moved)
    scene.run(200)  # settled (mass damping: 30 /s)
    pieces, label = body.driver.model.tetmesh.components()
    tip = label == label[scene.attachments[0].nodes_a[0]]
    assert pieces == 2 and not body.driver.model.fixed[tip].any()
    weight = body.masses[tip].sum() * 9.81  # the tip piece's, 0.1226 N: all the spring holds
    assert weight == pytest.approx(1060.0 * (L - 0.0705) * W * W * 9.81, rel=1e-3)
    assert scene.contacts[("beam", "tip")] == pytest.approx([0.0, 0.0, weight], rel=1e-6, abs=1e-9 * weight)
    stretch = -50.0 * body.driver.displacements()[scene.attachments[0].nodes_a, 2].sum()
    assert stretch == pytest.approx(weight, rel=1e-6)  # the springs' stretch says so too

    prony = rt.SolidModel(rt.meshes.box(L, W, W, nx=10, ny=2, nz=2),
                          rt.Prony(rt.NeoHookean(mu=1e4, kappa=1e5), g=[0.5], tau=[0.05]), element="tet4").fix("x0")
    scene = rt.Scene()
    scene.add_body("b", rt.DirectSimulator(prony, 5e-3, large_deformation=True), prony.mesh)
    with pytest.raises(ModelError, match="Prony"):
        scene.add_scalpel("k", "b", Keyframes(PATH).device())
    with pytest.raises(ModelError, match="position"):
        scene.add_scalpel("k", "b", "a device")
    with pytest.raises(ModelError, match="no body named"):
        scene.add_scalpel("k", "nobody", Keyframes(PATH).device())
    assert scene.scalpels == [] and scene.bodies[0].driver.model is prony  # nothing taken


@pytest.mark.parametrize("compiled", [True, False])
def test_a_probe_above_a_slit_in_its_plane_touches_nothing(compiled):
    """The slit's two lips are coincident faces: a probe 10 mm above the slit, in its plane, took one of them
    for the closest face and was 'inside' by 10 mm (a kick of 5.7 mm on a beam nothing touched). The
    closest feature's side is now its faces' normals summed (the top edge's: up)."""
    model, scene, knife = _beam_scene(x=L / 2)
    scene.compiled = compiled
    scene.run(30)
    assert knife.cuts >= 1
    scene.add_tool("probe", Keyframes([[0.0, L / 2, W / 2, W + 0.01]]).device(), kind="probe", radius=0.0015,
                   stiffness=300.0)
    U0 = np.asarray(scene.body("beam").driver.displacements()).copy()
    scene.run(5)
    assert np.all(scene.contacts[("beam", "probe")] == 0.0)
    assert np.abs(np.asarray(scene.body("beam").driver.displacements()) - U0).max() < 1e-9


def test_a_grasper_holds_the_piece_the_scalpel_cuts_free_and_carries_its_weight():
    """The surgeon's grasp-and-cut: a grasper holds the top of a cantilever near its tip, still, while the
    scalpel cuts across the beam at 0.705 L from below through its whole height. The tip piece, parted, hangs
    in the grasp alone (its grasped node is the cut model's tethered one): settled, the grasp's force is the
    piece's weight (1e-6), upward, and nothing else holds it."""
    model = rt.SolidModel(rt.meshes.box(L, W, W, nx=20, ny=4, nz=4), MAT, element="tet4").fix("x0")
    scene = rt.Scene(gravity=(0.0, 0.0, -9.81))
    scene.add_body("beam", rt.DirectSimulator(model, 5e-3, rt.Damping(alpha=60.0), large_deformation=True), model.mesh)
    hold = [[0.0, 0.09, W / 2, W], [10.0, 0.09, W / 2, W]]
    grasper = scene.add_tool("grip", Keyframes(hold, [[0.0, 100.0]]).device(), kind="grasper", radius=0.004)
    path = [[0.0, 0.0705, -0.005, -0.01], [0.1, 0.0705, -0.005, -0.01], [0.2, 0.0705, W + 0.005, -0.01]]
    knife = scene.add_scalpel("knife", "beam", Keyframes(path).device(), blade=(0.0, 0.0, W + 0.02), toughness=0.0)
    scene.run(400)  # settled (the tip piece swings aside while it is cut; mass damping 30 /s)
    body = scene.body("beam")
    pieces, label = body.driver.model.tetmesh.components()
    assert knife.cuts >= 1 and knife.cutter.refused is None and pieces == 2 and grasper.held is not None
    tip = label == label[grasper.held.nodes_a[0]]
    assert not body.driver.model.fixed[tip].any() and body.driver.model.tethered.size == grasper.held.nodes_a.size
    weight = body.masses[tip].sum() * 9.81  # (0.4 % over the plane x = 0.0705's: the cut is where the blade met
    assert weight == pytest.approx(1060.0 * (L - 0.0705) * W * W * 9.81, rel=1e-2)  # the sagging beam)
    assert scene.contacts[("beam", "grip")] == pytest.approx([0.0, 0.0, weight], rel=1e-6, abs=1e-6 * weight)


def test_a_cut_job_that_fails_is_raised_by_its_step_with_zero_force_and_the_scene_cuts_on_to_the_same_beam():
    """A cut job failing with an error of its own (not rt.cut's refusal) is raised by the step it failed in,
    the step taken (it was said only by the blade's next tick in the tissue, which then stopped the scalpel
    for good, and never while the blade was out of it); the hand is given zero force at that step; the scene
    steps on, and the next strips' jobs take the failed job's strips with their own: the beam ends cut node
    for node as a run in which no job failed cuts it."""
    _, clean, knife0 = _beam_scene()
    clean.run(30)
    model, scene, knife = _beam_scene()
    cutter, device = knife.cutter, knife.device
    real, calls = cutter._cut, []

    def fails(*args, **kwargs):
        calls.append(scene.steps)
        if len(calls) <= 2:
            raise ValueError("a fault of the cut's own")
        return real(*args, **kwargs)

    cutter._cut = fails
    raised = []
    while scene.steps < 30:
        before = scene.steps
        try:
            scene.step()
        except ModelError as exc:
            raised.append((before, str(exc)))
            assert scene.steps == before + 1 and np.all(device.forces[-1] == 0.0)  # the step taken, the hand freed
    assert [k for k, _ in raised] == calls[:2] and knife.cuts >= 1 and knife0.cuts >= 1
    assert "scalpel knife: a cut job failed (ValueError: a fault of the cut's own)" in raised[0][1]
    assert cutter.stop_reason is None and cutter._applied == knife0.cutter._applied > 0  # (the stroke's last strips
    # cut no face whole: in neither model)
    a, b = scene.body("beam").driver.model.tetmesh, clean.body("beam").driver.model.tetmesh
    assert a.n_tets == b.n_tets and a.n_vertices == b.n_vertices > model.n_nodes  # (on element faces: nodes copied)
    assert np.array_equal(np.sort(np.asarray(a.vertices), axis=0), np.sort(np.asarray(b.vertices), axis=0))


def test_the_scene_viewer_says_a_failed_cut_job_and_steps_on_to_the_cut(tmp_path):
    """In the scene viewer's session a cut job's failure is said in the panel (session.error) and the clock
    steps on (a failed step stops it); the beam is cut in the end as without the failure."""
    from rtfem.viewer.scene_session import SceneSession

    scene = load_scene(_scene_file(tmp_path))
    knife = scene.scalpels[0]
    real, calls = knife.cutter._cut, []

    def fails_once(*args, **kwargs):
        calls.append(scene.steps)
        if len(calls) == 1:
            raise RuntimeError("a fault of the cut's own")
        return real(*args, **kwargs)

    knife.cutter._cut = fails_once
    session = SceneSession(scene, playing=False)
    for _ in range(140):  # 0.7 s: the blade has crossed the beam (0.3 - 0.6 s)
        session.step()
    assert scene.steps == 140 and len(calls) > 1 and knife.cuts >= 1
    assert "scalpel knife: a cut job failed (RuntimeError: a fault of the cut's own)" in session.error
    clean = load_scene(_scene_file(tmp_path))
    clean.run(140)
    assert _same_mesh(knife.model.tetmesh, clean.scalpels[0].model.tetmesh, tol=1e-15)
