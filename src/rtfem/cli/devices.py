"""``rtfem devices`` (which haptic adapters can run here, and what to install) and ``rtfem igtl``
(the OpenIGTLink bridge on a mesh: a tracked tool in, the deformed organ and its force out)."""

from __future__ import annotations

import argparse
import contextlib
import logging
import signal
import socket
import sys
import threading
import time
from urllib.parse import urlparse

from ..errors import RtfemError
from ..interaction.devices import DEVICES, open_device  # noqa: F401 (rtfem view --device opens through it)
from .common import add_model_options, build_model, damping_of, port, positive


def _service_listening(url: str, timeout: float = 0.3) -> bool:
    """Whether something accepts TCP connections at a ws:// address (the Inverse Service's)."""
    u = urlparse(url)
    try:
        with socket.create_connection((u.hostname or "localhost", u.port or 80), timeout=timeout):
            return True
    except OSError:
        return False


def adapters(haply_url: str = "ws://localhost:10001") -> list[tuple[str, str, bool, str]]:
    """(adapter, what it needs, found here, what to do) for each device adapter of rt.devices."""
    from ..interaction.devices import forcedimension, haply, openhaptics

    def loads(make):
        """(loaded, the library's name or why not)."""
        try:
            return True, f"found: {make()._name}"
        except RtfemError as exc:
            return False, str(exc)

    hd, hd_what = loads(openhaptics.hd_library)
    dhd, dhd_what = loads(forcedimension.dhd_library)
    try:  # rtfem's own OpenIGTLink transport needs crcmod's CRC-64 (the igtl extra brings it with pyigtl)
        import crcmod  # noqa: F401

        igtl = True
    except ImportError:
        igtl = False
    try:
        import websockets  # noqa: F401

        ws = True
    except ImportError:
        ws = False
    listening = ws and _service_listening(haply_url)
    return [
        ("openhaptics", "3D Systems OpenHaptics (libHD)", hd, hd_what),
        ("forcedimension", "Force Dimension SDK (libdhd)", dhd, dhd_what),
        ("haply", f"Haply Inverse Service at {haply_url}", listening,
         "listening" if listening else ("pip install websockets (the viewer extra)" if not ws else haply.HOW)),
        ("igtl", "OpenIGTLink (crcmod, the igtl extra)", igtl,
         "installed" if igtl else "pip install 'rtfem[igtl]' (make installs it)"),
    ]


def cmd_devices(args: argparse.Namespace) -> int:
    from .bench import format_table

    rows = [[name, needs, "yes" if ok else "no", what] for name, needs, ok, what in adapters(args.haply_url)]
    print(format_table(["adapter", "needs", "found here", "what to do"], rows))
    return 0


def cmd_igtl(args: argparse.Namespace) -> int:
    """Serve until --seconds, SIGINT (Ctrl-C) or SIGTERM (rc 0, a line saying which); a bridge that
    stops on its own ends the command with rc 2 and the reason."""
    from ..drivers.modal import ModalSimulator
    from ..interaction.devices import IGTLServer
    from ..interaction.devices.igtl import warn_exposed
    from ..interaction.devices.igtl_net import listen_socket
    from .common import _modes

    with _igtl_log():
        sock, loopback = listen_socket(args.host, args.port)  # a bad address or a busy port: said before any work
        sock.close()
        if not loopback:
            warn_exposed(args.host, args.port)
        model = build_model(args)
        modes = _modes(model, args)
        driver = ModalSimulator(modes, args.dt, damping_of(args), static_correction=True)
        return _serve_igtl(args, IGTLServer(model.mesh, driver, port=args.port, host=args.host,
                                            tool_radius=args.tool_radius * 1e-3, stiffness=args.stiffness))


def _serve_igtl(args: argparse.Namespace, server) -> int:
    with _stop_signals() as stopped, server:
        print(f"rtfem igtl: serving OpenIGTLink on {args.host}:{server.port}: send a TRANSFORM '{server.TOOL}' (mm); "
              f"'{server.ORGAN}' (POLYDATA, mm) and '{server.FORCE}' (TRANSFORM, N) come back. Ctrl-C stops.", flush=True)
        t0 = time.perf_counter()
        while args.seconds is None or time.perf_counter() - t0 < args.seconds:
            if stopped.wait(0.1):
                print(f"rtfem igtl: stopped by {stopped.name}", flush=True)
                break
            if server.error is not None:
                raise RtfemError(f"the OpenIGTLink bridge stopped: {server.error}")
        print(f"rtfem igtl: {server.received} poses taken, {server.refused} messages refused", flush=True)
    return 0


@contextlib.contextmanager
def _igtl_log():
    """The bridge's log (clients coming and going, dropped, refused messages) as lines on stderr."""
    logger = logging.getLogger("rtfem.igtl")
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("rtfem igtl: %(message)s"))
    level, propagate = logger.level, logger.propagate
    logger.addHandler(handler)
    logger.setLevel(logging.INFO)
    logger.propagate = False
    try:
        yield
    finally:
        logger.removeHandler(handler)
        logger.setLevel(level)
        logger.propagate = propagate


class _Stopped(threading.Event):
    name = ""


@contextlib.contextmanager
def _stop_signals():
    """An Event set by SIGINT or SIGTERM while the block runs (on the main thread; elsewhere never),
    the previous handlers put back after it."""
    stopped = _Stopped()
    if threading.current_thread() is not threading.main_thread():
        yield stopped
        return

    def handler(signum, frame):
        stopped.name = signal.Signals(signum).name
        stopped.set()

    previous = {sig: signal.signal(sig, handler) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield stopped
    finally:
        for sig, old in previous.items():
            signal.signal(sig, old)


def add_device_commands(sub) -> None:
    p = sub.add_parser("devices", help="the haptic device adapters, whether each one's SDK or service is found here, "
                                       "and what to install")
    p.add_argument("--haply-url", default="ws://localhost:10001", help="the Haply Inverse Service's address to check")
    p.set_defaults(func=cmd_devices)

    p = sub.add_parser("igtl", help="an OpenIGTLink server (3D Slicer, PLUS): a tracked tool pressed against the organ, "
                                    "the deformed organ and the contact force sent back")
    add_model_options(p)
    p.add_argument("--port", type=port, default=18944, help="port (default 18944, OpenIGTLink's)")
    p.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1: this machine only; any other, "
                   "0.0.0.0 included, lets the network send poses and read the organ: a warning says so)")
    p.add_argument("--tool-radius", type=positive, default=5.0, metavar="MM", help="the sphere tool's radius in mm "
                   "(default 5)")
    p.add_argument("--stiffness", type=positive, default=200.0, help="coupling spring between the tracked pose and the "
                   "tool, N/m (default 200)")
    p.add_argument("--seconds", type=positive, default=None, help="serve this long, then stop (default: until Ctrl-C)")
    p.set_defaults(func=cmd_igtl)
