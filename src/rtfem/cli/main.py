"""The ``rtfem`` command: every step of the job on the embedded liver or on your own mesh.

    rtfem info [MESH]                      mesh check and repair report
    rtfem modes [MESH] -n 40 -o FILE       precompute the modal basis (.npz)
    rtfem simulate [MESH] ...              headless run: scripted probe or load file -> .pvd + .csv
    rtfem simulate SCENE.toml ...          a scene file: bodies under gravity on obstacles -> .pvd each + contacts.csv
    rtfem simulate --example gallbladder   the scene shipped with rtfem: liver, gallbladder, grasper and probe
    rtfem view --example cut               a scalpel drawn into the hanging solid liver (issue 57)
    rtfem impedance [MESH] -o FILE         precompute an impedance map (.npz)
    rtfem batch PLAN.toml                  many organs' bases, maps and reduced models, on a cluster or here
    rtfem bench [MESH]                     time per step: modal vs direct, measured now
    rtfem pictures [MESH] --out DIR        PNG/GIF pictures and plots
    rtfem view [MESH]                      the interactive web viewer
    rtfem devices                          the haptic device adapters: found here, or what to install
    rtfem igtl [MESH]                      an OpenIGTLink server: a tracked tool in, the organ and its force out
    rtfem demo                             the scripted demo of `make demo HEADLESS=1`
    rtfem cache [--clear]                  the precomputed meshes, modes and reduced models kept here

Exit codes: 0 ok, 2 bad input (one line on stderr, no traceback), 130 interrupted.
"""

from __future__ import annotations

import argparse
import contextlib
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .. import validate
from ..errors import ModelError, RtfemError
from .cache import report as cache_report
from .common import (
    MAX_FRAMES, MAX_STEPS, _Parser, _modes, _one_line, _vector, add_model_options, add_scheduler_options, build_model,
    check_scheduler, count, damping_of, fixed_nodes, fraction, mesh_of_args, nonnegative, open_fraction,
    port, positive, progress_bar, scheduler_of, time_list,
)

if TYPE_CHECKING:
    from ..io.scenario import RunWriter


# ---------------------------------------------------------------- commands
def cmd_info(args: argparse.Namespace) -> int:
    from ..mesh.tetmesh import TetMesh

    mesh = mesh_of_args(args)
    print(f"mesh        {args.mesh or 'embedded default liver'}")
    if isinstance(mesh, TetMesh):
        print(f"volume mesh {mesh.n_vertices} nodes, {mesh.n_tets} tets of {mesh.tets.shape[1]} nodes, "
              f"volume {mesh.volume():.4g}")
        print("check       " + str(mesh.report).replace("\n", "\n            "))
        print(f"quality     {mesh.quality()}")
        mesh = mesh.surface
        print("surface     (the boundary, drawn and touched)")
    lo, hi = mesh.bounds()
    print(f"size        {mesh.used_vertices().size} vertices, {mesh.n_triangles} triangles, {mesh.edges().shape[0]} edges")
    ext = hi - lo
    print(f"extent      {ext[0]:.4g} x {ext[1]:.4g} x {ext[2]:.4g} m (x, y, z; coordinates read as metres), surface area "
          f"{mesh.areas().sum():.4g} m^2")
    if ext.max() > 5.0:
        print(f"            an organ {ext.max():.3g} m across: if the file is in millimetres, give --scale 1e-3")
    if mesh.is_closed():
        print(f"volume      {mesh.volume():.4g} m^3")
    print("check       " + str(mesh.report).replace("\n", "\n            "))
    if mesh.groups:
        print("groups      " + ", ".join(f"{k} ({len(v)} vertices)" for k, v in sorted(mesh.groups.items())))
    from ..fe.linalg import available_backends, default_backend

    print(f"solver      {default_backend()} (sparse Cholesky in use; available: {', '.join(available_backends())})")
    from ..drivers.gpu import status

    print(f"gpu field   {status()}")
    return 0


def _output_file(path: str) -> Path:
    """Refuse an output that is an existing directory before any work is done."""
    if Path(path).is_dir():
        raise RtfemError(f"-o {path!r} is a directory; give a file name, e.g. {str(Path(path) / 'out.npz')!r}")
    return Path(path)


