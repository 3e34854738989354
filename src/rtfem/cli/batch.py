"""``rtfem batch PLAN.toml``: many organs or parameter sets precomputed into one folder of modal
bases, impedance maps and reduced nonlinear models, on a Dask cluster (one organ a task: each
worker builds, solves and writes its organ) or here, with a summary table (printed, and
``summary.csv`` in the folder). Resumable: a file already there that loads onto its organ's model
(the same mesh, supports, material and settings) is kept, not recomputed.

A plan::

    out = "bases"                 # the folder, relative to the plan (created)
    scheduler = "local:2"         # optional (--scheduler overrides): tcp://HOST:PORT or local:N

    [defaults]                    # optional: what every organ takes unless it says otherwise
    build = ["modes", "map"]      # any of modes, map, reduced
    modes = 20

    [[organ]]
    name = "liver-soft"           # the files' stem: liver-soft.modes.npz, .map.npz, .reduced.npz
    mesh = "liver.vtu"            # relative to the plan; omitted: the embedded liver
    solid = true                  # fill a surface with tets (as --solid)
    E = 20000.0                   # and the other model options of the command line (see KEYS)
    radius = 0.02                 # the map's radius in m (map), its times in s: times = [0.01, 0.05]
    derivatives = 10              # reduced: the modal derivatives of the lowest this many modes

On a cluster the folder (and the mesh files) must be reachable by every worker at the same path:
a shared file system (NFS, a cluster's scratch), or a folder synced to an object store afterwards.
"""

from __future__ import annotations

import argparse
import csv
import time
import tomllib
from pathlib import Path

from ..errors import RtfemError

__all__ = ["cmd_batch", "add_batch_command", "load_plan", "run_organ", "KEYS"]

# plan key -> the command line's flag (None: a key of the batch's own)
KEYS = {"name": None, "mesh": None, "build": None, "radius": None, "times": None, "method": None,
        "derivatives": None, "solid": "--solid", "element": "--element", "mass": "--mass", "fix": "--fix",
        "material": "--material", "E": "--E", "nu": "--nu", "density": "--density", "thickness": "--thickness",
        "scale": "--scale", "edge_length": "--edge-length", "modes": "-n"}
BUILD = ("modes", "map", "reduced")


def load_plan(path: str | Path) -> tuple[Path, str | None, list[dict]]:
    """(the output folder, the plan's scheduler or None, each organ's settings with the defaults
    filled in and its mesh path made absolute), every organ checked before any work.

    Parameters
    ----------
    path : the plan file (TOML; see the module's docstring).

    Returns
    -------
    tuple

    Raises
    ------
    RtfemError
        A plan that cannot be read, an unknown key (named with its organ), a missing name or mesh
        file, two organs of one name, nothing to build.
    """
    path = Path(path)
    try:
        plan = tomllib.loads(path.read_text())
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise RtfemError(f"{path}: cannot read the plan: {exc}") from None
    unknown = set(plan) - {"out", "scheduler", "defaults", "organ"}
    if unknown:
        raise RtfemError(f"{path}: unknown top-level key(s) {sorted(unknown)}: a plan has out, scheduler, [defaults] "
                         "and [[organ]] tables")
    defaults = plan.get("defaults", {})
    organs = plan.get("organ", [])
    if not isinstance(defaults, dict) or not isinstance(organs, list) or not organs:
        raise RtfemError(f"{path}: give at least one [[organ]] table (and [defaults] as a table)")
    specs, names = [], set()
    for i, organ in enumerate(organs):
        spec = {"build": ["modes"], "modes": 20, **defaults, **organ}
        where = f"{path}: organ {i + 1} ({spec.get('name', 'no name')})"
        bad = set(spec) - set(KEYS)
        if bad:
            raise RtfemError(f"{where}: unknown key(s) {sorted(bad)}; known: {', '.join(KEYS)}")
        name = spec.get("name")
        if not isinstance(name, str) or not name or "/" in name or name in names:
            raise RtfemError(f"{where}: each organ needs its own name (a file stem, no '/')")
        names.add(name)
        build = spec["build"]
        if isinstance(build, str):
            build = [build]
        if not isinstance(build, list) or not build or not set(build) <= set(BUILD):
            raise RtfemError(f"{where}: build = {spec['build']!r}: give a list of {', '.join(BUILD)}")
        spec["build"] = [b for b in BUILD if b in build]
        if spec.get("mesh") is not None:
            mesh = (path.parent / str(spec["mesh"])).resolve()
            if not mesh.is_file():
                raise RtfemError(f"{where}: mesh file {str(mesh)!r} does not exist")
            spec["mesh"] = str(mesh)
        specs.append(spec)
    out = (path.parent / str(plan.get("out", path.stem))).resolve()
    return out, plan.get("scheduler"), specs


