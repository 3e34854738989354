"""An OpenIGTLink bridge to surgical navigation (3D Slicer's OpenIGTLinkIF, PLUS, ROS bridges):
a tracked tool streamed in, the deformed organ and the contact force streamed out, over pyigtl
(the ``igtl`` extra), the Python implementation of the OpenIGTLink protocol.

In: a TRANSFORM named ``ToolToReference`` (4x4, millimetres, the organ's coordinates) places a
sphere tool, which a :class:`~rtfem.ToolContact` in a :class:`~rtfem.HapticLoop` presses against
the organ. Out: a POLYDATA ``Organ`` (the deformed surface, millimetres, triangles) at up to
``surface_rate``, a TRANSFORM ``Force`` whose translation is the force on the tool in newtons (the
PLUS toolkit's convention for haptic devices) at up to ``force_rate``, and a STRING ``Status`` when a
message is refused. A malformed or non-finite transform is refused with a ``Status`` and the server
keeps serving.

:class:`IGTLDevice` is the same link as a haptic Device (``rtfem view --device igtl``): the pose is
the hand, a STRING ``Buttons`` holding a bit mask is its buttons (OpenIGTLink has no button message:
this is rtfem's convention), and the force the hand feels goes back as ``Force``.
"""

from __future__ import annotations

import signal
import threading
import time

import numpy as np

from ... import validate
from ...errors import DeviceError
from .base import SharedDevice
from .hardware import HardwareDevice
from .native import ServoThread
from .workspace import Workspace

__all__ = ["IGTLServer", "IGTLDevice", "IGTLLink"]


def _pyigtl():
    try:
        import pyigtl
    except ImportError:
        raise DeviceError("the OpenIGTLink bridge needs pyigtl: pip install 'rtfem[igtl]' (make installs it)") from None
    return pyigtl


class IGTLLink:
    """One OpenIGTLink server and its messages: the tool's pose in, Status and Force out.

    Parameters
    ----------
    port, host : where to listen (127.0.0.1: this machine only).

    Raises
    ------
    DeviceError
        pyigtl missing, not on the main thread (pyigtl installs signal handlers), the port in use.
    ModelError
        A port that is not 1..65535.
    """

    TOOL, ORGAN, FORCE, STATUS, BUTTONS = "ToolToReference", "Organ", "Force", "Status", "Buttons"

    def __init__(self, port: int = 18944, host: str = "127.0.0.1") -> None:
        pyigtl = _pyigtl()
        self.port = validate.count(port, "port", 1, 65535, what="a TCP port")
        if threading.current_thread() is not threading.main_thread():
            raise DeviceError("an OpenIGTLink server must be made on the main thread (pyigtl installs signal handlers)")
        loopback = host in ("127.0.0.1", "localhost", "::1")
        try:
            self.server = pyigtl.OpenIGTLinkServer(port=self.port, local_server=loopback,
                                                   iface=None if loopback else host, start_now=False)
        except OSError as exc:
            raise DeviceError(f"OpenIGTLink: cannot listen on {host}:{self.port} ({exc.strerror or exc}); choose "
                              "another --port") from None
        self.pyigtl = pyigtl
        self.refused = self.received = 0
        self.buttons = 0

    def status(self, text: str) -> None:
        self.server.send_message(self.pyigtl.StringMessage(text, device_name=self.STATUS), wait=False)

    def send(self, message) -> None:
        if self.server.is_connected():
            self.server.send_message(message, wait=False)

    def send_force(self, force) -> None:
        M = np.eye(4)
        M[:3, 3] = force
        self.send(self.pyigtl.TransformMessage(M, device_name=self.FORCE))

    def poll(self) -> np.ndarray | None:
        """The newest valid tool pose's position (m) among the messages that arrived, or None; a
        ``Buttons`` string sets :attr:`buttons`; what cannot be taken gets a Status."""
        position = None
        for message in self.server.get_latest_messages():
            try:
                if message.device_name == self.TOOL:
                    if message.message_type != "TRANSFORM":
                        raise ValueError(f"a {message.message_type} message, not a TRANSFORM")
                    M = np.asarray(message.matrix, dtype=float)
                    if M.shape != (4, 4) or not np.all(np.isfinite(M)):
                        raise ValueError(f"a 4x4 matrix of finite numbers is needed, got {M.shape}"
                                         f"{' with non-finite values' if M.size and not np.all(np.isfinite(M)) else ''}")
                    position = M[:3, 3] * 1e-3
                    self.received += 1
                elif message.device_name == self.BUTTONS:
                    self.buttons = validate.count(int(str(message.string).strip()), "Buttons", 0, 2**31 - 1)
            except Exception as exc:  # the link keeps serving
                self.refused += 1
                self.status(f"refused {message.device_name}: {exc}")
        return position

    def close(self) -> None:
        """Stop the server; pyigtl's signal handlers are put back."""
        self.server.stop()
        if threading.current_thread() is threading.main_thread():
            for sig, previous in getattr(self.server, "_previous_signal_handlers", {}).items():
                signal.signal(sig, previous)


