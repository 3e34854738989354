"""rt.devices: the workspace map, the servo's safety (clamp, rate limit, watchdog, clutch) and the
OpenHaptics adapter against a stub libHD.so compiled here from tests/stubs/hd_stub.c (the C
compiler on the machine; without one these tests skip and say so): positions from the stylus in
millimetres arrive in the organ's frame in metres, the loop's force reaches the device rotated,
clamped and rate limited, and an HD error, a disconnection or a loop that stops feeding forces
zero the force with a reason."""

from __future__ import annotations

import ctypes
import ctypes.util
import json
import shutil
import subprocess
import threading
import time
from pathlib import Path

import numpy as np
import pytest

import rtfem as rt
from rtfem.interaction.devices import Workspace
from rtfem.interaction.devices.servo import Servo

STUBS = Path(__file__).resolve().parent / "stubs"

R_STYLUS = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])  # stylus y up -> organ z up


def _rotation(axis, angle):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


# ------------------------------------------------------------------------------------- workspace


def test_fit_centres_the_workspace_on_the_organs_top_and_fits_the_organ():
    organ = (np.array([-0.1, -0.05, 0.0]), np.array([0.1, 0.05, 0.08]))
    device = (np.array([-0.08, -0.06, -0.035]), np.array([0.08, 0.06, 0.035]))
    ws = Workspace.fit(device, organ, rotation=R_STYLUS, fill=0.8)
    assert np.allclose(ws.to_organ([0.0, 0.0, 0.0]), [0.0, 0.0, 0.08])  # the workspace's centre: the organ's top
    corners = np.array([[x, y, z] for x in device_lo_hi(device, 0) for y in device_lo_hi(device, 1)
                        for z in device_lo_hi(device, 2)])
    mapped = np.array([ws.to_organ(c) for c in corners])
    span = mapped.max(axis=0) - mapped.min(axis=0)
    extent = organ[1] - organ[0]
    assert np.all(span >= extent - 1e-12)  # the organ fits in the mapped workspace
    assert np.isclose(np.max(extent / span), 0.8)  # and fills 0.8 of it along the tightest axis
    f = np.array([0.3, -1.2, 2.0])
    assert np.allclose(R_STYLUS @ ws.force_to_device(f), f)


def device_lo_hi(box, axis):
    return box[0][axis], box[1][axis]


@pytest.mark.parametrize("bad", [dict(scale=0), dict(scale=np.nan), dict(rotation=np.diag([1.0, 1.0, -1.0])),
                                 dict(rotation=np.ones((3, 3))), dict(offset=(0, 0)), dict(clutch=40)])
def test_bad_workspaces_are_refused(bad):
    with pytest.raises(rt.ModelError):
        Workspace(**bad)


# ------------------------------------------------------------------------------------------ servo


def _servo(**kw):
    ws = Workspace(scale=2.0, rotation=_rotation([1, 2, 3], 0.7), offset=(0.01, -0.02, 0.05), clutch=1)
    return Servo(ws, kw.pop("max_force", 3.0), max_rate=kw.pop("max_rate", 1e6), watchdog=kw.pop("watchdog", 20),
                 rate=1000.0)


def test_servo_maps_positions_and_forces_through_the_workspace():
    s = _servo()
    R = s.workspace.rotation
    x = np.array([0.003, -0.02, 0.011])
    s.mailbox[3:6] = [0.5, -0.2, 0.9]
    s.mailbox[6] = 1
    f = s.tick(x)
    assert np.allclose(s.mailbox[:3], [0.01, -0.02, 0.05] + 2.0 * R @ x)
    assert np.allclose(f, R.T @ [0.5, -0.2, 0.9])


def test_servo_clamps_the_force_and_limits_its_rate():
    s = _servo(max_force=3.0, max_rate=2000.0)  # 2 N per 1 ms tick
    s.mailbox[3:6] = [0.0, 0.0, 10.0]
    out = []
    for k in range(5):
        s.mailbox[6] += 1
        out.append(np.linalg.norm(s.tick([0.0, 0.0, 0.0])))
    assert np.allclose(out, [2.0, 3.0, 3.0, 3.0, 3.0])  # up by at most 2 N a tick, then the 3 N clamp


