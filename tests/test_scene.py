"""Scene files and `rtfem simulate scene.toml` (rtfem.interaction.scene_file, rtfem.cli.scene): a body
resting on a plane settles with the plane's force in contacts.csv equal to its weight; every bad
file names the file, the table and the key, before any precompute where it can."""

from __future__ import annotations

import csv

import numpy as np
import pytest

import rtfem as rt
from rtfem.cli.main import main
from rtfem.interaction.scene_file import load_scene

SCENE = """gravity = [0, 0, -9.81]

[[body]]
name = "box"
mesh = "box.vtu"
element = "tet4"
material = { E = 3e4, nu = 0.3, density = 1000 }
modes = 20
alpha = 20.0

[[obstacle]]
name = "table"
plane = { point = [0, 0, -0.002], normal = [0, 0, 1] }
friction = 0.3
"""


HANG = """
[[attachment]]
name = "ligament"
body = "box"
nodes = "z>0.049"
to = "world"
stiffness = 500.0
"""


LIFT = """
[[tool]]
name = "hand"
kind = "grasper"
path = [[0.0, 0.05, 0.05, 0.049], [0.3, 0.05, 0.05, 0.049], [0.8, 0.05, 0.05, 0.079]]
closed = [[0.2, 9.0]]
radius = 0.015
stiffness = 2000.0
"""


@pytest.fixture()
def folder(tmp_path):
    rt.save_mesh(rt.meshes.box(0.1, 0.1, 0.05, nx=4, ny=4, nz=2), tmp_path / "box.vtu")
    (tmp_path / "scene.toml").write_text(SCENE)
    return tmp_path


def test_rtfem_simulate_a_scene_file_settles_on_the_plane_with_its_weight(folder, capsys):
    assert main(["simulate", str(folder / "scene.toml"), "--duration", "1.5", "--out", str(folder / "out")]) == 0
    with open(folder / "out" / "contacts.csv") as fh:
        rows = list(csv.reader(fh))
    assert rows[0] == ["t", "a", "b", "fx", "fy", "fz"] and len(rows) == 1501
    t, a, b, *f = rows[-1]
    weight = 0.1 * 0.1 * 0.05 * 1000 * 9.81
    assert (a, b) == ("box", "table") and abs(float(f[2]) - weight) < 0.01 * weight
    assert (folder / "out" / "box" / "box.pvd").exists()
    assert "weight 4.905 N" in capsys.readouterr().out


def test_a_scene_file_body_hung_on_springs_they_carry_its_weight(folder):
    """The box hung by its top face, nothing under it: the springs' force in contacts.csv is its weight."""
    (folder / "scene.toml").write_text(SCENE.split("[[obstacle]]")[0] + HANG)
    assert main(["simulate", str(folder / "scene.toml"), "--duration", "1.0", "--out", str(folder / "out")]) == 0
    with open(folder / "out" / "contacts.csv") as fh:
        t, a, b, *f = list(csv.reader(fh))[-1]
    weight = 0.1 * 0.1 * 0.05 * 1000 * 9.81
    assert (a, b) == ("box", "ligament") and abs(float(f[2]) - weight) < 0.01 * weight


def test_a_scene_file_grasper_lifts_the_box_off_the_table(folder):
    """A scripted grasper closes on the box's top and lifts it 3 cm: contacts.csv ends with the
    grasper carrying the weight and the table nothing."""
    (folder / "scene.toml").write_text(SCENE + LIFT)
    assert main(["simulate", str(folder / "scene.toml"), "--duration", "1.6", "--out", str(folder / "out")]) == 0
    with open(folder / "out" / "contacts.csv") as fh:
        last = {(a, b): np.array(f, float) for t, a, b, *f in list(csv.reader(fh))[-2:]}
    weight = 0.1 * 0.1 * 0.05 * 1000 * 9.81
    assert np.abs(last[("box", "table")]).max() == 0.0
    assert abs(last[("box", "hand")][2] - weight) < 0.01 * weight


