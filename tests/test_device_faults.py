"""Issue 53, section 1: a device stop leaves no force on the hand. Every fault of every hardware
adapter (an error the SDK reports, a disconnection, a silence, a message or a position that is
malformed or out of range, an exception on the servo's thread) ends in HardwareDevice.fault: the
servo stops, the reason is recorded, zero force is commanded to the device or its service and the
device is released (or left idle, rendering zero). Tested on a bare adapter, on Haply against a
hostile fake Inverse Service (the last command it received is an explicit zero and the connection is
closed), and on OpenHaptics and Force Dimension against the stub libraries of tests/stubs."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

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