def test_watchdog_stops_a_servo_the_loop_no_longer_feeds_and_restart_resumes():
    s = _servo(watchdog=20)
    s.mailbox[3:6] = [0.0, 0.0, 1.0]
    s.mailbox[6] = 1
    assert s.reason is None and np.linalg.norm(s.tick([0, 0, 0])) > 0.99
    for _ in range(20):
        s.tick([0, 0, 0])
    assert s.reason is None  # 20 ticks without a new force: still within the watchdog
    f = s.tick([0, 0, 0])
    assert np.array_equal(f, np.zeros(3)) and "fell behind" in s.reason and "20 servo ticks" in s.reason
    s.mailbox[6] += 1
    assert np.array_equal(s.tick([0, 0, 0]), np.zeros(3))  # stays stopped until restarted
    s.restart()
    s.mailbox[6] += 1
    assert s.reason is None and np.linalg.norm(s.tick([0, 0, 0])) > 0.99


def test_a_non_finite_force_stops_the_servo():
    s = _servo()
    s.mailbox[3:6] = [0.0, np.nan, 1.0]
    s.mailbox[6] = 1
    assert np.array_equal(s.tick([0, 0, 0]), np.zeros(3)) and "not finite" in s.reason


def test_the_clutch_freezes_the_tool_and_re_indexes_the_offset():
    s = _servo()
    s.mailbox[3:6] = [0.0, 0.0, 1.0]
    s.mailbox[6] = 1
    s.tick([0.0, 0.0, 0.0])
    before = s.mailbox[:3].copy()
    s.mailbox[6] += 1
    f = s.tick([0.05, 0.0, 0.0], buttons=0b10)  # the clutch (button 1) held while the hand moves 5 cm
    assert np.allclose(s.mailbox[:3], before) and np.array_equal(f, np.zeros(3))
    s.mailbox[6] += 1
    s.tick([0.05, 0.01, 0.0], buttons=0b11)
    assert np.allclose(s.mailbox[:3], before)
    s.mailbox[6] += 1
    s.tick([0.05, 0.01, 0.0], buttons=0b01)  # released: the tool goes on from where it was
    assert np.allclose(s.mailbox[:3], before)
    s.mailbox[6] += 1
    s.tick([0.06, 0.01, 0.0])
    assert np.allclose(s.mailbox[:3], before + 2.0 * s.workspace.rotation @ [0.01, 0.0, 0.0])


@pytest.mark.parametrize("bad", [dict(max_force=0), dict(max_rate=-1), dict(watchdog=0)])
def test_bad_servo_settings_are_refused(bad):
    with pytest.raises(rt.ModelError):
        _servo(**bad)


# -------------------------------------------------------------------------- OpenHaptics, stubbed


