"""``rtfem batch PLAN.toml``: many organs or parameter sets precomputed into one folder of modal
bases, impedance maps and reduced nonlinear models, on a Dask cluster (one organ a task: each
worker builds, solves and writes its organ) or here, with a summary table (printed, and
``summary.csv`` in the folder). Resumable: a file already there that loads onto its organ's model
(the same mesh, supports, material and settings) is kept, not recomputed.

A plan::

    out = "bases"                 # the folder, inside the plan's folder (created; --out DIR: any folder)
    scheduler = "local:2"         # optional, local:N only (--scheduler overrides; a remote cluster only there)

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

A plan is someone's file: it is read as :func:`rtfem.userfiles.read_toml` reads one (a regular file,
size-capped, nested at most 16 deep), every key is checked before any work (all problems said at
once), it never chooses a remote cluster (``--scheduler`` does), and what it writes stays in the
output folder (organ names are file stems: no separators, no control or bidirectional characters).
"""

from __future__ import annotations

import argparse
import csv
import time
from pathlib import Path

from .. import validate
from ..errors import RtfemError

__all__ = ["cmd_batch", "add_batch_command", "load_plan", "run_organ", "KEYS"]

# plan key -> the command line's flag (None: a key of the batch's own)
KEYS = {"name": None, "mesh": None, "build": None, "radius": None, "times": None, "method": None,
        "derivatives": None, "solid": "--solid", "element": "--element", "mass": "--mass", "fix": "--fix",
        "material": "--material", "E": "--E", "nu": "--nu", "density": "--density", "thickness": "--thickness",
        "scale": "--scale", "edge_length": "--edge-length", "modes": "-n"}
BUILD = ("modes", "map", "reduced")


MAX_ORGANS = 10_000  # organs of one plan (a summary row each)
MAX_MODES = 2000
MAX_PROBLEMS = 12  # problems of a plan said in its one line


def load_plan(path: str | Path, *, out: str | Path | None = None) -> tuple[Path, str | None, list[dict]]:
    """(the output folder, the plan's scheduler or None, each organ's settings with the defaults
    filled in and its mesh path made absolute), the whole plan checked before any work: every key's
    type and range in [defaults] and in each organ, every problem said at once.

    Parameters
    ----------
    path : the plan file (TOML; see the module's docstring): a regular file within the size cap
        (:func:`rtfem.userfiles.read_toml`).
    out : the output folder the command line gives (``--out``); None: the plan's ``out``, which must
        stay inside the plan's folder.

    Returns
    -------
    tuple

    Raises
    ------
    RtfemError
        A plan that cannot be read (a pipe, a device, too large, not TOML, nested too deep), an
        unknown key, a value of the wrong type or range (named with its organ and key), a missing
        or unreadable mesh file, an organ name that cannot name files or is used twice, nothing to
        build, an ``out`` outside the plan's folder, a ``scheduler`` other than ``local:N`` (a
        file never chooses a remote cluster: the command line's ``--scheduler`` does).
    """
    from ..userfiles import read_toml

    path = Path(path)
    plan = read_toml(path, "plan", error=RtfemError)
    unknown = set(plan) - {"out", "scheduler", "defaults", "organ"}
    if unknown:
        raise RtfemError(f"{path}: unknown top-level key(s) {sorted(unknown)}: a plan has out, scheduler, [defaults] "
                         "and [[organ]] tables")
    defaults = plan.get("defaults", {})
    organs = plan.get("organ", [])
    if not isinstance(defaults, dict) or not isinstance(organs, list) or not organs:
        raise RtfemError(f"{path}: give at least one [[organ]] table (and [defaults] as a table)")
    if len(organs) > MAX_ORGANS:
        raise RtfemError(f"{path}: {len(organs):,} organs, more than the {MAX_ORGANS:,} a plan may have: split it")
    problems: list[str] = []
    scheduler = _plan_scheduler(plan.get("scheduler"), problems)
    folder = _plan_out(path, plan.get("out", path.stem), out, problems)
    n_before = len(problems)
    _check_table(defaults, "[defaults]", path.parent, problems)
    defaults_ok = len(problems) == n_before
    specs, names = [], set()
    for i, organ in enumerate(organs):
        where = f"organ {i + 1}" + (f" ({validate.show(organ.get('name'))})" if isinstance(organ, dict) else "")
        if not isinstance(organ, dict):
            problems.append(f"{where}: give a table")
            continue
        before = len(problems)
        _check_table(organ, where, path.parent, problems)
        if "name" not in organ:
            problems.append(f"{where}: each organ needs its own name (a file stem)")
        elif organ["name"] in names:
            problems.append(f"{where}: name {organ['name']!r} is used twice: each organ needs its own name")
        names.add(organ.get("name"))
        spec = {"build": ["modes"], "modes": 20, **defaults, **organ}
        if len(problems) == before and defaults_ok:
            spec["build"] = [b for b in BUILD if b in _as_list(spec["build"])]
            if spec.get("mesh") is not None:
                spec["mesh"] = str((path.parent / spec["mesh"]).resolve())
            _check_organ(spec, where, problems)
        specs.append(spec)
    if problems:
        more = f"; and {len(problems) - MAX_PROBLEMS} more" if len(problems) > MAX_PROBLEMS else ""
        raise RtfemError(f"{path}: {len(problems)} problem(s), nothing run: " + "; ".join(problems[:MAX_PROBLEMS]) + more)
    return folder, scheduler, specs


