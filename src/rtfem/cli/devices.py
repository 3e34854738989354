"""``rtfem devices`` (which haptic adapters can run here, and what to install) and ``rtfem igtl``
(the OpenIGTLink bridge on a mesh: a tracked tool in, the deformed organ and its force out)."""

from __future__ import annotations

import argparse
import socket
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
    try:
        import pyigtl  # noqa: F401

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
        ("igtl", "pyigtl (OpenIGTLink)", igtl, "installed" if igtl else "pip install 'rtfem[igtl]' (make installs it)"),
    ]


def cmd_devices(args: argparse.Namespace) -> int:
    from .bench import format_table

    rows = [[name, needs, "yes" if ok else "no", what] for name, needs, ok, what in adapters(args.haply_url)]
    print(format_table(["adapter", "needs", "found here", "what to do"], rows))
    return 0


def cmd_igtl(args: argparse.Namespace) -> int:
    from ..drivers.modal import ModalSimulator
    from ..interaction.devices import IGTLServer
    from .common import _modes

    model = build_model(args)
    modes = _modes(model, args)
    driver = ModalSimulator(modes, args.dt, damping_of(args), static_correction=True)
    with IGTLServer(model.mesh, driver, port=args.port, host=args.host, tool_radius=args.tool_radius * 1e-3,
                    stiffness=args.stiffness) as server:
        print(f"rtfem igtl: serving OpenIGTLink on {args.host}:{server.port}: send a TRANSFORM '{server.TOOL}' (mm); "
              f"'{server.ORGAN}' (POLYDATA, mm) and '{server.FORCE}' (TRANSFORM, N) come back. Ctrl-C stops.", flush=True)
        t0 = time.perf_counter()
        while args.seconds is None or time.perf_counter() - t0 < args.seconds:
            time.sleep(0.1)
            if server.loop.error is not None:
                raise RtfemError(f"the contact loop stopped: {server.loop.error}")
        print(f"rtfem igtl: {server.received} poses taken, {server.refused} messages refused", flush=True)
    return 0


def add_device_commands(sub) -> None:
    p = sub.add_parser("devices", help="the haptic device adapters, whether each one's SDK or service is found here, "
                                       "and what to install")
    p.add_argument("--haply-url", default="ws://localhost:10001", help="the Haply Inverse Service's address to check")
    p.set_defaults(func=cmd_devices)

    p = sub.add_parser("igtl", help="an OpenIGTLink server (3D Slicer, PLUS): a tracked tool pressed against the organ, "
                                    "the deformed organ and the contact force sent back")
    add_model_options(p)
    p.add_argument("--port", type=port, default=18944, help="port (default 18944, OpenIGTLink's)")
    p.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1: this machine only)")
    p.add_argument("--tool-radius", type=positive, default=5.0, metavar="MM", help="the sphere tool's radius in mm "
                   "(default 5)")
    p.add_argument("--stiffness", type=positive, default=200.0, help="coupling spring between the tracked pose and the "
                   "tool, N/m (default 200)")
    p.add_argument("--seconds", type=positive, default=None, help="serve this long, then stop (default: until Ctrl-C)")
    p.set_defaults(func=cmd_igtl)