@pytest.mark.parametrize("edit, match", [
    (lambda s: s.replace('name = "box"\n', ""), r"scene.toml: \[\[body\]\] 1: key 'name': missing"),
    (lambda s: s.replace("modes = 20", "modes = 0"), r"\[\[body\]\] 1 'box': key 'modes'"),
    (lambda s: s.replace("modes = 20", "modez = 20"), r"key 'modez': unknown \(known: "),
    (lambda s: s.replace("nu = 0.3", "nu = 0.7"), r"\[\[body\]\] 1 'box': key 'material': .*nu"),
    (lambda s: s.replace('mesh = "box.vtu"', 'mesh = "nothing.vtu"'), r"\[\[body\]\] 1 'box': key 'mesh'"),
    (lambda s: s.replace("normal = [0, 0, 1]", "normal = [0, 0, 0]"), r"\[\[obstacle\]\] 1 'table': key 'plane'"),
    (lambda s: s.replace("plane = {", "plain = {"), r"\[\[obstacle\]\] 1 'table': key 'plain': unknown"),
    (lambda s: s + "\n[[tool]]\nname = 'jaw'\n", r"\[\[tool\]\] 1 'jaw': key 'path': missing"),
    (lambda s: s + LIFT.replace('"grasper"\npath', '"scissors"\npath'), r"\[\[tool\]\] 1 'hand': key 'kind'"),
    (lambda s: s + LIFT.replace("[0.8, 0.05", "[0.1, 0.05"), r"key 'path': .*times must increase"),
    (lambda s: s + LIFT.replace("[[0.2, 9.0]]", "[[0.2, 0.1]]"), r"key 'closed': .*t_off > t_on"),
    (lambda s: s + LIFT.replace("radius = 0.015", "radius = -1"), r"key 'radius'"),
    (lambda s: s + LIFT.replace('kind = "grasper"', 'kind = "probe"'), r"key 'closed': only a grasper closes"),
    (lambda s: s.replace("friction = 0.3", "friction = 0.3\nmesh = 'box.vtu'"),
     r"\[\[obstacle\]\] 1 'table': key 'plane': give plane = .* or mesh = a surface file, one of them"),
    (lambda s: s.replace("plane = { point = [0, 0, -0.002], normal = [0, 0, 1] }", ""),
     r"\[\[obstacle\]\] 1 'table': key 'plane': give plane = .* or mesh"),
    (lambda s: s.replace("plane = { point = [0, 0, -0.002], normal = [0, 0, 1] }", "mesh = 'nothing.stl'"),
     r"\[\[obstacle\]\] 1 'table': key 'mesh'"),
    (lambda s: s + LIFT.replace("[[tool]]", "[[tool]]\ndevice = 'mouse'"), r"\[\[tool\]\] 1 'hand': key 'device': .*'mouse'; "
     "choose one of 'openhaptics', 'forcedimension', 'haply', 'igtl'"),
    (lambda s: s + LIFT.replace("[[tool]]", "[[tool]]\ndevice = 'igtl'"), r"key 'path': a tool follows a scripted path "
     "or a live device, not both"),
    (lambda s: s + LIFT.replace("[[tool]]", "[[tool]]\ndevice = 'haply'\nport = 1").split("path")[0],
     r"key 'port': is for device = 'igtl'"),
    (lambda s: s + LIFT.replace("[[tool]]", "[[tool]]\nmax_force = 3.0"), r"key 'max_force': is for a tool on a live device"),
    (lambda s: s + LIFT.replace("[[tool]]", "[[tool]]\ndevice = 'igtl'\nport = 70000").split("path")[0],
     r"key 'port': .*a TCP port"),
    (lambda s: s + HANG.replace('"box"', '"boxx"'), r"\[\[attachment\]\] 1 'ligament': key 'body': no body named 'boxx'"),
    (lambda s: s + HANG.replace('to = "world"', 'to = "sky"'), r"key 'to': no body named 'sky' .*or 'world'"),
    (lambda s: s + HANG.replace("z>0.049", "z>0.2"), r"key 'nodes': .*'z>0.2' selects no node of box"),
    (lambda s: s + HANG.replace("500.0", "-5"), r"key 'stiffness': .*> 0"),
    (lambda s: s + HANG.replace('to = "world"', 'to = "box"'), r"key 'nodes': .*attached to itself"),
    (lambda s: s + HANG.replace("stiffness", "stifness"), r"key 'stifness': unknown"),
    (lambda s: s.replace("gravity = [0, 0, -9.81]", "gravity = [0, -9.81]"), r"the top level: key 'gravity'"),
    (lambda s: s.replace("[[body]]", "[[bodies]]"), r"the top level: key 'bodies': unknown"),
    (lambda s: s.replace('name = "table"', 'name = "box"'), r"\[\[obstacle\]\] 1 'box'.*named 'box'"),
    (lambda s: "gravity = [0, 0, -9.81\n", r"scene.toml: not a TOML scene file"),
])
def test_bad_scene_files_name_the_file_the_table_and_the_key(folder, edit, match):
    (folder / "scene.toml").write_text(edit(SCENE))
    with pytest.raises(rt.ModelError, match=match):
        load_scene(folder / "scene.toml")