def cmd_modes(args: argparse.Namespace) -> int:
    _output_file(args.output)
    model = build_model(args)
    basis = _modes(model, args)
    f = basis.frequencies
    print("frequencies " + ", ".join(f"{x:.3f}" for x in f[:8]) + (f" ... {f[-1]:.2f}" if f.size > 8 else "") + " Hz")
    out = basis.save(args.output)
    print(f"wrote       {out} ({out.stat().st_size / 2**20:.1f} MiB); load with rt.ModalBasis.load(path, model=...)")
    return 0


def _held_out(cubature: dict) -> str:
    """The cubature's force error on poses it was not trained on, for the reduced model's line (a model
    saved before it was measured has none)."""
    err = cubature.get("held_out_error")
    return "" if err is None else f" (force error {err * 100:.1f} % on {cubature['held_out_poses']} untrained poses)"


def _probe_point(model, at: str | None) -> int:
    if at is not None:
        return model.nearest_free_node(_vector(at, "--at"))
    from ..mesh.selection import probe_vertex

    return probe_vertex(model)


def _check_simulate(args: argparse.Namespace) -> tuple[int, int]:
    """Refuse a run that cannot work before any work: returns (steps, steps per frame)."""
    validate.time_step(args.dt, "--dt")
    if args.at is not None:
        _vector(args.at, "--at")
    if args.method == "sldm" and not args.load:
        raise RtfemError("--method sldm answers given loads (it has no state to step a contact with): add --load FILE")
    n_float = args.duration / args.dt
    if n_float > MAX_STEPS:
        raise RtfemError(f"--duration {args.duration:g} s at --dt {args.dt:g} s is {n_float:.3g} steps, more than the "
                         f"{MAX_STEPS:,} steps a run may take (one CSV row each): shorten --duration or raise --dt")
    n_steps = int(round(n_float))
    if n_steps < 1:
        raise RtfemError(f"--duration {args.duration} is shorter than one step (--dt {args.dt})")
    frame_every = max(1, int(round(1 / args.fps / args.dt)))
    if n_steps // frame_every > MAX_FRAMES:
        raise RtfemError(f"--fps {args.fps:g} over {args.duration:g} s writes {n_steps // frame_every:,} VTU frames, more "
                         f"than {MAX_FRAMES:,}: lower --fps")
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise RtfemError(f"--out {args.out!r} is a file; give a folder for the frames")
    return n_steps, frame_every


def _drawn(model):
    """What a run's frames hold: a solid's volume (tets, for ParaView's clips and slices), a shell's surface."""
    return getattr(model, "tetmesh", model.mesh)


def _simulate_probe(args, model, sim, n_steps: int, frame_every: int, bar, record) -> tuple[RunWriter, str]:
    """A scripted point probe presses the organ: one CSV row per step, frames at --fps."""
    from ..interaction.haptics import Probe
    from ..interaction.devices import ScriptedDevice
    from ..io.scenario import RunWriter

    mesh = model.mesh
    node = _probe_point(model, args.at)
    X, nrm = np.asarray(mesh.vertices)[node], mesh.vertex_normals()[node]
    device = ScriptedDevice.press(X, nrm, args.depth, args.duration, approach=0.001)
    probe = Probe(mesh, sim, stiffness=args.stiffness)
    out = RunWriter(args.out, _drawn(model), ["t", "probe_x", "probe_y", "probe_z", "force_x", "force_y", "force_z", "force",
                                     "contact_node", "u_x", "u_y", "u_z"], frame_every)
    for k in range(n_steps):
        t = k * args.dt
        pos = device.position(t)
        f = probe.update(pos)
        contact = probe.contact_node if probe.contact_node is not None else -1
        out.row([t + args.dt, *pos, *f, float(np.linalg.norm(f)), contact, *sim.displacement(node)])
        out.frame(k + 1, t + args.dt, sim.displacements)
        record(t + args.dt, {probe.contact_node: tuple(-f)} if probe.contact_node is not None else None)
        bar(k + 1, n_steps, f"t = {t:.3f} s")
    what = (f"point probe at vertex {node}, {args.depth * 1e3:g} mm deep along its inward normal, stiffness "
            f"{args.stiffness:g} N/m")
    return out, what


