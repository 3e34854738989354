"""Scene files: a :class:`~rtfem.Scene` from TOML (read with the standard library's ``tomllib``).

::

    gravity = [0, 0, -9.81]        # m/s^2 (default: this)
    dt = 0.001                     # s (default)
    friction = 0.2                 # Coulomb between bodies (default 0)
    view = [0.2, 0.8, -0.5]        # rtfem view: the camera's direction from the scene's centre

    [[body]]
    name = "box"
    mesh = "box.vtu"               # a path relative to this file (a surface with kind = "solid" is meshed
                                   # into tets), or an embedded mesh: "rtfem:liver", "rtfem:gallbladder:3"
    scale = 1.0                    # coordinates' factor (1e-3: a mesh in mm)
    rotate = [90, 0, 30]           # degrees about the scene's x, then y, then z axis (extrinsic), about the
                                   # file's origin (after scale); default none
    translate = [0.2, 0, 0.005]    # then moved by this (m): the body's rest is R (scale X) + translate
    kind = "solid"                 # or "shell" (default: a volume file is a solid, a surface a shell)
    element = "tet10"              # solids: tet4 or tet10 (default tet10)
    material = { E = 3e4, nu = 0.45, density = 1060, thickness = 0.004 }   # law = "linear" (the default)
    # or any law --material takes (solids; the modal body uses its linearization at rest):
    # material = { law = "neo-hookean", mu = 3000, kappa = 30000, density = 1060 }       (or E and nu)
    # material = { law = "mooney-rivlin", c10 = 500, c01 = 200, kappa = 30000 }         (or nu for kappa)
    # material = { law = "ogden", mu = [2000], alpha = [8], nu = 0.45, prony = { g = [0.5], tau = [0.1] } }
    # material = { tissue = "liver#2", density = 1060 }   # a sourced set (rt.tissue), as --material liver#2
    # or, for a tet mesh of regions (mesh.labels), a table per label or region name:
    # material = { liver = { E = 3e4 }, tumor = { law = "neo-hookean", mu = 1e5, kappa = 1e6 } }
    fix = "bottom:0.1"             # a node selection (rt.select_nodes) of the placed body; absent: a free body
    modes = 20                     # the modal basis (a free body's six rigid-body modes among them)
    alpha = 10.0                   # mass-proportional damping (1/s)

    [[obstacle]]
    name = "table"
    plane = { point = [0, 0, 0], normal = [0, 0, 1] }
    friction = 0.3

    [[obstacle]]                   # a fixed rigid surface: its triangles' winding gives the free side
    name = "spine"
    mesh = "spine.stl"             # a path relative to this file (scale as for bodies)

    [[attachment]]                 # springs holding nodes of a body (ligaments, vessels)
    name = "ligament"
    body = "box"
    nodes = "z>0.049"              # a node selection of that body
    to = "world"                   # or another body's name: each node to its nearest surface node
    stiffness = 500.0              # each spring (N/m)

    [[tool]]                       # a probe or a grasper on a scripted hand
    name = "grasper"
    kind = "grasper"               # or "probe" (a sphere of radius, pressing)
    radius = 0.01                  # the probe's radius; the grasper's reach from its tip (m)
    stiffness = 300.0              # probe: its virtual coupling (absent: at the hand); grasper: its hold (N/m)
    friction = 0.0                 # probe: Coulomb against the bodies
    path = [[0, 0.05, 0.05, 0.06], [0.5, 0.05, 0.05, 0.049]]   # rows t, x, y, z (s, m): linear between
    closed = [[0.6, 2.0]]          # grasper: closed from t_on to t_off (s)

    [[tool]]                       # a scalpel cutting a body as it goes (issue 57): that body runs full order
    name = "knife"                 # (a lagged corotational step; element = "tet4"; its alpha damps it) and
    kind = "scalpel"               # its cut faces become surface
    body = "box"                   # the body it cuts
    blade = [0, 0, 0.03]           # m, from the tip (the path's point) to the heel (default: this)
    toughness = 164.0              # J/m^2: the cutting resistance per unit area opened (default: liver's)
    path = [[0, 0.05, -0.01, 0.04], [1, 0.05, 0.03, 0.04]]   # the tip; closed = [[t_on, t_off]]: cuts then only

    [[tool]]                       # a probe or a grasper on a live hand (rtfem view; a grasper closes on
    name = "probe"                 # the device's first button)
    device = "igtl"                # openhaptics, forcedimension, haply or igtl (rtfem devices: which are here)
    max_force = 5.0                # the most the device renders (N; default 10)
    port = 18944                   # igtl: the OpenIGTLink port; haply: url = "ws://localhost:10001" (this machine)

Every error names the file, the table (``[[body]] 2 "box"``) and the key, and says what it needs.
The file is read as :func:`rtfem.userfiles.read_toml` reads one (a regular file within a size cap,
nested at most 16 deep); names are ones that may name files (``rtfem simulate`` writes a folder per
body: no path separators, no control or bidirectional-text characters); at most
:data:`MAX_TABLES` tables of each kind; a scripted path stays within 1 km of the origin. All of this
is checked before any device is opened or any body meshed.
A live device is opened before any precompute (a missing SDK is said at once), fitted to the
bodies' bounds where it has a workspace to fit, and closed again if the file turns out bad; close
them with :func:`close_devices` when done.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .. import validate
from ..errors import ModelError, RtfemError
from .scene import Scene

__all__ = ["load_scene", "close_devices", "BODY_KEYS", "OBSTACLE_KEYS", "ATTACHMENT_KEYS", "TOOL_KEYS"]

TOP_KEYS = {"gravity", "dt", "friction", "view", "body", "obstacle", "attachment", "tool"}
BODY_KEYS = {"name", "mesh", "scale", "rotate", "translate", "kind", "element", "material", "fix", "modes", "alpha"}
OBSTACLE_KEYS = {"name", "plane", "mesh", "scale", "friction"}
ATTACHMENT_KEYS = {"name", "body", "nodes", "to", "stiffness"}
TOOL_KEYS = {"name", "kind", "radius", "stiffness", "friction", "path", "closed", "device", "max_force", "url", "port",
             "body", "blade", "toughness"}
SCALPEL_KEYS = {"body", "blade", "toughness"}  # a scalpel's alone; radius, stiffness and friction are not its
BUILTIN = "rtfem:"  # mesh = "rtfem:liver" names an embedded mesh
#: the most tables of each kind a scene file may have: each body is meshed and reduced before the first
#: step (seconds to minutes each), and every step solves one contact problem over all of them
MAX_TABLES = {"body": 32, "obstacle": 64, "attachment": 256, "tool": 32}
MAX_GRAVITY = 1e3  # m/s^2
MAX_PLACE = 1e3  # m: a body placed within 1 km of the origin (as a scripted path)
MAX_BLADE = 1.0  # m: a scalpel's blade at most this long


class _Where:
    """Names a place in the file for messages, and checks one value there."""

    def __init__(self, path: Path, table: str) -> None:
        self.path, self.table = path, table

    def error(self, key: str | None, what: str) -> ModelError:
        at = f"{self.path}: {self.table}" + (f": key {key!r}" if key else "")
        return ModelError(f"{at}: {what}")

    def check(self, key: str, fn, *args, **kw):
        try:
            return fn(*args, **kw)
        except RtfemError as exc:
            raise self.error(key, str(exc)) from None

    def keys(self, table: dict, allowed: set, required: tuple = ()) -> None:
        for k in required:
            if k not in table:
                raise self.error(k, "missing")
        for k in table:
            if k not in allowed:
                raise self.error(k, f"unknown (known: {', '.join(sorted(allowed))})")


def load_scene(path, *, progress=None, dt: float | None = None, live: bool = True) -> Scene:
    """The scene a TOML file describes (see the module's docstring), its bodies' modes computed.

    Parameters
    ----------
    path : the scene file.
    progress : ``progress(message)`` called before each body's precompute (a line for the CLI).
    dt : the bodies' time step (s) instead of the file's (the viewer's, to keep real time).
    live : open the tools' live devices (False: a tool on a device is refused, as for a headless run).

    Returns
    -------
    Scene

    Raises
    ------
    ModelError
        A file that is not TOML, an unknown, missing or bad key (the message names the file, the
        table and the key), a mesh file that cannot be read, a body that cannot be modelled.
    """
    from ..userfiles import read_toml

    p = Path(validate.path_like(path, "path"))
    doc = read_toml(p, "scene file")  # a regular file within the size cap, nested at most 16 deep
    top = _Where(p, "the top level")
    top.keys(doc, TOP_KEYS)
    _check_counts(doc, top)
    gravity = top.check("gravity", validate.vector, doc.get("gravity", (0.0, 0.0, -9.81)), "gravity", 3)
    if not np.linalg.norm(gravity) <= MAX_GRAVITY:
        raise top.error("gravity", f"{np.asarray(gravity).tolist()} m/s^2 is more than {MAX_GRAVITY:g} m/s^2 (100 g): "
                        "give the acceleration in m/s^2, e.g. [0, 0, -9.81]")
    dt = top.check("dt", validate.time_step, doc.get("dt", 1e-3) if dt is None else dt, "dt")
    friction = top.check("friction", validate.in_range, doc.get("friction", 0.0), "friction", 0.0, 10.0,
                         what="Coulomb's coefficient between bodies")
    scene = Scene(gravity, friction=friction)
    if "view" in doc:
        view = top.check("view", validate.vector, doc["view"], "view", 3)
        if not np.linalg.norm(view) > 0:
            raise top.error("view", "must be a non-zero direction: where the viewer's camera looks from")
        scene.view = np.asarray(view, dtype=float)
    bodies, obstacles = doc.get("body", []), doc.get("obstacle", [])
    if not isinstance(bodies, list) or not bodies:
        raise top.error("body", "a scene needs at least one [[body]] table")
    tools = doc.get("tool", [])
    tools = tools if isinstance(tools, list) else [tools]
    devices: dict[int, object] = {}
    try:  # the live devices first: a missing SDK is said before any precompute
        for i, table in enumerate(tools):
            if isinstance(table, dict) and "device" in table:
                devices[i] = _open_device(table, _Where(p, _table_name("tool", i, table)), live)
        places = [_Where(p, _table_name("tool", i, table)) for i, table in enumerate(tools)]
        tools = [(where, _tool(table, where, devices.get(i))) for i, (table, where) in enumerate(zip(tools, places))]
        _fill(scene, doc, p, bodies, obstacles, tools, devices, dt, progress)
    except BaseException:
        for device in devices.values():
            device.close()
        raise
    return scene


def _check_counts(doc: dict, top: _Where) -> None:
    """Each kind of table within :data:`MAX_TABLES`, and every table's name one that may name files,
    before any device is opened or any body meshed."""
    from ..userfiles import file_stem

    for kind, most in MAX_TABLES.items():
        tables = doc.get(kind, [])
        tables = tables if isinstance(tables, list) else [tables]
        if len(tables) > most:
            raise top.error(kind, f"{len(tables):,} [[{kind}]] tables, more than the {most} a scene may have: "
                            + ("each body is meshed and its modes computed before the first step (seconds to minutes "
                               "each), and every step solves the contacts of all of them together" if kind == "body"
                               else "every step works through each of them"))
        for i, table in enumerate(tables):
            if isinstance(table, dict) and "name" in table:
                where = _Where(top.path, _table_name(kind, i, table))
                where.check("name", file_stem, table["name"], "the name")


def close_devices(scene: Scene) -> None:
    """Close the scene's tools' and scalpels' devices (a scene file's live hands) and the scalpels' cut
    workers; closing twice does nothing."""
    for tool in (*scene.tools, *scene.scalpels):
        close = getattr(tool.device, "close", None)
        if close is not None:
            close()
    for scalpel in scene.scalpels:
        scalpel.close()


def _open_device(table: dict, where: _Where, live: bool):
    from urllib.parse import urlsplit

    from .devices import DEVICES, open_device

    if not live:
        raise where.error("device", f"{table['device']!r} is a live hand, which `rtfem view` runs; a headless run "
                                    "needs a scripted path = [[t, x, y, z], ...]")
    name = where.check("device", validate.choice, table["device"], "device", DEVICES)
    for key in ("path", "closed"):
        if key in table:
            raise where.error(key, "a tool follows a scripted path or a live device, not both")
    for key, only in (("url", "haply"), ("port", "igtl")):
        if key in table and name != only:
            raise where.error(key, f"is for device = {only!r}")
    max_force = where.check("max_force", validate.positive, table.get("max_force", 10.0), "max_force",
                            "the largest force the device renders, in N")
    url = table.get("url", "ws://localhost:10001")
    if not isinstance(url, str) or not url.startswith(("ws://", "wss://")):
        raise where.error("url", f"{validate.show(url)}: give the Haply Inverse Service's ws:// address")
    host = urlsplit(url).hostname or ""
    if not (host == "localhost" or host.startswith("127.") or host == "::1"):
        raise where.error("url", f"{validate.show(url)}: a scene file names a device on this machine only (localhost, "
                          "127.0.0.1, [::1]); a file never chooses where rtfem connects. For a service elsewhere, use "
                          "rtfem view --device haply --haply-url on the command line")
    port = where.check("port", validate.count, table.get("port", 18944), "port", 1, 65535, what="a TCP port")
    return where.check("device", open_device, name, max_force, url, port)


def _fill(scene: Scene, doc: dict, p: Path, bodies, obstacles, tools, devices: dict, dt: float, progress) -> None:
    """The file's bodies, obstacles, attachments and ``tools`` (checked: (where, what add_tool takes))
    into ``scene`` (the live ``devices`` opened)."""
    names = [table.get("name") for table in bodies if isinstance(table, dict)]
    for where, (_, _, kind, options) in tools:
        if kind == "scalpel" and options["body"] not in names:
            raise where.error("body", f"no body named {validate.show(options['body'])} (bodies: "
                              f"{', '.join(map(str, names))})")
    cut = {options["body"] for _, (_, _, kind, options) in tools if kind == "scalpel"}
    for i, table in enumerate(bodies):
        where = _Where(p, _table_name("body", i, table))
        if progress is not None:
            progress(f"body {table.get('name', i + 1)}: " + ("full order (a scalpel cuts it) ..." if table.get("name") in cut
                                                              else "modes ..."))
        _add_body(scene, table, where, p.parent, dt, full=table.get("name") in cut)
    for i, table in enumerate(obstacles if isinstance(obstacles, list) else [obstacles]):
        where = _Where(p, _table_name("obstacle", i, table))
        _add_obstacle(scene, table, where, p.parent)
    attachments = doc.get("attachment", [])
    for i, table in enumerate(attachments if isinstance(attachments, list) else [attachments]):
        where = _Where(p, _table_name("attachment", i, table))
        if not isinstance(table, dict):
            raise where.error(None, "must be a table")
        where.keys(table, ATTACHMENT_KEYS, ("name", "body", "nodes"))
        names = [b.name for b in scene.bodies]
        for key in ("body", "to"):
            if key in table and table[key] not in names and not (key == "to" and table[key] == "world"):
                raise where.error(key, f"no body named {table[key]!r} (bodies: {', '.join(names)}"
                                  + (", or 'world')" if key == "to" else ")"))
        to = table.get("to", "world")
        where.check("stiffness", validate.positive, table.get("stiffness", 500.0), "stiffness", "a spring in N/m")
        where.check("nodes", scene.attach, table["name"], table["body"], table["nodes"],
                    None if to == "world" else to, stiffness=table.get("stiffness", 500.0))
    for where, (name, device, kind, options) in tools:  # checked before the bodies (_tool)
        if kind == "scalpel":
            where.check("name", scene.add_scalpel, name, options.pop("body"), device, **options)
        else:
            where.check("name", scene.add_tool, name, device, kind=kind, **options)
    if devices:  # the devices' workspaces fitted to the bodies (where the adapter fits one)
        X = np.concatenate([b.X[b.surface] for b in scene.bodies])
        for device in devices.values():
            attach = getattr(device, "attach", None)
            if attach is not None:
                attach((X.min(axis=0), X.max(axis=0)))


def _add_obstacle(scene: Scene, table, where: _Where, folder: Path) -> None:
    from ..mesh.files import load_mesh
    from ..mesh.tetmesh import TetMesh

    if not isinstance(table, dict):
        raise where.error(None, "must be a table")
    where.keys(table, OBSTACLE_KEYS, ("name",))
    if ("plane" in table) == ("mesh" in table):
        raise where.error("plane", "give plane = { point, normal } or mesh = a surface file, one of them")
    friction = where.check("friction", validate.in_range, table.get("friction", 0.0), "friction", 0.0, 10.0,
                           what="Coulomb's coefficient")
    if "mesh" in table:
        scale = where.check("scale", validate.positive, table.get("scale", 1.0), "scale", "a coordinate factor")
        spec = str(table["mesh"])
        mesh = _builtin(spec, where) if spec.startswith(BUILTIN) else where.check(
            "mesh", load_mesh, folder / spec, scale=scale)
        if isinstance(mesh, TetMesh):
            mesh = mesh.surface
        where.check("mesh", scene.add_obstacle, table["name"], mesh, friction)
        return
    plane = table["plane"]
    if not isinstance(plane, dict) or set(plane) != {"point", "normal"}:
        raise where.error("plane", "must be { point = [x, y, z], normal = [nx, ny, nz] } (m)")
    where.check("plane", scene.add_plane, table["name"], plane["point"], plane["normal"], friction)


def _tool(table, where: _Where, device=None) -> tuple:
    """A [[tool]] table checked (before any body is meshed): its name, device (a scripted one for a
    path), kind and options, what :meth:`Scene.add_tool` (a scalpel's: :meth:`Scene.add_scalpel`) takes."""
    if not isinstance(table, dict):
        raise where.error(None, "must be a table")
    where.keys(table, TOOL_KEYS, ("name",) if device is not None else ("name", "path"))
    kind = table.get("kind", "probe")
    where.check("kind", validate.choice, kind, "kind", ("probe", "grasper", "scalpel"))
    if kind == "scalpel":
        return table["name"], _device(table, where, device), kind, _scalpel_options(table, where, device)
    for key in SCALPEL_KEYS & set(table):
        raise where.error(key, "is for a scalpel (kind = 'scalpel')")
    device = _device(table, where, device)
    if kind == "probe" and "closed" in table:
        raise where.error("closed", "only a grasper closes; a probe presses where its path takes it")
    options = {k: table[k] for k in ("radius", "stiffness", "friction") if k in table}
    for key, fn, args in (("radius", validate.positive, ("a length in m",)), ("stiffness", validate.positive, ("N/m",)),
                          ("friction", validate.in_range, (0.0, 10.0))):
        if key in options:
            where.check(key, fn, options[key], key, *args)
    return table["name"], device, kind, options


def _device(table: dict, where: _Where, device=None):
    """The tool's live ``device``, or the scripted one its ``path`` (and ``closed``) make."""
    from .scene_tools import Keyframes

    if device is not None:
        return device
    for key in ("max_force", "url", "port"):
        if key in table:
            raise where.error(key, "is for a tool on a live device (device = ...)")
    path = where.check("path", Keyframes, table["path"])
    return where.check("closed", Keyframes, path.path, table.get("closed", [])).device()


def _scalpel_options(table: dict, where: _Where, device) -> dict:
    """A scalpel's options (what Scene.add_scalpel takes): the body it cuts, its blade, its toughness,
    and whether it cuts only while closed (a path's ``closed`` times, a live hand's first button)."""
    for key in ("radius", "stiffness", "friction"):
        if key in table:
            raise where.error(key, "is for a probe or a grasper; a scalpel has blade and toughness")
    if "body" not in table:
        raise where.error("body", "missing: name the body the scalpel cuts")
    options = {"body": table["body"], "button": "closed" in table or "device" in table}
    if "blade" in table:
        blade = options["blade"] = where.check("blade", validate.vector, table["blade"], "blade", 3)
        if not 0 < np.linalg.norm(blade) <= MAX_BLADE:
            raise where.error("blade", f"{np.asarray(blade).tolist()}: give the vector from the blade's tip to its heel "
                              f"in m, of some length up to {MAX_BLADE:g} m, e.g. [0, 0, 0.03]")
    if "toughness" in table:
        options["toughness"] = where.check("toughness", validate.nonnegative, table["toughness"], "toughness",
                                           "J/m^2, a number >= 0 (liver: 164)")
    return options


def _table_name(kind: str, i: int, table) -> str:
    """``[[body]] 2 'liver'`` (the name when the table has one)."""
    name = table.get("name") if isinstance(table, dict) else None
    return f"[[{kind}]] {i + 1}" + (f" {name!r}" if name is not None else "")


def _add_body(scene: Scene, table, where: _Where, folder: Path, dt: float, full: bool = False) -> None:
    from ..drivers.modal import ModalSimulator
    from ..fe.build import make_model
    from ..fe.material import Damping, Material
    from ..reduction.precompute import cached_modes

    if not isinstance(table, dict):
        raise where.error(None, "must be a table")
    where.keys(table, BODY_KEYS, ("name", "mesh"))
    mat = _material(table, where)  # before any meshing
    mesh, kind = _body_mesh(table, where, folder)
    if kind == "shell" and isinstance(mat, dict):
        raise where.error("material", "a material per region is for solids (a labelled tet mesh); a shell takes one")
    if kind == "shell" and not isinstance(mat, Material):
        law = table["material"].get("law")
        raise where.error("material", f"law {law!r} is for solids (kind = 'solid', tets); a shell takes law = 'linear' "
                          "with E, nu, density and thickness")
    if isinstance(mat, dict):  # a region's key that names none is the material's fault, said so
        from ..fe.regions import region_materials

        where.check("material", region_materials, mat, mesh)
    options = {"element": table.get("element", "tet10")} if kind == "solid" else {}
    model = where.check("element" if options else "mesh", make_model, mesh, mat, **options)
    fix = table.get("fix")
    if fix is not None:
        where.check("fix", model.fix, fix)
        where.check("fix", model.check_restrained)
    alpha = where.check("alpha", validate.nonnegative, table.get("alpha", 10.0), "alpha", "damping in 1/s")
    if full:
        driver = _full_order(model, table, where, dt, Damping(alpha=alpha))
    else:
        modes = where.check("modes", validate.count, table.get("modes", 20), "modes", 1, 2000)
        basis = where.check("modes", cached_modes, model, modes)  # through the precompute cache
        driver = ModalSimulator(basis, dt, Damping(alpha=alpha), static_correction=fix is not None)
    where.check("name", scene.add_body, table["name"], driver, model.mesh)
    scene.bodies[-1].model = model


def _full_order(model, table: dict, where: _Where, dt: float, damping):
    """A body a scalpel cuts: the full-order lagged corotational step (a cut opens only there), tet4."""
    from ..drivers.fullorder import DirectSimulator

    if not hasattr(model, "tetmesh"):
        raise where.error("kind", "a scalpel cuts solids: give kind = 'solid' (a shell cannot be cut yet)")
    if "modes" in table:
        raise where.error("modes", "a body a scalpel cuts runs full order (a cut opens only there): leave modes out")
    if "fix" not in table:
        raise where.error("fix", "missing: a body a scalpel cuts must be held (fix = a node selection); a piece cut "
                          "free with nothing holding it falls away, and a free body would all go")
    if model.element != "tet4":  # (a cut tet10 liver's next steps turned split elements inside out; the viewer cuts one
        # as tet4 on its corners, a scene file names its element)
        raise where.error("element", f"{model.element!r}: a body a scalpel cuts must be element = 'tet4' for now (a cut "
                          "tet10 organ turned its split elements inside out in the steps after, issue 57)")
    return where.check("mesh", DirectSimulator, model, dt, damping, large_deformation=True)


def _body_mesh(table: dict, where: _Where, folder: Path):
    """The body's mesh, of its kind ("solid": tets, a surface file meshed; "shell": a surface), placed:
    scaled, rotated, translated (:func:`placement`)."""
    from ..mesh.files import load_mesh
    from ..mesh.tetmesh import TetMesh

    scale = where.check("scale", validate.positive, table.get("scale", 1.0), "scale", "a coordinate factor")
    R, t = placement(table, where)
    if str(table["mesh"]).startswith(BUILTIN):
        mesh = _builtin(str(table["mesh"]), where, solid=table.get("kind") == "solid")
        mesh = mesh if scale == 1.0 else mesh.scaled(scale)
    else:
        mesh = where.check("mesh", load_mesh, folder / str(table["mesh"]), scale=scale)
    kind = table.get("kind", "solid" if isinstance(mesh, TetMesh) else "shell")
    if kind not in ("solid", "shell"):
        raise where.error("kind", f"{validate.show(kind)}: give 'solid' or 'shell'")
    if kind == "solid" and not isinstance(mesh, TetMesh):
        from ..mesh.meshing import tetrahedralize

        mesh = where.check("mesh", tetrahedralize, mesh)
    if R is not None:
        X = np.asarray(mesh.vertices) @ R.T + t
        if isinstance(mesh, TetMesh):
            mesh = TetMesh(X, mesh.tets, repair=False, groups=mesh.groups, labels=mesh.labels,
                           region_names=mesh.region_names)
        else:
            mesh = type(mesh)(X, mesh.triangles, repair=False, groups=mesh.groups)
    if kind == "shell" and isinstance(mesh, TetMesh):
        mesh = mesh.surface
    return mesh, kind


def placement(table: dict, where: _Where) -> tuple[np.ndarray | None, np.ndarray]:
    """A body's ``rotate = [rx, ry, rz]`` (degrees) and ``translate = [x, y, z]`` (m) as R (3, 3)
    and t (3,): the mesh's point X (after ``scale``) is placed at R X + t, R = Rz(rz) Ry(ry) Rx(rx):
    turned about the scene's fixed x axis by rx, then about its fixed y axis by ry, then about its
    fixed z axis by rz (extrinsic x-y-z; scipy's ``Rotation.from_euler("xyz", ..., degrees=True)``),
    about the origin of the file's coordinates, then moved by t. R is None when neither is given."""
    if "rotate" not in table and "translate" not in table:
        return None, np.zeros(3)
    rotate = _triple(table, "rotate", where, "[rx, ry, rz], degrees about x, then y, then z")
    if not np.all(np.abs(rotate) <= 360.0):
        raise where.error("rotate", f"{np.asarray(rotate).tolist()}: give the angles in degrees, -360 .. 360 each "
                          "(about x, then y, then z)")
    t = _triple(table, "translate", where, "[x, y, z] in m")
    if not np.linalg.norm(t) <= MAX_PLACE:
        raise where.error("translate", f"{np.asarray(t).tolist()} m is more than {MAX_PLACE:g} m from the origin: give "
                          "the offset in metres")
    R = np.eye(3)
    for axis, angle in enumerate(np.radians(rotate)):
        c, s = np.cos(angle), np.sin(angle)
        i, j = (axis + 1) % 3, (axis + 2) % 3
        turn = np.eye(3)
        turn[i, i], turn[i, j], turn[j, i], turn[j, j] = c, -s, s, c
        R = turn @ R
    return R, np.asarray(t, dtype=float)


def _triple(table: dict, key: str, where: _Where, what: str) -> np.ndarray:
    try:
        return validate.vector(table.get(key, (0.0, 0.0, 0.0)), key, 3)
    except RtfemError as exc:
        raise where.error(key, f"{exc} ({key} = {what})") from None


def _material(table: dict, where: _Where):
    """The body's ``material`` table: any law ``--material`` takes
    (:func:`rtfem.fe.viscoelastic.material_from_table`), or one such table per region of a labelled
    tet mesh, keyed by region name or label (``material = { 1 = {...}, tumor = {...} }``; the keys
    as written, resolved by :func:`rtfem.fe.regions.region_materials`)."""
    from ..fe.viscoelastic import material_from_table

    raw = table.get("material", {})
    if isinstance(raw, dict) and any(isinstance(v, dict) for k, v in raw.items() if k != "prony") and \
            not all(isinstance(v, dict) for v in raw.values()):
        raise where.error("material", "a material is either one law's keys (E, nu, law, tissue, ...) or one table per "
                          "region ({ liver = { ... }, tumor = { ... } }), not both: put "
                          f"{', '.join(sorted(k for k, v in raw.items() if not isinstance(v, dict)))} inside the regions' "
                          "tables")
    if isinstance(raw, dict) and raw and all(isinstance(v, dict) for v in raw.values()):
        return {k: where.check(f"material.{k}", material_from_table, v) for k, v in raw.items()}

    return where.check("material", material_from_table, table.get("material", {}))


def _builtin(spec: str, where: _Where, solid: bool = False):
    """``rtfem:liver`` (level 3), ``rtfem:gallbladder`` (level 2), or ``rtfem:NAME:LEVEL``: the embedded meshes;
    the liver with kind = "solid" is its volume (``rt.meshes.liver(level, solid=True)``: at level 3 the tets
    shipped with rtfem, the same on every machine)."""
    from ..mesh import meshes

    parts = spec[len(BUILTIN):].split(":")
    makers = {"liver": (meshes.liver, 3), "gallbladder": (meshes.gallbladder, 2)}
    if parts[0] not in makers or len(parts) > 2 or (len(parts) == 2 and not parts[1].isdigit()):
        raise where.error("mesh", f"{spec!r}: the embedded meshes are {', '.join(BUILTIN + m for m in makers)}, "
                          f"with a level as {BUILTIN}liver:4")
    make, level = makers[parts[0]]
    level = int(parts[1]) if len(parts) == 2 else level
    if solid and parts[0] == "liver":
        return where.check("mesh", make, level, solid=True)
    return where.check("mesh", make, level)


def contact_rows(scene: Scene) -> list[list]:
    """The scene's contact records of this step as CSV rows t, a, b, fx, fy, fz (the force on body a
    from obstacle, body or attachment b)."""
    return [[scene.time, a, b, *np.asarray(f).tolist()] for (a, b), f in scene.contacts.items()]
