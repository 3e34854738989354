"""Devices: where the hand is and what it feels (``rt.devices``).

Every device is a :class:`Device`: ``position(t)`` (m, the organ's frame), ``set_force(t, f)``
(N), ``buttons``, ``close()`` and ``stop_reason``, and works with Probe, Grasp, ToolContact,
HapticLoop and the viewer unchanged. Scripted and software devices: :class:`ScriptedDevice`,
:class:`CallbackDevice`, :class:`SharedDevice`. The hardware adapters are SharedDevices whose
position and force the device's own servo thread exchanges with the simulation's loop through
the shared mailbox, after the :class:`Workspace` map and the safety of :mod:`.servo` (a force
clamped to the device's maximum, a rate limit, a watchdog on the simulation).
"""

from .base import MAILBOX, CallbackDevice, Device, Press, ScriptedDevice, SharedDevice
from .forcedimension import ForceDimension
from .haply import Haply
from .hardware import HardwareDevice
from .igtl import IGTLDevice, IGTLServer
from .openhaptics import OpenHaptics
from .workspace import Workspace

__all__ = ["Device", "ScriptedDevice", "Press", "CallbackDevice", "SharedDevice", "Workspace", "HardwareDevice",
           "OpenHaptics", "ForceDimension", "Haply", "IGTLServer", "IGTLDevice",
           "MAILBOX"]
