"""``rtfem view``: the viewer on an organ (its session precomputed with a bar per stage, or run
headless with ``--benchmark``), on a scene file or an example (:mod:`rtfem.cli.scene`), or on a
written run, replayed (:mod:`rtfem.viewer.replay`)."""

from __future__ import annotations

import argparse
import time

import numpy as np

from ..errors import RtfemError
from .cache import report as cache_report
from .common import build_model, model_options, progress_bar


class _StageBars:
    """progress(stage, done, total, message) of a multi-stage precompute: one CLI bar per stage."""

    def __init__(self) -> None:
        self.stage, self.bar = None, None

    def __call__(self, stage: str, done: int, total: int, message: str = "") -> None:
        if stage != self.stage:
            self.close()
            self.stage = stage
            self.bar = progress_bar(stage, unit="step")
            self.bar_fn = self.bar.__enter__()
        self.bar_fn(done, total, message)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.__exit__(None, None, None)
            self.bar = None


def cmd_view(args: argparse.Namespace) -> int:
    from ..viewer.session import Settings
    from .scene import is_scene, view_scene

    if args.mesh and not args.example and _is_run(args.mesh):
        return _view_run(args)
    if is_scene(args):
        check_address(args.host, args.port)
        return view_scene(args)

    if args.benchmark is None:
        check_address(args.host, args.port)
    if args.local and args.method != "nonlinear":
        raise RtfemError("--local adds a patch to the reduced nonlinear model's basis at each grab: use it with --method "
                         "nonlinear")
    if (args.adapt is not None or args.adapt_radius is not None) and (args.method != "nonlinear" or args.local):
        raise RtfemError("--adapt and --adapt-radius localize the reduced nonlinear model where its error estimate is "
                         "large: use them with --method nonlinear and without --local (which localizes at every grab)")
    adapt = Settings.adapt * 1e3 if args.adapt is None else args.adapt  # mm; the panel's defaults
    adapt_radius = Settings.adapt_radius * 1e3 if args.adapt_radius is None else args.adapt_radius
    if adapt > 1000 or adapt_radius > 50:
        raise RtfemError(f"--adapt {adapt:g} mm / --adapt-radius {adapt_radius:g} mm: give at most 1000 mm and 50 mm")
    if args.shell and args.solid:
        raise RtfemError("--shell and --solid contradict each other: give one (a closed surface is a solid by default)")
    if args.device and args.benchmark is not None:
        raise RtfemError("--device and --benchmark: the benchmark's hand is scripted; drop one")
    settings = Settings(method=args.method, n_modes=args.modes, dt=args.dt, alpha=args.alpha, E=args.E,
                        grasp_stiffness=args.stiffness, grab_radius=args.grab_radius * 1e-3, large=args.large,
                        local=(args.local or 0.0) * 1e-3, adapt=adapt * 1e-3, adapt_radius=adapt_radius * 1e-3,
                        max_force=args.max_force).check()  # before any work
    device = None
    if args.device:  # opened before the precompute: a missing SDK says so at once
        from .devices import open_device

        device = open_device(args.device, args.max_force, args.haply_url, args.igtl_port)
    try:
        return _view(args, settings, device)
    finally:
        if device is not None:
            device.close()


def _view(args: argparse.Namespace, settings, device) -> int:
    from ..viewer.session import Session

    model = build_model(args)
    mesh = getattr(model, "tetmesh", model.mesh)  # a solid: the viewer builds the same model of the volume
    t0 = time.perf_counter()
    bars = _StageBars()
    try:
        material = getattr(model, "materials", None) or getattr(model, "law", None) or model.material
        session = Session(mesh, material, np.flatnonzero(model.held_nodes), settings,
                          model_options(args, mesh), progress=bars)
    finally:
        bars.close()
    print(f"precomputed {settings.label} in {time.perf_counter() - t0:.1f} s", flush=True)
    print(cache_report(modes=session.modes, reduced_model=getattr(session.driver, "reduced", None)), flush=True)
    if args.benchmark is not None:
        import json

        from ..viewer.benchmark import run

        report = run(session, args.benchmark)
        report["precompute_s"] = round(time.perf_counter() - t0 - report["seconds"], 1)
        print(json.dumps(report), flush=True)
        return 0 if report["error"] is None else 1
    from ..viewer.app import serve

    if device is not None:
        session.attach_device(device)
        print(f"rtfem view: the hand is the {args.device} device's; its first button grabs (rtfem devices checks it)",
              flush=True)
    serve(session=session, host=args.host, port=args.port)
    return 0


def _is_run(path: str) -> bool:
    from pathlib import Path

    return Path(path).suffix.lower() == ".pvd" or Path(path).is_dir()


def _view_run(args: argparse.Namespace) -> int:
    """``rtfem view out.pvd`` / ``rtfem view DIR``: replay a written run (:mod:`rtfem.viewer.replay`)."""
    for flag, what in (("benchmark", "--benchmark"), ("device", "--device")):
        if getattr(args, flag, None):
            raise RtfemError(f"{what} is for a live organ; {args.mesh} is a written run, which the viewer replays")
    check_address(args.host, args.port)
    from ..viewer.replay import serve_replay

    serve_replay(args.mesh, host=args.host, port=args.port,
                 progress=lambda message: print(f"replay      {message}", flush=True))
    return 0


def check_address(host: str, port: int) -> None:
    """Refuse, before any precompute, a host that is not an address of this machine."""
    import errno
    import socket

    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except (socket.gaierror, UnicodeError) as exc:
        raise RtfemError(f"--host {host}: unknown address ({getattr(exc, 'strerror', None) or exc})") from None
    family, _, _, _, addr = infos[0]
    with socket.socket(family, socket.SOCK_STREAM) as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind(addr)
        except OSError as exc:
            if exc.errno == errno.EADDRINUSE:
                return  # the viewer moves to the next free port and says so
            raise RtfemError(f"--host {host}: cannot serve on this address ({exc.strerror or exc}); give an address "
                             "of this machine, e.g. 127.0.0.1 (this machine only) or 0.0.0.0 (the network)") from None
