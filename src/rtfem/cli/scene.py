"""``rtfem simulate scene.toml``: a scene file run headless (each body's .pvd series and contacts.csv);
``rtfem view scene.toml``: the scene viewer; ``--example NAME``: a scene shipped with rtfem."""

from __future__ import annotations

import argparse
import csv
import time
from pathlib import Path

import numpy as np

from ..errors import RtfemError
from .common import MAX_FRAMES, MAX_STEPS, progress_bar


def is_scene(args: argparse.Namespace) -> bool:
    """Whether the command runs a scene: a .toml MESH, or ``--example`` (MESH set to its file)."""
    example = getattr(args, "example", None)
    if example:
        if args.mesh:
            raise RtfemError(f"give a mesh or scene file, or --example {example}, not both")
        from importlib import resources

        args.mesh = str(resources.files("rtfem") / "scenes" / f"{example}.toml")
    return bool(args.mesh) and str(args.mesh).lower().endswith(".toml")


#: the time steps the viewer may step a scene at to keep real time (s)
VIEW_STEPS = (0.001, 0.002, 0.0025, 0.004, 0.005, 0.01, 0.02)
#: the share of dt a step may take for the viewer to step at that dt: at 1 ms the example scene's steps
#: of 0.82-0.92 ms held 0.97-1.00x real time in the viewer, headless chromium drawing on the same 2 cores
#: included (benchmarks/scene_viewer.py; the stepping thread at nice -10, the frame thread beside it)
VIEW_SHARE = 0.9


def view_scene(args: argparse.Namespace) -> int:
    """``rtfem view scene.toml`` / ``--example``: the scene viewer (:func:`scene_for_viewer`)."""
    from ..interaction.scene_file import close_devices
    from ..viewer.scene_view import SceneSession, serve_scene

    for flag, what in (("device", "--device"), ("benchmark", "--benchmark")):
        if getattr(args, flag, None):
            raise RtfemError(f"{what} is for a single organ; a scene's tools are in its file (device = ... for a "
                             "live hand) and the mouse")
    scene = scene_for_viewer(args.mesh)
    try:
        for tool in scene.tools:
            if getattr(tool.device, "attach", None) is not None:
                print(f"scene       tool {tool.name} ({tool.kind}) follows its live device"
                      + (" (its first button closes it)" if tool.kind == "grasper" else ""), flush=True)
        print("scene       the scene starts when the first browser connects (play / pause / restart in the panel)",
              flush=True)
        serve_scene(SceneSession(scene), host=args.host, port=args.port)
    finally:
        close_devices(scene)
    return 0


def scene_for_viewer(path):
    """The scene file ``path`` loaded for the viewer, at t = 0: stepped at the file's dt when a step
    (the median of 50, timed here) takes under VIEW_SHARE of it, else at the smallest of VIEW_STEPS that
    keeps real time (said, with the rate the file's dt would run at)."""
    from ..interaction.scene_file import close_devices, load_scene
    from ..viewer.scene_view import rewind, snapshot

    def progress(message: str) -> None:
        print(f"scene       {message}", flush=True)

    scene = load_scene(path, progress=progress)
    try:
        start = snapshot(scene)
        steps = []
        for _ in range(60):
            t0 = time.perf_counter()
            scene.step()
            steps.append(time.perf_counter() - t0)
        rewind(scene, start)  # the scene waits at t = 0 for the first browser
        cost, dt = float(np.median(steps[10:])), scene.dt
        if cost > VIEW_SHARE * dt:
            new = next((d for d in VIEW_STEPS if d > dt and cost <= VIEW_SHARE * d), VIEW_STEPS[-1])
            print(f"scene       a step takes {cost * 1e3:.1f} ms here now: the viewer steps the scene at dt = "
                  f"{new * 1e3:g} ms to keep real time (at the file's {dt * 1e3:g} ms it would run at {dt / cost:.2f}x; "
                  "the step's cost depends on this machine and what else runs on it)", flush=True)
            close_devices(scene)  # the file's live devices are opened again with the scene
            scene = load_scene(path, progress=progress, dt=new)
    except BaseException:
        close_devices(scene)
        raise
    return scene


def _body_folder(out: Path, name: str) -> Path:
    """``out/<name>``, a body's folder: its name one that may name files, the folder (and the
    files named after the body in it) inside ``out`` once links are followed."""
    from ..userfiles import file_stem, inside

    file_stem(name, "body name", error=RtfemError)
    folder = out / name
    for path in (folder, folder / f"{name}.pvd", folder / f"{name}.csv"):
        inside(out, path, f"body {name!r}'s output", error=RtfemError)
    return folder


