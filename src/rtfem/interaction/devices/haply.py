"""Haply Inverse3 through the Haply Inverse Service's WebSocket JSON API (service 3.x, default
``ws://localhost:10001``).

The service streams state messages, ``{"inverse3": [{"device_id": ..., "state": {"cursor_position":
{"x", "y", "z"}, ...}}], "wireless_verse_grip": [{"state": {"buttons": {...}}}]}`` (metres), and sends
the next one after the client's command, ``{"inverse3": [{"device_id": ..., "commands":
{"set_cursor_force": {"values": {"x", "y", "z"}}}}]}`` (newtons). The servo (:mod:`.servo`) runs once
per state message, on a thread of its own, through the ``websockets`` library's client.
"""

from __future__ import annotations

import json
import threading

import numpy as np

from ... import validate
from ...errors import DeviceError
from .hardware import HardwareDevice
from .workspace import Workspace

__all__ = ["Haply"]

# the fit's default usable workspace: a 20 cm cube round the service's origin (give usable= from your
# device's manual)
CUBE = (np.array([-0.1, -0.1, -0.1]), np.array([0.1, 0.1, 0.1]))
HOW = "Start Haply's Inverse Service (https://docs.haply.co), or give the url= it listens on."


def _buttons(message: dict) -> int:
    """The first VerseGrip's buttons as a bit mask (its button names in sorted order: a, b, c)."""
    grips = message.get("wireless_verse_grip") or []
    pressed = (grips[0].get("state", {}).get("buttons") or {}) if grips else {}
    return sum(1 << i for i, k in enumerate(sorted(pressed)) if pressed[k])


def _position(message: dict, device_id) -> tuple[float, float, float]:
    for dev in message["inverse3"]:
        if dev.get("device_id") == device_id:
            p = dev["state"]["cursor_position"]
            x = (float(p["x"]), float(p["y"]), float(p["z"]))
            if not all(np.isfinite(x)):
                raise ValueError(f"a non-finite cursor position {p}")
            return x
    raise KeyError(f"no state for Inverse3 {device_id!r}")


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
    timeout : seconds to connect, and without a state message before the device counts as gone.

    Raises
    ------
    DeviceError
        The websockets library missing, the service unreachable (the address named), no Inverse3
        in its first message, no max_force.
    ModelError
        A bad url, workspace, usable box, max_force, max_rate, watchdog, rate or timeout.
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
        self._thread = None
        try:
            self._ws = connect(url, open_timeout=self.timeout, max_size=None)
        except Exception as exc:  # refused, unreachable, not a WebSocket, bad address
            raise DeviceError(f"Haply: cannot reach the Inverse Service at {url} ({type(exc).__name__}: {exc}). "
                              f"{HOW}") from None
        try:
            first = json.loads(self._ws.recv(timeout=self.timeout))
            devices = first.get("inverse3") or []
            if not devices:
                raise DeviceError(f"Haply: the Inverse Service at {url} reports no Inverse3 (is it plugged in?)")
            self.device_id = devices[0].get("device_id")
            self._start_servo(workspace, usable, validate.positive(max_force, "max_force", "the largest force in N"),
                              max_rate, watchdog, rate)
            self._thread = threading.Thread(target=self._run, args=(first,), name="rtfem-haply-servo", daemon=True)
            from ...threads import background

            background(self._thread, self.close)
            self._thread.start()
        except DeviceError:
            self._ws.close()
            raise
        except Exception as exc:  # a first message that is not the service's
            self._ws.close()
            raise DeviceError(f"Haply: the first message from {url} is not the Inverse Service's state "
                              f"({type(exc).__name__}: {exc})") from None

    def _run(self, message: dict) -> None:
        """The servo thread: a tick per state message, the force back as the service's command."""
        from websockets.exceptions import ConnectionClosed

        try:
            while not self._closing.is_set():
                f = self.servo.tick(_position(message, self.device_id), _buttons(message))
                self._ws.send(json.dumps({"inverse3": [{"device_id": self.device_id, "commands": {
                    "set_cursor_force": {"values": {"x": float(f[0]), "y": float(f[1]), "z": float(f[2])}}}}]}))
                message = json.loads(self._ws.recv(timeout=self.timeout))
        except ConnectionClosed:
            if not self._closing.is_set():
                self._detail = "the Inverse Service closed the connection"
                self.servo.stop(3)
        except TimeoutError:
            self._detail = f"no state from the Inverse Service for {self.timeout:g} s"
            self.servo.stop(3)
        except (ValueError, KeyError, TypeError, AttributeError, IndexError) as exc:
            self._detail = f"a message that is not the service's state ({type(exc).__name__}: {exc})"
            self.servo.stop(2)

    def _open(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def restart(self) -> None:
        """Render again after a watchdog or force stop; a lost connection needs a new Haply()."""
        if not self._open():
            raise DeviceError(f"Haply: the connection to {self.url} is gone ({self.stop_reason}); open a new "
                              "rt.devices.Haply")
        super().restart()

    def close(self) -> None:
        """Stop the servo and close the connection (the service zeroes the force); closing twice does nothing."""
        if not self._closing.is_set():
            self._closing.set()
            if hasattr(self, "servo"):
                self.servo.stop(4)
            self._ws.close()
            if self._thread is not None and threading.current_thread() is not self._thread:
                self._thread.join(2.0)
