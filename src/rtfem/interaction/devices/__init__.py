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
           "MAILBOX", "DEVICES", "open_device"]

#: the hardware adapters by the names the CLI and scene files use
DEVICES = ("openhaptics", "forcedimension", "haply", "igtl")


def open_device(name: str, max_force: float = 10.0, haply_url: str = "ws://localhost:10001", igtl_port: int = 18944):
    """The adapter ``name`` (one of :data:`DEVICES`) opened with its defaults and ``max_force`` (N) at most.

    Parameters
    ----------
    name : "openhaptics", "forcedimension", "haply" or "igtl".
    max_force : the largest force rendered (N).
    haply_url : the Haply Inverse Service's address (haply).
    igtl_port : the OpenIGTLink port listened on (igtl).

    Returns
    -------
    HardwareDevice
        The opened adapter (close it when done).

    Raises
    ------
    ModelError
        A name not listed, a bad max_force, URL or port.
    DeviceError
        The device's SDK or service missing, the device not found, the port in use.
    """
    from ... import validate

    validate.choice(name, "device", DEVICES)
    if name == "openhaptics":
        return OpenHaptics(max_force=max_force)
    if name == "forcedimension":
        return ForceDimension(max_force=max_force)
    if name == "haply":
        return Haply(haply_url, max_force=max_force)
    return IGTLDevice(igtl_port, max_force=max_force)

from ...lazy import submodules  # noqa: E402

__getattr__ = submodules(__name__)  # submodules on first use (rt.mesh.meshing)