def simulate_scene(args: argparse.Namespace) -> int:
    """Run the scene file ``args.mesh`` for ``args.duration`` s into ``args.out``: a folder per body with
    its ``<body>.pvd`` frames (``--fps``) and ``<body>.csv`` (t and the total contact force on it), and
    ``contacts.csv`` with t, a, b, fx, fy, fz: the force on body a from obstacle, body or attachment b, every step."""
    from ..interaction.scene_file import contact_rows, load_scene
    from ..io.scenario import RunWriter
    from ..storage import atomic_target
    from ..userfiles import inside
    from ..threads import runtime

    if getattr(args, "scheduler", None) is not None:
        raise RtfemError("--scheduler is for --method nonlinear on one organ; a scene's bodies are reduced here")
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise RtfemError(f"--out {args.out!r} is a file; give a folder for the frames")
    scene = load_scene(args.mesh, progress=lambda message: print(f"scene       {message}", flush=True), live=False)
    dt = scene.dt
    n_steps = int(round(args.duration / dt))
    if not 1 <= n_steps <= MAX_STEPS:
        raise RtfemError(f"--duration {args.duration:g} s is {args.duration / dt:.3g} steps of the scene's dt = {dt:g} s: "
                         f"give 1 .. {MAX_STEPS:,} steps")
    frame_every = max(1, int(round(1 / args.fps / dt)))
    if n_steps // frame_every > MAX_FRAMES:
        raise RtfemError(f"--fps {args.fps:g} writes {n_steps // frame_every:,} frames a body, more than {MAX_FRAMES:,}")
    writers = {b.name: RunWriter(_body_folder(out, b.name), getattr(b.model, "tetmesh", b.mesh), ["t", "fx", "fy", "fz"],
                                 frame_every, name=b.name) for b in scene.bodies}
    rows = []
    t0 = time.perf_counter()
    with runtime(), progress_bar("simulate (scene)", unit="steps") as bar:
        for k in range(n_steps):
            scene.step()
            step_rows = contact_rows(scene)
            rows += step_rows
            for b in scene.bodies:
                total = np.sum([r[3:] for r in step_rows if r[1] == b.name], axis=0) if step_rows else np.zeros(3)
                writers[b.name].row([scene.time, *np.atleast_1d(total).tolist()])
                writers[b.name].mesh = getattr(b.model, "tetmesh", b.mesh)  # (a scalpel's body: the cut mesh)
                writers[b.name].frame(k, scene.time, b.driver.displacements)
            if k % 100 == 99 or k == n_steps - 1:
                bar(k + 1, n_steps)
    elapsed = time.perf_counter() - t0
    for w in writers.values():
        w.close()
    path = inside(out, out / "contacts.csv", "contacts file")
    with atomic_target(path) as tmp, open(tmp, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["t", "a", "b", "fx", "fy", "fz"])
        w.writerows([[f"{r[0]:.9g}", r[1], r[2], *(f"{v:.9g}" for v in r[3:])] for r in rows])
    print(f"ran         {n_steps} steps of {dt * 1e3:g} ms in {elapsed:.2f} s ({n_steps * dt / elapsed:.2f} x real time)")
    for b in scene.bodies:
        f = sum((f for (a, _), f in scene.contacts.items() if a == b.name), np.zeros(3))
        print(f"body        {b.name}: {b.mass:.4g} kg (weight {b.mass * np.linalg.norm(scene.gravity):.4g} N), "
              f"{_material(b.model, not hasattr(b.driver, 'modes'))}; force of obstacles, bodies and attachments now "
              f"{np.round(f, 4).tolist()} N")
    for sc in scene.scalpels:
        print(f"scalpel     {sc.name}: {sc.cuts} cut(s) of {sc.body}, now {sc.model.n_nodes} nodes"
              + (f"; its last strip was not cut: {sc.cutter.refused}" if sc.cutter.refused else ""))
    print(f"wrote       {path} ({len(rows)} rows) and {', '.join(f'{b.name}/{b.name}.pvd' for b in scene.bodies)}")
    return 0


def _material(model, full: bool = False) -> str:
    """What a body's material is, and what its modes use of it (a law's linearization at rest)."""
    if getattr(model, "materials", None) is not None:  # a material per region
        return "regions " + "; ".join(f"{label}: {law!r}" for label, law in model.materials.items())
    law, lin = getattr(model, "law", None), model.material
    if law is None:
        return f"linear, E = {lin.E:.4g} Pa, nu = {lin.nu:.4g}"
    if full:
        return f"{law!r}, full order"
    return f"{law!r} on its modes: its linearization at rest, E = {lin.E:.4g} Pa, nu = {lin.nu:.4g}"