def _simulate_schedule(args, model, sim, schedule, n_steps: int, frame_every: int, bar, record) -> RunWriter:
    """Given loads: stepped by a driver, or answered whole by SLDM (Duhamel superposition)."""
    from ..io.scenario import RunWriter

    nodes = schedule.nodes
    header = ["t"] + [f"{c}{n}" for n in nodes for c in ("f_x@", "f_y@", "f_z@", "u_x@", "u_y@", "u_z@")]
    out = RunWriter(args.out, _drawn(model), header, frame_every)
    zero = np.zeros(3)
    times = (np.arange(n_steps) + 1) * args.dt
    if sim is None:
        from ..reduction.sldm import SLDM

        print(f"sldm        factorizing K and building the Krylov basis of each load pattern ({len(schedule.nodes)} "
              "loaded node(s))", flush=True)
        with progress_bar("sldm (Lanczos)", unit="vectors") as sbar:
            U_all = SLDM(model, damping_of(args), progress=sbar).response(schedule, times, tol=args.tol)
    for k, t in enumerate(times):
        f = schedule.forces_at(t - args.dt)
        if sim is None:
            U = U_all[k]
        else:
            sim.step({n: tuple(v) for n, v in f.items()} or None)
            U = sim.displacements()
        out.row([t] + [v for n in nodes for v in (*f.get(n, zero), *U[n])])
        out.frame(k + 1, t, U)
        if sim is not None:
            record(t, {n: tuple(v) for n, v in f.items()})
        bar(k + 1, n_steps, f"t = {t:.3f} s")
    return out


def cmd_simulate(args: argparse.Namespace) -> int:
    from ..drivers.fullorder import DirectSimulator
    from ..io.scenario import LoadSchedule
    from ..drivers.modal import ModalSimulator

    from .scene import is_scene, simulate_scene

    if is_scene(args):  # a scene file (or --example): its bodies, obstacles, gravity
        return simulate_scene(args)
    n_steps, frame_every = _check_simulate(args)
    address = check_scheduler(args)  # its form and certificates before any work
    if address is not None and args.method != "nonlinear":
        raise RtfemError("--scheduler computes the modal derivatives of --method nonlinear; the other methods run here")
    model = build_model(args)
    if not args.load and args.depth > 0.5 * model.mesh.diagonal():  # before any precompute
        raise ModelError(f"--depth {args.depth:g} m is more than half the organ's size ({model.mesh.diagonal():.3g} m "
                         "across): the probe would pass through it. Give the indentation in m, e.g. 0.005")
    schedule = LoadSchedule.from_csv(args.load, model.n_nodes) if args.load else None
    damping = damping_of(args)
    large = getattr(args, "large", False)
    if large and args.method == "sldm":
        raise RtfemError("--large: SLDM superposes linear responses; use --method modal (modal warping) or direct (the "
                         "corotational full order)")
    if getattr(args, "local", None) and args.method != "nonlinear":
        raise RtfemError("--local adds a patch to the reduced nonlinear model's basis: use it with --method nonlinear")
    if args.method == "modal":
        sim = ModalSimulator(_modes(model, args), args.dt, damping, static_correction=True, warping=large)
    elif args.method == "direct":
        sim = DirectSimulator(model, args.dt, damping, large_deformation=large)
    elif args.method == "nonlinear":
        from ..drivers.reduced_nonlinear import reduced_nonlinear_driver

        local = None
        if args.local:  # the patch around the probed vertex, or the loaded nodes
            local = (schedule.nodes if schedule is not None else [_probe_point(model, args.at)], args.local * 1e-3)
        modes = _modes(model, args)
        with scheduler_of(args, address) as scheduler, progress_bar("modal derivatives", unit="mode") as bar:
            sim = reduced_nonlinear_driver(model, modes, args.dt, damping, local=local, progress=bar,
                                           scheduler=scheduler, cache=True)
        print(cache_report(modes=modes, reduced_model=sim.reduced))
        info = sim.reduced.info
        patch = "" if "local" not in info else (f" + {info['local']['coordinates']} of a {args.local:g} mm patch "
                                                f"({info['local']['nodes']} nodes)")
        print(f"reduced     {sim.reduced.size} coordinates ({modes.n_modes} modes + {sim.reduced.n_derivatives} "
              f"derivatives{patch}), cubature on {info['cubature']['elements']} of "
              f"{info['cubature']['of']} elements{_held_out(info['cubature'])}, static correction")
    else:
        sim = None
    from ..threads import runtime

    from .indicator import ErrorRecord

    errors = ErrorRecord(model, args.out, args.error_every, args.method == "nonlinear", sim)
    record = errors.maybe
    t0 = time.perf_counter()
    # the steps on one BLAS thread (rtfem.threads); SLDM's Krylov build (no stepping) keeps BLAS's threads
    stepping = runtime() if sim is not None else contextlib.nullcontext()
    with stepping, progress_bar(f"simulate ({args.method})", unit="steps") as bar:
        if schedule is None:
            out, what = _simulate_probe(args, model, sim, n_steps, frame_every, bar, record)
        else:
            out = _simulate_schedule(args, model, sim, schedule, n_steps, frame_every, bar, record)
            what = f"{len(schedule)} load rows from {args.load} on {len(schedule.nodes)} node(s)"
    elapsed = time.perf_counter() - t0
    csv_path, pvd = out.close()
    error_line = errors.close(n_steps * args.dt)
    print(f"load        {what}")
    label = {"modal": "modal, warped", "direct": "direct, corotational"}.get(args.method) if large else args.method
    label = "reduced nonlinear" if args.method == "nonlinear" else label
    print(f"ran         {n_steps} steps of {args.dt * 1e3:g} ms ({label}) in {elapsed:.2f} s "
          f"({n_steps * args.dt / elapsed:.2f} x real time, including the output)")
    if schedule is None:
        forces = np.array([r[7] for r in out.rows])
        print(f"force       peak {forces.max():.4f} N, final {forces[-1]:.4f} N")
    print(f"wrote       {csv_path} ({len(out.rows)} rows), {pvd} ({len(out.frames)} frames; open in ParaView)")
    if error_line:
        print(error_line)
    return 0