VOLUME_SUFFIXES = (".vtu", ".vtk", ".msh", ".mesh", ".inp")  # the files an organ is a solid from


def _as_list(value) -> list:
    return [value] if isinstance(value, str) else value


def _plan_scheduler(value, problems: list) -> str | None:
    """The plan's ``scheduler``: only ``local:N`` (N worker processes on this machine, at most its
    cores); a plan never chooses a remote cluster."""
    import os

    if value is None:
        return None
    cores = os.cpu_count() or 1
    text = value.strip() if isinstance(value, str) else ""
    n = text[6:] if text.startswith("local:") else ""
    if not (n.isdigit() and 1 <= int(n) <= cores):
        problems.append(f"scheduler = {validate.show(value)}: a plan may only ask for local:N (N from 1 to this "
                        f"machine's {cores} cores); a remote cluster is chosen on the command line, --scheduler "
                        "tcp://HOST:PORT or tls://HOST:PORT, never by a file (a Dask scheduler runs code on the client "
                        "that connects to it)")
        return None
    return text


def _plan_out(path: Path, value, given, problems: list) -> Path:
    """The output folder: --out as given, else the plan's ``out``, which must stay in the plan's folder."""
    if given is not None:
        return Path(given).resolve()
    base = path.parent.resolve()
    if not isinstance(value, str) or not value.strip():
        problems.append(f"out = {validate.show(value)}: give a folder relative to the plan, e.g. out = \"bases\"")
        return base
    folder = (base / value).resolve()
    if folder != base and base not in folder.parents:
        problems.append(f"out = {value!r} is outside the plan's folder {str(base)!r}: a plan writes only beside itself; "
                        "give a folder there, or name any folder with --out on the command line")
    return folder