def _model_args(spec: dict) -> argparse.Namespace:
    """The command line's parsed options for an organ (its defaults for what the organ leaves out)."""
    import contextlib
    import io

    from .common import add_model_options

    parser = argparse.ArgumentParser(prog=f"organ {spec['name']}", exit_on_error=False, add_help=False)
    add_model_options(parser)
    argv = [spec["mesh"]] if spec.get("mesh") else []
    for key, flag in KEYS.items():
        value = spec.get(key)
        if flag is None or value is None or value is False:
            continue
        argv += [flag] if value is True else [flag, str(value)]
    said = io.StringIO()
    try:
        with contextlib.redirect_stderr(said):
            return parser.parse_args(argv)
    except (SystemExit, argparse.ArgumentError) as exc:
        why = str(exc) if isinstance(exc, argparse.ArgumentError) else said.getvalue().strip().splitlines()[-1]
        raise RtfemError(f"organ {spec['name']}: {why}") from None


def run_organ(spec: dict, out: str) -> dict:
    """One organ's precompute (on a worker or here): its model, then each file of ``build`` not
    already there and valid, written into ``out``. Returns its summary row (never raises: an
    error is the row's ``error``).

    Parameters
    ----------
    spec : the organ's settings (from :func:`load_plan`).
    out : the output folder.

    Returns
    -------
    dict
        name, nodes, dof, what was built and kept, seconds, error.
    """
    row = {"name": spec["name"], "nodes": 0, "dof": 0, "built": [], "kept": [], "seconds": 0.0, "error": ""}
    t0 = time.perf_counter()
    try:
        _organ(spec, Path(out), row)
    except Exception as exc:  # noqa: BLE001 - a row of the table, the batch goes on
        row["error"] = f"{type(exc).__name__}: {exc}"
    row["seconds"] = round(time.perf_counter() - t0, 2)
    return row


def _organ(spec: dict, out: Path, row: dict) -> None:
    from ..drivers.impedance import ImpedanceMap
    from ..reduction.modal import ModalBasis, modal_analysis
    from ..reduction.reduced import ReducedNonlinearModel
    from .common import build_model

    model = build_model(_model_args(spec), quiet=True)
    row["nodes"], row["dof"] = model.n_nodes, model.n_dofs
    stem = out / spec["name"]

    def kept(kind: str, loader):
        path = Path(f"{stem}.{kind}.npz")
        if not path.is_file():
            return None
        try:
            value = loader(path)
        except RtfemError:  # another model, settings or a damaged file: recomputed
            return None
        row["kept"].append(kind)
        return value

    def check_modes(path):
        basis = ModalBasis.load(path, model=model)
        if basis.n_modes != int(spec["modes"]):
            raise RtfemError("another number of modes")
        return basis

    modes = kept("modes", check_modes)
    if modes is None:
        modes = modal_analysis(model, int(spec["modes"]))
        if "modes" in spec["build"]:
            modes.save(f"{stem}.modes.npz")
            row["built"].append("modes")
    if "map" in spec["build"] and kept("map", lambda p: _check_map(ImpedanceMap.load(p, model=model), spec,
                                                                   modes.n_modes)) is None:
        kw = {"radius": spec.get("radius"), "method": spec.get("method", "modal")}
        if spec.get("times") is not None:
            kw["times"] = spec["times"]
        ImpedanceMap.build(model, modes=modes, n_modes=modes.n_modes, **kw).save(f"{stem}.map.npz")
        row["built"].append("map")
    if "reduced" in spec["build"] and kept("reduced", lambda p: ReducedNonlinearModel.load(p, model)) is None:
        red = ReducedNonlinearModel(model, modes, min(int(spec.get("derivatives", 10)), modes.n_modes))
        red.train_cubature(16, tol=0.05)
        red.save(f"{stem}.reduced.npz")
        row["built"].append("reduced")


