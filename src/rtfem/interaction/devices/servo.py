"""The servo step every hardware adapter runs at its device's rate, on the device's thread: the
hand's position through the :class:`~rtfem.interaction.devices.Workspace` into the mailbox the
simulation's loop reads, and the loop's force back to the device, with the safety a user's hand
needs between them.

Safety, in this order every servo tick:

* **watchdog**: once the loop has written a first force, a loop that writes none for
  ``watchdog`` servo ticks has fallen behind (or stopped): the force goes to zero at once and the
  servo stops with that reason;
* **finite**: a force that is not finite stops the servo (zero force);
* **clutch**: while the clutch button is held the force is zero (and the tool does not move);
* **clamp**: the force's magnitude is clamped to the device's maximum;
* **rate**: the force changes by at most ``max_rate`` N/s (an increase; a stop zeroes at once).

A stopped servo renders zero until :meth:`Servo.restart`; the simulation's state is untouched.
The adapters' faults (the device's errors, a disconnection, input malformed or out of range, an
exception in the adapter, a close) stop it from outside, through ``HardwareDevice.fault``, which
also commands zero force to the device and releases it.
The step is one function on one float64 array (:data:`LAYOUT`) so that the same code runs in
Python, compiled by numba, or as a C callback of a device's scheduler without the GIL.
"""

from __future__ import annotations

import math

import numpy as np

from ... import validate
from .base import MAILBOX
from .workspace import Workspace

__all__ = ["Servo", "STOP_REASONS", "SIMULATION_STOPS", "LAYOUT"]

# the servo's array: [0, 8) the mailbox (position, force, forces written, buttons); [8, 22) the
# workspace (scale, R, offset, clutch mask); then the limits, the state and the device's I/O
_WS, _MAXF, _RATE, _WATCH, _DT = 8, 22, 23, 24, 25
_STOP, _COUNT, _IDLE, _LAST, _HELD, _FROZEN, _TICKS = 26, 27, 28, 29, 32, 33, 36
_IN, _OUT, _BUTTONS = 37, 40, 43
LAYOUT = 44

STOP_REASONS = {1: "the simulation fell behind: no force from its loop for {watch} servo ticks",
                2: "the device reported an error", 3: "the device disconnected", 4: "closed",
                5: "the simulation's force was not finite",
                6: "the device sent input that is malformed or out of range",
                7: "the adapter failed"}
#: the stops the simulation causes (the device is fine; :meth:`Servo.restart` renders again); the others
#: are the device's or the adapter's faults and go through ``HardwareDevice.fault``
SIMULATION_STOPS = (1, 5)


def servo_step(b):
    """One servo tick on the array ``b`` (see :data:`LAYOUT`): reads the device's position (m, its
    frame) at b[37:40] and buttons at b[43], writes the tool's position into the mailbox b[0:3] and
    the force for the device (N, its frame) at b[40:43]."""
    b[_TICKS] += 1.0
    s = b[_WS]
    mask = int(b[_WS + 13])
    buttons = int(b[_BUTTONS])
    held = mask != 0 and (buttons & mask) != 0
    if held and b[_HELD] == 0.0:  # the clutch closes: the tool stays where the last tick put it
        b[_HELD] = 1.0
        for i in range(3):
            b[_FROZEN + i] = b[i]
    elif not held:
        b[_HELD] = 0.0
    x0, x1, x2 = b[_IN], b[_IN + 1], b[_IN + 2]
    for i in range(3):  # offset + s R x
        b[i] = b[_WS + 10 + i] + s * (b[_WS + 1 + 3 * i] * x0 + b[_WS + 2 + 3 * i] * x1 + b[_WS + 3 + 3 * i] * x2)
        if held:  # re-index the offset so that the hand's position maps to the frozen point
            b[_WS + 10 + i] += b[_FROZEN + i] - b[i]
            b[i] = b[_FROZEN + i]
    b[7] = buttons
    count = b[6]
    if count != b[_COUNT]:
        b[_COUNT] = count
        b[_IDLE] = 0.0
    else:
        b[_IDLE] += 1.0
    if b[_STOP] == 0.0 and count > 0.0 and b[_IDLE] > b[_WATCH]:
        b[_STOP] = 1.0
    f0, f1, f2 = b[3], b[4], b[5]
    if b[_STOP] == 0.0 and not (math.isfinite(f0) and math.isfinite(f1) and math.isfinite(f2)):
        b[_STOP] = 5.0
    if b[_STOP] != 0.0:
        for i in range(3):
            b[_LAST + i] = 0.0
            b[_OUT + i] = 0.0
        return
    if held:
        t0 = t1 = t2 = 0.0
    else:  # R^T f
        t0 = b[_WS + 1] * f0 + b[_WS + 4] * f1 + b[_WS + 7] * f2
        t1 = b[_WS + 2] * f0 + b[_WS + 5] * f1 + b[_WS + 8] * f2
        t2 = b[_WS + 3] * f0 + b[_WS + 6] * f1 + b[_WS + 9] * f2
    mag = math.sqrt(t0 * t0 + t1 * t1 + t2 * t2)
    if mag > b[_MAXF]:
        c = b[_MAXF] / mag
        t0, t1, t2 = t0 * c, t1 * c, t2 * c
    d0, d1, d2 = t0 - b[_LAST], t1 - b[_LAST + 1], t2 - b[_LAST + 2]
    change = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
    most = b[_RATE] * b[_DT]
    k = most / change if change > most else 1.0
    b[_LAST] += k * d0
    b[_LAST + 1] += k * d1
    b[_LAST + 2] += k * d2
    for i in range(3):
        b[_OUT + i] = b[_LAST + i]