#: the scenes shipped with rtfem (rtfem/scenes/NAME.toml): --example NAME
EXAMPLES = ("gallbladder", "cut")
LARGE_MAP = 2**30  # bytes: an impedance map past this needs --allow-large


def cmd_impedance(args: argparse.Namespace) -> int:
    from ..drivers.impedance import ImpedanceMap

    output = _output_file(args.output)
    address = check_scheduler(args)  # its form and certificates before any work
    model = build_model(args)
    times = args.times
    nodes = None
    if args.nodes:
        nodes, how = fixed_nodes(model.mesh, args.nodes, "--nodes")
        print(f"loaded      {nodes.size} nodes ({how})")
    kw = dict(nodes=nodes, radius=args.radius, metric=args.metric, threshold=args.threshold, method=args.method,
              n_modes=args.modes, tol=args.tol, workers=args.workers, memory_limit=args.memory_limit * 2**30,
              scheduler=address)
    if times is not None:
        kw["times"] = times
    size = ImpedanceMap.estimate_bytes(model, nodes=nodes, radius=args.radius, metric=args.metric,
                                       **({"times": times} if times is not None else {}))
    print(f"estimate    about {size['bytes'] / 2**20:,.0f} MiB to write ({size['loaded']:,} loaded nodes, "
          f"{size['kept_per_node']:,.0f} kept per node, {size['samples']} samples each"
          f"{'; --threshold keeps fewer' if args.threshold else ''})", flush=True)
    if size["bytes"] > LARGE_MAP and not args.allow_large:
        raise RtfemError(f"the map would be about {size['bytes'] / 2**30:.1f} GiB, more than {LARGE_MAP / 2**30:g} GiB: "
                         "pass --allow-large to write it, or give a smaller --radius, a --threshold, fewer --times or "
                         "--nodes")
    with scheduler_of(args, address) as kw["scheduler"], progress_bar("impedance", unit="nodes") as bar:
        imap = ImpedanceMap.build(model, damping_of(args), progress=bar, **kw)
    if not imap.info.get("complete", True):
        # interrupted: keep what was finished, beside (never over) the requested output
        name = output.name[:-4] if output.name.endswith(".npz") else output.name
        partial = imap.save(output.with_name(name + ".partial.npz"))
        why = imap.info.get("error") or "interrupted"
        print(f"rtfem: {why}: kept {imap.loaded.size} of {imap.info['requested_nodes']} loaded nodes in "
              f"{partial}; {args.output} was not touched", file=sys.stderr)
        return 130 if why == "interrupted" else 1
    out = imap.save(output)
    print(f"map         {imap}")
    print(f"wrote       {out} ({out.stat().st_size / 2**20:.1f} MiB); load with rt.ImpedanceMap.load(path, model=...)")
    return 0