def _check_map(imap, spec: dict, n_modes: int):
    """The map kept when it was built with the organ's settings (and whole); else ModelError."""
    import numpy as np

    from ..errors import ModelError

    radius, method = spec.get("radius"), spec.get("method", "modal")
    same = (imap.info.get("complete", True) and imap.info.get("radius") == (float(radius) if radius else -1.0)
            and imap.info.get("method") == method and (method != "modal" or imap.info.get("n_modes") == n_modes)
            and (spec.get("times") is None or np.array_equal(imap.times, np.asarray(spec["times"], float))))
    if not same:
        raise ModelError("another radius, method, times or modes, or incomplete")
    return imap


def _organ_task(out: str, specs: list) -> list:
    return [run_organ(spec, out) for spec in specs]


def cmd_batch(args: argparse.Namespace) -> int:
    """``rtfem batch PLAN``: run the plan (see the module's docstring); 0 when every organ is done,
    1 when one failed (its error in the table), 130 when interrupted."""
    from ..cluster import connect, run_tasks

    out, scheduler, specs = load_plan(args.plan)
    scheduler = args.scheduler or scheduler
    out.mkdir(parents=True, exist_ok=True)
    rows: list[dict] = []
    t0 = time.perf_counter()

    def collect(batch) -> None:
        for row in batch:
            rows.append(row)
            what = row["error"] or ", ".join(f"built {b}" for b in row["built"]) or "all kept"
            print(f"[{len(rows)}/{len(specs)}] {row['name']}: {what} ({row['seconds']:.1f} s)", flush=True)

    why = ""
    print(f"batch       {len(specs)} organ(s) into {out}" + (f" on {scheduler}" if scheduler else " here"), flush=True)
    if scheduler:
        with connect(scheduler) as client:
            why = run_tasks(client, _organ_task, (str(out),), [[s] for s in specs], collect)
    else:
        try:
            for spec in specs:
                collect([run_organ(spec, str(out))])
        except KeyboardInterrupt:
            why = "interrupted"
    _summary(out, specs, rows, time.perf_counter() - t0)
    if why:
        print(f"rtfem: batch stopped ({why}); run it again to finish: what is written is kept")
        return 130 if why == "interrupted" else 1
    return 1 if any(r["error"] for r in rows) else 0


def _summary(out: Path, specs: list, rows: list, seconds: float) -> None:
    """The table, printed in the plan's order and written to summary.csv."""
    order = {s["name"]: i for i, s in enumerate(specs)}
    rows = sorted(rows, key=lambda r: order[r["name"]])
    head = ["name", "nodes", "dof", "built", "kept", "seconds", "error"]
    with open(out / "summary.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(head)
        for r in rows:
            w.writerow([r["name"], r["nodes"], r["dof"], " ".join(r["built"]), " ".join(r["kept"]), r["seconds"],
                        r["error"]])
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    for r in rows:
        print(f"| {r['name']} | {r['nodes']:,} | {r['dof']:,} | {' '.join(r['built']) or '-'} | "
              f"{' '.join(r['kept']) or '-'} | {r['seconds']:.1f} | {r['error'] or '-'} |")
    print(f"summary     {len(rows)} of {len(specs)} organ(s) in {seconds:.1f} s; {out / 'summary.csv'}")


def add_batch_command(sub) -> None:
    """The ``batch`` subcommand on the ``rtfem`` parser's subparsers."""
    p = sub.add_parser("batch", help="precompute many organs or parameter sets (a TOML plan) into one folder",
                       description="Modal bases, impedance maps and reduced nonlinear models of every [[organ]] of "
                       "the plan, one organ a task on a Dask cluster (--scheduler) or here; what is there and valid "
                       "is kept; a summary table (summary.csv). See the manual: Precompute on a cluster.")
    p.add_argument("plan", help="the plan (TOML)")
    p.add_argument("--scheduler", metavar="ADDRESS", help="tcp://HOST:PORT or local:N (overrides the plan's)")
    p.set_defaults(func=cmd_batch)
