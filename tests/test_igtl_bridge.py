"""The OpenIGTLink bridge keeps serving (issue 53, section 2) and the OpenIGTLink adapter stops on
every fault with zero force (section 1): each case with a real socket on loopback, in bounded time.

Clients here are raw sockets (to send what a broken or hostile peer sends, and to read what comes
back in order) and pyigtl's own messages (what a real client packs)."""

from __future__ import annotations

import logging
import os
import select
import signal
import socket
import struct
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

import rtfem as rt
from rtfem.interaction.devices import igtl_wire as wire
from rtfem.interaction.devices.igtl import POSE_LIMIT_MM, IGTLLink

pyigtl = pytest.importorskip("pyigtl", reason="the igtl extra (pyigtl) is not installed: pip install 'rtfem[igtl]'")

HEADER = struct.Struct(">H12s20sIIQQ")


def _free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _until(predicate, timeout=5.0, what="the condition"):
    t0 = time.perf_counter()
    while not predicate():
        assert time.perf_counter() - t0 < timeout, f"{what}: not within {timeout} s"
        time.sleep(0.005)


def _pose(xyz_mm, name="ToolToReference") -> bytes:
    M = np.eye(4)
    M[:3, 3] = xyz_mm
    return pyigtl.TransformMessage(M, device_name=name).pack()


def _string(text, name="Buttons") -> bytes:
    return pyigtl.StringMessage(text, device_name=name).pack()


class Raw:
    """A client on a plain socket: sends bytes, reads the messages that come back in their order."""

    def __init__(self, port: int) -> None:
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=5.0)
        self.buf = b""
        self.eof = False
        self.seen: list[tuple[str, str, bytes]] = []

    def send(self, data: bytes) -> None:
        self.sock.sendall(data)

    def read(self, seconds: float, until=None) -> list[tuple[str, str, bytes]]:
        """The messages read for ``seconds`` (or until ``until(messages)``), oldest first."""
        out: list[tuple[str, str, bytes]] = []
        end = time.perf_counter() + seconds
        while not self.eof and time.perf_counter() < end:
            ready, _, _ = select.select([self.sock], [], [], max(0.0, min(0.05, end - time.perf_counter())))
            if ready:
                try:
                    chunk = self.sock.recv(1 << 16)
                except ConnectionResetError:
                    chunk = b""
                if not chunk:
                    self.eof = True
                self.buf += chunk
            while len(self.buf) >= HEADER.size:
                _, kind, name, _, _, size, _ = HEADER.unpack(self.buf[:HEADER.size])
                if len(self.buf) < HEADER.size + size:
                    break
                body = self.buf[HEADER.size:HEADER.size + size]
                self.buf = self.buf[HEADER.size + size:]
                out.append((kind.rstrip(b"\0").decode(), name.rstrip(b"\0").decode(), body))
            if until is not None and until(out):
                break
        self.seen += out
        return out

    def close(self) -> None:
        self.sock.close()


def _force(body: bytes) -> np.ndarray:
    return np.frombuffer(body, ">f4")[9:12].astype(float)


def _forces(messages) -> list[np.ndarray]:
    return [_force(b) for k, n, b in messages if n == "Force"]


def _statuses(messages) -> list[str]:
    return [b[4:].decode() for k, n, b in messages if n == "Status"]