_COMPILED = None


def compiled_step():
    """``servo_step`` compiled by numba (nogil), or the Python function without numba."""
    global _COMPILED
    if _COMPILED is None:
        try:
            import numba

            _COMPILED = numba.njit(nogil=True, cache=True, error_model="numpy")(servo_step)
        except Exception:  # pragma: no cover - numba absent
            _COMPILED = servo_step
    return _COMPILED


class Servo:
    """The servo's array and its settings: what an adapter's servo thread steps.

    Parameters
    ----------
    workspace : the :class:`~rtfem.interaction.devices.Workspace` (device frame -> organ frame).
    max_force : the largest force magnitude rendered (N): the device's nominal maximum, read from it
        where its API says it, or less.
    max_rate : the largest change of the force per second (N/s).
    watchdog : servo ticks without a new force from the loop before it stops (the simulation fell
        behind by that many of the device's ticks).
    rate : the servo's rate (Hz): the rate limit's time step.

    Raises
    ------
    ModelError
        A workspace that is not one; a non-positive max_force, max_rate or rate; a watchdog that is
        not a count >= 1.
    """

    def __init__(self, workspace: Workspace, max_force: float, *, max_rate: float = 1000.0, watchdog: int = 50,
                 rate: float = 1000.0) -> None:
        from ...errors import ModelError

        if not isinstance(workspace, Workspace):
            raise ModelError(f"workspace={validate.show(workspace)} must be an rt.devices.Workspace")
        self.buf = np.zeros(LAYOUT)
        self.buf[_WS:_WS + 14] = workspace.packed()
        self.buf[_MAXF] = validate.positive(max_force, "max_force", "the largest force in N")
        self.buf[_RATE] = validate.positive(max_rate, "max_rate", "the largest force change in N/s")
        self.buf[_WATCH] = validate.count(watchdog, "watchdog", 1, 10**7, what="servo ticks")
        self.buf[_DT] = 1.0 / validate.positive(rate, "rate", "the servo's rate in Hz")
        self.workspace = workspace
        self.step = compiled_step()

    @property
    def mailbox(self) -> np.ndarray:
        """The mailbox (a view of the servo's array): what the simulation's loop reads and writes."""
        return self.buf[:MAILBOX]

    def tick(self, x_device, buttons: int = 0) -> np.ndarray:
        """One servo tick (the Python entry: the adapters' C callbacks step the array directly):
        the device's position (m, its frame) and buttons in, the force for the device (N) out."""
        self.buf[_IN:_IN + 3] = x_device
        self.buf[_BUTTONS] = buttons
        self.step(self.buf)
        return self.buf[_OUT:_OUT + 3].copy()

    def stop(self, code: int, *, replace: bool = False) -> None:
        """Stop rendering (zero force) with a reason (a key of :data:`STOP_REASONS`); the first
        reason is kept unless ``replace``."""
        if self.buf[_STOP] == 0.0 or replace:
            self.buf[_STOP] = float(code)
        self.buf[_OUT:_OUT + 3] = 0.0
        self.buf[_LAST:_LAST + 3] = 0.0

    def restart(self) -> None:
        """Render again after a stop (the force ramps up from zero at the rate limit)."""
        self.buf[_STOP] = self.buf[_IDLE] = 0.0
        self.buf[_COUNT] = self.buf[6]

    @property
    def code(self) -> int:
        """The stop's code (a key of :data:`STOP_REASONS`; 0 while rendering)."""
        return int(self.buf[_STOP])

    @property
    def reason(self) -> str | None:
        code = int(self.buf[_STOP])
        return None if code == 0 else STOP_REASONS[code].format(watch=int(self.buf[_WATCH]))

    @property
    def ticks(self) -> int:
        return int(self.buf[_TICKS])

    @property
    def force(self) -> np.ndarray:
        """The force last handed to the device (N, the device's frame)."""
        return self.buf[_OUT:_OUT + 3].copy()