def cmd_bench(args: argparse.Namespace) -> int:
    from .bench import dynamics_table

    model = build_model(args)
    rows = dynamics_table(model, args.modes_list, dt=args.dt, damping=damping_of(args), direct_steps=args.direct_steps,
                          large=args.large)
    from .bench import print_table

    print_table(rows)
    if args.plot:
        from .plots import plot_bench

        print(f"wrote       {plot_bench(rows, args.plot)}")
    return 0


def cmd_pictures(args: argparse.Namespace) -> int:
    from .plots import pictures

    model = build_model(args)
    for path in pictures(model, Path(args.out), n_modes=args.modes, damping=damping_of(args), dt=args.dt,
                         gif=not args.no_gif, mp4=args.mp4, scaling_levels=() if args.no_scaling else (2, 3, 4),
                         say=print):
        print(f"wrote       {path}")
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    from .demo import main as demo_main

    return demo_main(["--out", args.out])


# ---------------------------------------------------------------- parser
def _add_info_and_modes(sub) -> None:
    p = sub.add_parser("info", help="check a mesh file (or the embedded liver) and report repairs")
    p.add_argument("mesh", nargs="?", help="mesh file (OBJ, STL, PLY, OFF, VTK, VTU, MSH, ...); default: the embedded liver")
    p.add_argument("--scale", type=positive, default=1.0, help="coordinate scale factor (1e-3 turns mm into m)")
    p.add_argument("--solid", action="store_true", help="mesh a surface into tets (fTetWild) and report the volume mesh")
    p.add_argument("--edge-length", type=positive, default=None, metavar="M", help="target tet edge length in m for --solid")
    p.set_defaults(func=cmd_info)

    p = sub.add_parser("modes", help="precompute the r lowest modes and save them (.npz)")
    add_model_options(p)
    p.add_argument("-o", "--output", default="liver.modes.npz", help="output file (default liver.modes.npz)")
    p.set_defaults(func=cmd_modes)

def _add_simulate(sub) -> None:
    p = sub.add_parser("simulate", help="headless run: a scripted probe (default) or a load file; writes .pvd + .csv",
                       description="A point probe presses the organ along the inward normal (1 mm approach, press to "
                       "--depth over 20 % of the run, hold to 60 %, release by 80 %), or the loads of --load act. "
                       "Writes response.pvd (+ frames) and response.csv to --out.")
    add_model_options(p)
    p.add_argument("--method", choices=("modal", "direct", "sldm", "nonlinear"), default="modal",
                   help="modal (r modes + static correction, default), direct (Newmark on the full model, the "
                        "baseline), sldm (Krylov, --load only) or nonlinear (the reduced nonlinear model: the r modes "
                        "and the modal derivatives of up to 20 of them, cubature forces; large deformation, shell or solid)")
    p.add_argument("--local", type=positive, metavar="MM", help="--method nonlinear: also every dof within MM mm of the "
                   "probed (or loaded) vertex in the basis, for pulls of centimetres (see the manual: Which model when)")
    add_scheduler_options(p, "--method nonlinear: the modal derivatives on a Dask cluster (tcp://HOST:PORT, "
                          "tls://HOST:PORT with --tls-*, or local:N; the cluster extra)")
    p.add_argument("--example", choices=EXAMPLES, help="run a scene shipped with rtfem: gallbladder (the liver and the "
                   "gallbladder hung beneath it, a grasper retracting its fundus, a probe on the liver); cut (the solid "
                   "liver hanging, a scalpel drawn 4 cm into its right lobe)")
    p.add_argument("--duration", type=positive, default=1.0, help="simulated time in s (default 1)")
    p.add_argument("--load", metavar="CSV", help="load file: rows t,node,fx,fy,fz (N); a row holds until the node's next row")
    p.add_argument("--at", metavar="X,Y,Z", help="probe point (m; nearest free vertex); default: the free vertex "
                   "farthest from the supports")
    p.add_argument("--depth", type=positive, default=0.005, help="probe indentation in m (default 0.005)")
    p.add_argument("--stiffness", type=positive, default=200.0, help="probe coupling spring in N/m (default 200)")
    p.add_argument("--tol", type=open_fraction, default=1e-6, help="SLDM tolerance (default 1e-6)")
    p.add_argument("--fps", type=positive, default=60.0, help="frames per simulated second written to the .pvd (default 60)")
    p.add_argument("--error-every", type=nonnegative, default=0.1, metavar="S", help="--method nonlinear: the reduced "
                   "model's error estimate (the full order's residual) every S s of simulated time and at the end, in "
                   "error_estimate.csv (default 0.1; 0: none)")
    p.add_argument("-o", "--out", default="out/simulate", help="output folder (default out/simulate)")
    p.set_defaults(func=cmd_simulate)