def _checks() -> dict:
    """Each plan key's check: value -> None, or raises an RtfemError saying what is wrong."""
    from ..fe.solid import ELEMENTS
    from ..userfiles import file_stem

    def number(key, *, lo=None, hi=None, what=""):
        if lo is not None:
            return lambda v: validate.in_range(v, key, lo, hi, lo_open=True, hi_open=True, what=what)
        return lambda v: validate.positive(v, key, what or "a number > 0")

    def text(key, what):
        def check(v):
            if not isinstance(v, str) or not v.strip():
                raise RtfemError(f"{key} = {validate.show(v)}: give {what}")
        return check

    def materials(v):  # one law, or a list of [REGION=]LAW as --material repeated
        laws = v if isinstance(v, list) else [v]
        if not laws or len(laws) > 1000 or not all(isinstance(t, str) and t.strip() for t in laws):
            raise RtfemError(f"material = {validate.show(v)}: give a law (linear, neo-hookean, mooney-rivlin:C10,C01, "
                             "ogden:mu1,alpha1, a tissue set such as liver), or a list of REGION=LAW for a mesh of regions")

    def build(v):
        v = _as_list(v)
        if not isinstance(v, list) or not v or not all(isinstance(b, str) and b in BUILD for b in v):
            raise RtfemError(f"build = {validate.show(v)}: give a list of {', '.join(BUILD)}")

    return {
        "name": lambda v: file_stem(v, "name", error=RtfemError), "build": build,
        "mesh": text("mesh", "a mesh file's path relative to the plan"),
        "solid": lambda v: _boolean("solid", v), "element": lambda v: validate.choice(v, "element", ELEMENTS),
        "mass": lambda v: validate.choice(v, "mass", ("lumped", "consistent")),
        "fix": text("fix", "a region: a group name, AXIS<VALUE, bottom:FRACTION or nodes:i,j,k"),
        "material": materials,
        "E": number("E", what="Young's modulus in Pa"), "nu": number("nu", lo=-1.0, hi=0.5, what="Poisson's ratio"),
        "density": number("density", what="kg/m^3"), "thickness": number("thickness", what="a shell's thickness in m"),
        "scale": number("scale", what="a factor on the coordinates"),
        "edge_length": number("edge_length", what="a tet edge length in m"),
        "modes": lambda v: validate.count(v, "modes", 1, MAX_MODES),
        "derivatives": lambda v: validate.count(v, "derivatives", 1, MAX_MODES),
        "radius": number("radius", what="the map's radius of influence in m"),
        "times": lambda v: validate.times(v, "times"),
        "method": lambda v: validate.choice(v, "method", ("modal", "sldm")),
    }


def _boolean(key: str, value) -> None:
    if not isinstance(value, bool):
        raise RtfemError(f"{key} = {validate.show(value)}: give true or false")


def _check_table(table: dict, where: str, folder: Path, problems: list) -> None:
    """Every key of one table of the plan ([defaults] or an organ) known and of its type and range."""
    from ..userfiles import regular_file

    checks = _checks()
    bad = sorted(set(table) - set(KEYS), key=str)
    if bad:
        problems.append(f"{where}: unknown key(s) {bad}; known: {', '.join(KEYS)}")
    for key in KEYS:
        if key not in table:
            continue
        try:
            checks[key](table[key])
            if key == "mesh":
                regular_file(folder / table["mesh"], "mesh file", error=RtfemError)
        except RtfemError as exc:
            problems.append(f"{where}: {validate.one_line(str(exc))}")


def _check_organ(spec: dict, where: str, problems: list) -> None:
    """The organ's settings as a whole: the command line's parser takes them, the material is one."""
    from ..fe.material import Material
    from .common import material_texts, materials_from_texts

    try:
        args = _model_args(spec)
        given = materials_from_texts(material_texts(args), Material(E=args.E, nu=args.nu, thickness=args.thickness,
                                                                    density=args.density))
    except RtfemError as exc:
        problems.append(f"{where}: {validate.one_line(str(exc))}")
        return
    if isinstance(given, dict) and not _is_solid(spec):
        problems.append(f"{where}: material REGION=LAW needs a solid of regions (a volume file such as .vtu or .msh, "
                        "or solid = true), but this organ is a shell: give one material")


