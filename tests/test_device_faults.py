"""Issue 53, section 1: a device stop leaves no force on the hand. Every fault of every hardware
adapter (an error the SDK reports, a disconnection, a silence, a message or a position that is
malformed or out of range, an exception on the servo's thread) ends in HardwareDevice.fault: the
servo stops, the reason is recorded, zero force is commanded to the device or its service and the
device is released (or left idle, rendering zero). Tested on a bare adapter, on Haply against a
hostile fake Inverse Service (the last command it received is an explicit zero and the connection is
closed), and on OpenHaptics and Force Dimension against the stub libraries of tests/stubs."""

from __future__ import annotations

import json
import threading
import time

import numpy as np
import pytest
from test_devices import _recorded, _script, _stub, _wait_frames

import rtfem as rt
from rtfem.interaction.devices import Workspace
from rtfem.interaction.devices.hardware import HardwareDevice

ZERO = [0.0, 0.0, 0.0]


def _until(predicate, timeout=5.0):
    t0 = time.perf_counter()
    while not predicate():
        assert time.perf_counter() - t0 < timeout, "not within the generous wait"
        time.sleep(0.002)


# --------------------------------------------------------------------------- the one fault path


class BareAdapter(HardwareDevice):
    """An adapter with no device: it logs its zero commands and releases, which may be told to fail."""

    NAME = "a bare adapter"

    def __init__(self, zero_raises=None, shutdown_raises=None):
        self._start_servo(Workspace(), ((-0.1,) * 3, (0.1,) * 3), 5.0, 1e5, 10, 1000.0)
        self.log, self.is_open = [], True
        self.zero_raises, self.shutdown_raises = zero_raises, shutdown_raises

    def _command_zero(self):
        self.log.append("zero")
        if self.zero_raises is not None:
            raise self.zero_raises

    def _shutdown(self):
        self.log.append("shutdown")
        self.is_open = False
        if self.shutdown_raises is not None:
            raise self.shutdown_raises

    def _open(self):
        return self.is_open


def _rendering(dev, f=(0.0, 0.0, 3.0)):
    dev.set_force(0.0, f)
    return dev._tick((0.0, 0.0, 0.0), 0)


def test_fault_stops_zeroes_records_and_releases_once():
    dev = BareAdapter()
    assert np.array_equal(_rendering(dev), [0.0, 0.0, 3.0])
    dev.fault(3, "the cable is out")
    assert np.array_equal(dev.servo.force, ZERO) and dev.log == ["zero", "shutdown"]
    assert dev.stop_reason == "the device disconnected: the cable is out"
    dev.fault(2, "a second fault")  # idempotent: the first reason stays, nothing is commanded again
    dev.close()
    assert dev.log == ["zero", "shutdown"] and dev.stop_reason == "the device disconnected: the cable is out"
    with pytest.raises(rt.DeviceError, match=r"a bare adapter is closed \(the device disconnected: the cable is out\): "
                                             "open a new one"):
        dev.restart()


def test_a_device_fault_replaces_the_simulations_stop_but_a_close_does_not():
    dev = BareAdapter()
    _rendering(dev)
    for _ in range(12):  # the watchdog: 10 ticks without a new force
        dev._tick((0.0, 0.0, 0.0), 0)
    assert dev.stop_reason == "the simulation fell behind: no force from its loop for 10 servo ticks"
    dev.fault(6, "a position of nonsense")
    assert dev.stop_reason == "the device sent input that is malformed or out of range: a position of nonsense"
    dev = BareAdapter()
    dev.servo.stop(1)
    dev.close()
    assert dev.stop_reason.startswith("the simulation fell behind") and dev.log == ["zero", "shutdown"]


def test_a_fault_that_leaves_the_device_idle_can_be_restarted():
    dev = BareAdapter()
    _rendering(dev)
    dev.fault(2, "HD_EXCEEDED_MAX_FORCE (0x0201)", release=False)
    assert dev.log == ["zero"] and np.array_equal(dev._tick((0.0, 0.0, 0.0), 0), ZERO)
    dev.restart()
    assert dev.stop_reason is None
    assert np.array_equal(_rendering(dev), [0.0, 0.0, 3.0])


