"""Haply Inverse3 through the Haply Inverse Service's WebSocket JSON API (service 3.x, default
``ws://localhost:10001``).

The service streams state messages, ``{"inverse3": [{"device_id": ..., "state": {"cursor_position":
{"x", "y", "z"}, ...}}], "wireless_verse_grip": [{"state": {"buttons": {...}}}]}`` (metres), and sends
the next one after the client's command, ``{"inverse3": [{"device_id": ..., "commands":
{"set_cursor_force": {"values": {"x", "y", "z"}}}}]}`` (newtons). The servo (:mod:`.servo`) runs once
per state message, on a thread of its own, through the ``websockets`` library's client.

Every message is read as a peer's input, strictly (:func:`read_state`): a text frame of at most
:data:`MAX_FRAME` bytes (a larger one is refused from its header by the WebSocket layer, unread), a
JSON object with at most :data:`MAX_CONTAINERS` objects and arrays (so no deep nesting reaches the
parser), coordinates that are JSON numbers (not booleans, strings, NaN or Infinity) within
:data:`~rtfem.interaction.devices.hardware.REACH` of the service's origin, at most
:data:`~rtfem.interaction.devices.hardware.MAX_BUTTONS` buttons whose states are booleans. Anything
else, a silence longer than ``timeout``, a closed connection or an exception on the servo thread is a
fault (:meth:`HardwareDevice.fault`): a zero-force command to the service (on a new connection when
the old one is gone), then the connection closed.
"""

from __future__ import annotations

import json
import math
import threading

import numpy as np

from ... import validate
from ...errors import DeviceError
from .hardware import MAX_BUTTONS, REACH, HardwareDevice
from .workspace import Workspace

__all__ = ["Haply", "read_state", "MAX_FRAME", "MAX_CONTAINERS"]

# the fit's default usable workspace: a 20 cm cube round the service's origin (give usable= from your
# device's manual)
CUBE = (np.array([-0.1, -0.1, -0.1]), np.array([0.1, 0.1, 0.1]))
HOW = "Start Haply's Inverse Service (https://docs.haply.co), or give the url= it listens on."
#: the largest frame read (bytes): a state message for one Inverse3 and a VerseGrip is about 300 bytes,
#: so this leaves room for a hundred devices, while a hostile or broken service cannot make the process
#: buffer more than this per message (with ``max_size=None`` one 200 MB frame took it to 799 MB)
MAX_FRAME = 64 * 1024
#: the most JSON objects and arrays in a message (a state has about 8): bounds the nesting the parser
#: meets far below the interpreter's recursion limit
MAX_CONTAINERS = 256
_MAX_ID = 64  # characters of a device_id


class Refused(ValueError):
    """A message that is not the Inverse Service's state (why, in words)."""


def _no_constant(name: str):
    raise Refused(f"{name} where a number belongs (JSON has no such value)")


def _field(obj, key: str, kind: type, where: str):
    """``obj[key]``, which must be a ``kind`` (dict: a JSON object, list: an array)."""
    if not isinstance(obj, dict):
        raise Refused(f"{where} is {validate.show(obj, 40)}, not a JSON object")
    value = obj.get(key)
    if not isinstance(value, kind):
        raise Refused(f"{where}.{key} is {validate.show(value, 40)}, not a JSON {'object' if kind is dict else 'array'}")
    return value


