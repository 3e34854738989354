"""What the ``rtfem`` commands share: progress bars (tqdm, or plain lines when stderr is not a
terminal), option parsing and checks, and building the mesh, the supports and the model from the
command line's options."""

from __future__ import annotations

import argparse
import contextlib
import sys
import time

import numpy as np

from .. import validate
from ..errors import RtfemError



class _LineProgress:
    """Plain progress lines, at most one a second (stderr is a file or a pipe: no bar to redraw)."""

    def __init__(self, label: str, unit: str, stream) -> None:
        self.label, self.unit, self.stream = label, unit, stream
        self.t0 = self._last = time.perf_counter()
        self.done = self.total = 0
        self.message = ""

    def __call__(self, done: int, total: int, message: str = "") -> None:
        self.done, self.total, self.message = done, total, message
        now = time.perf_counter()
        if now - self._last >= 1.0:
            self._last = now
            self._write(now)

    def _write(self, now: float) -> None:
        self.stream.write(f"{self.label}: {self.done}/{self.total} {self.unit} {self.message} "
                          f"({now - self.t0:.1f} s)\n")
        self.stream.flush()

    def close(self) -> None:
        self._write(time.perf_counter())


class _TqdmProgress:
    """A tqdm bar on a terminal, fed by progress(done, total, message)."""

    def __init__(self, label: str, unit: str, stream) -> None:
        from tqdm import tqdm

        self.bar = tqdm(desc=label, unit=unit, file=stream, total=None, dynamic_ncols=True, mininterval=0.1, leave=True)

    def __call__(self, done: int, total: int, message: str = "") -> None:
        bar = self.bar
        if total != bar.total:
            bar.total = total
        if message:
            bar.set_postfix_str(message, refresh=False)
        bar.update(done - bar.n)

    def close(self) -> None:
        self.bar.close()


@contextlib.contextmanager
def progress_bar(label: str, unit: str = "it", stream=None):
    """The CLI's rendering of the library's progress(done, total, message) callbacks: a tqdm bar on
    a terminal, a plain line a second otherwise (logs, CI, pipes)."""
    stream = stream or sys.stderr
    bar = _TqdmProgress(label, unit, stream) if stream.isatty() else _LineProgress(label, unit, stream)
    try:
        yield bar
    finally:
        bar.close()


