"""What every hardware adapter shares: a SharedDevice whose mailbox is its servo's, a workspace
fitted to the organ a loop attaches it to, the check of what the device reports, a stop reason, a
restart, and :meth:`HardwareDevice.fault`: the one path every fault of every adapter ends in.

A fault (an error the device or its SDK reports, a disconnection, a timeout, input that is malformed
or out of range, an exception anywhere in the adapter's servo thread or callback, and ``close()``)
does, in this order and whatever fails on the way:

1. the servo stops: its output is zero from this tick on (and stays zero until a restart);
2. the reason is recorded: ``stop_reason`` reads the servo's reason, then the detail;
3. the adapter commands zero force explicitly (:meth:`HardwareDevice._command_zero`: a zero-force
   message to the service, a zero force written to the SDK), so no earlier force stays commanded;
4. the adapter releases the device (:meth:`HardwareDevice._shutdown`: the connection closed, the
   scheduler or thread stopped, the force output disabled), unless the fault leaves it safely idle
   (the servo rendering zero every tick, as after an SDK's own recoverable safety error).
"""

from __future__ import annotations

import math
import threading

import numpy as np

from ... import validate
from ...errors import DeviceError
from .base import SharedDevice
from .servo import SIMULATION_STOPS, STOP_REASONS, Servo
from .workspace import Workspace

__all__ = ["HardwareDevice", "REACH", "MAX_BUTTONS"]

#: the farthest a device may report its handle from its own origin (m): every desktop device reaches
#: less than a metre, so a position beyond this is the device's, the SDK's or the service's error
REACH = 10.0
#: the most buttons a device may report: the servo keeps them as a bit mask in a float64 (exact to 2^53)
MAX_BUTTONS = 32
_STOP_REPLACES = (2, 3, 6, 7)  # device faults that replace a simulation's stop (the device is gone now)


