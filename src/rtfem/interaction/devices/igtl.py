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
"""

from __future__ import annotations

import signal
import threading
import time

import numpy as np

from ... import validate
from ...errors import DeviceError
from .base import SharedDevice

__all__ = ["IGTLServer"]


def _pyigtl():
    try:
        import pyigtl
    except ImportError:
        raise DeviceError("the OpenIGTLink bridge needs pyigtl: pip install 'rtfem[igtl]' (make installs it)") from None
    return pyigtl


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

    TOOL, ORGAN, FORCE, STATUS = "ToolToReference", "Organ", "Force", "Status"

    def __init__(self, mesh, driver, *, port: int = 18944, host: str = "127.0.0.1", tool_radius: float = 0.005,
                 stiffness: float = 200.0, rate: float = 1000.0, surface_rate: float = 30.0,
                 force_rate: float = 100.0) -> None:
        from ..contact import Tool, ToolContact
        from ..loop import HapticLoop

        pyigtl = _pyigtl()
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
        self.refused = 0
        self.received = 0
        if threading.current_thread() is not threading.main_thread():
            raise DeviceError("rt.devices.IGTLServer must be made on the main thread (pyigtl installs signal handlers)")
        loopback = host in ("127.0.0.1", "localhost", "::1")
        try:
            self.server = pyigtl.OpenIGTLinkServer(port=self.port, local_server=loopback,
                                                   iface=None if loopback else host, start_now=False)
        except OSError as exc:
            raise DeviceError(f"OpenIGTLink: cannot listen on {host}:{self.port} ({exc.strerror or exc}); choose "
                              "another --port") from None
        self._pyigtl = pyigtl
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._bridge, name="rtfem-igtl", daemon=True)

    def start(self) -> "IGTLServer":
        """Serve: the server, the contact loop and the bridge between them."""
        from ...threads import background

        self.server.start()
        self.loop.start()
        background(self._thread, self._stop.set)
        self._thread.start()
        return self

    def _status(self, text: str) -> None:
        self.server.send_message(self._pyigtl.StringMessage(text, device_name=self.STATUS), wait=False)

    def _pose(self, message) -> None:
        """A ToolToReference transform: the tool there (mm -> m), or a Status saying why not."""
        try:
            M = np.asarray(message.matrix, dtype=float)
            if M.shape != (4, 4) or not np.all(np.isfinite(M)):
                raise ValueError(f"a 4x4 matrix of finite numbers is needed, got {M.shape} "
                                 f"{'with non-finite values' if M.size and not np.all(np.isfinite(M)) else ''}")
            self.device.move_to(M[:3, 3] * 1e-3)
            self.received += 1
        except Exception as exc:  # the bridge keeps serving
            self.refused += 1
            self._status(f"refused {self.TOOL}: {exc}")

    def _bridge(self) -> None:
        last_surface = last_force = 0.0
        while not self._stop.is_set():
            for message in self.server.get_latest_messages():
                if message.device_name == self.TOOL:
                    if message.message_type == "TRANSFORM":
                        self._pose(message)
                    else:
                        self.refused += 1
                        self._status(f"refused {self.TOOL}: a {message.message_type} message, not a TRANSFORM")
            now = time.perf_counter()
            if self.loop.error is not None:
                self._status(f"the contact loop stopped: {self.loop.error}")
                return
            if now - last_force >= self.force_period and self.server.is_connected():
                M = np.eye(4)
                M[:3, 3] = self.device.force
                self.server.send_message(self._pyigtl.TransformMessage(M, device_name=self.FORCE), wait=False)
                last_force = now
            if now - last_surface >= self.surface_period and self.server.is_connected():
                self.server.send_message(self._pyigtl.PolyDataMessage(
                    points=(self._X + self.surface_displacements()) * 1e3, polygons=self._polygons,
                    device_name=self.ORGAN), wait=False)
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
            self.server.stop()
        if threading.current_thread() is threading.main_thread():
            for sig, previous in getattr(self.server, "_previous_signal_handlers", {}).items():
                signal.signal(sig, previous)

    def __enter__(self) -> "IGTLServer":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()
