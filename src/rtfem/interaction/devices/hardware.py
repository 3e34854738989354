"""What every hardware adapter shares: a SharedDevice whose mailbox is its servo's, a workspace
fitted to the organ a loop attaches it to, a stop reason and a restart."""

from __future__ import annotations

import numpy as np

from ... import validate
from ...errors import DeviceError
from .base import SharedDevice
from .servo import Servo
from .workspace import Workspace

__all__ = ["HardwareDevice"]


class HardwareDevice(SharedDevice):
    """The base of the adapters: subclasses open the device, call :meth:`_start_servo`, then run
    :attr:`servo`'s ticks on the device's thread, and say in :meth:`_open` whether it is open."""

    NAME = "the device"
    ROTATION: np.ndarray | None = None  # the device's axes in the organ's frame for the default fit (None: identity)
    _detail = ""

    def _start_servo(self, workspace, usable, limit: float, max_rate: float, watchdog: int, rate: float) -> None:
        """The servo, with ``workspace`` or a default one fitted to the organ on :meth:`attach` (over
        the device's ``usable`` box, the second button clutching)."""
        self.usable = tuple(np.array(validate.point(p, "usable"), dtype=float) for p in usable)
        if workspace is not None and not isinstance(workspace, Workspace):
            from ...errors import ModelError

            raise ModelError(f"workspace={validate.show(workspace)} must be an rt.devices.Workspace (or None: fitted)")
        self._fit = workspace is None
        ws = Workspace(rotation=self.ROTATION, clutch=1) if workspace is None else workspace
        self.servo = Servo(ws, limit, max_rate=max_rate, watchdog=watchdog, rate=rate)
        self.mailbox = self.servo.mailbox

    def _open(self) -> bool:  # pragma: no cover - every adapter defines it
        raise NotImplementedError

    def _shutdown(self) -> None:  # pragma: no cover - every adapter defines it
        """Release the device (idempotent: also what a failed constructor calls)."""
        raise NotImplementedError

    def close(self) -> None:
        """Stop rendering (the reason: closed, unless it had stopped already) and release the device;
        closing twice does nothing."""
        if self._open():
            self.servo.stop(4)
        self._shutdown()

    def attach(self, organ_bounds) -> None:
        """Fit the default workspace to an organ's bounds (lo, hi), as a loop does when it starts (a
        workspace given to the constructor is kept)."""
        if self._fit:
            ws = Workspace.fit(self.usable, organ_bounds, rotation=self.ROTATION, clutch=1)
            self.servo.buf[8:22] = ws.packed()
            self.servo.workspace = ws

    def move_to(self, position) -> None:
        raise DeviceError(f"{self.NAME}'s position is its handle's: it cannot be moved in software")

    @property
    def stop_reason(self) -> str | None:
        reason = self.servo.reason if hasattr(self, "servo") else None
        return None if reason is None else reason + (f": {self._detail}" if self._detail else "")

    @stop_reason.setter
    def stop_reason(self, value) -> None:  # the servo keeps the reason (Device.close would set it)
        pass

    def restart(self) -> None:
        """Render forces again after a stop that was not a close (the simulation's state is untouched;
        the force ramps up from zero at the rate limit)."""
        if not self._open():
            raise DeviceError(f"{self.NAME} is closed: open a new one")
        self._detail = ""
        self.servo.restart()