class HardwareDevice(SharedDevice):
    """The base of the adapters: subclasses open the device, call :meth:`_start_servo`, then run
    :attr:`servo`'s ticks (through :meth:`_tick`) on the device's thread, send every fault to
    :meth:`fault`, say in :meth:`_open` whether the device is open, and implement
    :meth:`_command_zero` and :meth:`_shutdown`."""

    NAME = "the device"
    ROTATION: np.ndarray | None = None  # the device's axes in the organ's frame for the default fit (None: identity)
    _detail = ""
    _released = False  # a fault released the device: no restart, only a new adapter
    _servo_ident: int | None = None  # the servo thread's (or the SDK scheduler's) threading.get_ident()

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
        self._fault_lock = threading.Lock()

    def _open(self) -> bool:  # pragma: no cover - every adapter defines it
        raise NotImplementedError

    def _shutdown(self) -> None:  # pragma: no cover - every adapter defines it
        """Release the device (idempotent: also what a failed constructor calls; called on the servo's
        own thread too, which it must not join)."""
        raise NotImplementedError

    def _command_zero(self) -> None:
        """Command zero force to the device now (a zero-force message, a zero force written to the SDK),
        after the servo stopped: each adapter says how; an exception here is noted in the stop reason.
        The base commands nothing beyond the servo's own zero output."""

    # ------------------------------------------------------------------------------------ faults

    def fault(self, code: int, detail: str = "", *, release: bool = True) -> None:
        """The one path of every fault: stop the servo with ``code`` (a key of
        :data:`~rtfem.interaction.devices.servo.STOP_REASONS`: 2 the device reported an error, 3 it
        disconnected (or fell silent), 4 closed, 6 its input was malformed or out of range, 7 the
        adapter failed; any other code counts as 7; zero force at the servo's output), record
        ``detail`` (``stop_reason`` reads the reason, then the detail), command zero force
        (:meth:`_command_zero`) and, with ``release``, release the device (:meth:`_shutdown`; no
        restart after it). ``release=False`` leaves it safely idle: open, the servo rendering zero
        every tick until :meth:`restart`.

        Idempotent (after a release it does nothing; the first reason is kept, except that a device's
        fault replaces a stop the simulation caused) and thread-safe (a fault raised on the servo's
        own thread while another thread is handling one leaves it to that thread, which stops the
        servo thread and releases the device). It raises nothing of its own: what fails in the
        zero command or the release is noted in the stop reason; a KeyboardInterrupt or SystemExit
        that arrives while it runs is raised again once every step has run."""
        pending = None
        try:
            if isinstance(code, bool) or not isinstance(code, int) or code not in STOP_REASONS or code in SIMULATION_STOPS:
                detail, code = f"{detail} (fault() was given code {validate.show(code, 20)}, not a device's)", 7
            pending = self._fault(code, validate.one_line(str(detail), 300), bool(release))
        except BaseException as exc:  # noqa: BLE001 - a fault must not raise (a lock, a format)
            if isinstance(exc, (KeyboardInterrupt, SystemExit)):
                pending = exc
        if pending is not None:
            raise pending

    def _fault(self, code: int, detail: str, release: bool) -> BaseException | None:
        lock = getattr(self, "_fault_lock", None)
        me = threading.get_ident()  # the servo's thread: the SDK's scheduler's, else the adapter's _thread
        on_servo = me == self._servo_ident or me == getattr(getattr(self, "_thread", None), "ident", None)
        if lock is not None and not lock.acquire(blocking=not on_servo):
            return None  # another thread is in a fault now: it zeroes, stops this thread and releases
        try:
            if self._released:
                return None
            servo = getattr(self, "servo", None)
            if servo is not None:
                current = servo.code
                first = current == 0 or (current in SIMULATION_STOPS and code in _STOP_REPLACES)
                servo.stop(code, replace=first)
                if first:
                    self._detail = detail
            steps = [(self._command_zero, "no zero-force command was sent")]
            if release:
                self._released = True
                steps.append((self._shutdown, "releasing the device failed"))
            notes, pending = [], None
            for step, failed in steps:
                try:
                    step()
                except BaseException as exc:  # noqa: BLE001 - noted in the stop reason
                    notes.append(f"{failed} ({type(exc).__name__}: {validate.one_line(str(exc), 120)})")
                    if isinstance(exc, (KeyboardInterrupt, SystemExit)):
                        pending = exc
            if notes:
                self._detail = "; ".join(n for n in [self._detail, *notes] if n)
            return pending
        finally:
            if lock is not None:
                lock.release()

    def _failed(self, exc: BaseException) -> None:
        """An exception that escaped the adapter's servo thread or callback: a fault (code 7) naming it."""
        self.fault(7, f"{type(exc).__name__} in {self.NAME}'s servo: {validate.one_line(str(exc), 160)}")

    def _tick(self, x, buttons: int) -> np.ndarray:
        """One servo tick on what the device reported: a position (m, the device's frame) that is not
        three finite numbers within :data:`REACH` of its origin, or buttons that are not a mask of
        :data:`MAX_BUTTONS` bits, is a fault (code 6) and the force is zero."""
        x0, x1, x2 = float(x[0]), float(x[1]), float(x[2])
        if not (math.isfinite(x0) and math.isfinite(x1) and math.isfinite(x2)):
            self.fault(6, f"a position that is not finite ({x0!r}, {x1!r}, {x2!r})")
            return np.zeros(3)
        if abs(x0) > REACH or abs(x1) > REACH or abs(x2) > REACH:
            self.fault(6, f"a position of ({x0:.4g}, {x1:.4g}, {x2:.4g}) m, beyond {REACH:g} m of the device's origin")
            return np.zeros(3)
        if not 0 <= buttons < 1 << MAX_BUTTONS:
            self.fault(6, f"buttons {validate.show(buttons)} that are not a mask of {MAX_BUTTONS} bits")
            return np.zeros(3)
        return self.servo.tick((x0, x1, x2), buttons)

    # ---------------------------------------------------------------------------------- the rest

    def close(self) -> None:
        """Stop rendering (the reason: closed, unless it had stopped already), command zero force and
        release the device (:meth:`fault` with code 4); closing twice does nothing."""
        self.fault(4, "")

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
        """Render forces again after a stop that left the device open (the simulation fell behind, its
        force was not finite, an SDK's recoverable error); the simulation's state is untouched and the
        force ramps up from zero at the rate limit. After a fault that released the device, or a
        close, open a new one."""
        if self._released or not self._open():
            raise DeviceError(f"{self.NAME} is closed ({self.stop_reason}): open a new one")
        self._detail = ""
        self.servo.restart()