# ---------------------------------------------------------------- option types (argparse type= checks)
def _option(check, parse=float, expect: str = "a number"):
    """An argparse ``type=``: the text parsed by ``parse``, then checked by a :mod:`rtfem.validate`
    rule (the same rules as the library's arguments); a refusal becomes argparse's one-line error."""

    def convert(text: str):
        try:
            value = parse(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not {expect}") from None
        try:
            return check(value)
        except RtfemError as exc:
            raise argparse.ArgumentTypeError(validate.one_line(str(exc))) from None

    return convert


def _comma_floats(text: str) -> list[float]:
    """'0.01,0.1,0.5' -> [0.01, 0.1, 0.5]; empty items are an error."""
    parts = [t.strip() for t in text.split(",")]
    if any(not t for t in parts):
        raise ValueError(text)
    return [float(t) for t in parts]


positive = _option(lambda x: validate.positive(x, "value"))
nonnegative = _option(lambda x: validate.nonnegative(x, "value"))
fraction = _option(lambda x: validate.in_range(x, "value", 0.0, 1.0, hi_open=True))
open_fraction = _option(lambda x: validate.in_range(x, "value", 0.0, 1.0, lo_open=True, hi_open=True))
poisson = _option(lambda x: validate.in_range(x, "nu", -1.0, 0.5, lo_open=True, hi_open=True, what="Poisson's ratio"))
count = _option(lambda x: validate.count(x, "value", 1), int, "a whole number")
mode_count = _option(lambda x: validate.count(x, "value", 1, what="ask for at least one mode"), int, "a whole number")
port = _option(lambda x: validate.count(x, "port", 0, 65535), int, "a whole number")
time_list = _option(lambda x: validate.times(x, "times").tolist(), _comma_floats,
                    "a comma-separated list of times in s, e.g. 0.01,0.1,0.5")


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors: ``rtfem: error: ...`` and exit 2, no usage dump."""

    def error(self, message: str):  # type: ignore[override]
        cmd = self.prog.split()[-1] if " " in self.prog else ""
        hint = f"; see rtfem {cmd} --help" if cmd else "; see rtfem --help"
        if message.startswith("argument --material: expected one argument"):  # --material -1=LAW: '-1=...' read as a flag
            hint = "; a value starting with '-' (a region labelled -1) is given as --material=-1=LAW" + hint
        self.exit(2, f"rtfem: error: {_one_line(message)}{hint}\n")


def _one_line(text) -> str:
    return validate.one_line(str(text))


def _vector(text: str, what: str) -> np.ndarray:
    try:
        v = np.array([float(x) for x in text.split(",")])
    except ValueError:
        raise RtfemError(f"{what}={text!r}: give three numbers separated by commas, e.g. 0.05,0.05,0") from None
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise RtfemError(f"{what}={text!r}: give three finite numbers separated by commas")
    return v


def load_mesh_arg(path: str | None, scale: float = 1.0, solid: bool | str = False, edge_length: float | None = None):
    """The mesh of a command: the file (a TetMesh for a volume file), or the embedded liver; with
    ``solid`` a surface is meshed into tets first (kept on disk, so a second run reuses them);
    ``solid="auto"``: a closed surface is, an open one is not."""
    from ..mesh import meshes
    from ..mesh.files import load_mesh
    from ..mesh.meshing import cached_tetrahedralize, is_cached, mesher_available
    from ..mesh.tetmesh import TetMesh

    embedded = path is None and edge_length is None  # the shipped tets: no mesher needed
    if solid == "auto" and not embedded and not mesher_available():
        print("shell       the mesh extra (pytetwild) is not installed, so the surface is modelled as a shell; "
              "pip install 'rtfem[mesh]' (make installs it) to mesh a closed organ into tets", flush=True)
        solid = False
    if path is None:
        _check_organ_size(meshes.liver(), "the embedded liver", scale, factor=scale)  # before any meshing
        if solid:  # True, or "auto": the embedded liver is closed
            spacing = None if edge_length is None else edge_length / scale
            if not embedded and not is_cached(meshes.liver(3), spacing):
                print("meshing     the embedded liver into tets (fTetWild, a few seconds; kept for later runs) ...",
                      flush=True)
            mesh = meshes.liver(solid=True, spacing=spacing)
        else:
            mesh = meshes.liver()
        return mesh if scale == 1.0 else mesh.scaled(scale)
    mesh = load_mesh(path, scale=scale)
    _check_organ_size(mesh, path, scale)
    if solid == "auto" and not isinstance(mesh, TetMesh):
        solid = mesh.is_closed()
        if not solid:
            print(f"surface     {path} is open: modelled as a shell", flush=True)
    if solid and not isinstance(mesh, TetMesh):
        print(f"meshing     {path} into tets (fTetWild) ...", flush=True)
        mesh = cached_tetrahedralize(mesh, edge_length)
    return mesh


SMALLEST_ORGAN = 1e-3  # m: a mesh smaller than this across is a units mistake (a scale given twice, microns)


def _check_organ_size(mesh, name: str, scale: float, factor: float = 1.0) -> None:
    """Refuse a mesh under :data:`SMALLEST_ORGAN` across (times ``factor``, the scale still to be
    applied): the commands read coordinates as metres, and an organ (or a tissue sample) is
    millimetres to metres across."""
    lo, hi = mesh.bounds()
    size = float(np.max(hi - lo)) * factor
    if size < SMALLEST_ORGAN:
        hint = f" after --scale {scale:g}" if scale != 1.0 else ""
        raise RtfemError(f"{name} is {size:.3g} m across{hint}: the commands read coordinates as metres and an organ is "
                         f"at least {SMALLEST_ORGAN * 1e3:g} mm across; check --scale (1e-3 turns millimetres into "
                         "metres; a file already in metres needs none)")


def fixed_nodes(mesh, spec: str | None, option: str = "--fix") -> tuple[np.ndarray, str]:
    """Parse a region (--fix, --nodes) with :func:`rtfem.select_nodes`; None: the group 'attachment' if
    the mesh has one, else bottom:0.1. An empty region is refused."""
    from ..mesh.selection import describe_selection

    if spec is None:
        spec = "attachment" if "attachment" in mesh.groups else "bottom:0.1"
    nodes, how = describe_selection(mesh, spec, option)
    if nodes.size == 0:
        what = "nothing would hold the organ" if option == "--fix" else "nothing to load"
        raise RtfemError(f"{option} {spec!r} selects no vertex: {what}; choose another region")
    return nodes, how


def add_model_options(p: argparse.ArgumentParser, *, dynamics: bool = True) -> None:
    from ..fe.material import Material

    m = Material()
    p.add_argument("mesh", nargs="?", help="mesh file (OBJ, STL, PLY, OFF, VTK, VTU, MSH, ...); default: the embedded liver")
    p.add_argument("--scale", type=positive, default=1.0, help="coordinate scale factor (1e-3 turns mm into m)")
    g = p.add_argument_group("solid (tetrahedral) models: a volume file (VTU/VTK/MSH/MESH/INP with tets) is one already")
    g.add_argument("--solid", action="store_true",
                   help="mesh a surface into tets (fTetWild, the mesh extra) and model the volume instead of a shell")
    g.add_argument("--edge-length", type=positive, default=None, metavar="M",
                   help="target tet edge length in m for --solid (default 5 %% of the organ's diagonal)")
    g.add_argument("--element", choices=("tet4", "tet10", "tet4-anp"), default="tet10",
                   help="tet10 (quadratic, the default: does not lock at nu = 0.45), tet4 (linear, fast; too stiff "
                        "for nearly incompressible tissue) or tet4-anp (tet4 with an averaged nodal pressure: no "
                        "volumetric locking; the linear methods, and the full-order nonlinear ones with a --material law)")
    g.add_argument("--mass", choices=("lumped", "consistent"), default="lumped", help="solid mass matrix (default lumped)")
    g = p.add_argument_group("material and supports")
    g.add_argument("--E", type=positive, default=m.E, help=f"Young's modulus in Pa (default {m.E:g})")
    g.add_argument("--nu", type=poisson, default=m.nu, help=f"Poisson's ratio (default {m.nu:g})")
    g.add_argument("--thickness", type=positive, default=m.thickness, help=f"shell thickness in m (default {m.thickness:g})")
    g.add_argument("--density", type=positive, default=m.density, help=f"density in kg/m^3 (default {m.density:g})")
    g.add_argument("--material", action="append", default=None, metavar="[REGION=]LAW",
                   help="a solid's material law: linear (default; corotated in the nonlinear methods), neo-hookean "
                        "(mu and kappa of --E and --nu; linear:E[,nu] and neo-hookean:E[,nu] their own), "
                        "mooney-rivlin:C10,C01 or ogden:mu1,alpha1[,mu2,alpha2...] (Pa; kappa keeps --nu's ratio to mu), "
                        "each optionally +prony:g1,tau1[,g2,tau2...] (its isochoric stress relaxing: --method direct "
                        "--large or nonlinear), or a sourced tissue set (liver, skin, ...: rt.tissue). The nonlinear "
                        "methods use the law, the linear ones its linearization at rest (a relaxing law's long-term one). "
                        "A mesh with regions: repeat it as REGION=LAW (a region's name or label), e.g. "
                        "--material liver --material tumor=linear:3e5 (a region not named takes the LAW given "
                        "without one: linear of --E and --nu if none is)")
    g.add_argument("--fix", default=None, metavar="REGION",
                   help="fixed nodes: a group name, AXIS<VALUE or AXIS>VALUE (m), bottom:FRACTION or nodes:i,j,k "
                        "(default: the group 'attachment' if the mesh has one, else bottom:0.1)")
    if dynamics:
        g = p.add_argument_group("dynamics")
        g.add_argument("-n", "--modes", type=mode_count, default=40, help="number of modes r (default 40)")
        g.add_argument("--alpha", type=nonnegative, default=8.0, help="mass-proportional damping B = alpha M, 1/s (default 8)")
        g.add_argument("--dt", type=positive, default=1e-3, help="time step in s (default 1e-3: a 1 kHz haptic loop)")
        g.add_argument("--large", action="store_true",
                       help="large deformation: modal warping for the modal method, the corotational full order (Newton "
                            "per step) for direct")


def mesh_of_args(args):
    return load_mesh_arg(args.mesh, args.scale, _solid_wanted(args), args.edge_length)


def _solid_wanted(args):
    """--solid (True), --shell or a command without it (False); ``rtfem view`` without either:
    "auto", a closed surface is a solid organ, an open one (a hollow organ) a shell."""
    if args.solid or not hasattr(args, "shell"):
        return bool(args.solid)
    return False if args.shell else "auto"


def model_options(args, mesh) -> dict:
    """The model options the arguments give for this mesh (a solid's element and mass)."""
    from ..mesh.tetmesh import TetMesh

    return {"element": args.element, "mass": args.mass} if isinstance(mesh, TetMesh) else {}


def warn(text: str) -> None:
    """A warning of the command line: one line on stderr (the work goes on)."""
    print(f"rtfem: warning: {_one_line(text)}", file=sys.stderr, flush=True)


LOCKING_NU = 0.49  # plain tet4 at or above this Poisson's ratio locks


def locking_warning(element: str | None, nu: float) -> str | None:
    """What a model of plain tet4 at nu >= :data:`LOCKING_NU` deserves to be told (None otherwise)."""
    if element != "tet4" or nu < LOCKING_NU:
        return None
    return (f"tet4 at nu = {nu:g} locks: linear tets of a nearly incompressible material are far too stiff "
            "(displacements and frequencies wrong by factors, worse as nu nears 0.5); use --element tet4-anp or tet10")


def build_model(args, *, quiet: bool = False):
    from ..fe.linalg import preload

    preload()  # MKL loads on the other core while the mesh is read and the model assembled (issue 54)
    from ..fe.material import Material
    from ..fe.build import make_model
    from ..fe.tissues import tissue_from_text
    from ..mesh.tetmesh import TetMesh

    base = Material(E=args.E, nu=args.nu, thickness=args.thickness, density=args.density)
    texts = material_texts(args)  # a bad --material before any work
    material = materials_from_texts(texts, base)
    mesh = mesh_of_args(args)
    locking = locking_warning(args.element, args.nu) if isinstance(mesh, TetMesh) else None
    if isinstance(material, dict):
        material = region_materials_of(material, mesh)
    elif isinstance(mesh, TetMesh) and mesh.regions.size > 1 and not quiet:
        names = {v: k for k, v in mesh.region_names.items()}
        warn(f"the mesh has {mesh.regions.size} regions ({', '.join(names.get(int(r), str(r)) for r in mesh.regions)}); "
             "this command gives them all one material (a material per region: --material REGION=LAW for each, a "
             "scene file's material table, or rt.SolidModel(mesh, {label: material}))")
    if locking and not quiet:
        warn(locking)
    nodes, how = fixed_nodes(mesh, args.fix)
    model = make_model(mesh, material, **model_options(args, mesh))
    model.fix(nodes)
    model.check_restrained()
    if not quiet:
        name = args.mesh or ("embedded default liver" + (", solid" if isinstance(mesh, TetMesh) else ""))
        if isinstance(mesh, TetMesh):
            size = (f"{model.n_nodes:,} nodes, {mesh.n_tets:,} {args.element} tets, "
                    f"{model.mesh.n_triangles:,} surface triangles")
        else:
            size = f"{mesh.n_vertices:,} vertices, {mesh.n_triangles:,} triangles"
        print(f"model       {name}: {size}, {model.n_dofs:,} dof; {nodes.size} nodes fixed ({how})")
        if getattr(model, "materials", None) is not None:
            names = {v: k for k, v in mesh.region_names.items()}
            for label, law in model.materials.items():
                print(f"region      {names.get(label, label)} (label {label}, {int(np.sum(mesh.labels == label)):,} tets): "
                      f"{law!r}")
        elif getattr(model, "law", None) is not None:
            lin = model.material
            print(f"material    {model.law!r} (the linear methods use its linearization at rest: E = {lin.E:.4g} Pa, "
                  f"nu = {lin.nu:.4g})")
        for _, text in texts:
            source = tissue_from_text(text, Material(E=args.E, nu=args.nu, density=args.density))
            if source is not None:  # a sourced set: where it was read, how sure, what was not in it
                print("tissue      " + str(source).replace("\n", "\n            "))
    return model


def material_texts(args) -> list[tuple[str | None, str]]:
    """The ``--material`` options as (region or None, law text): "linear" when none is given."""
    given = getattr(args, "material", None) or ["linear"]
    if isinstance(given, str):  # a batch plan's one material
        given = [given]
    out, plain = [], 0
    for text in given:
        region, eq, law = str(text).rpartition("=")  # a law has no '=': a region's name may
        if not eq:
            region, law = law, ""
        if eq and not region.strip():
            raise RtfemError(f"--material {text!r}: name the region before '=' (REGION=LAW), or give LAW alone")
        out.append((region.strip() if eq else None, (law if eq else region).strip()))
        plain += not eq
    if plain > 1:
        raise RtfemError(f"--material is given {plain} times without a region: give one LAW, and REGION=LAW for "
                         "each region that differs from it")
    if not plain:  # the regions not named: the default law (linear, of --E and --nu)
        out.append((None, "linear"))
    return out


def materials_from_texts(texts, base):
    """One material (no region named) or {region key: material} with the plain LAW under None."""
    from ..fe.viscoelastic import material_from_text

    if all(region is None for region, _ in texts):
        return material_from_text(texts[0][1], base)
    out = {}
    for region, text in texts:
        if region in out:
            raise RtfemError(f"--material: region {region!r} is given two materials")
        out[region] = material_from_text(text, base)
    return out


def region_materials_of(given: dict, mesh) -> dict:
    """{label: material} for every region of ``mesh`` from the command line's (the plain LAW for
    the regions not named; a region by its name, else by the label it spells); a shell refused."""
    from ..fe.regions import region_materials
    from ..mesh.tetmesh import TetMesh

    if not isinstance(mesh, TetMesh):
        raise RtfemError("--material REGION=LAW: the model is a shell; give one --material LAW (regions come from a "
                         "volume file's region data, or rtfem mesh LABELS)")
    given = dict(given)
    default = given.pop(None, None)
    names = {v: k for k, v in mesh.region_names.items()}
    merged = dict(given)
    if default is not None:
        merged.update({label: default for label in mesh.regions.tolist() if not _names(label, given, names)})
    return region_materials(merged, mesh)


def _names(label: int, given: dict, names: dict) -> bool:
    """Whether a key of ``given`` (a REGION as typed) names region ``label`` (its name or its label)."""
    return names.get(label) in given or (str(label) in given and str(label) not in names)


def damping_of(args):
    from ..fe.material import Damping

    return Damping(alpha=args.alpha)


MAX_STEPS = 2_000_000  # steps of one `rtfem simulate` run (each keeps a CSV row in memory)
MAX_FRAMES = 10_000  # VTU frames of one run


def _modes(model, args, *, quiet=False):
    """The r lowest modes of ``model``, through the precompute cache (rtfem.cache)."""
    from ..reduction.precompute import cached_modes

    r = args.modes
    if r < 1:
        raise RtfemError(f"--modes {r}: ask for at least one mode")
    if quiet:
        return cached_modes(model, r)
    with progress_bar(f"modes (r = {r})", unit="solve") as bar:
        return cached_modes(model, r, progress=bar)


# ---------------------------------------------------------------- a Dask cluster (--scheduler)
def add_scheduler_options(p: argparse.ArgumentParser, what: str) -> None:
    """--scheduler (``what`` says what runs there) and Dask's TLS certificates for tls:// addresses."""
    p.add_argument("--scheduler", metavar="ADDRESS", help=what + ". Dask runs code from any client that reaches its "
                   "scheduler, and this one unpickles what comes back: across a network use tls:// (see the manual: "
                   "Precompute on a cluster)")
    g = p.add_argument_group("a cluster over TLS (--scheduler tls://HOST:PORT; Dask's certificates, PEM files)")
    g.add_argument("--tls-ca-file", metavar="PEM", help="the CA certificate(s) that signed the scheduler's certificate "
                   "and this client's")
    g.add_argument("--tls-cert", metavar="PEM", help="this client's certificate, signed by that CA")
    g.add_argument("--tls-key", metavar="PEM", help="this client's private key (when the --tls-cert file does not hold it)")
    p.add_argument("--stall-timeout", metavar="S", type=positive, default=None,
                   help="with --scheduler: stop when for S seconds no result has come back and no task has run "
                        "(default 600; and when no worker is left for min(S, 30) s), keeping what came back")


def check_scheduler(args) -> str | None:
    """The command line's --scheduler, checked before any work: its form, the TLS files a tls:// address
    needs (each a regular file), and a warning for plain tcp:// beyond this machine. None: here."""
    from ..cluster import check_address, is_loopback
    from ..userfiles import regular_file

    tls = {"--tls-ca-file": getattr(args, "tls_ca_file", None), "--tls-cert": getattr(args, "tls_cert", None),
           "--tls-key": getattr(args, "tls_key", None)}
    address = None if args.scheduler is None else check_address(args.scheduler)
    given = [flag for flag, v in tls.items() if v is not None]
    if given and not (address or "").startswith("tls://"):
        raise RtfemError(f"{', '.join(given)}: the certificates are for --scheduler tls://HOST:PORT")
    if address is None:
        if getattr(args, "stall_timeout", None) is not None:
            raise RtfemError("--stall-timeout is for a run on a cluster: give --scheduler too")
        return None
    if address.startswith("tls://"):
        missing = [flag for flag in ("--tls-ca-file", "--tls-cert") if tls[flag] is None]
        if missing:
            raise RtfemError(f"--scheduler {address}: a tls:// scheduler needs {' and '.join(missing)} (and --tls-key "
                             "when the certificate file does not hold the key): the CA's certificate and this client's, "
                             "signed by it")
        for flag, value in tls.items():
            if value is not None:
                regular_file(value, f"{flag} file", error=RtfemError)
    elif address.startswith("tcp://") and not is_loopback(address):
        warn(f"--scheduler {address} is plain tcp://: neither encrypted nor authenticated, so whoever reaches that "
             "scheduler (or sits between) can run code on this machine through Dask; use tls:// with certificates, "
             "or a private network you trust")
    return address


@contextlib.contextmanager
def _quiet_dask(address: str | None):
    """With a scheduler, Dask's own log records (a lost scheduler's reconnect tracebacks, ~35 lines)
    are kept off stderr: the command says in one line why a run stopped."""
    import logging

    if address is None:
        yield
        return
    loggers = [logging.getLogger(name) for name in ("distributed", "distributed.client", "distributed.comm")]
    levels = [log.level for log in loggers]
    for log in loggers:
        log.setLevel(logging.CRITICAL + 1)
    try:
        yield
    finally:
        for log, level in zip(loggers, levels):
            log.setLevel(level)


@contextlib.contextmanager
def scheduler_of(args, address: str | None):
    """What the library's ``scheduler=`` takes for the checked ``address`` (:func:`check_scheduler`):
    None (here), the address (tcp://, local:N), or a Client connected over TLS with the --tls-*
    certificates (closed on exit)."""
    from ..cluster import STALL_TIMEOUT, connect, security, stall_timeout

    with stall_timeout(getattr(args, "stall_timeout", None) or STALL_TIMEOUT), _quiet_dask(address):
        if address is None or not address.startswith("tls://"):
            yield address
            return
        with connect(address, security=security(args.tls_ca_file, args.tls_cert, args.tls_key)) as client:
            yield client