def test_scene_refusals(folder):
    sc = rt.Scene()
    with pytest.raises(rt.ModelError, match="no body"):
        sc.step()
    with pytest.raises(rt.ModelError, match="gravity"):
        rt.Scene(gravity=(0, 0))
    model = rt.SolidModel(rt.meshes.box(0.1, 0.1, 0.05, nx=2, ny=2, nz=1), rt.Material(E=3e4, nu=0.3, density=1000.0),
                          element="tet4")
    sim = rt.ModalSimulator(rt.modal_analysis(model, 8), dt=1e-3)
    with pytest.raises(rt.ModelError, match="another mesh|mesh of"):
        sc.add_body("a", sim, rt.meshes.plate(0.1, nx=2))
    sc.add_body("a", sim, model.mesh)
    with pytest.raises(rt.ModelError, match="already has a body, obstacle, attachment, tool or scalpel named 'a'"):
        sc.add_plane("a", (0, 0, 0), (0, 0, 1))
    with pytest.raises(rt.ModelError, match="friction"):
        sc.add_plane("p", (0, 0, 0), (0, 0, 1), friction=-1)
    other = rt.ModalSimulator(rt.modal_analysis(model, 8), dt=2e-3)
    with pytest.raises(rt.ModelError, match="dt = 0.002 s"):
        sc.add_body("b", other, model.mesh)
    with pytest.raises(rt.ModelError, match="kind='scissors'; give one of 'probe', 'grasper'"):
        sc.add_tool("t", rt.ScriptedDevice(lambda t: (0, 0, 0)), kind="scissors")
    with pytest.raises(rt.ModelError, match="position\\(t\\) and set_force"):
        sc.add_tool("t", lambda t: (0, 0, 0))
    with pytest.raises(rt.ModelError, match="radius"):
        sc.add_tool("t", rt.ScriptedDevice(lambda t: (0, 0, 0)), radius=0.0)
    tool = sc.add_tool("t", rt.ScriptedDevice(lambda t: (0.0, np.nan, 0.0)))
    with pytest.raises(rt.ModelError, match="tool t: the device's position.*non-finite"):
        sc.step()
    sc.tools.remove(tool)
    with pytest.raises(rt.ModelError, match="must be an rt.TriMesh with triangles"):
        sc.add_obstacle("o", rt.meshes.box(0.1, 0.1, 0.1, 1, 1, 1))
    with pytest.raises(rt.ModelError, match="friction"):
        sc.add_obstacle("o", rt.meshes.plate(0.1, nx=2), friction=-1.0)
    with pytest.raises(rt.ModelError, match="times must increase"):
        rt.Keyframes([[0.0, 0, 0, 0], [0.0, 0, 0, 1]])
    with pytest.raises(rt.ModelError, match="rows \\[t, x, y, z\\]"):
        rt.Keyframes([[0.0, 0, 0]])
    assert [b.name for b in sc.bodies] == ["a"] and sc.obstacles == [] and sc.tools == []  # nothing half added
    assert main(["simulate", str(folder / "nothing.toml")]) == 2  # one line, exit 2
    for argv in (["simulate", "--example", "gallbladder", str(folder / "scene.toml")],  # before any precompute
                 ["view", "--example", "gallbladder", str(folder / "scene.toml")],
                 ["view", "--example", "gallbladder", "--benchmark", "1"]):
        assert main(argv) == 2, argv
    np.testing.assert_equal(sc.time, 0.0)


def test_the_example_scene_the_grasper_and_the_cystic_plate_hold_the_gallbladder(tmp_path):
    """rtfem simulate --example gallbladder: by 1.3 s the grasper has retracted the fundus and stopped,
    the probe presses the liver, and the gallbladder is in equilibrium: the grasper's and the cystic
    plate's forces on it carry its weight, rho t A of its 2 mm wall (2 %), and balance across."""
    out = tmp_path / "out"
    assert main(["simulate", "--example", "gallbladder", "--duration", "1.3", "--fps", "10", "--out", str(out)]) == 0
    with open(out / "contacts.csv") as fh:
        rows = list(csv.reader(fh))
    last = {(a, b): np.array(f, float) for t, a, b, *f in rows[1:] if t == rows[-1][0]}
    X = np.asarray(rt.meshes.gallbladder().vertices)[np.asarray(rt.meshes.gallbladder().triangles)]
    area = 0.5 * np.linalg.norm(np.cross(X[:, 1] - X[:, 0], X[:, 2] - X[:, 0]), axis=1).sum()
    weight = 1030 * 0.002 * area * 9.81  # the scene file's wall
    held = last[("gallbladder", "grasper")] + last[("gallbladder", "cystic plate")]
    assert np.linalg.norm(last[("gallbladder", "grasper")]) > 1.0  # retracting: a newton or more
    assert abs(held[2] - weight) < 0.02 * weight and np.abs(held[:2]).max() < 0.02 * weight
    assert last[("liver", "probe")][2] < -0.1  # the probe presses the liver down
    assert np.allclose(last[("liver", "cystic plate")], -last[("gallbladder", "cystic plate")])


