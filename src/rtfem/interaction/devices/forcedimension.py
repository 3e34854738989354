"""Force Dimension omega / sigma / delta and the Novint Falcon through the DHD C API (ctypes).

The SDK (``dhdc.h``) works in metres and newtons; ``dhdGetPosition`` and ``dhdSetForce`` return 0 on
success, a positive value for a success with a note (a time guard, saturated motors) and -1 on an
error, whose number and text ``dhdErrorGetLast`` / ``dhdErrorGetLastStr`` give. The SDK has no
scheduler: the servo (:mod:`.servo`) runs on a thread of its own at ``rate``.
"""

from __future__ import annotations

import ctypes
import threading
from ctypes import POINTER, byref, c_byte, c_char_p, c_double, c_int, c_ubyte

import numpy as np

from ... import validate
from ...errors import DeviceError
from .hardware import HardwareDevice
from .native import ServoThread, load_library
from .workspace import Workspace

__all__ = ["ForceDimension"]

_SIGNATURES = {
    "dhdOpen": ([], c_int), "dhdClose": ([c_byte], c_int), "dhdEnableForce": ([c_ubyte, c_byte], c_int),
    "dhdGetPosition": ([POINTER(c_double), POINTER(c_double), POINTER(c_double), c_byte], c_int),
    "dhdSetForce": ([c_double, c_double, c_double, c_byte], c_int), "dhdGetButton": ([c_int, c_byte], c_int),
    "dhdGetMaxForce": ([c_byte], c_double), "dhdErrorGetLast": ([], c_int), "dhdErrorGetLastStr": ([], c_char_p),
}
_DISCONNECTED = (2, 5, 7)  # DHD_ERROR_COM, DHD_ERROR_NO_DEVICE_FOUND, DHD_ERROR_TIMEOUT
HOW = ("Install Force Dimension's SDK (https://www.forcedimension.com/software/sdk: libdhd / dhd64.dll), or give "
       "library='/path/to/libdhd.so' or $RTFEM_DHD_LIB.")
# the default usable workspace: a box round an omega.x's translation workspace (160 mm across, 110 mm high)
OMEGA_BOX = (np.array([-0.08, -0.08, -0.055]), np.array([0.08, 0.08, 0.055]))


def dhd_library(library=None) -> ctypes.CDLL:
    """The DHD library with its functions' signatures declared."""
    return load_library(library, "RTFEM_DHD_LIB", ("dhd", "libdhd.so", "dhd64"), "Force Dimension", HOW, _SIGNATURES)


