"""3D Systems Touch / Phantom devices through the OpenHaptics HD API (ctypes).

The names, constants and signatures are those of the SDK's ``HD/hdDefines.h`` (version 3.00),
``HD/hdScheduler.h`` and ``HD/hdDevice.h``: positions in millimetres, forces in newtons. The servo
(:mod:`.servo`) runs inside the HD scheduler's thread, as an asynchronous callback between
``hdBeginFrame`` and ``hdEndFrame``, at the scheduler's rate (1 kHz by default); the simulation's
loop meets it in the shared mailbox.
"""

from __future__ import annotations

import atexit
import ctypes
import threading
import weakref
from ctypes import CFUNCTYPE, POINTER, Structure, byref, c_char_p, c_double, c_int, c_uint, c_ulong, c_ushort, c_void_p

import numpy as np

from ... import validate
from ...errors import DeviceError
from .hardware import HardwareDevice
from .native import load_library
from .workspace import Workspace

__all__ = ["OpenHaptics", "HD_ERRORS"]

HD_SUCCESS = 0x0000
HD_ERRORS = {0x0100: "HD_INVALID_ENUM", 0x0101: "HD_INVALID_VALUE", 0x0102: "HD_INVALID_OPERATION",
             0x0103: "HD_INVALID_INPUT_TYPE", 0x0104: "HD_BAD_HANDLE", 0x0200: "HD_WARM_MOTORS",
             0x0201: "HD_EXCEEDED_MAX_FORCE", 0x0202: "HD_EXCEEDED_MAX_FORCE_IMPULSE",
             0x0203: "HD_EXCEEDED_MAX_VELOCITY", 0x0204: "HD_FORCE_ERROR", 0x0300: "HD_DEVICE_FAULT",
             0x0301: "HD_DEVICE_ALREADY_INITIATED", 0x0302: "HD_COMM_ERROR", 0x0303: "HD_COMM_CONFIG_ERROR",
             0x0304: "HD_TIMER_ERROR", 0x0400: "HD_ILLEGAL_BEGIN", 0x0401: "HD_ILLEGAL_END", 0x0402: "HD_FRAME_ERROR",
             0x0500: "HD_INVALID_PRIORITY", 0x0501: "HD_SCHEDULER_FULL", 0x0600: "HD_INVALID_LICENSE"}
_DISCONNECTED = (0x0300, 0x0302, 0x0303)  # a fault or the link gone: "disconnected"
HD_CURRENT_BUTTONS = 0x2000
HD_CURRENT_POSITION = 0x2050
HD_USABLE_WORKSPACE_DIMENSIONS = 0x2551
HD_NOMINAL_MAX_FORCE = 0x2603
HD_CURRENT_FORCE = 0x2700
HD_FORCE_OUTPUT = 0x4000
HD_INVALID_HANDLE = 0xFFFFFFFF
HD_CALLBACK_DONE, HD_CALLBACK_CONTINUE = 0, 1
HD_DEFAULT_SCHEDULER_PRIORITY = 0xFFFF // 2

# the stylus's frame (x right, y up, z toward the user) on the organ's (z up, the viewer looking along +y)
STYLUS_TO_ORGAN = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


class HDErrorInfo(Structure):
    _fields_ = [("errorCode", c_uint), ("internalErrorCode", c_int), ("hHD", c_uint)]


CALLBACK = CFUNCTYPE(c_uint, c_void_p)

_SIGNATURES = {
    "hdInitDevice": ([c_char_p], c_uint), "hdDisableDevice": ([c_uint], None),
    "hdMakeCurrentDevice": ([c_uint], None), "hdBeginFrame": ([c_uint], None), "hdEndFrame": ([c_uint], None),
    "hdGetError": ([], HDErrorInfo), "hdGetErrorString": ([c_uint], c_char_p), "hdEnable": ([c_uint], None),
    "hdGetDoublev": ([c_uint, POINTER(c_double)], None), "hdGetIntegerv": ([c_uint, POINTER(c_int)], None),
    "hdSetDoublev": ([c_uint, POINTER(c_double)], None), "hdDisable": ([c_uint], None), "hdStartScheduler": ([], None),
    "hdStopScheduler": ([], None), "hdScheduleAsynchronous": ([CALLBACK, c_void_p, c_ushort], c_ulong),
    "hdUnschedule": ([c_ulong], None),
}
HOW = ("Install 3D Systems' OpenHaptics (the Touch device drivers and the OpenHaptics developer edition, "
       "https://support.3dsystems.com), or give library='/path/to/libHD.so' or $RTFEM_OPENHAPTICS_LIB.")