def _thread_cpu(thread: threading.Thread) -> float:
    """Seconds of CPU a thread used (Linux: /proc/self/task/<tid>/stat, user + system)."""
    with open(f"/proc/self/task/{thread.native_id}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


@pytest.fixture(scope="module")
def plate():
    """A 10 cm plate held at its edge (a shell, 10 modes, static correction)."""
    mesh = rt.meshes.plate(0.1, nx=6)
    model = rt.ShellModel(mesh, rt.Material(E=3e5, nu=0.45, thickness=0.004, density=1060))
    model.fix("boundary")
    modes = rt.modal_analysis(model, 10)
    return mesh, rt.ModalSimulator(modes, dt=1e-3, damping=rt.Damping(alpha=30.0), static_correction=True)


@pytest.fixture
def server(plate):
    mesh, sim = plate
    sim.reset()
    srv = rt.devices.IGTLServer(mesh, sim, port=_free_port(), tool_radius=0.005, stiffness=300.0).start()
    yield srv
    t0 = time.perf_counter()
    srv.close()
    assert time.perf_counter() - t0 < 3.0  # close() returns promptly, whatever the clients did
    assert srv.error is None, srv.error


CENTRE = np.array([50.0, 50.0, 0.0])  # mm: the plate's centre, its surface at z = 0
PRESSED = CENTRE + [0.0, 0.0, 5.0 - 3.0]  # the 5 mm sphere's bottom 3 mm below the surface


def _press(client: Raw, xyz=PRESSED, seconds=0.5, timeout=10.0) -> np.ndarray:
    """Stream a pose for ``seconds``, and on while no force comes back (a loop still starting, on a
    busy machine) up to ``timeout``; the last Force read (N)."""
    t0 = time.perf_counter()
    force = np.zeros(3)
    while time.perf_counter() - t0 < seconds or (not np.any(force) and time.perf_counter() - t0 < timeout):
        client.send(_pose(xyz))
        forces = _forces(client.read(0.01))
        if forces:
            force = forces[-1]
    forces = _forces(client.read(0.1, until=lambda m: bool(_forces(m))))
    assert forces, "no Force came back"
    return forces[-1]


# ------------------------------------------------------------------ the transport


def test_our_messages_are_pyigtls_bytes_and_pyigtls_are_read():
    """pack() writes what pyigtl writes (its CRC-64 included), and a version-2 message (extended
    header, metadata) that pyigtl packs reads as its content."""
    M = np.arange(16, dtype=float).reshape(4, 4)
    ours = wire.pack("TRANSFORM", "Force", wire.transform_body(M), timestamp=1234.5)
    theirs = pyigtl.TransformMessage(M, timestamp=1234.5, device_name="Force").pack()
    assert ours == theirs
    ours = wire.pack("STRING", "Status", wire.string_body("refused: x"), timestamp=7.25)
    assert ours == pyigtl.StringMessage("refused: x", timestamp=7.25, device_name="Status").pack()
    v2 = pyigtl.TransformMessage(M, device_name="ToolToReference")
    v2.header_version, v2.metadata = 2, {"key": "value"}
    data = v2.pack()
    header = wire.parse_header(data[:58])
    assert header.version == 2 and header.name == "ToolToReference"
    assert np.allclose(wire.read_transform(wire.content_of(header, data[58:]))[:3], M[:3])


def test_a_header_fragment_then_a_close_leaves_the_server_idle_and_serving(caplog):
    """20 bytes of a header, then a close: the server says so in one line, spends no CPU on the dead
    socket (its thread under 0.1 s of CPU over a second), serves the next client, and close()
    returns at once."""
    caplog.set_level(logging.INFO, logger="rtfem.igtl")
    link = IGTLLink(_free_port()).start()
    try:
        bad = Raw(link.port)
        bad.send(_pose([1.0, 2.0, 3.0])[:20])
        bad.close()
        _until(lambda: "disconnected in the middle of a message (20 of the 58 header bytes)" in caplog.text,
               what="the fragment's line")
        cpu = _thread_cpu(link.server._thread)
        time.sleep(1.0)
        assert _thread_cpu(link.server._thread) - cpu < 0.1  # not spinning on the closed socket
        good = Raw(link.port)
        good.send(_pose([1.0, 2.0, 3.0]))
        _until(lambda: link.received == 1, what="the next client's pose")
        assert np.allclose(link.poll(), [1e-3, 2e-3, 3e-3])
        good.close()
    finally:
        t0 = time.perf_counter()
        link.close()
        assert time.perf_counter() - t0 < 1.0
    assert "Traceback" not in caplog.text


def test_a_drip_is_dropped_at_its_deadline_while_another_client_is_served(caplog):
    """A TRANSFORM's body sent one byte a second: dropped 2 s after its first byte (the message
    deadline), while a second client's poses are taken meanwhile."""
    caplog.set_level(logging.INFO, logger="rtfem.igtl")
    link = IGTLLink(_free_port()).start()
    drip, other = Raw(link.port), Raw(link.port)
    try:
        message = _pose([5.0, 5.0, 5.0])
        t0 = time.perf_counter()
        drip.send(message[:60])  # the header and 2 body bytes
        taken = []
        k = 60
        while not drip.eof and time.perf_counter() - t0 < 5.0:
            other.send(_pose([k, 0.0, 0.0]))  # served meanwhile
            try:
                drip.send(message[k:k + 1])
            except OSError:
                pass
            k += 1
            drip.read(1.0)
            p = link.poll()
            if p is not None:
                taken.append(p)
        dropped = time.perf_counter() - t0
        assert drip.eof and 1.9 < dropped < 3.2, dropped
        assert "a message must arrive within 2 s of its first byte" in caplog.text
        assert len(taken) >= 2  # the other client was served while the drip lasted
        other.send(_pose([1.0, 1.0, 1.0]))
        _until(lambda: link.poll() is not None, what="the other client still served")
    finally:
        drip.close()
        other.close()
        link.close()


def test_an_idle_client_does_not_lock_out_another(server):
    """One client connected and silent (reading nothing): a second presses the tool and feels the force."""
    idle = socket.create_connection(("127.0.0.1", server.port))
    try:
        client = Raw(server.port)
        _until(lambda: server.clients == 2, what="both connected")
        f = _press(client)
        assert f[2] > 0.05, f  # pushed back out of the plate
        assert server.clients == 2
        client.close()
    finally:
        idle.close()


def test_too_many_clients_are_told_no_and_the_others_kept(caplog):
    link = IGTLLink(_free_port(), max_clients=2).start()
    clients = [Raw(link.port) for _ in range(3)]
    try:
        _until(lambda: "refused client" in caplog.text and link.server.clients == 2, what="the third refused")
        assert "at most 2" in caplog.text
        clients[0].send(_pose([1.0, 0.0, 0.0]))
        _until(lambda: link.received == 1)
    finally:
        for c in clients:
            c.close()
        link.close()


@pytest.mark.parametrize("data, reason", [
    (b"GET / HTTP/1.1\r\nHost: x\r\n\r\n" + b"\0" * 40, "not an OpenIGTLink header"),
    (HEADER.pack(1, b"TRANSFORM", b"ToolToReference", 0, 0, 2**63, 0), "more than the 4096 bytes read of a TRANSFORM"),
    (HEADER.pack(1, b"IMAGE", b"x", 0, 0, 200 << 20, 0), "IMAGE body of 209715200 bytes"),
])
def test_what_cannot_be_framed_drops_its_sender_with_the_reason(data, reason, caplog):
    link = IGTLLink(_free_port()).start()
    try:
        bad = Raw(link.port)
        bad.send(data)
        bad.read(2.0)
        assert bad.eof and reason in caplog.text
        good = Raw(link.port)
        good.send(_pose([1.0, 0.0, 0.0]))
        _until(lambda: link.received == 1)
    finally:
        link.close()


def test_a_bad_crc_or_a_wrong_size_is_refused_with_a_status_and_the_stream_goes_on():
    link = IGTLLink(_free_port()).start()
    try:
        client = Raw(link.port)
        good = _pose([1.0, 0.0, 0.0])
        corrupt = good[:-1] + bytes([good[-1] ^ 1])
        short = wire.pack("TRANSFORM", "ToolToReference", b"\0" * 40)
        client.send(corrupt + short + _string("7"))
        status = _statuses(client.read(2.0, until=lambda m: len(_statuses(m)) == 2))
        assert "CRC-64 does not match" in status[0] and "48 expected" in status[1]
        _until(lambda: link.buttons == 7, what="the message after them taken")
        assert link.refused == 2 and link.poll() is None
    finally:
        link.close()


# ------------------------------------------------------------------ the bridge


@pytest.mark.parametrize("bad", [[0.0, 0.0, 1e10], [np.finfo(np.float32).max, 0.0, 0.0], [np.nan, 0.0, 0.0]],
                         ids=["1e10 mm", "float32 max", "NaN"])
def test_an_out_of_range_pose_is_refused_with_a_status_and_zero_force_and_all_are_still_served(server, bad):
    """A TRANSFORM at 1e10 mm, float32's largest, or NaN: a Status with the reason to its sender, the
    tool lifted (every Force after it zero), the bridge alive, every client still served."""
    client, watcher = Raw(server.port), Raw(server.port)
    try:
        assert _press(client)[2] > 0.05
        client.send(_pose(bad))
        after = client.read(2.0, until=lambda m: bool(_statuses(m)))
        status = _statuses(after)[0]
        assert status.startswith("refused ToolToReference:")
        assert ("non-finite" in status) if np.isnan(bad[0]) else (f"more than {POSE_LIMIT_MM:g} mm" in status)
        later = client.read(0.3)
        assert _forces(later) and all(np.all(f == 0.0) for f in _forces(later))
        forces = _forces(watcher.read(0.3))
        assert forces and np.all(forces[-1] == 0.0)  # every client sees the zero force
        assert server.error is None and server._thread.is_alive()
        assert _press(client)[2] > 0.05  # a valid pose presses again
        organ = [b for k, n, b in watcher.read(0.5, until=lambda m: any(n == "Organ" for _, n, _ in m)) if n == "Organ"]
        assert organ, "the watcher still gets the Organ"
    finally:
        client.close()
        watcher.close()


def test_the_pose_senders_disconnect_lifts_the_tool(server):
    client, watcher = Raw(server.port), Raw(server.port)
    try:
        assert _press(client)[2] > 0.05
        client.close()
        watcher.read(0.2)
        forces = _forces(watcher.read(0.3))
        assert forces and all(np.all(f == 0.0) for f in forces)
    finally:
        watcher.close()


def test_a_bridge_that_stops_says_why_to_its_clients_and_to_its_owner(server, monkeypatch):
    client = Raw(server.port)
    try:
        client.read(0.2)

        def broken():
            raise RuntimeError("the driver is gone")

        monkeypatch.setattr(server, "surface_displacements", broken)
        status = _statuses(client.read(2.0, until=lambda m: bool(_statuses(m))))
        assert status and "the bridge stopped: RuntimeError: the driver is gone" in status[0]
        _until(lambda: not server._thread.is_alive())
        assert server.error == "RuntimeError: the driver is gone"
        server.error = None  # the fixture checks that nothing else went wrong
    finally:
        client.close()


# ------------------------------------------------------------------ rtfem igtl


class _Proc:
    """``rtfem igtl`` in a subprocess, its stdout and stderr read as they come."""

    def __init__(self, *args: str) -> None:
        self.proc = subprocess.Popen([sys.executable, "-m", "rtfem.cli.main", "igtl", *args], stdout=subprocess.PIPE,
                                     stderr=subprocess.PIPE, text=True, env=dict(os.environ, PYTHONUNBUFFERED="1"))
        self.out: list[str] = []
        self.err: list[str] = []
        for stream, lines in ((self.proc.stdout, self.out), (self.proc.stderr, self.err)):
            threading.Thread(target=lambda s=stream, l=lines: l.extend(iter(s.readline, "")), daemon=True).start()

    def wait_for(self, text: str, timeout: float = 60.0) -> None:
        _until(lambda: any(text in line for line in self.out + self.err) or self.proc.poll() is not None, timeout,
               what=repr(text))
        assert any(text in line for line in self.out + self.err), (self.out, self.err)

    def stop(self, sig) -> tuple[int, float]:
        t0 = time.perf_counter()
        self.proc.send_signal(sig)
        rc = self.proc.wait(timeout=10)
        time.sleep(0.1)
        return rc, time.perf_counter() - t0


@pytest.fixture(scope="module")
def plate_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("igtl") / "plate.stl"
    rt.save_mesh(rt.meshes.plate(0.1, nx=6), path)
    return [str(path), "--fix", "x<0.001", "-n", "6", "--E", "300000"]


def test_rtfem_igtl_on_every_interface_warns_serves_and_stops_on_sigterm(plate_file):
    """--host 0.0.0.0: a warning, then served (a client on loopback presses and feels the force); a
    normal disconnect and an abrupt one (reset) are one line each, no traceback; SIGTERM ends it in
    a few seconds with rc 0 and a line saying so."""
    port = _free_port()
    proc = _Proc(*plate_file, "--host", "0.0.0.0", "--port", str(port))
    try:
        proc.wait_for("serving OpenIGTLink")
        assert any("warning: 0.0.0.0 is not a loopback address" in line for line in proc.err), proc.err
        client = Raw(port)
        tip = [95.0, 50.0, 5.0 - 2.0]  # mm: 2 mm into the free edge
        assert _press(client, tip, seconds=1.0)[2] > 1e-4  # N, up: the tool pushed back out
        client.close()
        proc.wait_for("disconnected")
        reset = Raw(port)
        reset.read(0.3)  # Forces and Organs are coming; then a reset (SO_LINGER 0) while they are sent
        reset.sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
        reset.close()
        time.sleep(0.5)
        rc, took = proc.stop(signal.SIGTERM)
        assert rc == 0 and took < 5.0, (rc, took, proc.err)
        assert any("stopped by SIGTERM" in line for line in proc.out), proc.out
        assert not any("Traceback" in line for line in proc.err), proc.err
        assert sum("disconnected" in line for line in proc.err) == 2, proc.err
    finally:
        if proc.proc.poll() is None:
            proc.proc.kill()


def test_rtfem_igtl_after_a_header_fragment_serves_and_stops_on_sigint(plate_file):
    """20 bytes of a header then a close, on `rtfem igtl`: the next client is served and SIGINT
    (Ctrl-C) ends it in a few seconds, rc 0."""
    port = _free_port()
    proc = _Proc(*plate_file, "--port", str(port))
    try:
        proc.wait_for("serving OpenIGTLink")
        bad = Raw(port)
        bad.send(_pose([1.0, 1.0, 1.0])[:20])
        bad.close()
        proc.wait_for("in the middle of a message")
        client = Raw(port)
        assert _press(client, [95.0, 50.0, 3.0], seconds=1.0)[2] > 1e-4
        rc, took = proc.stop(signal.SIGINT)
        client.close()
        assert rc == 0 and took < 5.0, (rc, took, proc.err)
        assert any("stopped by SIGINT" in line for line in proc.out) and any("poses taken" in line for line in proc.out)
        assert not any("Traceback" in line for line in proc.err), proc.err
    finally:
        if proc.proc.poll() is None:
            proc.proc.kill()


def test_rtfem_igtl_exits_non_zero_when_the_bridge_stops(plate_file, monkeypatch, capsys):
    from rtfem.cli.main import main

    def broken(self):
        raise RuntimeError("the driver is gone")

    monkeypatch.setattr(rt.devices.IGTLServer, "surface_displacements", broken)
    assert main(["igtl", *plate_file, "--port", str(_free_port()), "--seconds", "20"]) == 2
    err = capsys.readouterr().err
    assert "rtfem: error: the OpenIGTLink bridge stopped: RuntimeError: the driver is gone" in err


def test_rtfem_igtl_refuses_an_address_not_of_this_machine_before_any_work(plate_file, capsys):
    from rtfem.cli.main import main

    t0 = time.perf_counter()
    assert main(["igtl", *plate_file, "--host", "192.0.2.1", "--port", str(_free_port())]) == 2
    assert time.perf_counter() - t0 < 5.0
    assert "cannot listen on 192.0.2.1" in capsys.readouterr().err
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        assert main(["igtl", *plate_file, "--port", str(busy.getsockname()[1])]) == 2
        assert "choose another --port" in capsys.readouterr().err


# ------------------------------------------------------------------ IGTLDevice: every fault, one path


@pytest.fixture
def device():
    """An IGTLDevice rendering 1 N up (fed once; the watchdog kept out of the way) to a client."""
    dev = rt.devices.IGTLDevice(_free_port(), max_force=2.0, max_rate=1e5, watchdog=10**7, force_rate=500.0)
    client = Raw(dev.link.port)
    client.send(_pose([10.0, 20.0, 30.0]))
    _until(lambda: np.allclose(dev.position(0.0), [0.010, 0.020, 0.030]), what="the first pose")
    dev.set_force(0.0, [0.0, 0.0, 1.0])
    forces = _forces(client.read(2.0, until=lambda m: any(np.allclose(f, [0, 0, 1]) for f in _forces(m))))
    assert np.allclose(forces[-1], [0.0, 0.0, 1.0])
    yield dev, client
    client.close()
    dev.close()


def _zero_after_fault(dev, client, reason: str) -> None:
    """The one fault path, seen from outside: the reason, zero force at the servo and as the last
    Force each client reads, the link closed (the client reads its end), the port free, no restart."""
    _until(lambda: dev.stop_reason is not None, what="the fault")
    assert reason in dev.stop_reason, dev.stop_reason
    assert np.all(dev.servo.force == 0.0)
    later = _forces(client.read(2.0))  # those sent before the fault first, if the client had not read them
    zero = [i for i, f in enumerate(later) if np.all(f == 0.0)]
    assert zero and all(np.all(f == 0.0) for f in later[zero[0]:]), later
    assert client.eof  # released: the link is closed
    with pytest.raises(rt.DeviceError, match="open a new one"):
        dev.restart()
    rt.devices.IGTLDevice(dev.link.port).close()  # the port is free


@pytest.mark.parametrize("bad, reason", [
    (_pose([1e10, 0.0, 0.0]), "the device sent input that is malformed or out of range: refused ToolToReference: "
                              "its translation (1e+10, 0, 0) mm lies more than 10000 mm from the origin"),
    (_pose([np.nan, 0.0, 0.0]), "non-finite"),
    (wire.pack("TRANSFORM", "ToolToReference", b"\0" * 44), "a TRANSFORM body of 44 bytes"),
    (_string("1", name="ToolToReference"), "a STRING message, not a TRANSFORM"),
    (_string("left"), "refused Buttons: 'left' is not a bit mask"),
    (_string("9" * 400), "refused Buttons"),
], ids=["1e10 mm", "NaN", "short body", "wrong type", "buttons text", "buttons 400 digits"])
def test_igtl_device_faults_on_a_bad_pose_or_buttons(device, bad, reason):
    dev, client = device
    client.send(bad)
    _zero_after_fault(dev, client, reason)
    assert any(s.startswith("refused") for s in _statuses(client.seen))  # the sender was told why


def test_igtl_device_faults_when_its_servo_fails(device, monkeypatch):
    dev, client = device

    def broken():
        raise RuntimeError("a bug")

    monkeypatch.setattr(dev.link, "poll", broken)
    _zero_after_fault(dev, client, "the adapter failed: RuntimeError in an OpenIGTLink tool's servo: a bug")


def test_igtl_device_faults_when_the_poses_sender_disconnects(device):
    dev, client = device
    watcher = Raw(dev.link.port)
    try:
        watcher.read(0.1)
        client.close()
        _zero_after_fault(dev, watcher, "the device disconnected: the pose's sender (127.0.0.1:")
        assert "is gone: disconnected" in dev.stop_reason
    finally:
        watcher.close()


def test_igtl_device_faults_when_a_pose_is_late(device):
    """The pose's sender starts a message and stalls: dropped at the 2 s deadline, and the device stops."""
    dev, client = device
    client.send(_pose([1.0, 2.0, 3.0])[:30])
    time.sleep(1.5)
    assert dev.stop_reason is None
    _until(lambda: dev.stop_reason is not None, timeout=3.0, what="the deadline")
    assert "a message must arrive within 2 s of its first byte" in dev.stop_reason
    assert np.all(dev.servo.force == 0.0)


def test_igtl_device_faults_when_poses_stop_for_pose_timeout():
    dev = rt.devices.IGTLDevice(_free_port(), max_rate=1e5, watchdog=10**7, pose_timeout=0.3)
    client = Raw(dev.link.port)
    try:
        t0 = time.perf_counter()
        while time.perf_counter() - t0 < 0.6:  # streaming: no fault
            client.send(_pose([1.0, 2.0, 3.0]))
            client.read(0.02)
        dev.set_force(0.0, [0.0, 0.0, 1.0])
        assert dev.stop_reason is None
        _zero_after_fault(dev, client, "the device disconnected: no ToolToReference pose for 0.3")
    finally:
        client.close()
        dev.close()
    assert "no ToolToReference pose" in dev.stop_reason  # the first reason stays after close


def test_igtl_device_close_sends_a_last_zero_force_and_frees_the_port(device):
    dev, client = device
    dev.close()
    rest = client.read(1.0)
    assert client.eof and _forces(rest) and np.all(_forces(rest)[-1] == 0.0)
    assert dev.stop_reason == "closed"
    rt.devices.IGTLDevice(dev.link.port).close()


def test_a_flood_of_bad_poses_is_refused_in_a_few_log_lines(caplog):
    """2,000 refused poses in a burst: each answered, the log one line a second at most."""
    caplog.set_level(logging.INFO, logger="rtfem.igtl")
    link = IGTLLink(_free_port()).start()
    try:
        client = Raw(link.port)
        client.send(_pose([np.nan, 0.0, 0.0]) * 2000)
        _until(lambda: link.refused == 2000, what="every pose refused")
        lines = [r for r in caplog.records if "refused ToolToReference" in r.getMessage()]
        assert 1 <= len(lines) <= 3, len(lines)
        client.send(_pose([1.0, 0.0, 0.0]))
        _until(lambda: link.received == 1, what="a valid pose after the flood")
    finally:
        link.close()


def test_a_client_that_reads_nothing_is_dropped_and_holds_no_more_than_a_message_of_each_name(caplog):
    link = IGTLLink(_free_port(), send_timeout=0.5).start()
    deaf = socket.create_connection(("127.0.0.1", link.port))
    try:
        _until(lambda: link.server.clients == 1)
        frame = wire.pack("POLYDATA", "Organ", b"\0" * (1 << 20))
        t0 = time.perf_counter()
        while link.server.clients and time.perf_counter() - t0 < 20.0:
            link.send("Organ", frame)  # the newest replaces the one waiting: one frame held, never a queue
            peers = list(link.server._peers)
            assert all(len(p.outbox) <= 1 for p in peers)
            time.sleep(0.01)
        assert link.server.clients == 0
        assert "dropped: read nothing sent to it for 0.5 s" in caplog.text
    finally:
        deaf.close()
        link.close()