class ForceDimension(HardwareDevice):
    """A Force Dimension device (omega, sigma, delta, Novint Falcon) as an rtfem Device.

    Parameters
    ----------
    library : the DHD library (a path or a name); default ``$RTFEM_DHD_LIB``, else libdhd on the
        system's library path.
    workspace : the :class:`~rtfem.interaction.devices.Workspace` from the device's frame to the
        organ's; default: fitted when a loop attaches the device to an organ (``usable`` centred on the
        organ's top, the device's z up), with the second button as the clutch.
    usable : (lo, hi), the device's usable workspace (m) for that fit; default an omega.x's.
    max_force : the largest force rendered (N); at most the device's limit (``dhdGetMaxForce``); needed
        when the device enforces none.
    max_rate, watchdog : the servo's force-rate limit (N/s) and its watchdog (servo ticks).
    rate : the servo thread's rate (Hz).
    buttons : how many of the device's buttons are read each tick.

    Raises
    ------
    DeviceError
        The library not found or not DHD, no device (``dhdOpen``'s error), a device without a force
        limit and no max_force, the force not enabled.
    ModelError
        A bad workspace, usable box, max_force, max_rate, watchdog, rate or buttons.

    Every fault (a DHD call that fails, a position that is not finite or beyond 10 m, an exception on
    the servo thread, ``close()``) stops the servo thread, writes zero force, disables the force and
    closes the device, and sets ``stop_reason``; after it, open a new ForceDimension.
    """

    NAME = "a Force Dimension device"

    def __init__(self, library=None, *, workspace: Workspace | None = None, usable=OMEGA_BOX,
                 max_force: float | None = None, max_rate: float = 1000.0, watchdog: int = 50, rate: float = 1000.0,
                 buttons: int = 2) -> None:
        self._dhd = dhd = dhd_library(library)
        self._id, self._thread, self._detail = None, None, ""
        self.n_buttons = validate.count(buttons, "buttons", 0, 16)
        rate = validate.positive(rate, "rate", "the servo's rate in Hz")
        device = dhd.dhdOpen()
        if device < 0:
            raise DeviceError(f"Force Dimension: dhdOpen() opened no device: {self._last_error()}")
        self._id = device
        try:
            limit = float(dhd.dhdGetMaxForce(device))
            self.device_max_force = limit if limit > 0 else None
            if max_force is None and self.device_max_force is None:
                raise DeviceError("Force Dimension: the device enforces no force limit (dhdGetMaxForce gave -1): give "
                                  "max_force= in N (what your device renders continuously)")
            given = None if max_force is None else validate.positive(max_force, "max_force", "the largest force in N")
            limit = min(v for v in (given, self.device_max_force) if v is not None)
            self._start_servo(workspace, usable, limit, max_rate, watchdog, rate)
            if dhd.dhdEnableForce(1, device) < 0:
                raise DeviceError(f"Force Dimension: dhdEnableForce failed: {self._last_error()}")
            self._p = (c_double(), c_double(), c_double())
            self._thread = ServoThread(self._servo, rate, "rtfem-dhd-servo", on_error=self._failed).start(at_exit=self.close)
        except BaseException:
            self._shutdown()
            raise

    def _last_error(self) -> str:
        text = self._dhd.dhdErrorGetLastStr()
        text = validate.one_line(text.decode(errors="replace"), 120) if text else "no text"
        return f"{text} (DHD error {self._dhd.dhdErrorGetLast()})"

    def _sdk_fault(self, prefix: str = "") -> None:
        """A DHD call that failed: a fault (disconnected, or the device's error), the device released."""
        code = self._dhd.dhdErrorGetLast()
        self.fault(3 if code in _DISCONNECTED else 2, prefix + self._last_error())

    def _servo(self) -> bool:
        """One servo tick on the servo thread; False (the thread ends) once a fault released the device."""
        self._servo_ident = threading.get_ident()
        dhd, device, (px, py, pz) = self._dhd, self._id, self._p
        if self._released or device is None:
            return False
        if dhd.dhdGetPosition(byref(px), byref(py), byref(pz), device) < 0:
            self._sdk_fault()
            return False
        buttons = 0
        for i in range(self.n_buttons):
            if dhd.dhdGetButton(i, device) == 1:
                buttons |= 1 << i
        f = self._tick((px.value, py.value, pz.value), buttons)
        if self._released:  # the position was refused: the fault zeroed the force and closed the device
            return False
        if dhd.dhdSetForce(float(f[0]), float(f[1]), float(f[2]), device) < 0:
            self._sdk_fault("dhdSetForce: ")
            return False
        return True

    def _open(self) -> bool:
        return self._id is not None

    @property
    def servo_error(self) -> BaseException | None:
        """An exception that ended the servo thread (None while it runs); ``stop_reason`` names it too."""
        return None if self._thread is None else self._thread.error

    def _command_zero(self) -> None:
        """Stop the servo thread (joined, unless this is it: no force is written after this one), then
        write zero force."""
        if self._thread is not None:
            self._thread.stop()
        if self._id is not None and self._dhd.dhdSetForce(0.0, 0.0, 0.0, self._id) < 0:
            raise DeviceError(f"dhdSetForce(0, 0, 0) failed: {self._last_error()}")

    def _shutdown(self) -> None:
        """Stop the servo thread, zero the force, disable it and close the device (idempotent)."""
        if self._thread is not None:
            self._thread.stop()
        if self._id is not None:
            device, self._id = self._id, None
            self._dhd.dhdSetForce(0.0, 0.0, 0.0, device)
            self._dhd.dhdEnableForce(0, device)
            self._dhd.dhdClose(device)