def test_what_fails_in_the_zero_command_or_the_release_is_noted_and_the_rest_still_runs():
    dev = BareAdapter(zero_raises=OSError("broken pipe"), shutdown_raises=RuntimeError("stuck"))
    dev.fault(3, "gone")
    assert dev.log == ["zero", "shutdown"]
    assert dev.stop_reason == ("the device disconnected: gone; no zero-force command was sent (OSError: broken pipe); "
                               "releasing the device failed (RuntimeError: stuck)")
    dev = BareAdapter(zero_raises=KeyboardInterrupt())
    with pytest.raises(KeyboardInterrupt):  # raised again, once the device is released
        dev.fault(7, "boom")
    assert dev.log == ["zero", "shutdown"] and dev.stop_reason.startswith("the adapter failed: boom; no zero-force")


@pytest.mark.parametrize("code", ["3", 1, 99, None])
def test_a_fault_given_a_code_that_is_not_a_devices_counts_as_the_adapters_failure(code):
    dev = BareAdapter()
    dev.fault(code, "lost")
    assert dev.stop_reason == f"the adapter failed: lost (fault() was given code {code!r}, not a device's)"
    assert dev.log == ["zero", "shutdown"]


def test_faults_from_many_threads_release_once():
    dev = BareAdapter()
    start = threading.Barrier(8)

    def hit(k):
        start.wait()
        dev.fault(2 + k % 2, f"thread {k}")

    threads = [threading.Thread(target=hit, args=(k,)) for k in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(5.0)
    assert dev.log == ["zero", "shutdown"] and dev.stop_reason is not None


@pytest.mark.parametrize("x, buttons, detail", [
    ((np.nan, 0.0, 0.0), 0, "a position that is not finite (nan, 0.0, 0.0)"),
    ((0.0, -np.inf, 0.0), 0, "a position that is not finite (0.0, -inf, 0.0)"),
    ((0.0, 0.0, 11.0), 0, "a position of (0, 0, 11) m, beyond 10 m of the device's origin"),
    ((0.0, 0.0, 0.0), 1 << 40, "buttons 1099511627776 that are not a mask of 32 bits"),
    ((0.0, 0.0, 0.0), -1, "buttons -1 that are not a mask of 32 bits")])
def test_the_devices_input_is_checked_before_the_servo(x, buttons, detail):
    dev = BareAdapter()
    _rendering(dev)
    assert np.array_equal(dev._tick(x, buttons), ZERO) and np.array_equal(dev.servo.force, ZERO)
    assert dev.stop_reason == f"the device sent input that is malformed or out of range: {detail}"
    assert dev.log == ["zero", "shutdown"]


# ----------------------------------------------------------------- Haply, a hostile Inverse Service


def _state(x="0.01", y="0.02", z="0.03", buttons='{"a": false, "b": false, "c": false}', device="05DA", pad=""):
    """A state message as raw JSON text, so that a test can put anything in any field."""
    return (f'{{"inverse3": [{{"device_id": "{device}", "state": {{"cursor_position": {{"x": {x}, "y": {y}, '
            f'"z": {z}}}}}}}], "wireless_verse_grip": [{{"device_id": "61576", "state": {{"buttons": {buttons}}}}}]'
            f'{pad}}}')


SILENCE, CLOSE = "silence", "close"


def _recv(ws):
    try:
        return ws.recv()
    except Exception:  # the client closed
        return None


def _send(ws, frame):
    try:
        ws.send(frame)
    except Exception:  # the client closed meanwhile: what it sent before is still read
        pass


class InverseService:
    """A fake Inverse Service on loopback that records every command on every connection. It sends
    good states until it has been commanded at least ``trigger`` N; then, once, it sends ``hostile``
    (a text or binary frame) instead of the next state, or falls silent (SILENCE), or closes the
    connection (CLOSE); after that it only records what it is sent, on any connection. With
    ``hostile=None`` it only sends good states."""

    def __init__(self, hostile, trigger=2.9):
        from websockets.sync.server import serve

        self.hostile, self.trigger = hostile, trigger
        self.commands: list[tuple[int, list[float]]] = []  # (connection, force)
        self.connections = self.open = 0
        self.fired = False
        self.lock = threading.Lock()
        self.server = serve(self._handler, "127.0.0.1", 0, max_size=2**20)
        self.url = f"ws://127.0.0.1:{self.server.socket.getsockname()[1]}"
        threading.Thread(target=self.server.serve_forever, daemon=True).start()

    def _handler(self, ws):
        with self.lock:
            self.connections += 1
            self.open += 1
            n = self.connections
        try:
            _send(ws, _state())
            while True:
                try:
                    msg = json.loads(ws.recv())
                except Exception:  # the client closed
                    return
                f = [msg["inverse3"][0]["commands"]["set_cursor_force"]["values"][c] for c in "xyz"]
                self.commands.append((n, f))
                if self.fired:
                    continue
                if self.hostile is not None and np.linalg.norm(f) >= self.trigger:
                    self.fired = True
                    if self.hostile == CLOSE:
                        ws.close()
                        return
                    if self.hostile != SILENCE:
                        _send(ws, self.hostile)
                    continue
                time.sleep(0.0005)
                _send(ws, _state())
        finally:
            with self.lock:
                self.open -= 1

    def stop(self):
        self.server.shutdown()


def _haply_fault(hostile, *, timeout=2.0, inject=None):
    """Open a Haply on an InverseService sending ``hostile``, command 3 N, wait for the fault: (the
    service, the device)."""
    service = InverseService(hostile)
    try:
        dev = rt.devices.Haply(service.url, workspace=Workspace(), max_force=5.0, max_rate=1e5, watchdog=10**6,
                               timeout=timeout)
        try:
            if inject is not None:
                inject(dev)
            dev.set_force(0.0, [0.0, 0.0, 3.0])
            _until(lambda: dev.stop_reason is not None and not dev._thread.is_alive())
            _until(lambda: service.open == 0)  # every connection closed
        finally:
            dev.close()
    finally:
        service.stop()
    return service, dev


def _assert_zero_last(service, *, connections=1):
    forces = [f for _, f in service.commands]
    assert [0.0, 0.0, 3.0] in forces  # 3 N was commanded before the fault
    assert service.commands[-1][1] == ZERO  # and the last command the service received is an explicit zero
    assert service.connections == connections and service.open == 0


REFUSED = "the device sent input that is malformed or out of range: the Inverse Service's message: "
HOSTILE = {
    "not JSON": ("not the service's json", "not JSON (JSONDecodeError: Expecting value: line 1 column 1 (char 0))"),
    "NaN": (_state(x="NaN"), "NaN where a number belongs (JSON has no such value)"),
    "Infinity": (_state(z="-Infinity"), "-Infinity where a number belongs (JSON has no such value)"),
    "1e400": (_state(y="1e400"), "cursor_position.y = inf m is not a finite coordinate within 10 m of the service's "
                                 "origin"),
    "a JSON list": ("[1, 2, 3]", "a JSON list, not an object"),
    "a binary frame": (b"\x00\x01\x02", "a binary frame of 3 bytes, not the service's JSON text"),
    "a 400-digit integer": (_state(x="9" * 400), "cursor_position.x is an integer of about 10^400 m, beyond 10 m of "
                                                 "the service's origin"),
    "nested 30,000 deep": ("[" * 30000 + "]" * 30000, "30000 JSON objects and arrays (nested or not), over 256"),
    "2,000 buttons": (_state(buttons="{" + ", ".join(f'"b{i}": true' for i in range(2000)) + "}"),
                      "2000 buttons on the VerseGrip, over 32"),
    "x = true, y = '0.01'": (_state(x="true", y='"0.01"'), "cursor_position.x is True, not a number"),
    "y = '0.01'": (_state(y='"0.01"'), "cursor_position.y is '0.01', not a number"),
    "11 m away": (_state(x="11.0"), "cursor_position.x = 11.0 m is not a finite coordinate within 10 m of the "
                                    "service's origin"),
    "a button 'yes'": (_state(buttons='{"a": "yes"}'), "button 'a' is 'yes', not true or false"),
    "another device": (_state(device="0000"), "no state for Inverse3 '05DA'"),
    "no cursor": ('{"inverse3": [{"device_id": "05DA", "state": {}}]}',
                  "inverse3[0].state.cursor_position is None, not a JSON object"),
}


@pytest.mark.parametrize("case", list(HOSTILE))
def test_haply_a_hostile_frame_ends_in_a_zero_force_command_and_a_closed_connection(case):
    frame, detail = HOSTILE[case]
    service, dev = _haply_fault(frame)
    _assert_zero_last(service)
    assert dev.stop_reason == REFUSED + detail
    with pytest.raises(rt.DeviceError, match="open a new rt.devices.Haply"):
        dev.restart()


@pytest.mark.parametrize("case, frame", [("nested 100,000 deep", "[" * 100000 + "]" * 100000),
                                         ("a 1 MB frame", _state(pad=', "pad": "' + "x" * 2**20 + '"'))])
def test_haply_a_frame_over_64_kib_is_refused_unread_and_zero_commanded_on_a_new_connection(case, frame):
    service, dev = _haply_fault(frame)
    _assert_zero_last(service, connections=2)  # the refused frame closed the first connection
    assert service.commands[-1][0] == 2
    assert dev.stop_reason == ("the device sent input that is malformed or out of range: the Inverse Service sent a "
                               "frame the WebSocket layer refused (close code 1009: over 64 KiB)")


def test_haply_silence_ends_in_a_zero_force_command_and_a_closed_connection():
    service, dev = _haply_fault(SILENCE, timeout=0.3)
    _assert_zero_last(service)
    assert dev.stop_reason == "the device disconnected: no state from the Inverse Service for 0.3 s"


def test_haply_a_closed_connection_ends_in_a_zero_force_command_on_a_new_one():
    service, dev = _haply_fault(CLOSE)
    _assert_zero_last(service, connections=2)
    assert dev.stop_reason == "the device disconnected: the Inverse Service closed the connection"


@pytest.mark.parametrize("error", [RecursionError("injected"), OverflowError("injected"), MemoryError("injected")])
def test_haply_an_exception_on_the_servo_thread_is_a_fault(error):
    """What killed the thread before (a RecursionError, an OverflowError), from anywhere in the tick."""

    def inject(dev):
        tick = dev.servo.tick

        def failing(x, buttons=0):
            if np.linalg.norm(dev.servo.force) > 2.9:  # once 3 N is being rendered
                raise error
            return tick(x, buttons)

        dev.servo.tick = failing

    service = InverseService(None)  # never hostile: the adapter fails on its own
    try:
        dev = rt.devices.Haply(service.url, workspace=Workspace(), max_force=5.0, max_rate=1e5, watchdog=10**6)
        inject(dev)
        dev.set_force(0.0, [0.0, 0.0, 3.0])
        _until(lambda: dev.stop_reason is not None and not dev._thread.is_alive())
        _until(lambda: service.open == 0)
    finally:
        service.stop()
    _assert_zero_last(service)
    assert dev.stop_reason == f"the adapter failed: {type(error).__name__} in a Haply Inverse3's servo: injected"


def test_haply_close_commands_zero_before_closing():
    service = InverseService(None)
    try:
        with rt.devices.Haply(service.url, workspace=Workspace(), max_force=5.0, max_rate=1e5,
                              watchdog=10**6) as dev:
            dev.set_force(0.0, [0.0, 0.0, 3.0])
            _until(lambda: any(f == [0.0, 0.0, 3.0] for _, f in service.commands))
        _until(lambda: service.open == 0)
    finally:
        service.stop()
    _assert_zero_last(service)
    assert dev.stop_reason == "closed"


@pytest.mark.parametrize("first, detail", [
    (b"\x00", "Refused: a binary frame of 1 bytes, not the service's JSON text"),
    ("[" * 1000 + "]" * 1000, "Refused: 1000 JSON objects and arrays (nested or not), over 256"),
    ('{"inverse3": [{"device_id": true}]}', "Refused: device_id True is not a string or integer of at most 64 "
                                            "characters")])
def test_haply_a_hostile_first_message_is_refused(first, detail):
    from websockets.sync.server import serve

    server = serve(lambda ws: (_send(ws, first), _recv(ws)), "127.0.0.1", 0)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    url = f"ws://127.0.0.1:{server.socket.getsockname()[1]}"
    try:
        with pytest.raises(rt.DeviceError) as err:
            rt.devices.Haply(url, max_force=2.0, timeout=1.0)
        assert str(err.value) == f"Haply: the first message from {url} is not the Inverse Service's state ({detail})"
    finally:
        server.shutdown()


# -------------------------------------------------------------------------- OpenHaptics, stubbed


@pytest.fixture(scope="module")
def libhd(tmp_path_factory):
    return _stub(tmp_path_factory, "hd_stub.c", "libHD_faults.so")


@pytest.fixture(scope="module")
def libdhd(tmp_path_factory):
    return _stub(tmp_path_factory, "dhd_stub.c", "libdhd_faults.so")


def _rendering_1n(dev, lib):
    """Render 1 N (one force from the loop: the watchdog is off) and wait until the device has it."""
    dev.set_force(0.0, [0.0, 0.0, 1.0])
    _until(lambda: _renders(lib, [0.0, 0.0, 1.0], after=5))


def _renders(lib, force, after=0):
    """The stub's last frame (past ``after`` frames) has ``force``, its frame count read once: the servo
    runs on meanwhile, and reading it twice (for the length, for the index) raced when a frame came in between."""
    k = lib.stub_frame()
    return k > after and np.allclose(_recorded(lib, k)[k - 1], force)


def _openhaptics_fault(lib, path, stylus_mm, inject=None, disconnect=None):
    _script(lib, stylus_mm)
    dev = rt.devices.OpenHaptics(library=path, workspace=Workspace(), max_rate=1e5, watchdog=10**6)
    try:
        assert lib.stub_force_output() == 1
        _rendering_1n(dev, lib)
        if inject is not None:
            inject(dev)
        if disconnect is not None:
            lib.stub_disconnect(lib.stub_frame() + 5)
        _until(lambda: dev.stop_reason is not None)
        k = lib.stub_frame()
        _wait_frames(lib, k + 5)  # frames go on: each writes zero
        k = lib.stub_frame()
        last = _recorded(lib, k)[k - 5:k]
        state = lib.stub_force_output(), lib.stub_scheduled()
    finally:
        dev.close()
    assert lib.stub_scheduled() == 0  # close stopped the scheduler and unscheduled the servo
    return dev, last, state


@pytest.mark.parametrize("where, detail", [
    (np.nan, "a position that is not finite (nan, 0.0, 0.0)"),
    (1e7, "a position of (1e+04, 0, 0) m, beyond 10 m of the device's origin")])
def test_openhaptics_a_position_not_finite_or_out_of_reach_zeroes_and_disables_the_force(libhd, where, detail):
    path, lib = libhd
    stylus = np.zeros((400, 3))
    stylus[300:, 0] = where  # mm, from frame 300 on
    dev, last, (output, scheduled) = _openhaptics_fault(lib, path, stylus)
    assert np.array_equal(last, np.zeros((5, 3)))  # the force written in the frames after the fault
    assert output == 0 and scheduled == 1  # force output off; the callback is kept, writing zero
    assert dev.stop_reason == f"the device sent input that is malformed or out of range: {detail}"


def test_openhaptics_a_disconnection_zeroes_and_disables_the_force(libhd):
    path, lib = libhd
    dev, last, (output, scheduled) = _openhaptics_fault(lib, path, np.zeros((1, 3)), disconnect=True)
    assert np.array_equal(last, np.zeros((5, 3))) and output == 0 and scheduled == 1
    assert dev.stop_reason == "the device disconnected: HD_COMM_ERROR (0x0302)"
    with pytest.raises(rt.DeviceError, match=r"an OpenHaptics device is closed \(the device disconnected"):
        dev.restart()


@pytest.mark.parametrize("error", [RecursionError("injected"), MemoryError("injected"), ZeroDivisionError("injected")])
def test_openhaptics_an_exception_in_the_callback_is_a_fault_not_a_dropped_callback(libhd, error):
    """An exception out of a ctypes callback returns 0 (HD_CALLBACK_DONE): the scheduler used to drop
    the servo with the last force on the motors and no reason."""
    path, lib = libhd

    def inject(dev):
        def failing(x, buttons=0):
            raise error

        dev.servo.tick = failing

    dev, last, (output, scheduled) = _openhaptics_fault(lib, path, np.zeros((1, 3)), inject=inject)
    assert np.array_equal(last, np.zeros((5, 3))) and output == 0 and scheduled == 1
    assert dev.stop_reason == f"the adapter failed: {type(error).__name__} in an OpenHaptics device's servo: injected"


def test_openhaptics_a_recoverable_hd_error_leaves_it_idle_at_zero_until_restart(libhd):
    path, lib = libhd
    _script(lib, np.zeros((1, 3)))
    with rt.devices.OpenHaptics(library=path, workspace=Workspace(), max_rate=1e5, watchdog=10**6) as dev:
        _rendering_1n(dev, lib)
        lib.stub_fail(lib.stub_frame() + 3, 0x0201)  # HD_EXCEEDED_MAX_FORCE
        _until(lambda: dev.stop_reason is not None)
        k = lib.stub_frame()
        _wait_frames(lib, k + 5)
        assert np.array_equal(_recorded(lib, k + 5)[k:k + 5], np.zeros((5, 3)))
        assert lib.stub_force_output() == 1  # idle, not released
        assert dev.stop_reason == "the device reported an error: HD_EXCEEDED_MAX_FORCE (0x0201)"
        dev.restart()
        dev.set_force(0.0, [0.0, 0.0, 1.0])
        _until(lambda: _renders(lib, [0.0, 0.0, 1.0]))
    k = lib.stub_frame()
    assert np.array_equal(_recorded(lib, k)[k - 1], ZERO)  # close wrote a zero frame before stopping
    assert dev.stop_reason == "closed" and lib.stub_scheduled() == 0


# ---------------------------------------------------------------------- Force Dimension, stubbed


def _forcedimension_fault(lib, path, handle, inject=None, fail=None):
    _script(lib, handle)
    dev = rt.devices.ForceDimension(library=path, workspace=Workspace(), max_force=5.0, max_rate=1e5,
                                    watchdog=10**6)
    try:
        _rendering_1n(dev, lib)
        if inject is not None:
            inject(dev)
        if fail is not None:
            lib.stub_fail(lib.stub_frame() + 5, fail)
        _until(lambda: dev.stop_reason is not None and not dev._thread.thread.is_alive())
        k = lib.stub_frame()
        last, state = _recorded(lib, k)[k - 1], lib.stub_state()
    finally:
        dev.close()
    return dev, last, state


@pytest.mark.parametrize("where, detail", [
    (np.nan, "a position that is not finite (0.0, nan, 0.0)"),
    (-40.0, "a position of (0, -40, 0) m, beyond 10 m of the device's origin")])
def test_forcedimension_a_position_not_finite_or_out_of_reach_zeroes_and_closes(libdhd, where, detail):
    path, lib = libdhd
    handle = np.zeros((400, 3))
    handle[300:, 1] = where  # m, from the 300th read on
    dev, last, state = _forcedimension_fault(lib, path, handle)
    assert np.array_equal(last, ZERO) and state == 0  # the last force written is zero; force off, device closed
    assert dev.stop_reason == f"the device sent input that is malformed or out of range: {detail}"
    with pytest.raises(rt.DeviceError, match=r"a Force Dimension device is closed"):
        dev.restart()


@pytest.mark.parametrize("code, reason", [
    (2, "the device disconnected: communication error between the host and the device (DHD error 2)"),
    (1, "the device reported an error: undefined error (DHD error 1)")])
def test_forcedimension_an_sdk_error_zeroes_and_closes(libdhd, code, reason):
    path, lib = libdhd
    dev, last, state = _forcedimension_fault(lib, path, np.zeros((1, 3)), fail=code)
    assert np.array_equal(last, ZERO) and state == 0
    assert dev.stop_reason == reason


@pytest.mark.parametrize("error", [RecursionError("injected"), OverflowError("injected"), MemoryError("injected")])
def test_forcedimension_an_exception_on_the_servo_thread_is_a_fault(libdhd, error):
    path, lib = libdhd

    def inject(dev):
        def failing(x, buttons=0):
            raise error

        dev.servo.tick = failing

    dev, last, state = _forcedimension_fault(lib, path, np.zeros((1, 3)), inject=inject)
    assert np.array_equal(last, ZERO) and state == 0
    assert dev.stop_reason == f"the adapter failed: {type(error).__name__} in a Force Dimension device's servo: injected"
    assert dev.servo_error is error


def test_forcedimension_close_writes_zero_last(libdhd):
    path, lib = libdhd
    _script(lib, np.zeros((1, 3)))
    with rt.devices.ForceDimension(library=path, workspace=Workspace(), max_force=5.0, max_rate=1e5,
                                   watchdog=10**6) as dev:
        _rendering_1n(dev, lib)
    k = lib.stub_frame()
    assert np.array_equal(_recorded(lib, k)[k - 1], ZERO) and lib.stub_state() == 0
    assert dev.stop_reason == "closed"