def _add_impedance(sub) -> None:
    p = sub.add_parser("impedance", help="precompute an impedance map (responses to unit loads) and save it (.npz)")
    add_model_options(p)
    p.add_argument("-o", "--output", default="liver.map.npz", help="output file (default liver.map.npz)")
    p.add_argument("--nodes", metavar="REGION", help="loaded nodes, same forms as --fix (default: every free node)")
    p.add_argument("--radius", type=positive, help="radius of influence in m (default: none)")
    p.add_argument("--metric", choices=("euclidean", "geodesic"), default="euclidean", help="distance for --radius")
    p.add_argument("--threshold", type=fraction, help="drop responses below this fraction of each column's largest")
    p.add_argument("--times", type=time_list, help="response samples in s, comma-separated (default 0.005,...,0.5)")
    p.add_argument("--method", choices=("modal", "sldm"), default="modal", help="modal (r modes + static correction) or sldm")
    p.add_argument("--tol", type=open_fraction, default=1e-6, help="SLDM tolerance (default 1e-6)")
    p.add_argument("--workers", type=count, default=1, help="threads (default 1)")
    add_scheduler_options(p, "compute the columns on a Dask cluster: tcp://HOST:PORT (a running 'dask scheduler' and "
                          "its workers), tls://HOST:PORT (with --tls-*) or local:N (N worker processes here, on "
                          "loopback); needs the cluster extra")
    p.add_argument("--memory-limit", type=positive, default=4.0, help="refuse maps above this many GiB (default 4)")
    p.add_argument("--allow-large", action="store_true", help="write a map estimated past 1 GiB (refused otherwise)")
    p.set_defaults(func=cmd_impedance)

def _add_bench_and_pictures(sub) -> None:
    p = sub.add_parser("bench", help="time per step of the modal simulator against direct integration, measured now")
    add_model_options(p)
    p.add_argument("--modes-list", type=count, nargs="+", default=[10, 40, 100], help="r values (default 10 40 100)")
    p.add_argument("--direct-steps", type=count, default=30, help="direct Newmark steps timed (default 30)")
    p.add_argument("--plot", metavar="PNG", help="also plot the table")
    p.set_defaults(func=cmd_bench)

    p = sub.add_parser("pictures", help="PNG mode shapes and deformed states, a GIF of a response, and plots")
    add_model_options(p)
    p.add_argument("-o", "--out", default="out/pictures", help="output folder (default out/pictures)")
    p.add_argument("--no-gif", action="store_true", help="skip the animated GIF")
    p.add_argument("--mp4", action="store_true", help="also write an MP4 (needs imageio-ffmpeg)")
    p.add_argument("--no-scaling", action="store_true", help="skip the scaling curves (they time the liver at 3 sizes)")
    p.set_defaults(func=cmd_pictures)