class IGTLServer:
    """An OpenIGTLink server driving a sphere tool against an organ and streaming the organ back.

    Parameters
    ----------
    mesh : the organ's surface (:class:`~rtfem.TriMesh`; a solid's ``model.mesh``).
    driver : any Driver on it.
    port, host : where to listen (127.0.0.1: this machine only; 3D Slicer's default port 18944).
    tool_radius : the sphere tool's radius (m).
    stiffness : the coupling spring between the tracked pose and the tool (N/m).
    rate : the contact loop's rate (Hz).
    surface_rate, force_rate : the most ``Organ`` and ``Force`` messages sent per second.

    Raises
    ------
    DeviceError
        pyigtl missing, not on the main thread (pyigtl installs signal handlers), the port in use.
    ModelError
        A bad driver, radius, stiffness, port or rate (ToolContact's and HapticLoop's checks).
    """

    TOOL, ORGAN, FORCE, STATUS = IGTLLink.TOOL, IGTLLink.ORGAN, IGTLLink.FORCE, IGTLLink.STATUS

    def __init__(self, mesh, driver, *, port: int = 18944, host: str = "127.0.0.1", tool_radius: float = 0.005,
                 stiffness: float = 200.0, rate: float = 1000.0, surface_rate: float = 30.0,
                 force_rate: float = 100.0) -> None:
        from ..contact import Tool, ToolContact
        from ..loop import HapticLoop

        _pyigtl()
        self.port = validate.count(port, "port", 1, 65535, what="a TCP port")
        self.surface_period = 1.0 / validate.positive(surface_rate, "surface_rate", "messages per second")
        self.force_period = 1.0 / validate.positive(force_rate, "force_rate", "messages per second")
        self.contact = ToolContact(mesh, driver, Tool.sphere(tool_radius), stiffness=stiffness)
        lo, hi = mesh.bounds()
        # until a pose arrives the tool waits above the organ, out of contact
        self.device = SharedDevice([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, hi[2] + 0.1 * np.linalg.norm(hi - lo)])
        self.loop = HapticLoop(self.contact, self.device, rate=rate)
        self._surface = mesh.used_vertices()
        self._X = np.asarray(mesh.vertices)[self._surface]
        local = np.full(mesh.n_vertices, -1, dtype=np.int64)
        local[self._surface] = np.arange(self._surface.size)
        tri = local[np.asarray(mesh.triangles)]
        self._polygons = np.column_stack([np.full(len(tri), 3), tri]).ravel().astype(np.int64)
        self.link = IGTLLink(port, host)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._bridge, name="rtfem-igtl", daemon=True)

    @property
    def received(self) -> int:
        return self.link.received

    @property
    def refused(self) -> int:
        return self.link.refused

    def start(self) -> "IGTLServer":
        """Serve: the server, the contact loop and the bridge between them."""
        from ...threads import background

        self.link.server.start()
        self.loop.start()
        background(self._thread, self._stop.set)
        self._thread.start()
        return self

    def _bridge(self) -> None:
        link = self.link
        last_surface = last_force = 0.0
        while not self._stop.is_set():
            position = link.poll()
            if position is not None:
                self.device.move_to(position)
            now = time.perf_counter()
            if self.loop.error is not None:
                link.status(f"the contact loop stopped: {self.loop.error}")
                return
            if now - last_force >= self.force_period:
                link.send_force(self.device.force)
                last_force = now
            if now - last_surface >= self.surface_period:
                link.send(link.pyigtl.PolyDataMessage(points=(self._X + self.surface_displacements()) * 1e3,
                                                      polygons=self._polygons, device_name=link.ORGAN))
                last_surface = now
            time.sleep(0.001)

    def surface_displacements(self) -> np.ndarray:
        """The organ's surface displacements now (m)."""
        from ...drivers.base import displacements_at

        return displacements_at(self.contact.driver, self._surface)

    def close(self) -> None:
        """Stop the bridge, the loop and the server (pyigtl's signal handlers are put back)."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(2.0)
        try:
            self.loop.stop()
        finally:
            self.link.close()

    def __enter__(self) -> "IGTLServer":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()


class IGTLDevice(HardwareDevice):
    """A tracked tool over OpenIGTLink as a haptic Device (``rtfem view --device igtl``): the
    ``ToolToReference`` pose (mm, the organ's coordinates) is the hand, a STRING ``Buttons`` (a bit
    mask, e.g. "1" to close the viewer's jaw; rtfem's convention) its buttons, and the force the hand
    feels goes back as the ``Force`` TRANSFORM (N) at up to ``force_rate``. The servo runs on a thread
    of its own at ``rate``, with the adapters' safety (a clamp, a rate limit, the watchdog).

    Parameters
    ----------
    port, host : where to listen.
    workspace : from the pose's frame to the organ's (default: the identity, the poses being in the
        organ's coordinates).
    max_force, max_rate, watchdog, rate : the servo's (N, N/s, servo ticks, Hz).
    force_rate : the most Force messages sent per second.

    Raises
    ------
    DeviceError
        pyigtl missing, not on the main thread, the port in use.
    ModelError
        A bad port, workspace, max_force, max_rate, watchdog, rate or force_rate.
    """

    NAME = "an OpenIGTLink tool"

    def __init__(self, port: int = 18944, host: str = "127.0.0.1", *, workspace: Workspace | None = None,
                 max_force: float = 10.0, max_rate: float = 1000.0, watchdog: int = 50, rate: float = 1000.0,
                 force_rate: float = 100.0) -> None:
        self.force_period = 1.0 / validate.positive(force_rate, "force_rate", "messages per second")
        self._start_servo(Workspace() if workspace is None else workspace, ((-0.1,) * 3, (0.1,) * 3),
                          validate.positive(max_force, "max_force", "the largest force in N"), max_rate, watchdog, rate)
        self.link = IGTLLink(port, host)
        self.link.server.start()
        self._x = np.zeros(3)
        self._last_force = 0.0
        self._thread = ServoThread(self._servo, rate, "rtfem-igtl-servo").start()

    def _servo(self) -> bool:
        position = self.link.poll()
        if position is not None:
            self._x = position
        f = self.servo.tick(self._x, self.link.buttons)
        now = time.perf_counter()
        if now - self._last_force >= self.force_period:
            self.link.send_force(f)
            self._last_force = now
        return True

    def _open(self) -> bool:
        return self._thread is not None

    def _shutdown(self) -> None:
        """Stop the servo thread and the server."""
        if self._thread is not None:
            self._thread.stop()
            self._thread = None
            self.link.close()