def _free_port():
    import socket

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


LIVE = """
[[tool]]
name = "probe"
kind = "probe"
radius = 0.01
stiffness = 500.0
device = "igtl"
max_force = 1.0
port = {port}
"""


def test_a_scene_files_probe_on_a_live_device_presses_the_box_and_the_force_goes_back(folder):
    """[[tool]] device = "igtl": load_scene opens the OpenIGTLink adapter before the precompute; a
    client's ToolToReference pose (mm) 5 mm into the box's top is the probe's hand, the box is pressed
    (the probe's force on it points down), the force goes back to the client as 'Force' (clamped to the
    file's max_force), and close_devices frees the port. `rtfem simulate` refuses the live hand."""
    pyigtl = pytest.importorskip("pyigtl", reason="the igtl extra (pyigtl) is not installed: pip install 'rtfem[igtl]'")
    import time

    from rtfem.interaction.scene_file import close_devices

    port = _free_port()
    (folder / "scene.toml").write_text(SCENE + LIVE.format(port=port))
    assert main(["simulate", str(folder / "scene.toml"), "--duration", "0.1", "--out", str(folder / "out")]) == 2
    scene = load_scene(folder / "scene.toml")
    client = pyigtl.OpenIGTLinkClient("127.0.0.1", port)
    try:
        t0 = time.perf_counter()
        while not client.is_connected():
            assert time.perf_counter() - t0 < 10.0
            time.sleep(0.01)
        M = np.eye(4)
        M[:3, 3] = [50.0, 50.0, 50.0 + 10.0 - 5.0]  # the sphere's centre 5 mm below its touching height (mm)
        client.send_message(pyigtl.TransformMessage(M, device_name="ToolToReference"), wait=True)
        device = scene.tools[0].device
        while not np.allclose(device.position(0.0), M[:3, 3] * 1e-3):
            assert time.perf_counter() - t0 < 10.0
            time.sleep(0.002)
        force, start = None, time.perf_counter()
        while time.perf_counter() - start < 1.5:  # ~1 kHz: the device's watchdog is fed
            scene.step()
            got = [m for m in client.get_latest_messages() if m.device_name == "Force"]
            if got:
                force = np.asarray(got[-1].matrix)[:3, 3]
            time.sleep(max(0.0, scene.dt - 2e-4))
        pressed = scene.contacts[("box", "probe")]
        assert pressed[2] < -0.5  # the probe pushes the box down into the table
        # the hand feels the box pushing back, clamped to the file's max_force
        assert force is not None and abs(np.linalg.norm(force) - 1.0) < 1e-6 and force[2] > 0.999
    finally:
        client.stop()
        close_devices(scene)
    rt.devices.IGTLDevice(port).close()  # the port is free again


def test_a_scene_file_device_that_cannot_open_is_said_before_any_precompute(folder):
    """A device whose SDK is missing is named with the file, the table and the key before any body is
    computed; a file that turns out bad after a device opened closes it (its port is free)."""
    from rtfem.errors import DeviceError

    calls = []
    (folder / "scene.toml").write_text(SCENE + LIVE.format(port=1).replace('"igtl"', '"openhaptics"')
                                       .replace("port = 1", ""))
    try:
        rt.devices.OpenHaptics()
    except DeviceError:
        with pytest.raises(rt.ModelError, match=r"scene.toml: \[\[tool\]\] 1 'probe': key 'device': .*OpenHaptics"):
            load_scene(folder / "scene.toml", progress=calls.append)
        assert calls == []  # no precompute began
    pytest.importorskip("pyigtl", reason="the igtl extra (pyigtl) is not installed: pip install 'rtfem[igtl]'")
    port = _free_port()
    (folder / "scene.toml").write_text(SCENE.replace("modes = 20", "modes = 0") + LIVE.format(port=port))
    with pytest.raises(rt.ModelError, match=r"\[\[body\]\] 1 'box': key 'modes'"):
        load_scene(folder / "scene.toml")
    rt.devices.IGTLDevice(port).close()  # closed when the file was refused