def hd_library(library=None) -> ctypes.CDLL:
    """The HD API's library with its functions' signatures declared."""
    return load_library(library, "RTFEM_OPENHAPTICS_LIB", ("HD", "libHD.so"), "OpenHaptics", HOW, _SIGNATURES)


def _close_at_exit(ref) -> None:
    dev = ref()
    if dev is not None:
        dev.close()


def error_name(code: int) -> str:
    return f"{HD_ERRORS.get(code, 'an unknown HD error')} (0x{code:04X})"


class OpenHaptics(HardwareDevice):
    """A Touch / Phantom device (OpenHaptics HD API) as an rtfem Device.

    Parameters
    ----------
    device_name : the device's name in the Touch setup ("Default Device").
    library : the HD library (a path or a name); default ``$RTFEM_OPENHAPTICS_LIB``, else the SDK's
        ``libHD.so`` / ``HD.dll`` on the system's library path.
    workspace : the :class:`~rtfem.interaction.devices.Workspace` from the stylus's frame to the
        organ's; default: fitted when a loop attaches the device to an organ (the usable workspace
        centred on the organ's top, the stylus's y axis up), with the second button as the clutch.
    max_force : the largest force rendered (N); default and at most the device's nominal maximum
        (HD_NOMINAL_MAX_FORCE).
    max_rate, watchdog : the servo's force-rate limit (N/s) and its watchdog (servo ticks without a
        new force from the loop), :class:`~rtfem.interaction.devices.servo.Servo`.

    Raises
    ------
    DeviceError
        The library not found or not the HD API, the device not initialized or the scheduler not
        started (the HD error's name and code).
    ModelError
        A bad device name, workspace, max_force, max_rate or watchdog.

    Every fault writes zero force in the current or next frame and every frame after it. A
    disconnection (HD_DEVICE_FAULT, HD_COMM_ERROR, HD_COMM_CONFIG_ERROR), a position that is not
    finite or beyond 10 m, or an exception in the callback also disables the force output (the
    scheduler and the device are released by ``close()``: not from the scheduler's own thread); the
    SDK's other errors (HD_EXCEEDED_MAX_FORCE...) leave it idle, rendering zero until
    :meth:`restart`. ``stop_reason`` names the HD error or the exception.
    """

    RATE = 1000.0  # Hz: the HD scheduler's default rate
    NAME = "an OpenHaptics device"
    ROTATION = STYLUS_TO_ORGAN

    def __init__(self, device_name: str = "Default Device", library=None, *, workspace: Workspace | None = None,
                 max_force: float | None = None, max_rate: float = 1000.0, watchdog: int = 50) -> None:
        if not isinstance(device_name, str) or not device_name:
            raise DeviceError(f"device_name={validate.show(device_name)} must be the device's name, e.g. 'Default Device'")
        self._hd = hd = hd_library(library)
        self._handle = None
        self._detail = ""
        hhd = hd.hdInitDevice(device_name.encode())
        self._raise_error(f"hdInitDevice({device_name!r})")
        if hhd == HD_INVALID_HANDLE:
            raise DeviceError(f"OpenHaptics: hdInitDevice({device_name!r}) gave no device")
        self._hhd = hhd
        try:
            nominal, usable = c_double(), (c_double * 6)()
            hd.hdGetDoublev(HD_NOMINAL_MAX_FORCE, byref(nominal))
            hd.hdGetDoublev(HD_USABLE_WORKSPACE_DIMENSIONS, usable)
            self._raise_error("hdGetDoublev")
            self.nominal_max_force = float(nominal.value)
            limit = self.nominal_max_force if max_force is None else min(
                validate.positive(max_force, "max_force", "the largest force in N"), self.nominal_max_force)
            self._start_servo(workspace, (np.array(usable[:3]) * 1e-3, np.array(usable[3:]) * 1e-3),  # mm -> m
                              limit, max_rate, watchdog, self.RATE)
            self._position_mm, self._buttons, self._force = (c_double * 3)(), c_int(), (c_double * 3)()
            self._zero, self._zero_only, self._zero_written = (c_double * 3)(), False, threading.Event()
            self._callback = CALLBACK(self._servo)  # kept: the scheduler holds a pointer to it
            hd.hdEnable(HD_FORCE_OUTPUT)
            self._handle = hd.hdScheduleAsynchronous(self._callback, None, HD_DEFAULT_SCHEDULER_PRIORITY)
            hd.hdStartScheduler()
            self._raise_error("hdStartScheduler")
            atexit.register(_close_at_exit, weakref.ref(self))  # zero force, the scheduler stopped, at exit
        except BaseException:
            self._shutdown()
            raise

    def _raise_error(self, where: str) -> None:
        err = self._hd.hdGetError()
        if err.errorCode != HD_SUCCESS:
            raise DeviceError(f"OpenHaptics: {where} failed: {error_name(err.errorCode)}, internal code "
                              f"{err.internalErrorCode}")

    def _servo(self, data) -> int:
        """The HD scheduler's callback: one servo tick inside a frame. Nothing escapes it (an exception
        out of a ctypes callback returns 0, HD_CALLBACK_DONE: the scheduler would drop the callback with
        the last force still on the motors): every error is a fault, and once the force was zeroed by
        one the callback only writes zero."""
        hd, in_frame = self._hd, False
        try:
            self._servo_ident = threading.get_ident()
            if self._zero_only:
                self._zero_frame()
                return HD_CALLBACK_CONTINUE
            hd.hdBeginFrame(self._hhd)
            in_frame = True
            hd.hdGetDoublev(HD_CURRENT_POSITION, self._position_mm)
            hd.hdGetIntegerv(HD_CURRENT_BUTTONS, byref(self._buttons))
            p = self._position_mm
            f = self._tick((p[0] * 1e-3, p[1] * 1e-3, p[2] * 1e-3), self._buttons.value)
            self._force[0], self._force[1], self._force[2] = f[0], f[1], f[2]
            hd.hdSetDoublev(HD_CURRENT_FORCE, self._force)
            in_frame = False
            hd.hdEndFrame(self._hhd)
            err = hd.hdGetError()
            if err.errorCode != HD_SUCCESS:
                gone = err.errorCode in _DISCONNECTED  # a recoverable error leaves it idle (restart())
                self.fault(3 if gone else 2, error_name(err.errorCode), release=gone)
        except BaseException as exc:  # noqa: BLE001 - a fault, never out of the callback
            try:
                if in_frame:
                    hd.hdSetDoublev(HD_CURRENT_FORCE, self._zero)
                    hd.hdEndFrame(self._hhd)
            except BaseException:  # noqa: BLE001, S110 - the next frames write zero
                pass
            self._failed(exc)
        return HD_CALLBACK_CONTINUE

    def _zero_frame(self) -> None:
        """A frame that writes zero force and nothing else (the HD errors it raises are drained)."""
        hd = self._hd
        hd.hdBeginFrame(self._hhd)
        hd.hdSetDoublev(HD_CURRENT_FORCE, self._zero)
        hd.hdEndFrame(self._hhd)
        for _ in range(64):
            if hd.hdGetError().errorCode == HD_SUCCESS:
                break
        self._zero_written.set()

    def _command_zero(self) -> None:
        """From now on every frame writes zero force (this one too, on the scheduler's thread); from
        another thread, wait until the scheduler has written a zero frame."""
        self._zero_written.clear()
        self._zero_only = True
        if self._handle is None or threading.get_ident() == self._servo_ident:
            return
        if not self._zero_written.wait(0.25):
            raise DeviceError("the HD scheduler ran no frame in 0.25 s to write the zero force")

    def restart(self) -> None:
        """Render again after the simulation's stop or a recoverable HD error (HD_EXCEEDED_MAX_FORCE...);
        after a disconnection, an error in the adapter or a close, open a new OpenHaptics."""
        super().restart()
        self._zero_only = False

    def close(self) -> None:
        """Stop rendering (zero force written), stop the scheduler and disable the device; closing twice
        does nothing."""
        super().close()
        self._shutdown()  # what a fault on the scheduler's thread could not do there

    def _open(self) -> bool:
        return self._handle is not None

    def _shutdown(self) -> None:
        """Disable the force output; off the scheduler's thread also stop the scheduler, unschedule the
        servo and disable the device (on it, the callback writes zero until :meth:`close`)."""
        hd = self._hd
        if getattr(self, "_hhd", None) is not None:
            hd.hdDisable(HD_FORCE_OUTPUT)
        if threading.get_ident() == self._servo_ident:
            return
        if self._handle is not None:
            hd.hdStopScheduler()
            hd.hdUnschedule(self._handle)
            self._handle = None
        if getattr(self, "_hhd", None) is not None:
            hd.hdDisableDevice(self._hhd)
            self._hhd = None