def _stub(tmp_path_factory, source: str, name: str):
    """Compile tests/stubs/<source> into a shared library; (its path, the library for the test's controls)."""
    cc = shutil.which("cc") or shutil.which("gcc")
    if cc is None:
        pytest.skip(f"no C compiler to build the stub {name} (apt-get install gcc)")
    out = tmp_path_factory.mktemp(name.split(".")[0]) / name
    run = subprocess.run([cc, "-shared", "-fPIC", "-O1", "-o", str(out), str(STUBS / source), "-lpthread"],
                         capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    lib = ctypes.CDLL(str(out))
    lib.stub_script.argtypes = [ctypes.POINTER(ctypes.c_double), ctypes.POINTER(ctypes.c_int), ctypes.c_int]
    lib.stub_forces.argtypes = [ctypes.POINTER(ctypes.c_double), ctypes.c_int]
    lib.stub_fail.argtypes = [ctypes.c_int, ctypes.c_uint]
    return out, lib


@pytest.fixture(scope="module")
def libhd(tmp_path_factory):
    return _stub(tmp_path_factory, "hd_stub.c", "libHD_stub.so")


@pytest.fixture(scope="module")
def libdhd(tmp_path_factory):
    path, lib = _stub(tmp_path_factory, "dhd_stub.c", "libdhd_stub.so")
    lib.stub_max_force.argtypes = [ctypes.c_double]
    return path, lib


def _script(lib, positions_mm, buttons=None):
    p = np.ascontiguousarray(positions_mm, dtype=float)
    b = None if buttons is None else np.ascontiguousarray(buttons, dtype=np.int32)
    lib.stub_reset()
    lib.stub_script(p.ctypes.data_as(ctypes.POINTER(ctypes.c_double)),
                    None if b is None else b.ctypes.data_as(ctypes.POINTER(ctypes.c_int)), len(p))


def _recorded(lib, n):
    out = np.zeros((n, 3))
    lib.stub_forces(out.ctypes.data_as(ctypes.POINTER(ctypes.c_double)), n)
    return out


def _wait_frames(lib, n, timeout=5.0):
    t0 = time.perf_counter()
    while lib.stub_frame() < n:
        assert time.perf_counter() - t0 < timeout, f"the stub's scheduler reached frame {lib.stub_frame()} of {n}"
        time.sleep(0.002)


def test_openhaptics_positions_in_the_organs_frame_and_forces_back_clamped(libhd):
    path, lib = libhd
    n = 400
    stylus = np.column_stack([np.linspace(0, 20, n), np.full(n, 5.0), np.linspace(-10, 10, n)])  # mm
    _script(lib, stylus)
    ws = Workspace(scale=1.5, rotation=R_STYLUS, offset=(0.1, 0.2, 0.3))
    with rt.devices.OpenHaptics(library=path, workspace=ws, max_rate=1e5) as dev:
        assert dev.nominal_max_force == pytest.approx(3.3)  # read from the device (HD_NOMINAL_MAX_FORCE)
        _wait_frames(lib, 50)
        k = lib.stub_frame()
        x = dev.position(0.0)
        seen = [ws.to_organ(stylus[j] * 1e-3) for j in range(max(k - 3, 0), min(k + 3, n))]
        assert min(np.abs(x - s).max() for s in seen) < 1e-12  # mm -> m, then the workspace
        f_organ = np.array([0.4, -0.3, 1.1])
        t0 = time.perf_counter()
        while time.perf_counter() - t0 < 0.05:  # the loop's forces, fed faster than the watchdog
            dev.set_force(0.0, f_organ)
            time.sleep(0.001)
        k = lib.stub_frame()
        assert np.allclose(_recorded(lib, k)[k - 1], R_STYLUS.T @ f_organ)  # the device's frame
        while lib.stub_frame() < k + 20:
            dev.set_force(0.0, [0.0, 0.0, 50.0])  # far beyond the device's 3.3 N
            time.sleep(0.001)
        k = lib.stub_frame()
        assert np.linalg.norm(_recorded(lib, k)[k - 1]) == pytest.approx(3.3)
        assert dev.stop_reason is None
    assert dev.stop_reason == "closed"


def test_openhaptics_stops_when_the_loop_stops_and_on_hd_errors(libhd):
    path, lib = libhd
    _script(lib, np.zeros((1, 3)))
    with rt.devices.OpenHaptics(library=path, max_rate=1e5, watchdog=30) as dev:
        dev.set_force(0.0, [0.0, 0.0, 1.0])  # one force, then the loop "stops"
        k = lib.stub_frame()
        _wait_frames(lib, k + 60)
        assert "fell behind" in dev.stop_reason
        k = lib.stub_frame()
        assert np.array_equal(_recorded(lib, k)[k - 1], np.zeros(3))
        dev.restart()
        lib.stub_fail(lib.stub_frame() + 20, 0x0201)  # HD_EXCEEDED_MAX_FORCE
        t0 = time.perf_counter()
        while dev.stop_reason is None and time.perf_counter() - t0 < 2.0:
            dev.set_force(0.0, [0.0, 0.0, 1.0])
            time.sleep(0.001)
        assert dev.stop_reason == "the device reported an error: HD_EXCEEDED_MAX_FORCE (0x0201)"
        k = lib.stub_frame()
        _wait_frames(lib, k + 3)
        assert np.array_equal(_recorded(lib, k + 2)[k + 1], np.zeros(3))
        dev.restart()
        lib.stub_disconnect(lib.stub_frame() + 10)
        t0 = time.perf_counter()
        while dev.stop_reason is None and time.perf_counter() - t0 < 2.0:
            dev.set_force(0.0, [0.0, 0.0, 1.0])
            time.sleep(0.001)
        assert dev.stop_reason == "the device disconnected: HD_COMM_ERROR (0x0302)"


def test_openhaptics_refusals_name_the_problem(libhd, tmp_path):
    path, lib = libhd
    lib.stub_reset()
    with pytest.raises(rt.DeviceError, match=r"hdInitDevice\('missing'\) failed: HD_COMM_ERROR \(0x0302\)"):
        rt.devices.OpenHaptics("missing", library=path)
    with pytest.raises(rt.DeviceError, match="cannot load .*Install 3D Systems' OpenHaptics"):
        rt.devices.OpenHaptics(library=tmp_path / "libHD.so")
    with pytest.raises(rt.DeviceError, match="has no hdInitDevice"):
        rt.devices.OpenHaptics(library=ctypes.util.find_library("m"))  # a library, not the HD API


# ---------------------------------------------------------------------- Force Dimension, stubbed


def test_forcedimension_positions_forces_and_its_limit(libdhd):
    path, lib = libdhd
    n = 300
    handle = np.column_stack([np.linspace(-0.02, 0.02, n), np.zeros(n), np.linspace(0.0, 0.01, n)])  # m
    _script(lib, handle)
    R = _rotation([0, 0, 1], 0.5)
    ws = Workspace(scale=3.0, rotation=R, offset=(0.0, 0.1, -0.2))
    with rt.devices.ForceDimension(library=path, workspace=ws, max_force=5.0, max_rate=1e5) as dev:
        assert lib.stub_state() == 3  # open, force enabled
        _wait_frames(lib, 20)
        x = dev.position(0.0)
        assert min(np.abs(x - ws.to_organ(h)).max() for h in handle) < 1e-12  # metres in, organ frame out
        t0 = time.perf_counter()
        while time.perf_counter() - t0 < 0.05:
            dev.set_force(0.0, [1.0, 2.0, -0.5])
            time.sleep(0.001)
        k = lib.stub_frame()
        assert np.allclose(_recorded(lib, k)[k - 1], R.T @ [1.0, 2.0, -0.5])
        while lib.stub_frame() < k + 20:
            dev.set_force(0.0, [40.0, 0.0, 0.0])  # the device says 12 N, the user 5 N: 5 N
            time.sleep(0.001)
        k = lib.stub_frame()
        assert np.linalg.norm(_recorded(lib, k)[k - 1]) == pytest.approx(5.0)
        lib.stub_fail(lib.stub_frame() + 5, 2)  # DHD_ERROR_COM
        t0 = time.perf_counter()
        while dev.stop_reason is None and time.perf_counter() - t0 < 2.0:
            dev.set_force(0.0, [0.0, 0.0, 1.0])
            time.sleep(0.001)
        assert dev.stop_reason == ("the device disconnected: communication error between the host and the device "
                                   "(DHD error 2)")
    assert lib.stub_state() == 0  # force disabled, device closed
    assert dev.stop_reason.startswith("the device disconnected")


def test_forcedimension_refusals_name_the_problem(libdhd):
    path, lib = libdhd
    lib.stub_reset()
    lib.stub_no_device(1)
    with pytest.raises(rt.DeviceError, match=r"dhdOpen\(\) opened no device: no device found \(DHD error 5\)"):
        rt.devices.ForceDimension(library=path)
    lib.stub_reset()
    lib.stub_max_force(-1.0)  # a device enforcing no limit: the user must say one
    with pytest.raises(rt.DeviceError, match="enforces no force limit.*give max_force"):
        rt.devices.ForceDimension(library=path)
    assert lib.stub_state() == 0  # what was opened is closed again
    with rt.devices.ForceDimension(library=path, max_force=3.0) as dev:
        assert dev.servo.buf[22] == 3.0
    with pytest.raises(rt.DeviceError, match="Install Force Dimension's SDK"):
        rt.devices.ForceDimension(library="/nonexistent/libdhd.so")


# -------------------------------------------------------------------- Haply, a fake Inverse Service


class FakeInverseService:
    """A local WebSocket server speaking the Inverse Service 3.x JSON schema: a state message (the
    Inverse3's cursor position in m, a VerseGrip's buttons), then one more after each command it
    receives, whose force it records; it can close the connection, or send a message that is not
    JSON, after a given number of commands."""

    def __init__(self, positions, *, buttons=None, close_after=None, garbage_after=None):
        from websockets.sync.server import serve

        self.positions, self.buttons = np.asarray(positions, float), buttons
        self.close_after, self.garbage_after = close_after, garbage_after
        self.forces = []
        self.server = serve(self._handler, "127.0.0.1", 0)
        self.url = f"ws://127.0.0.1:{self.server.socket.getsockname()[1]}"
        threading.Thread(target=self.server.serve_forever, daemon=True).start()

    def _state(self, k):
        p = self.positions[min(k, len(self.positions) - 1)]
        b = 0 if self.buttons is None else self.buttons[min(k, len(self.buttons) - 1)]
        return json.dumps({"inverse3": [{"device_id": "05DA", "config": {"handedness": "right"},
                                         "state": {"cursor_position": {"x": p[0], "y": p[1], "z": p[2]}}}],
                           "wireless_verse_grip": [{"device_id": "61576", "state": {
                               "buttons": {"a": bool(b & 1), "b": bool(b & 2), "c": bool(b & 4)}}}]})

    def _handler(self, ws):
        k = 0
        ws.send(self._state(k))
        while True:
            try:
                msg = json.loads(ws.recv())
            except Exception:
                return
            self.forces.append([msg["inverse3"][0]["commands"]["set_cursor_force"]["values"][c] for c in "xyz"])
            k += 1
            if self.close_after is not None and k >= self.close_after:
                ws.close()
                return
            if self.garbage_after is not None and k >= self.garbage_after:
                ws.send("not the service's json")
                continue
            time.sleep(0.0005)
            ws.send(self._state(k))

    def stop(self):
        self.server.shutdown()


def _until(predicate, timeout=3.0):
    t0 = time.perf_counter()
    while not predicate():
        assert time.perf_counter() - t0 < timeout
        time.sleep(0.002)


def test_haply_positions_forces_and_buttons_through_the_service():
    n = 500
    cursor = np.column_stack([np.linspace(-0.05, 0.05, n), np.full(n, 0.02), np.zeros(n)])
    service = FakeInverseService(cursor, buttons=[0] * 100 + [0b100] * 400)
    R = _rotation([1, 1, 0], 0.3)
    ws = Workspace(scale=0.5, rotation=R, offset=(0.0, 0.0, 0.1))
    try:
        with rt.devices.Haply(service.url, workspace=ws, max_force=4.0, max_rate=1e5) as dev:
            assert dev.device_id == "05DA"
            _until(lambda: len(service.forces) > 150)
            x = dev.position(0.0)
            assert min(np.abs(x - ws.to_organ(c)).max() for c in cursor) < 1e-12
            assert dev.buttons == 0b100  # the VerseGrip's third button (c)
            t0 = time.perf_counter()
            while time.perf_counter() - t0 < 0.05:
                dev.set_force(0.0, [0.0, 30.0, 0.0])  # beyond the 4 N given
                time.sleep(0.001)
            assert np.linalg.norm(service.forces[-1]) == pytest.approx(4.0)
            assert np.allclose(np.array(service.forces[-1]) / 4.0, R.T @ [0.0, 1.0, 0.0])
            assert dev.stop_reason is None
    finally:
        service.stop()


def test_haply_stops_when_the_service_goes_or_sends_garbage():
    for kw, reason in ((dict(close_after=30), "the device disconnected: the Inverse Service closed the connection"),
                       (dict(garbage_after=30), "the device sent input that is malformed or out of range: the "
                                                "Inverse Service's message: not JSON (JSONDecodeError")):
        service = FakeInverseService(np.zeros((1, 3)), **kw)
        try:
            with rt.devices.Haply(service.url, max_force=2.0) as dev:
                _until(lambda: dev.stop_reason is not None)
                assert dev.stop_reason.startswith(reason), dev.stop_reason
                with pytest.raises(rt.DeviceError, match="open a new rt.devices.Haply"):
                    dev.restart()
        finally:
            service.stop()


def test_haply_refusals_name_the_problem():
    with pytest.raises(rt.DeviceError, match="give max_force"):
        rt.devices.Haply("ws://127.0.0.1:9")
    with socket_closed_port() as port:
        with pytest.raises(rt.DeviceError, match=f"cannot reach the Inverse Service at ws://127.0.0.1:{port}"):
            rt.devices.Haply(f"ws://127.0.0.1:{port}", max_force=2.0, timeout=1.0)
    with pytest.raises(rt.DeviceError, match="must be the service's WebSocket address"):
        rt.devices.Haply("localhost:10001", max_force=2.0)


class socket_closed_port:
    """A loopback port nothing listens on (bound, then closed)."""

    def __enter__(self):
        import socket

        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            return s.getsockname()[1]

    def __exit__(self, *exc):
        return False


# ------------------------------------------------------------------ OpenIGTLink, pyigtl's own client


@pytest.fixture(scope="module")
def plate():
    """A 10 cm plate held at its edge (a shell, 20 modes, static correction): the organ of the bridge test."""
    mesh = rt.meshes.plate(0.1, nx=10)
    model = rt.ShellModel(mesh, rt.Material(E=3e5, nu=0.45, thickness=0.004, density=1060))
    model.fix("boundary")
    modes = rt.modal_analysis(model, 20)
    return mesh, model, rt.ModalSimulator(modes, dt=1e-3, damping=rt.Damping(alpha=30.0), static_correction=True)


def _free_port():
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _pose(pyigtl, xyz_mm):
    M = np.eye(4)
    M[:3, 3] = xyz_mm
    return pyigtl.TransformMessage(M, device_name="ToolToReference")


def _polydata_reader(pyigtl):
    """A POLYDATA reader for pyigtl's client, which has none (its message table lacks POLYDATA and its
    PolyDataMessage._unpack_content, marked untested, indexes a struct.Struct): the OpenIGTLink
    POLYDATA body read as the protocol lays it out, ten big-endian uint32 (points, then count and byte
    size of vertices, lines, polygons, triangle strips, then attributes), float32 points, uint32 cells."""
    import struct

    class PolyData(pyigtl.PolyDataMessage):
        def _unpack_content(self, content):
            h = struct.unpack(">10I", content[:40])
            at = 40 + 12 * h[0]
            self.points = np.frombuffer(content[40:at], dtype=">f4").reshape(-1, 3).astype(float)
            at += h[2] + h[4]
            self.polygons = np.frombuffer(content[at:at + h[6]], dtype=">u4").astype(np.int64)
            self.n_polygons = h[5]

    return PolyData


def test_igtl_bridge_serves_a_pyigtl_client(plate, monkeypatch):
    """A tool moved into the organ feels a force pushing it back out (settled: within 5 % of the
    coupling spring in series with the plate's static point compliance at the centre, a sphere of
    5 mm on a 1 cm mesh touches about one node: 0.6 % measured), the Organ surface dents under it, the force is zero
    again once it leaves, and a NaN transform is refused without stopping the server."""
    pyigtl = pytest.importorskip("pyigtl", reason="the igtl extra (pyigtl) is not installed: pip install 'rtfem[igtl]'")
    monkeypatch.setitem(pyigtl.messages.message_type_to_class_constructor, "POLYDATA", _polydata_reader(pyigtl))
    mesh, model, sim = plate
    sim.reset()
    node = int(mesh.groups["center"][0])
    compliance = model.solve_static({node: (0.0, 0.0, 1.0)})[node, 2]  # m/N
    expected = 0.003 / (1.0 / 300.0 + compliance)  # 3 mm through the spring and the plate in series
    port = _free_port()
    centre = np.array([50.0, 50.0, 0.0])  # mm: the plate's centre, its surface at z = 0
    with rt.devices.IGTLServer(mesh, sim, port=port, tool_radius=0.005, stiffness=300.0):
        client = pyigtl.OpenIGTLinkClient("127.0.0.1", port)
        try:
            _until(client.is_connected, timeout=10.0)

            def latest(name, timeout=3.0):
                t0 = time.perf_counter()
                while time.perf_counter() - t0 < timeout:
                    found = [m for m in client.get_latest_messages() if m.device_name == name]
                    if found:
                        return found[-1]
                    time.sleep(0.01)
                raise AssertionError(f"no {name} message in {timeout} s")

            def settled(xyz, seconds=0.6):
                t0 = time.perf_counter()
                while time.perf_counter() - t0 < seconds:
                    client.send_message(_pose(pyigtl, xyz), wait=True)
                    time.sleep(0.01)
                client.get_latest_messages()  # drop what came before the tool got there
                time.sleep(0.1)
                return latest("Force"), latest("Organ")

            force, organ = settled(centre + [0, 0, 20.0])  # above the plate: no contact
            assert np.allclose(np.asarray(force.matrix)[:3, 3], 0.0)
            force, organ = settled(centre + [0, 0, 5.0 - 3.0])  # the sphere's bottom 3 mm below the surface
            f = np.asarray(force.matrix)[:3, 3]
            assert abs(f[2] - expected) < 0.05 * expected and f[2] > 5 * np.abs(f[:2]).max(), (f, expected)
            points = organ.points
            assert points.shape == (mesh.n_vertices, 3) and organ.n_polygons == len(mesh.triangles)
            assert np.array_equal(organ.polygons.reshape(-1, 4)[:, 0], np.full(len(mesh.triangles), 3))
            under = np.argmin(np.linalg.norm(points[:, :2] - centre[:2], axis=1))
            assert points[under, 2] < -0.5  # mm: the surface dents under the tool
            client.send_message(pyigtl.TransformMessage(np.full((4, 4), np.nan), device_name="ToolToReference"),
                                wait=True)
            status = latest("Status")
            assert "refused ToolToReference" in status.string and "non-finite" in status.string
            force, organ = settled(centre + [0, 0, 20.0])  # still serving: the tool leaves, the force is zero
            assert np.allclose(np.asarray(force.matrix)[:3, 3], 0.0, atol=1e-9)
        finally:
            client.stop()


# ------------------------------------------------------------------------------------------- CLI


def test_rtfem_devices_says_what_is_found_here(libhd, libdhd, tmp_path, monkeypatch, capsys):
    from rtfem.cli.main import main

    service = FakeInverseService(np.zeros((1, 3)))
    try:
        monkeypatch.setenv("RTFEM_OPENHAPTICS_LIB", str(libhd[0]))
        monkeypatch.setenv("RTFEM_DHD_LIB", str(tmp_path / "missing.so"))
        assert main(["devices", "--haply-url", service.url]) == 0
    finally:
        service.stop()
    rows = {line.split("|")[1].strip(): [c.strip() for c in line.split("|")[2:-1]]
            for line in capsys.readouterr().out.splitlines()[2:]}
    assert rows["openhaptics"][1] == "yes" and str(libhd[0]) in rows["openhaptics"][2]
    assert rows["forcedimension"][1] == "no" and "cannot load" in rows["forcedimension"][2]
    assert rows["haply"][1] == "yes"
    assert set(rows) == {"openhaptics", "forcedimension", "haply", "igtl"}


def test_rtfem_igtl_serves_a_mesh_file(tmp_path):
    """`rtfem igtl MESH` as a user runs it: a pyigtl client presses a tool into the plate's free edge
    and feels it pushed back out; a bad option is one line and exit 2 before any work."""
    import os
    import sys

    pyigtl = pytest.importorskip("pyigtl", reason="the igtl extra (pyigtl) is not installed: pip install 'rtfem[igtl]'")
    rt.save_mesh(rt.meshes.plate(0.1, nx=8), tmp_path / "plate.stl")
    port = _free_port()
    cmd = [sys.executable, "-m", "rtfem.cli.main", "igtl", str(tmp_path / "plate.stl"), "--fix", "x<0.001", "-n", "10",
           "--E", "300000", "--port", str(port), "--seconds", "20"]
    bad = subprocess.run(cmd[:5] + ["--tool-radius", "-2"], capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "--tool-radius" in bad.stderr and "Traceback" not in bad.stderr
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=dict(os.environ, PYTHONUNBUFFERED="1"))
    try:
        for line in proc.stdout:
            if "serving OpenIGTLink" in line:
                break
        client = pyigtl.OpenIGTLinkClient("127.0.0.1", port)
        try:
            _until(client.is_connected, timeout=10.0)
            tip = np.array([95.0, 50.0, 5.0 - 2.0])  # mm: the sphere's bottom 2 mm into the free edge
            t0 = time.perf_counter()
            force = None
            while time.perf_counter() - t0 < 5.0:
                client.send_message(_pose(pyigtl, tip), wait=True)
                got = [m for m in client.get_latest_messages() if m.device_name == "Force"]
                if got:
                    force = np.asarray(got[-1].matrix)[:3, 3]
                time.sleep(0.02)
            assert force is not None and force[2] > 1e-3  # N, pushing the tool back up out of the plate
        finally:
            client.stop()
        out, err = proc.communicate(timeout=60)
        assert proc.returncode == 0, err
        assert "poses taken" in out
    finally:
        if proc.poll() is None:
            proc.kill()


def test_igtl_server_refuses_bad_arguments_before_listening(plate):
    pytest.importorskip("pyigtl", reason="the igtl extra (pyigtl) is not installed: pip install 'rtfem[igtl]'")
    mesh, _, sim = plate
    for bad, match in ((dict(port=0), "port"), (dict(port=70000), "port"), (dict(tool_radius=-0.001), "radius"),
                       (dict(surface_rate=0), "surface_rate"), (dict(rate=-5), "rate")):
        with pytest.raises(rt.ModelError, match=match):
            rt.devices.IGTLServer(mesh, sim, **bad)
    with pytest.raises(rt.ModelError):
        rt.devices.IGTLServer(rt.meshes.plate(0.1, nx=4), sim)  # a driver of another mesh


# ------------------------------------------------------------------------------- the viewer's hand


def test_a_device_drives_the_viewers_hand_and_feels_the_grasp(libhd):
    """Session.attach_device (rtfem view --device): the stylus over the plate's centre presses its
    first button (the jaw closes on the centre vertex), lifts 1 cm (the organ follows, the stylus
    is pulled back down: the grasp's force, opposite to the organ's), lets go (no force)."""
    from rtfem.viewer.session import Session, Settings

    path, lib = libhd
    mesh = rt.meshes.plate(0.1, nx=10)
    session = Session(mesh, rt.Material(E=3e5, nu=0.45, thickness=0.004, density=1060), "boundary",
                      Settings(method="modal", n_modes=20, alpha=30.0, grab_radius=0.0))
    centre = np.asarray(mesh.vertices)[mesh.groups["center"][0]] * 1e3  # mm
    n = 3000
    t = np.arange(n)
    stylus = centre + np.outer(np.clip((t - 300) / 500, 0, 1) * 10.0, [0, 0, 1])  # up 1 cm over 0.3-0.8 s
    buttons = ((t >= 200) & (t < 2000)).astype(np.int32)  # held from 0.2 s to 2 s
    _script(lib, stylus, buttons)
    with rt.devices.OpenHaptics(library=path, workspace=Workspace(), max_rate=1e5) as dev:
        session.attach_device(dev)
        session.start()
        try:
            _wait_frames(lib, 1800, timeout=10.0)
            assert session.node == mesh.groups["center"][0]  # the button closed the jaw there
            k = lib.stub_frame()
            f = _recorded(lib, k)[k - 50:k].mean(axis=0)  # the force on the stylus (N, the device's frame = organ's)
            lift = session.displacements()[session.node]
            assert f[2] < -0.05 and abs(f[2]) > 10 * np.abs(f[:2]).max()  # pulled back down, towards the organ
            assert np.allclose(-f, session.force, rtol=0.05, atol=1e-3)  # what the grasp puts on the organ
            assert 1e-3 < lift[2] < 10e-3  # the organ follows the hand up, not all the way
            _wait_frames(lib, 2300, timeout=10.0)
            assert session.node is None  # the button let go: released
            k = lib.stub_frame()
            assert np.abs(_recorded(lib, k)[k - 20:k]).max() < 1e-9
            assert dev.stop_reason is None
        finally:
            session.stop()


def test_rtfem_view_device_refusals_come_before_any_work(tmp_path, monkeypatch, capsys):
    from rtfem.cli.main import main

    monkeypatch.setenv("RTFEM_OPENHAPTICS_LIB", str(tmp_path / "libHD.so"))  # not there
    t0 = time.perf_counter()
    assert main(["view", "--device", "openhaptics", "--port", str(_free_port())]) == 2
    assert time.perf_counter() - t0 < 5.0  # no precompute first
    err = capsys.readouterr().err
    assert "OpenHaptics: cannot load" in err and "Install 3D Systems' OpenHaptics" in err
    assert main(["view", "--device", "haply", "--benchmark", "1"]) == 2
    assert "the benchmark's hand is scripted" in capsys.readouterr().err
    assert main(["view", "--device", "mouse"]) == 2  # not an adapter: argparse's one line


def test_igtl_device_takes_poses_and_buttons_and_sends_the_force():
    """rt.devices.IGTLDevice (rtfem view --device igtl): a pyigtl client's ToolToReference pose (mm)
    is the hand (m), its 'Buttons' string the buttons, the loop's force comes back as 'Force' (clamped
    to max_force); a non-finite pose is refused with a Status and is a fault (issue 53's one path: zero
    force, sent as the last Force, stop_reason says why, the link closed). tests/test_igtl_bridge.py has
    the other faults."""
    pyigtl = pytest.importorskip("pyigtl", reason="the igtl extra (pyigtl) is not installed: pip install 'rtfem[igtl]'")
    port = _free_port()
    # 100 Hz: pyigtl's client thread sends only after 10 ms in which nothing arrived (comm.py), so Force
    # streamed faster starves its sends (pyigtl's own server only wrote in bursts between 10 ms waits)
    with rt.devices.IGTLDevice(port, max_force=2.0, max_rate=1e5, force_rate=100.0, watchdog=10**7) as dev:
        client = pyigtl.OpenIGTLinkClient("127.0.0.1", port)
        try:
            _until(client.is_connected, timeout=10.0)
            client.send_message(_pose(pyigtl, [12.0, -30.0, 45.0]), wait=True)
            client.send_message(pyigtl.StringMessage("1", device_name="Buttons"), wait=True)
            _until(lambda: np.allclose(dev.position(0.0), [0.012, -0.030, 0.045]) and dev.buttons == 1)
            t0 = time.perf_counter()
            force = None
            while time.perf_counter() - t0 < 1.0:
                dev.set_force(0.0, [0.0, 0.0, 9.0])  # the loop's force: beyond the 2 N
                got = [m for m in client.get_latest_messages() if m.device_name == "Force"]
                if got:
                    force = np.asarray(got[-1].matrix)[:3, 3]
                time.sleep(0.002)
            assert force is not None and np.allclose(force, [0.0, 0.0, 2.0])
            client.send_message(pyigtl.TransformMessage(np.full((4, 4), np.inf), device_name="ToolToReference"),
                                wait=True)
            _until(lambda: dev.stop_reason is not None)
            last = {}
            # the Status goes out from the link's thread as the pose is refused, the zero Force from the
            # servo's fault a tick later: under load they arrive in separate reads, so wait for both
            _until(lambda: last.update({m.device_name: m for m in client.get_latest_messages()})
                   or ("Status" in last and "Force" in last and np.all(last["Force"].matrix[:3, 3] == 0.0)),
                   timeout=10.0)
            assert "refused ToolToReference" in last["Status"].string and np.all(last["Force"].matrix[:3, 3] == 0.0)
            assert dev.link.refused == 1 and np.all(dev.servo.force == 0.0)
            assert np.allclose(dev.position(0.0), [0.012, -0.030, 0.045]) and dev.buttons == 1  # kept
        finally:
            client.stop()
    # the fault's reason stays after close (the watchdog kept out of the way)
    assert dev.stop_reason.startswith("the device sent input that is malformed or out of range: refused "
                                      "ToolToReference") and "non-finite" in dev.stop_reason