def _add_view_and_demo(sub) -> None:
    from .view import cmd_view

    p = sub.add_parser("view", help="the interactive web viewer: push and pull the organ with the mouse")
    add_model_options(p)
    p.add_argument("--shell", action="store_true",
                   help="model a closed surface as a shell (a hollow organ) instead of meshing it into tets (the "
                        "default for a closed surface; an open surface is always a shell)")
    p.add_argument("--method", choices=("modal", "impedance", "direct", "nonlinear"), default="nonlinear",
                   help="dynamics (default nonlinear: the reduced nonlinear model, modes + modal derivatives with "
                        "cubature forces and the static correction, large deformation of a shell or a solid; modal: "
                        "the linear modal model; impedance: a precomputed map; direct: the full model, the baseline)")
    p.add_argument("--max-force", type=positive, default=10.0, metavar="N",
                   help="the grasp's force limit in N (default 10, what a desktop haptic device renders); the panel "
                        "says when it clips")
    p.add_argument("--benchmark", type=positive, metavar="SECONDS",
                   help="no server: run the viewer's session headless for SECONDS with a scripted grab of the default "
                        "vertex pulled 3 cm and released, and print one JSON line (rates, step percentiles, force, "
                        "peak displacement)")
    p.add_argument("--device", choices=("openhaptics", "forcedimension", "haply", "igtl"),
                   help="drive the hand from a haptic device instead of the mouse: its first button grabs the surface "
                        "nearest it, the grasp's force goes back to it (rtfem devices says which are found here; igtl: "
                        "an OpenIGTLink ToolToReference pose, a STRING 'Buttons' its mask, the force back as 'Force')")
    p.add_argument("--haply-url", default="ws://localhost:10001", help="--device haply: the Inverse Service's address")
    p.add_argument("--igtl-port", type=port, default=18944, help="--device igtl: the OpenIGTLink port (default 18944)")
    p.add_argument("--stiffness", type=positive, default=200.0, help="grasp spring in N/m (default 200)")
    p.add_argument("--grab-radius", type=nonnegative, default=10.0, help="the jaw holds the surface within this radius "
                   "of the picked point, in mm (default 10; 0: one vertex)")
    p.add_argument("--local", type=positive, metavar="MM", help="--method nonlinear: each grab adds every dof within MM "
                   "mm of the held vertices to the basis (trained in the background, seconds; then swapped in mid-pull)")
    p.add_argument("--adapt", type=nonnegative, metavar="MM", help="--method nonlinear: when the error "
                   "estimate under a held grasp is above MM mm (default 0.5; 0: never), the basis is localized around it "
                   "once per grab, in the background (see --adapt-radius)")
    p.add_argument("--adapt-radius", type=positive, metavar="MM", help="the patch --adapt adds: every dof "
                   "within MM mm of the held vertices (default 10, at most 50)")
    p.add_argument("--host", default="127.0.0.1", help="address to serve on (default 127.0.0.1: this machine only)")
    p.add_argument("--port", type=port, default=8080, help="port (default 8080; a busy port moves to the next free one, "
                   "and says so)")
    p.add_argument("--example", choices=EXAMPLES, help="show a scene shipped with rtfem (MESH may also be a scene "
                   "file, .toml): gallbladder, the liver and the gallbladder beneath it, a grasper and a probe; cut, the "
                   "solid liver hanging, a scalpel drawn into its right lobe")
    p.epilog = ("MESH may also be a scene file (.toml: its bodies, obstacles and tools, played from when the page "
                "opens), or a written run to replay: a .pvd collection, or the folder rtfem simulate wrote (-o DIR; "
                "a scene's run: one .pvd per body in its subfolders)")
    p.set_defaults(func=cmd_view)

    p = sub.add_parser("demo", help="static poke, modal push-hold-release and a 1 kHz haptic session on the liver")
    p.add_argument("-o", "--out", default="out/demo", help="output folder (default: out/demo)")
    p.set_defaults(func=cmd_demo)


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """Every command's parser, or for ``info`` and ``modes`` only theirs (the others' imports: 40 ms of a cold start)."""
    ap = _Parser(prog="rtfem", description="Real-time simulation of deformable finite-element (shell and solid) "
                                 "models: modal analysis, spectral Lanczos decomposition, impedance maps.",
                                 epilog="Every command runs on the embedded default liver when no MESH is given.")
    sub = ap.add_subparsers(dest="command", required=True, metavar="COMMAND")
    if command in ("info", "modes"):
        _add_info_and_modes(sub)
        return ap
    from . import batch, cache, devices, segment
    for add in (_add_info_and_modes, _add_simulate, _add_impedance, batch.add_batch_command, _add_bench_and_pictures,
                _add_view_and_demo, devices.add_device_commands, cache.add_cache_command, segment.add_mesh_command):
        add(sub)
    return ap


def main(argv: list[str] | None = None) -> int:
    try:
        args = build_parser(*(sys.argv[1:] if argv is None else argv)[:1]).parse_args(argv)
    except SystemExit as exc:  # --help (0) or a bad option (2, one line already printed)
        return int(exc.code or 0) if not isinstance(exc.code, str) else 2
    try:
        return int(args.func(args))
    except RtfemError as exc:
        print(f"rtfem: error: {_one_line(exc)}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"rtfem: error: {_one_line(exc)}", file=sys.stderr)
        return 2
    except MemoryError:
        print("rtfem: error: out of memory: use a coarser mesh, fewer modes or a smaller map (--radius, --threshold)",
              file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("\nrtfem: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    raise SystemExit(main())