def _coordinate(value, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise Refused(f"{where} is {validate.show(value, 40)}, not a number")
    if isinstance(value, int) and abs(value) > REACH:  # compared as an integer: a 400-digit one cannot overflow
        raise Refused(f"{where} is an integer of about 10^{int(abs(value).bit_length() * 0.30103)} m, beyond "
                      f"{REACH:g} m of the service's origin")
    v = float(value)
    if not math.isfinite(v) or abs(v) > REACH:
        raise Refused(f"{where} = {v!r} m is not a finite coordinate within {REACH:g} m of the service's origin")
    return v


def device_id_of(value):
    """A device_id as the service writes it (a string, or an integer) of at most 64 characters."""
    if isinstance(value, bool) or not isinstance(value, (str, int)) or len(str(value)) > _MAX_ID:
        raise Refused(f"device_id {validate.show(value, 40)} is not a string or integer of at most {_MAX_ID} characters")
    return value


def parse(frame) -> dict:
    """The JSON object of one frame, or :class:`Refused` (a binary frame, a frame over
    :data:`MAX_FRAME`, too many objects and arrays, not JSON, NaN or Infinity, not an object)."""
    if not isinstance(frame, str):
        raise Refused(f"a binary frame of {len(frame)} bytes, not the service's JSON text")
    if len(frame) > MAX_FRAME:
        raise Refused(f"a frame of {len(frame)} characters, over {MAX_FRAME}")
    containers = frame.count("{") + frame.count("[")
    if containers > MAX_CONTAINERS:
        raise Refused(f"{containers} JSON objects and arrays (nested or not), over {MAX_CONTAINERS}")
    try:
        message = json.loads(frame, parse_constant=_no_constant)
    except Refused:
        raise
    except (ValueError, RecursionError) as exc:  # JSONDecodeError, an integer of over 4300 digits
        raise Refused(f"not JSON ({type(exc).__name__}: {validate.one_line(str(exc), 80)})") from None
    if not isinstance(message, dict):
        raise Refused(f"a JSON {type(message).__name__}, not an object")
    return message


def read_state(message: dict, device_id) -> tuple[tuple[float, float, float], int]:
    """The cursor position (m) of Inverse3 ``device_id`` and the first VerseGrip's buttons (a bit
    mask, the button names in sorted order: a, b, c) from one state message, or :class:`Refused`."""
    devices = _field(message, "inverse3", list, "the message")
    for i, dev in enumerate(devices):
        if not isinstance(dev, dict):
            raise Refused(f"inverse3[{i}] is {validate.show(dev, 40)}, not an object")
        if device_id_of(dev.get("device_id")) == device_id:
            p = _field(_field(dev, "state", dict, f"inverse3[{i}]"), "cursor_position", dict, f"inverse3[{i}].state")
            x = tuple(_coordinate(p.get(c), f"cursor_position.{c}") for c in "xyz")
            break
    else:
        raise Refused(f"no state for Inverse3 {device_id!r}")
    grips = message.get("wireless_verse_grip")
    if grips is None or grips == []:
        return x, 0
    if not isinstance(grips, list):
        raise Refused(f"wireless_verse_grip is {validate.show(grips, 40)}, not an array")
    pressed = _field(grips[0], "state", dict, "wireless_verse_grip[0]").get("buttons") or {}
    if not isinstance(pressed, dict):
        raise Refused(f"the VerseGrip's buttons are {validate.show(pressed, 40)}, not an object")
    if len(pressed) > MAX_BUTTONS:
        raise Refused(f"{len(pressed)} buttons on the VerseGrip, over {MAX_BUTTONS}")
    buttons = 0
    for i, k in enumerate(sorted(pressed)):
        if not isinstance(pressed[k], bool):
            raise Refused(f"button {validate.show(k, 20)} is {validate.show(pressed[k], 20)}, not true or false")
        buttons |= int(pressed[k]) << i
    return x, buttons


def command(device_id, f) -> str:
    """The service's command setting Inverse3 ``device_id``'s cursor force to ``f`` (N)."""
    return json.dumps({"inverse3": [{"device_id": device_id, "commands": {
        "set_cursor_force": {"values": {"x": float(f[0]), "y": float(f[1]), "z": float(f[2])}}}}]})


class Haply(HardwareDevice):
    """A Haply Inverse3 (with a VerseGrip's buttons) as an rtfem Device.

    Parameters
    ----------
    url : the Inverse Service's WebSocket address.
    workspace : the :class:`~rtfem.interaction.devices.Workspace` from the service's frame to the
        organ's; default: fitted when a loop attaches the device to an organ (``usable`` centred on
        the organ's top), with the second button as the clutch.
    usable : (lo, hi), the usable workspace (m) for that fit; default a 20 cm cube.
    max_force : the largest force rendered (N); required: the service does not report the device's.
    max_rate, watchdog : the servo's force-rate limit (N/s) and its watchdog (servo ticks).
    rate : the service's state rate (Hz): the rate limit's time step.
    timeout : seconds to connect, without a state message before the device counts as gone, and to
        close the connection.

    Raises
    ------
    DeviceError
        The websockets library missing, the service unreachable (the address named), a first message
        that is not the service's state or has no Inverse3, no max_force.
    ModelError
        A bad url, workspace, usable box, max_force, max_rate, watchdog, rate or timeout.

    Every fault (see the module's text) commands zero force, closes the connection and sets
    ``stop_reason``; after it, open a new Haply.
    """

    NAME = "a Haply Inverse3"

    def __init__(self, url: str = "ws://localhost:10001", *, workspace: Workspace | None = None, usable=CUBE,
                 max_force: float | None = None, max_rate: float = 1000.0, watchdog: int = 50, rate: float = 1000.0,
                 timeout: float = 2.0) -> None:
        try:
            from websockets.sync.client import connect
        except ImportError:  # pragma: no cover - a dependency of the viewer extra
            raise DeviceError("Haply: the adapter needs the websockets library (pip install websockets; the viewer "
                              "extra has it)") from None
        if not isinstance(url, str) or not url.startswith(("ws://", "wss://")):
            raise DeviceError(f"url={validate.show(url)} must be the service's WebSocket address, e.g. "
                              "ws://localhost:10001")
        if max_force is None:
            raise DeviceError("Haply: give max_force= in N (the Inverse Service does not report the device's "
                              "maximum)")
        self.url = url
        self.timeout = validate.positive(timeout, "timeout", "seconds")
        self._closing = threading.Event()
        self._send_lock = threading.Lock()
        self._zeroed = False  # once set (under _send_lock), no force but zero is sent
        self._thread = None
        self._connect = connect
        self._start_servo(workspace, usable, validate.positive(max_force, "max_force", "the largest force in N"),
                          max_rate, watchdog, rate)
        try:
            self._ws = self._connection()
        except Exception as exc:  # refused, unreachable, not a WebSocket, bad address
            raise DeviceError(f"Haply: cannot reach the Inverse Service at {url} ({type(exc).__name__}: "
                              f"{validate.one_line(str(exc), 160)}). {HOW}") from None
        try:
            first = parse(self._ws.recv(timeout=self.timeout))
            devices = first.get("inverse3")
            if not isinstance(devices, list) or not devices or not isinstance(devices[0], dict):
                raise DeviceError(f"Haply: the Inverse Service at {url} reports no Inverse3 (is it plugged in?)")
            self.device_id = device_id_of(devices[0].get("device_id"))
        except BaseException as exc:
            self._ws.close()
            if isinstance(exc, DeviceError) or not isinstance(exc, Exception):
                raise
            raise DeviceError(f"Haply: the first message from {url} is not the Inverse Service's state "
                              f"({type(exc).__name__}: {validate.one_line(str(exc), 160)})") from None
        from ...threads import background

        self._thread = threading.Thread(target=self._run, args=(first,), name="rtfem-haply-servo", daemon=True)
        background(self._thread, self.close)
        self._thread.start()

    def _connection(self):
        """A connection to the service: frames over MAX_FRAME refused from their header, a closing
        handshake that waits at most ``timeout``."""
        return self._connect(self.url, open_timeout=self.timeout, close_timeout=self.timeout, max_size=MAX_FRAME)

    def _run(self, message: dict) -> None:
        """The servo thread: a tick per state message, the force back as the service's command; every
        way out of it but a close is a fault."""
        from websockets.exceptions import ConnectionClosed

        self._servo_ident = threading.get_ident()
        try:
            while not self._closing.is_set():
                x, buttons = read_state(message, self.device_id)
                f = self._tick(x, buttons)
                if self._released:
                    return
                with self._send_lock:
                    if self._zeroed:
                        return
                    self._ws.send(command(self.device_id, f))
                message = parse(self._ws.recv(timeout=self.timeout))
        except ConnectionClosed as exc:
            if not self._closing.is_set():
                self._closed(exc)
        except TimeoutError:
            self.fault(3, f"no state from the Inverse Service for {self.timeout:g} s")
        except Refused as exc:
            self.fault(6, f"the Inverse Service's message: {exc}")
        except BaseException as exc:  # noqa: BLE001 - RecursionError, OverflowError, MemoryError...: a fault
            self._failed(exc)
            if isinstance(exc, (KeyboardInterrupt, SystemExit)):
                raise

    def _closed(self, exc) -> None:
        """The connection closed under the servo: by the service, or by the WebSocket layer refusing a
        frame (over MAX_FRAME, not UTF-8, not the protocol)."""
        sent, rcvd = exc.sent, exc.rcvd
        if sent is not None and sent.code != 1000 and (rcvd is None or exc.rcvd_then_sent is False):
            why = "over 64 KiB" if sent.code == 1009 else validate.one_line(sent.reason or "", 80)
            self.fault(6, f"the Inverse Service sent a frame the WebSocket layer refused (close code {sent.code}: "
                          f"{why})")
        else:
            self.fault(3, "the Inverse Service closed the connection")

    def _command_zero(self) -> None:
        """Command zero force: on the connection while it is open, else on a new one (the last force
        the service was given must not stay commanded); no force but zero is sent after this."""
        from websockets.exceptions import ConnectionClosed

        zero = command(self.device_id, (0.0, 0.0, 0.0))
        with self._send_lock:
            self._zeroed = True
            try:
                self._ws.send(zero)
                return
            except ConnectionClosed:
                pass
        ws = self._connection()  # a failure here is noted in the stop reason by fault()
        try:
            ws.recv(timeout=self.timeout)  # the service's first state (unread: only its turn to be answered)
            ws.send(zero)
        finally:
            ws.close()

    def _shutdown(self) -> None:
        """Close the connection (the closing handshake waits at most ``timeout``)."""
        self._ws.close()

    def _open(self) -> bool:
        return self._thread is not None and self._thread.is_alive() and not self._released

    def restart(self) -> None:
        """Render again after a watchdog or force stop; after a fault (the connection is closed), open a
        new Haply."""
        if not self._open():
            raise DeviceError(f"Haply: the connection to {self.url} is gone ({self.stop_reason}); open a new "
                              "rt.devices.Haply")
        super().restart()

    def close(self) -> None:
        """Stop the servo, command zero force, close the connection; closing twice does nothing."""
        self._closing.set()
        self.fault(4, "")
        if self._thread is not None and threading.current_thread() is not self._thread:
            self._thread.join(2.0 * self.timeout + 1.0)