def _is_solid(spec: dict) -> bool:
    """Whether an organ is a solid: ``solid = true``, or a volume file."""
    return bool(spec.get("solid")) or Path(spec.get("mesh") or "x.obj").suffix.lower() in VOLUME_SUFFIXES


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
        if isinstance(value, list):  # material: each [REGION=]LAW as the flag repeated
            argv += [a for v in value for a in (flag, str(v))]
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
    from ..userfiles import file_stem, inside
    from .common import build_model

    files = {kind: inside(out, out / f"{file_stem(spec['name'], 'name')}.{kind}.npz", "organ's file") for kind in BUILD}
    model = build_model(_model_args(spec), quiet=True)
    row["nodes"], row["dof"] = model.n_nodes, model.n_dofs

    def kept(kind: str, loader):
        path = files[kind]
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
            modes.save(files["modes"])
            row["built"].append("modes")
    if "map" in spec["build"] and kept("map", lambda p: _check_map(ImpedanceMap.load(p, model=model), spec,
                                                                   modes.n_modes)) is None:
        kw = {"radius": spec.get("radius"), "method": spec.get("method", "modal")}
        if spec.get("times") is not None:
            kw["times"] = spec["times"]
        ImpedanceMap.build(model, modes=modes, n_modes=modes.n_modes, **kw).save(files["map"])
        row["built"].append("map")
    if "reduced" in spec["build"] and kept("reduced", lambda p: ReducedNonlinearModel.load(p, model)) is None:
        red = ReducedNonlinearModel(model, modes, min(int(spec.get("derivatives", 10)), modes.n_modes))
        red.train_cubature(16, tol=0.05)
        red.save(files["reduced"])
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
    from .common import check_scheduler, locking_warning, scheduler_of, warn

    address = check_scheduler(args)  # the command line's; a plan's may only be local:N
    out, planned, specs = load_plan(args.plan, out=args.out)
    for spec in specs:  # a solid: --solid, or a volume file
        locking = locking_warning(spec.get("element"), float(spec.get("nu", 0.45))) if _is_solid(spec) else None
        if locking:
            warn(f"organ {spec['name']}: {locking}")
    with scheduler_of(args, address or planned) as scheduler:
        return _run(out, specs, scheduler)


def _run(out: Path, specs: list, scheduler) -> int:
    """The organs, on ``scheduler`` (an address or a Client) or here; the summary; the exit code."""
    from ..cluster import connect, run_tasks

    from ..userfiles import inside

    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise RtfemError(f"cannot make the output folder {str(out)!r}: {exc.strerror or exc}") from None
    inside(out, out / "summary.csv", "summary")  # before any work: not a link out of the folder
    rows: list[dict] = []
    t0 = time.perf_counter()

    def collect(batch) -> None:
        for row in batch:
            rows.append(row)
            what = row["error"] or ", ".join(f"built {b}" for b in row["built"]) or "all kept"
            print(f"[{len(rows)}/{len(specs)}] {row['name']}: {what} ({row['seconds']:.1f} s)", flush=True)

    why = ""
    where = getattr(getattr(scheduler, "scheduler", None), "address", scheduler)  # a Client's address
    print(f"batch       {len(specs)} organ(s) into {out}" + (f" on {where}" if scheduler is not None else " here"),
          flush=True)
    if scheduler is not None:
        with connect(scheduler) as client:
            why = run_tasks(client, _organ_task, (str(out),), [[s] for s in specs], collect,
                            stage=lambda message: print(f"cluster     {message}", flush=True))
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
    from ..userfiles import inside

    with open(inside(out, out / "summary.csv", "summary"), "w", newline="") as fh:
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
    from .common import add_scheduler_options

    p = sub.add_parser("batch", help="precompute many organs or parameter sets (a TOML plan) into one folder",
                       description="Modal bases, impedance maps and reduced nonlinear models of every [[organ]] of "
                       "the plan, one organ a task on a Dask cluster (--scheduler) or here; what is there and valid "
                       "is kept; a summary table (summary.csv). See the manual: Precompute on a cluster.")
    p.add_argument("plan", help="the plan (TOML)")
    p.add_argument("-o", "--out", metavar="DIR", help="the output folder (default: the plan's out, a folder beside the plan)")
    add_scheduler_options(p, "the organs on a Dask cluster: tcp://HOST:PORT, tls://HOST:PORT (with --tls-*) or local:N "
                          "(N worker processes here, on loopback); a plan's scheduler may only be local:N")
    p.set_defaults(func=cmd_batch)
