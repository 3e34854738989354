"""An OpenIGTLink bridge to surgical navigation (3D Slicer's OpenIGTLinkIF, PLUS, ROS bridges):
a tracked tool streamed in, the deformed organ and the contact force streamed out, over rtfem's
own OpenIGTLink server (:mod:`.igtl_net`: several clients at once, a deadline per message, bounded
sizes; the ``igtl`` extra brings the CRC it needs).

In: a TRANSFORM named ``ToolToReference`` (4x4, millimetres, the organ's coordinates) places a
sphere tool, which a :class:`~rtfem.ToolContact` in a :class:`~rtfem.HapticLoop` presses against
the organ. Out: a POLYDATA ``Organ`` (the deformed surface, millimetres, triangles) at up to
``surface_rate``, a TRANSFORM ``Force`` whose translation is the force on the tool in newtons (the
PLUS toolkit's convention for haptic devices) at up to ``force_rate``, and a STRING ``Status`` when a
message is refused. A malformed, non-finite or out-of-range transform (a translation beyond
:data:`POSE_LIMIT_MM`) is refused with a ``Status`` to its sender, the tool is lifted off the organ
(zero force, sent at once) until a valid pose comes, and the server keeps serving everyone.

:class:`IGTLDevice` is the same link as a haptic Device (``rtfem view --device igtl``): the pose is
the hand, a STRING ``Buttons`` holding a bit mask is its buttons (OpenIGTLink has no button message:
this is rtfem's convention), and the force the hand feels goes back as ``Force``. Any fault (a
refused pose or Buttons, the pose's sender gone or dropped, no pose for ``pose_timeout``, an error
of the link or of the servo) goes through :meth:`HardwareDevice.fault`: zero force, sent at once to
every client, the reason in ``stop_reason``, the link closed.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque

import numpy as np

from ... import validate
from ...errors import DeviceError
from . import igtl_wire as wire
from .igtl_net import Peer, WireServer
from .base import SharedDevice
from .hardware import HardwareDevice
from .native import ServoThread
from .workspace import Workspace

__all__ = ["IGTLServer", "IGTLDevice", "IGTLLink", "POSE_LIMIT_MM"]

log = logging.getLogger("rtfem.igtl")

#: the farthest a tracked pose's translation may lie from the organ's origin (mm): 10 m, beyond any
#: tracker's reach; a pose farther is refused, not clipped
POSE_LIMIT_MM = 1e4
_BAD_INPUT, _GONE, _FAILED = 6, 3, 7  # HardwareDevice.fault's codes: malformed input, disconnected, the adapter failed


_WARNED: set = set()


def warn_exposed(host: str, port: int) -> None:
    """Log (once per address) that ``host`` is not a loopback address."""
    if (host, port) in _WARNED:
        return
    _WARNED.add((host, port))
    log.warning("warning: %s is not a loopback address: any machine that reaches this one on port %d can send the "
                "tool's pose and read the organ (OpenIGTLink has no authentication or encryption); use 127.0.0.1 "
                "unless the network is trusted", host, port)


class IGTLLink:
    """One OpenIGTLink server and its messages: the tool's pose and the buttons in, Status and Force
    out, to any number of clients (see :class:`~rtfem.interaction.devices.igtl_net.WireServer`).

    Parameters
    ----------
    port, host : where to listen (127.0.0.1: this machine only; any other address is logged as a
        warning: OpenIGTLink has neither authentication nor encryption).
    message_timeout : seconds a message may take from its first byte to its last before its sender
        is dropped.
    send_timeout : seconds a client may leave what is sent to it unread before it is dropped.
    max_clients : clients at once.

    Raises
    ------
    DeviceError
        The igtl extra missing, an address that is not this machine's, the port in use.
    ModelError
        A port that is not 1..65535, a timeout that is not a positive number, a bad max_clients.
    """

    TOOL, ORGAN, FORCE, STATUS, BUTTONS = "ToolToReference", "Organ", "Force", "Status", "Buttons"

    def __init__(self, port: int = 18944, host: str = "127.0.0.1", *, message_timeout: float = 2.0,
                 send_timeout: float = 10.0, max_clients: int = 16) -> None:
        self.port = validate.count(port, "port", 1, 65535, what="a TCP port")
        self.server = WireServer(
            host, self.port, self._on_message, self._on_close,
            message_timeout=validate.in_range(message_timeout, "message_timeout", 0.0, 3600.0, lo_open=True,
                                              what="seconds"),
            send_timeout=validate.in_range(send_timeout, "send_timeout", 0.0, 3600.0, lo_open=True, what="seconds"),
            max_clients=validate.count(max_clients, "max_clients", 1, 1024, what="clients"))
        self.host = host
        if not self.server.loopback:
            warn_exposed(host, self.port)
        self._lock = threading.Lock()
        self._position: np.ndarray | None = None
        self._events: deque = deque(maxlen=64)
        self.source: Peer | None = None  # the client whose pose was taken last
        self.last_pose: float | None = None   # time.monotonic() of the last pose taken
        self.arrived = threading.Event()      # set by a pose or an event
        self.refused = self.received = 0
        self.buttons = 0
        self._logged, self._unlogged = -np.inf, 0  # the last refusal logged, and those since

    @property
    def error(self) -> str | None:
        """Why the server stopped serving, if it did without being closed."""
        return self.server.error

    def start(self) -> "IGTLLink":
        self.server.start()
        return self

    # ------------------------------------------------------------------ out
    def status(self, text: str, peer: Peer | None = None) -> None:
        """A STRING ``Status`` to ``peer``, or to every client."""
        self.server.send(None, wire.pack("STRING", self.STATUS, wire.string_body(validate.one_line(text, 2000))), peer)

    def send(self, name: str, data: bytes | None = None) -> None:
        """Send a packed message to every client (the newest of each ``name`` not yet begun replaces
        an older one); a pyigtl message object is packed here."""
        if data is None and hasattr(name, "pack"):
            name, data = name.device_name, name.pack()
        self.server.send(name, data)

    def send_force(self, force) -> None:
        M = np.eye(4)
        M[:3, 3] = force
        self.server.send(self.FORCE, wire.pack("TRANSFORM", self.FORCE, wire.transform_body(M)))

    # ------------------------------------------------------------------ in (the server's thread)
    def _on_message(self, peer: Peer, header: wire.Header, body: bytes) -> None:
        if not header.name_ok:
            self._refuse(peer, "a message", "its device name is not printable UTF-8", event=False)
            return
        if header.name not in (self.TOOL, self.BUTTONS):
            return  # not for rtfem: ignored, as any OpenIGTLink receiver does
        try:
            content = wire.content_of(header, body)
            if header.name == self.TOOL:
                position = self._pose(header, content)
                with self._lock:
                    self._position = position
                    self.source, self.last_pose = peer, time.monotonic()
                    self.received += 1
            else:
                self.buttons = self._buttons(header, content)
            self.arrived.set()
        except ValueError as exc:
            self._refuse(peer, header.name, str(exc))

    @staticmethod
    def _pose(header: wire.Header, content: bytes) -> np.ndarray:
        if header.kind != "TRANSFORM":
            raise ValueError(f"a {header.kind} message, not a TRANSFORM")
        M = wire.read_transform(content)
        if not np.all(np.isfinite(M)):
            raise ValueError("a 4x4 matrix of finite numbers is needed, got one with non-finite values")
        t = M[:3, 3]
        if np.abs(t).max() > POSE_LIMIT_MM:
            raise ValueError(f"its translation ({t[0]:.4g}, {t[1]:.4g}, {t[2]:.4g}) mm lies more than "
                             f"{POSE_LIMIT_MM:g} mm from the origin: out of any tracker's range (poses are in mm)")
        return t * 1e-3

    @staticmethod
    def _buttons(header: wire.Header, content: bytes) -> int:
        if header.kind != "STRING":
            raise ValueError(f"a {header.kind} message, not a STRING holding a bit mask")
        text = wire.read_string(content, limit=64).strip()
        if not (text.isascii() and text.isdigit() and len(text) <= 10) or int(text) > 2**31 - 1:
            raise ValueError(f"{validate.show(text, 30)} is not a bit mask (a whole number 0..{2**31 - 1})")
        return int(text)

    def _refuse(self, peer: Peer, name: str, reason: str, event: bool = True) -> None:
        text = f"refused {name}: {reason}"
        now = time.monotonic()
        with self._lock:
            self.refused += 1
            if event:
                self._events.append(("refused", name, text))
            quiet, self._unlogged = now - self._logged < 1.0, self._unlogged + 1
            if not quiet:  # one line a second at most, whatever a peer sends
                more = f" ({self._unlogged - 1} more refused since the last line)" if self._unlogged > 1 else ""
                self._logged, self._unlogged = now, 0
        if not quiet:
            log.info("%s from %s%s", text, peer.address, more)
        self.status(text, peer)
        if event:
            self.arrived.set()

    def _on_close(self, peer: Peer, reason: str) -> None:
        with self._lock:
            if peer is not self.source:
                return
            self.source = None
            self._events.append(("gone", self.TOOL, f"the pose's sender ({peer.address}) is gone: {reason}"))
        self.arrived.set()

    # ------------------------------------------------------------------ the owner's side
    def poll(self) -> np.ndarray | None:
        """The newest valid tool pose's position (m) since the last poll, or None; a ``Buttons``
        string sets :attr:`buttons`; what cannot be taken was answered with a Status (see
        :meth:`events`)."""
        if self._position is None:
            return None
        with self._lock:
            position, self._position = self._position, None
        return position

    def events(self) -> list[tuple[str, str, str]]:
        """What happened since the last call, oldest first: ("refused", name, why) for a pose or a
        Buttons refused, ("gone", name, why) when the client whose pose was taken last went."""
        if not self._events:
            return []
        with self._lock:
            out = list(self._events)
            self._events.clear()
        return out

    def close(self) -> None:
        """Stop the server (what waits to be sent, a last zero force, goes out first)."""
        self.server.close()


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
        The igtl extra missing, an address that is not this machine's, the port in use.
    ModelError
        A bad driver, radius, stiffness, port or rate (ToolContact's and HapticLoop's checks).
    """

    TOOL, ORGAN, FORCE, STATUS = IGTLLink.TOOL, IGTLLink.ORGAN, IGTLLink.FORCE, IGTLLink.STATUS

    def __init__(self, mesh, driver, *, port: int = 18944, host: str = "127.0.0.1", tool_radius: float = 0.005,
                 stiffness: float = 200.0, rate: float = 1000.0, surface_rate: float = 30.0,
                 force_rate: float = 100.0) -> None:
        from ..contact import Tool, ToolContact
        from ..loop import HapticLoop

        wire.crc64(b"")  # the igtl extra is there, or a DeviceError before any work
        self.port = validate.count(port, "port", 1, 65535, what="a TCP port")
        self.surface_period = 1.0 / validate.positive(surface_rate, "surface_rate", "messages per second")
        self.force_period = 1.0 / validate.positive(force_rate, "force_rate", "messages per second")
        self.contact = ToolContact(mesh, driver, Tool.sphere(tool_radius), stiffness=stiffness)
        lo, hi = mesh.bounds()
        # until a pose arrives (and whenever one is refused) the tool waits above the organ, out of contact
        self._park = np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, hi[2] + 0.1 * np.linalg.norm(hi - lo)])
        self.device = SharedDevice(self._park)
        self.loop = HapticLoop(self.contact, self.device, rate=rate)
        self._surface = mesh.used_vertices()
        self._X = np.asarray(mesh.vertices)[self._surface]
        local = np.full(mesh.n_vertices, -1, dtype=np.int64)
        local[self._surface] = np.arange(self._surface.size)
        tri = local[np.asarray(mesh.triangles)]
        self._n_polygons = len(tri)
        self._polygons = np.column_stack([np.full(len(tri), 3), tri]).ravel().astype(">u4").tobytes()
        self.link = IGTLLink(port, host)
        self.error: str | None = None  # why the bridge stopped, if it did while serving
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._bridge, name="rtfem-igtl", daemon=True)

    @property
    def received(self) -> int:
        return self.link.received

    @property
    def refused(self) -> int:
        return self.link.refused

    @property
    def clients(self) -> int:
        """The clients connected now."""
        return self.link.server.clients

    def start(self) -> "IGTLServer":
        """Serve: the server, the contact loop and the bridge between them."""
        from ...threads import background

        self.link.start()
        self.loop.start()
        background(self._thread, self._stop.set)
        self._thread.start()
        return self

    def _bridge(self) -> None:
        try:
            self._serve()
        except BaseException as exc:  # noqa: BLE001 - never a silent end: the reason goes to error and to clients
            self.error = validate.one_line(f"{type(exc).__name__}: {exc}" if not isinstance(exc, DeviceError)
                                           else str(exc), 500)
            log.error("the bridge stopped: %s", self.error)
            try:
                self.device.move_to(self._park)
                self.link.send_force(np.zeros(3))
                self.link.status(f"rtfem: the bridge stopped: {self.error}")
            except Exception:  # noqa: BLE001 - the link may be what failed
                pass

    def _serve(self) -> None:
        link = self.link
        last_surface = last_force = 0.0
        parked = -np.inf  # the loop's force count when the tool was last lifted off
        while not self._stop.is_set():
            link.arrived.clear()
            position = link.poll()
            if any(name == self.TOOL for _, name, _ in link.events()):
                # a pose refused or its sender gone: the tool leaves the organ, zero force now
                position = None
                self.device.move_to(self._park)
                parked = self.device.mailbox[6]
                self.device.mailbox[3:6] = 0.0
                link.send_force(np.zeros(3))
                last_force = time.perf_counter()
            if position is not None:
                self.device.move_to(position)
                parked = -np.inf
            if self.loop.error is not None:
                raise DeviceError(f"the contact loop stopped: {self.loop.error}")
            if link.error is not None:
                raise DeviceError(f"the OpenIGTLink server stopped: {link.error}")
            now = time.perf_counter()
            if now - last_force >= self.force_period:
                # zero until the loop has stepped twice from the lifted tool (a step under way used the old pose)
                link.send_force(self.device.force if self.device.mailbox[6] >= parked + 2 else np.zeros(3))
                last_force = now
            if now - last_surface >= self.surface_period:
                points = (self._X + self.surface_displacements()) * 1e3
                link.send(self.ORGAN, wire.pack("POLYDATA", self.ORGAN,
                                                wire.polydata_body(points, self._polygons, self._n_polygons)))
                last_surface = now
            wait = min(last_force + self.force_period, last_surface + self.surface_period) - time.perf_counter()
            link.arrived.wait(min(max(wait, 0.0), 0.05))

    def surface_displacements(self) -> np.ndarray:
        """The organ's surface displacements now (m)."""
        from ...drivers.base import displacements_at

        return displacements_at(self.contact.driver, self._surface)

    def close(self) -> None:
        """Stop the bridge, the loop and the server (a last zero force goes out to the clients)."""
        self._stop.set()
        self.link.arrived.set()
        if self._thread.is_alive():
            self._thread.join(2.0)
        try:
            self.loop.stop()
        finally:
            try:
                self.link.send_force(np.zeros(3))
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

    Every fault goes through :meth:`HardwareDevice.fault`: a refused pose or Buttons (malformed,
    non-finite, beyond :data:`POSE_LIMIT_MM`; code 6), the pose's sender disconnecting or dropped
    (its message late: the link's ``message_timeout``; code 3), no pose for ``pose_timeout`` seconds
    (code 3), the link's server or the servo's tick failing (code 7). The servo stops (zero force
    from that tick), ``stop_reason`` says why, a zero ``Force`` goes to every client and the link is
    closed (its port free): open a new device. ``close()`` does the same with "closed".

    Parameters
    ----------
    port, host : where to listen.
    workspace : from the pose's frame to the organ's (default: the identity, the poses being in the
        organ's coordinates).
    max_force, max_rate, watchdog, rate : the servo's (N, N/s, servo ticks, Hz).
    force_rate : the most Force messages sent per second.
    pose_timeout : seconds without a pose, once one came, before the device stops (None: poses may
        pause, as 3D Slicer's do: it sends a transform only when it changes; a tracker that streams,
        PLUS's, can say e.g. 0.5).

    Raises
    ------
    DeviceError
        The igtl extra missing, an address that is not this machine's, the port in use.
    ModelError
        A bad port, workspace, max_force, max_rate, watchdog, rate, force_rate or pose_timeout.
    """

    NAME = "an OpenIGTLink tool"
    _thread = None
    link = None

    def __init__(self, port: int = 18944, host: str = "127.0.0.1", *, workspace: Workspace | None = None,
                 max_force: float = 10.0, max_rate: float = 1000.0, watchdog: int = 50, rate: float = 1000.0,
                 force_rate: float = 100.0, pose_timeout: float | None = None) -> None:
        self.force_period = 1.0 / validate.positive(force_rate, "force_rate", "messages per second")
        self.pose_timeout = None if pose_timeout is None else validate.in_range(
            pose_timeout, "pose_timeout", 0.0, 3600.0, lo_open=True, what="seconds (or None)")
        self._start_servo(Workspace() if workspace is None else workspace, ((-0.1,) * 3, (0.1,) * 3),
                          validate.positive(max_force, "max_force", "the largest force in N"), max_rate, watchdog, rate)
        self.link = IGTLLink(port, host).start()
        self._x = np.zeros(3)
        self._last_force = 0.0
        self._since = time.monotonic()  # pose_timeout counts from the last pose, or from this (a restart)
        self._thread = ServoThread(self._step, rate, "rtfem-igtl-servo", on_error=self._failed).start(at_exit=self.close)

    def _step(self) -> bool:
        """One servo tick: what came from the link (faults first), the servo, the Force out; False once
        a fault released the device (the thread ends)."""
        link = self.link
        position = link.poll()
        for kind, _, why in link.events():
            self.fault(_BAD_INPUT if kind == "refused" else _GONE, why)
        if link.error is not None:
            self.fault(_FAILED, f"the OpenIGTLink server stopped ({link.error})")
        if position is not None:
            self._x = position
        if self.pose_timeout is not None and link.last_pose is not None and not self._released:
            quiet = time.monotonic() - max(link.last_pose, self._since)
            if quiet > self.pose_timeout:
                self.fault(_GONE, f"no {link.TOOL} pose for {quiet:.2f} s (pose_timeout={self.pose_timeout:g})")
        if self._released:
            return False
        f = self._tick(self._x, link.buttons)
        now = time.perf_counter()
        if now - self._last_force >= self.force_period:
            link.send_force(f)
            self._last_force = now
        return not self._released

    def _command_zero(self) -> None:
        """An explicit zero Force to every client, now (it goes out before the link closes)."""
        if self.link is not None:
            self.link.send_force(np.zeros(3))
            self._last_force = time.perf_counter()

    def restart(self) -> None:
        super().restart()
        self._since = time.monotonic()

    def _open(self) -> bool:
        return self._thread is not None and self._thread.thread.is_alive()

    def _shutdown(self) -> None:
        """Stop the servo thread (not joined from itself) and the link (what waits to be sent, the
        zero Force, goes out first; the port is free after it)."""
        if self._thread is not None:
            self._thread.stop()
            self._thread = None
        if self.link is not None:
            self.link.close()
