"""Reading and writing meshes: OBJ, STL, PLY, OFF, VTK/VTU, Gmsh, MEDIT, Abaqus and more via meshio.

Legacy ASCII VTK files (``# vtk DataFile Version 1.0 .. 3.0``, POLYDATA or
UNSTRUCTURED_GRID) that meshio cannot read are parsed here. Quads and polygons are split
into triangles; a file with tetrahedra (4 or 10 nodes) is a volume and loads as a TetMesh.
"""

from __future__ import annotations

import contextlib
import io
import os
import warnings
from pathlib import Path

import numpy as np

from .. import validate
from ..errors import MeshError, ModelError, RtfemWarning
from ..userfiles import regular_file
from .surface import TriMesh
from .tetmesh import TetMesh

__all__ = ["load_mesh", "save_mesh"]

_SURFACE_FORMATS = ".obj .stl .ply .off .vtk .vtu .msh .mesh .xdmf .med .inp"


def load_mesh(path: str | os.PathLike, *, scale: float = 1.0, repair: bool = True,
              merge_tol: float = 1e-10) -> TriMesh | TetMesh:
    """Load a mesh from a file: a :class:`TetMesh` when the file holds tetrahedra (4- or
    10-node; VTU/VTK, Gmsh .msh, MEDIT .mesh, Abaqus .inp), otherwise a :class:`TriMesh` of its
    surface cells (its ``.surface`` is the boundary of a volume).

    Parameters
    ----------
    path : mesh file (OBJ, STL, PLY, OFF, VTK legacy or XML, VTU, Gmsh MSH, ...).
    scale : factor applied to the coordinates; organ meshes are usually in millimetres and
        the model works in SI units, so ``scale=1e-3`` turns mm into m.
    repair, merge_tol : see :class:`TriMesh`; the repairs are listed in ``mesh.report``. A cut
        mesh (``rt.cut``) has twin nodes on its cut faces: load it with ``merge_tol=0``.

    Returns
    -------
    TriMesh or TetMesh

    Raises
    ------
    MeshError
        A missing or unreadable file (named), an unknown format, no triangles or tets in it, a
        bad scale, a mesh its checks refuse (non-manifold, degenerate, tangled: the message says
        what to repair).

    Warns
    -----
    RtfemWarning
        Coincident nodes of a tet mesh merged (a cut or a crack closed).
    """
    p = Path(validate.path_like(path, "path", error=MeshError))
    s = validate.positive(scale, "scale", "a factor on the coordinates (1e-3 turns mm into m)", error=MeshError)
    repair = validate.flag(repair, "repair", error=MeshError)
    merge_tol = validate.in_range(merge_tol, "merge_tol", 0.0, 1.0, hi_open=True, error=MeshError)
    regular_file(p, "mesh file", error=MeshError)  # a pipe or /dev/zero would never end
    points, triangles, tets, groups, regions = _read(p)
    if tets is not None:
        labels, names = regions or (None, None)
        mesh = TetMesh(points * s, tets, repair=repair, merge_tol=merge_tol, groups=groups, labels=labels,
                       region_names=names)
        if mesh.report.merged_nodes:  # a volume mesh's twin nodes are a cut or a crack (rt.cut writes them)
            warnings.warn(f"{p.name}: {mesh.report.merged_nodes} node(s) coincide with others and were merged, which "
                          "closes any cut or crack the mesh has; pass merge_tol=0 to keep them apart", RtfemWarning,
                          stacklevel=2)
    else:
        mesh = TriMesh(points * s, triangles, repair=repair, merge_tol=merge_tol, groups=groups)
    if s != 1.0:
        mesh.report.notes.append(f"coordinates scaled by {s:g}")
    return mesh


def save_mesh(mesh: TriMesh | TetMesh, path: str | os.PathLike, point_data: dict | None = None) -> None:
    """Write a mesh (optionally with per-vertex data) in the format the file suffix names.

    The file is written beside the target and renamed over it: an interrupted save leaves
    any previous file intact.

    Parameters
    ----------
    mesh : a :class:`~rtfem.TriMesh` or :class:`~rtfem.TetMesh`.
    path : the file; its suffix names the format (.stl, .obj, .ply, .vtk, .vtu, .msh, .mesh, ...).
    point_data : {name: (n,) or (n, k) array}, per-vertex fields written with it.

    Returns
    -------
    None

    Raises
    ------
    MeshError
        Not a mesh, a suffix that names no format, a field of the wrong length, or the writer
        failing (the message names the file).
    """
    import meshio

    from ..storage import atomic_target

    if not isinstance(mesh, (TriMesh, TetMesh)):
        raise MeshError(f"mesh={validate.show(mesh)} must be an rtfem TriMesh or TetMesh")
    p = Path(validate.path_like(path, "path", error=MeshError))
    fmt = getattr(meshio, "extension_to_filetypes", {}).get(p.suffix.lower())
    if fmt and "gmsh" in fmt:
        fmt = ["gmsh"]  # .msh is Gmsh's (meshio lists ANSYS first)
    if not fmt:
        raise MeshError(f"{str(p)!r}: the suffix {p.suffix!r} names no mesh format; use one of {_SURFACE_FORMATS}")
    data = {str(k): point_field(v, mesh.n_vertices, f"point_data[{k!r}]") for k, v in (point_data or {}).items()}
    if fmt[0] == "medit" and isinstance(mesh, TetMesh) and mesh.order == 2:
        raise MeshError(f"{str(p)!r}: MEDIT's .mesh format has no 10-node tets; save a 10-node mesh as .vtu, .msh or "
                        ".inp, or its corners (mesh.linear()) as .mesh")
    regions = _region_data(mesh, fmt[0]) if isinstance(mesh, TetMesh) and (mesh.labels.any() or mesh.region_names) \
        else {}  # (a named region 0 alone too: its name would be lost)
    with atomic_target(p, "mesh file") as tmp:
        try:
            meshio.write_points_cells(str(tmp), np.asarray(mesh.vertices), mesh_cells(mesh), point_data=data,
                                      **{"file_format": fmt[0], **regions})
            if fmt[0] == "vtu" and regions.get("field_data"):
                _vtu_field_data(tmp, regions["field_data"])
        except (ValueError, KeyError, TypeError) as exc:
            raise MeshError(f"could not write {str(p)!r}: {_clean(exc)}") from None


def _region_data(mesh: TetMesh, fmt: str) -> dict:
    """The keyword arguments that write a labelled mesh's regions in ``fmt``: Gmsh physical groups
    (with their names), MEDIT references, Abaqus element sets (by name), else a 'region' cell field
    (names as field data)."""
    labels = np.asarray(mesh.labels)
    if fmt == "abaqus":
        names = {v: k for k, v in mesh.region_names.items()}
        return {"cell_sets": {names.get(int(r), f"region{int(r)}"): [np.flatnonzero(labels == r)] for r in mesh.regions}}
    if fmt == "gmsh":  # written as Gmsh 2.2, whose physical tags are a cell field (Gmsh 4's are read too)
        return {"file_format": "gmsh22", "cell_data": {"gmsh:physical": [labels], "gmsh:geometrical": [labels]},
                "field_data": {k: np.array([v, 3]) for k, v in mesh.region_names.items()}}
    if fmt == "medit":
        return {"cell_data": {"medit:ref": [labels]}}
    return {"cell_data": {"region": [labels]}, "field_data": {k: np.array([v]) for k, v in mesh.region_names.items()}}


def _vtu_field_data(path: Path, fields: dict) -> None:
    """Add the regions' names to a VTU file as FieldData (integer arrays named by region, which
    meshio reads back as field_data; its writer leaves field data out)."""
    from xml.sax.saxutils import quoteattr

    arrays = "".join(f'<DataArray type="Int64" Name={quoteattr(str(k))} NumberOfTuples="1" format="ascii">'
                     f"{int(np.asarray(v).ravel()[0])}</DataArray>" for k, v in fields.items())
    text = Path(path).read_text()
    at = text.index("<UnstructuredGrid>") + len("<UnstructuredGrid>")
    Path(path).write_text(text[:at] + "\n<FieldData>" + arrays + "</FieldData>" + text[at:])


def _clean(exc: BaseException) -> str:
    return validate.one_line(f"{type(exc).__name__}: {exc}", 200)


def _read(p: Path) -> tuple:
    """Points, triangles (None for a volume), tets (None for a surface), point groups and the tets'
    regions (labels, {name: label}) or None. OBJ and legacy ASCII VTK are read here, without importing
    meshio (60 ms of a cold `rtfem modes`, issue 54)."""
    err: Exception | None = None
    suffix = p.suffix.lower()
    if suffix == ".obj":
        return _with_no_tets(_read_obj(p)) + (None,)
    if suffix == ".stl":
        _check_binary_stl(p)
    if suffix == ".vtk" and _is_legacy_ascii_vtk(p):
        return _read_legacy_vtk(p) + (None,)
    import meshio

    try:
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()), \
                warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # meshio's STL size probe overflows harmlessly
            m = meshio.read(str(p))
    except (Exception, SystemExit) as exc:  # meshio raises many kinds (and may sys.exit); report one clear error
        err = exc
    if err is not None:
        if p.suffix.lower() == ".vtk":
            return _read_legacy_vtk(p) + (None,)
        known = "" if p.suffix.lower() in _SURFACE_FORMATS.split() else f" (suffix {p.suffix!r} is not a known mesh format)"
        raise MeshError(
            f"could not read {str(p)!r} as a mesh{known}: {_clean(err)}. "
            f"Readable formats include {_SURFACE_FORMATS}"
        )
    cells = [(c.type, np.asarray(c.data)) for c in m.cells]
    groups = {k: np.asarray(v).ravel() for k, v in (m.point_sets or {}).items()}
    tets = _tets_from_cells(cells, p)
    tris = None if tets is not None else _triangles_from_cells(cells, p)
    return np.asarray(m.points, dtype=float), tris, tets, groups, (_regions(m, p) if tets is not None else None)


# the cell data a region label is read from (the first found), and where each format writes it
_LABEL_KEYS = ("gmsh:physical", "medit:ref", "region", "labels", "CellEntityIds", "RegionId", "MaterialIds")


def _regions(m, p: Path) -> tuple[np.ndarray, dict] | None:
    """The tets' region labels and names from a meshio mesh: a label cell field (Gmsh's physical
    groups, MEDIT's references, VTU's 'region'), or Abaqus-style element sets (each numbered from 1,
    in the file's order, named), with names from Gmsh's physical names or VTU field data."""
    blocks = [i for i, c in enumerate(m.cells) if c.type in ("tetra", "tetra10")]
    for key in _LABEL_KEYS:
        data = (m.cell_data or {}).get(key)
        if data is not None:
            labels = np.concatenate([np.asarray(data[i]).reshape(-1) for i in blocks])
            names = {}
            for name, value in (m.field_data or {}).items():
                v = np.asarray(value).reshape(-1)
                if v.size and (v.size == 1 or (v.size == 2 and int(v[1]) == 3)):
                    names[str(name)] = int(v[0])
            return labels, names
    sets = {name: v for name, v in (m.cell_sets or {}).items() if not name.startswith("gmsh:")}
    if not sets:
        return None
    sizes = [len(m.cells[i].data) for i in blocks]
    offsets = np.concatenate([[0], np.cumsum(sizes)])
    labels, names = np.zeros(int(offsets[-1]), dtype=np.int64), {}
    tags = {str(k): np.asarray(v).reshape(-1) for k, v in (m.field_data or {}).items()}
    for k, (name, per_block) in enumerate(sets.items(), start=1):
        tag = tags.get(str(name))
        k = int(tag[0]) if tag is not None and tag.size == 2 and int(tag[1]) == 3 else k  # Gmsh 4's physical tag
        for j, i in enumerate(blocks):
            if i < len(per_block) and per_block[i] is not None and len(per_block[i]):
                labels[offsets[j] + np.asarray(per_block[i], dtype=np.int64)] = k
                names[str(name)] = k
    return (labels, names) if names else None


def _with_no_tets(read: tuple) -> tuple:
    points, tris, groups = read
    return points, tris, None, groups


def _tets_from_cells(cells: list[tuple[str, np.ndarray]], p: Path) -> np.ndarray | None:
    """The tets of a volume file (4- or 10-node, not mixed), or None when it has none; a file with
    other volume cells (hexahedra, wedges, pyramids, tets of other orders) is refused, with or
    without tets beside them: dropping them would lose part of the volume, loading only its
    boundary triangles would make a shell of it."""
    linear = [d for c, d in cells if c == "tetra"]
    quadratic = [d for c, d in cells if c == "tetra10"]
    other = sorted({c for c, _ in cells if c.startswith(("hexahedron", "wedge", "pyramid"))
                    or (c.startswith("tetra") and c not in ("tetra", "tetra10"))})
    if other:
        raise MeshError(f"{str(p)!r} holds volume cells rtfem cannot use ({', '.join(other)}"
                        f"{', beside its tetrahedra' if linear or quadratic else ''}): its volumes are 4- or 10-node "
                        "tetrahedra. Convert the file to tets (e.g. Gmsh: mesh the volume with tetrahedra), or load "
                        "the boundary surface alone and fill it with rt.tetrahedralize")
    if linear and quadratic:
        raise MeshError(f"{str(p)!r} mixes 4-node and 10-node tets; rtfem needs one kind (convert the file, e.g. "
                        "in Gmsh with SetOrder 1 or 2)")
    found = linear or quadratic
    return np.concatenate(found).astype(np.int64) if found else None


def _read_obj(p: Path) -> tuple[np.ndarray, np.ndarray, dict]:
    """Wavefront OBJ: ``v`` lines and ``f`` lines (polygons fan-split).

    Face corners may be ``v``, ``v/vt``, ``v//vn`` or ``v/vt/vn``, with 1-based indices or
    negative ones relative to the vertices read so far (``f -3 -2 -1``). Errors name the
    line and use the file's own numbering. Other statements (vt, vn, g, o, s, usemtl, ...)
    are skipped.
    """
    try:
        text = p.read_bytes().decode("utf-8", errors="replace")
    except OSError as exc:
        raise MeshError(f"could not read {str(p)!r}: {exc.strerror or exc}") from None
    verts: list[tuple[float, float, float]] = []
    faces: list[list[int]] = []
    face_lines: list[int] = []
    for lineno, line in enumerate(text.splitlines(), start=1):
        parts = line.split()
        if not parts:
            continue
        key = parts[0]
        if key == "v":
            try:
                xyz = (float(parts[1]), float(parts[2]), float(parts[3]))
            except (IndexError, ValueError):
                raise MeshError(f"{str(p)!r} line {lineno}: a vertex needs 3 numbers, got "
                                f"{validate.show(line.strip(), 60)}") from None
            verts.append(xyz)
        elif key == "f":
            corners = []
            for c in parts[1:]:
                head = c.split("/", 1)[0]
                try:
                    k = int(head)
                except ValueError:
                    raise MeshError(f"{str(p)!r} line {lineno}: face corner {validate.show(c, 30)} is not a vertex "
                                    "index") from None
                if k == 0:
                    raise MeshError(f"{str(p)!r} line {lineno}: vertex index 0 does not exist (OBJ counts from 1)")
                corners.append(k - 1 if k > 0 else len(verts) + k)
                if corners[-1] < 0:
                    raise MeshError(f"{str(p)!r} line {lineno}: relative vertex index {k} reaches before the "
                                    f"first vertex ({len(verts)} vertices read so far)")
            if len(corners) < 3:
                raise MeshError(f"{str(p)!r} line {lineno}: a face needs at least 3 corners, got {len(corners)}")
            faces.append(corners)
            face_lines.append(lineno)
    if not faces:
        raise MeshError(f"{str(p)!r} holds no faces ('f' lines): it is not a surface mesh")
    nv = len(verts)
    tris = []
    for corners, lineno in zip(faces, face_lines):
        bad = [c for c in corners if c >= nv]
        if bad:
            raise MeshError(f"{str(p)!r} line {lineno}: face refers to vertex {bad[0] + 1}; the file has vertices "
                            f"1..{nv}")
        for i in range(1, len(corners) - 1):
            tris.append((corners[0], corners[i], corners[i + 1]))
    return np.array(verts, dtype=float).reshape(-1, 3), np.array(tris, dtype=np.int64), {}


def _check_binary_stl(p: Path) -> None:
    """A binary STL must hold 50 bytes per triangle its header counts; say so when it is cut short."""
    size = p.stat().st_size
    with open(p, "rb") as fh:
        head = fh.read(84)
    if head[:5].lower() == b"solid" and b"facet" in open(p, "rb").read(1024):
        return  # ASCII STL
    if len(head) < 84:
        raise MeshError(f"could not read {str(p)!r}: {size} bytes is neither an ASCII STL nor a binary one (its header "
                        "alone is 84 bytes); the file is truncated or not an STL")
    count = int.from_bytes(head[80:84], "little")
    need = 84 + 50 * count
    if size < need:
        raise MeshError(f"{str(p)!r} is truncated: its header counts {count} triangles ({need} bytes) but the file has "
                        f"{size} bytes ({max(size - 84, 0) // 50} complete triangles); export it again")


def _split_polygons(cells: np.ndarray) -> np.ndarray:
    """Fan-split k-gons into triangles; quads split along their shorter diagonal elsewhere."""
    k = cells.shape[1]
    parts = [cells[:, [0, i, i + 1]] for i in range(1, k - 1)]
    return np.concatenate(parts)


def _triangles_from_cells(cells: list[tuple[str, np.ndarray]], p: Path) -> np.ndarray:
    out: list[np.ndarray] = []
    for ctype, data in cells:
        if ctype in ("triangle", "triangle6", "triangle7"):
            out.append(data[:, :3])
        elif ctype in ("quad", "quad8", "quad9"):
            out.append(_split_polygons(data[:, :4]))
        elif ctype.startswith("polygon"):
            out.append(_split_polygons(data))
    if not out:
        found = ", ".join(sorted({c for c, _ in cells})) or "no cells"
        raise MeshError(f"{str(p)!r} holds no surface cells (found: {found}); rtfem needs triangles, quads or "
                        "polygons, or tetrahedra for a volume")
    return np.concatenate(out).astype(np.int64)


def _is_legacy_ascii_vtk(p: Path) -> bool:
    with open(p, "rb") as fh:
        head = fh.read(256).decode("latin-1").splitlines()
    return len(head) >= 3 and head[0].startswith("# vtk DataFile") and head[2].strip().upper() == "ASCII"


class _VtkTokens:
    """The whitespace-separated values of a legacy VTK file after its header, read in order;
    every shortfall or bad value is a MeshError naming the file and the section."""

    def __init__(self, p: Path, tokens: list[str]) -> None:
        self.p, self.tokens, self.pos = p, tokens, 0

    def more(self) -> bool:
        return self.pos < len(self.tokens)

    def take(self, k: int, what: str) -> list[str]:
        if self.pos + k > len(self.tokens):
            raise MeshError(f"{str(self.p)!r} is truncated: expected {k} more values in {what}")
        out = self.tokens[self.pos : self.pos + k]
        self.pos += k
        return out

    def count(self, what: str) -> int:
        tok = self.take(1, what)[0]
        try:
            k = int(tok)
        except ValueError:
            raise MeshError(f"{str(self.p)!r}: the count of {what} is {validate.show(tok, 30)}, not a whole number") from None
        if k < 0:
            raise MeshError(f"{str(self.p)!r}: negative count {k} in {what}")
        if k > len(self.tokens):
            raise MeshError(f"{str(self.p)!r} is truncated: {what} declares {k} entries, the file holds fewer values")
        return k

    def numbers(self, k: int, what: str, dtype) -> np.ndarray:
        values = self.take(k, what)
        try:
            return np.array(values, dtype=dtype)
        except ValueError:
            raise MeshError(f"{str(self.p)!r}: non-numeric value in {what}") from None

    def cell_rows(self, key: str) -> list[np.ndarray]:
        """A cell list: its count, its size, then per cell the number of indices and the indices."""
        n, size = self.count(key), self.count(key)
        flat = self.numbers(size, key, np.int64)
        rows, i = [], 0
        for c in range(n):
            k = int(flat[i]) if i < flat.size else -1
            if k < 0 or i + 1 + k > flat.size:
                raise MeshError(f"{str(self.p)!r}: {key} declares {n} cells in {size} values, but cell {c} does not fit "
                                "(a short or damaged cell list)")
            rows.append(flat[i + 1 : i + 1 + k])
            i += k + 1
        return rows


def _vtk_polygons(rows: list[np.ndarray]) -> list[np.ndarray]:
    return [_split_polygons(np.array([r for r in rows if len(r) == k])) for k in sorted({len(r) for r in rows}) if k >= 3]


def _vtk_strips(rows: list[np.ndarray]) -> list[np.ndarray]:
    """Triangle strips as triangles, alternate ones flipped to keep the orientation."""
    return [(r[[j, j + 1, j + 2]] if j % 2 == 0 else r[[j + 1, j, j + 2]])[None, :] for r in rows for j in range(len(r) - 2)]


# VTK cell types rtfem reads: the name meshio gives it and its node count (0: a polygon, any count from 3)
_VTK_TYPES = {5: ("triangle", 3), 9: ("quad", 4), 7: ("polygon", 0), 10: ("tetra", 4), 24: ("tetra10", 10),
              12: ("hexahedron", 8), 13: ("wedge", 6), 14: ("pyramid", 5), 25: ("hexahedron20", 20),
              26: ("wedge15", 15), 27: ("pyramid13", 13), 29: ("hexahedron27", 27)}


def _vtk_typed_cells(p: Path, cells_conn, types: np.ndarray) -> tuple[list[np.ndarray], np.ndarray | None]:
    """UNSTRUCTURED_GRID cells by VTK type: (triangle 5, quad 9, polygon 7) as triangles, and
    the tets (tetra 10, quadratic tetra 24) when there are any."""
    if cells_conn is None or len(cells_conn) != types.size:
        raise MeshError(f"{str(p)!r}: CELL_TYPES does not match CELLS")
    cells = []
    for t, (name, size) in _VTK_TYPES.items():
        sel = [np.asarray(cells_conn[i]) for i in np.flatnonzero(types == t)]
        short = [i for i, c in zip(np.flatnonzero(types == t), sel) if (len(c) != size if size else len(c) < 3)]
        if short:  # a ragged list: numpy would stack it into an error of its own
            i = short[0]
            raise MeshError(f"{str(p)!r}: cell {i} is VTK type {t} ({name}) with {len(cells_conn[i])} node indices, "
                            f"not {size or 'at least 3'} (a damaged CELLS list or wrong CELL_TYPES); re-export the mesh")
        if sel and name != "polygon":
            cells.append((name, np.array(sel)))
        elif sel:
            cells += [("polygon", s[None, :]) for s in sel]
    tets = _tets_from_cells(cells, p)
    if tets is not None:
        return [], tets
    return ([_triangles_from_cells(cells, p)] if cells else []), None


def _read_legacy_vtk(p: Path) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None, dict]:
    """Parse a legacy ASCII VTK file (POLYDATA polygons/strips or UNSTRUCTURED_GRID)."""
    try:
        text = p.read_text(encoding="latin-1")
    except OSError as exc:
        raise MeshError(f"could not read {str(p)!r}: {exc}") from None
    lines = text.splitlines()
    if len(lines) < 4 or not lines[0].startswith("# vtk DataFile"):
        raise MeshError(f"{str(p)!r} is not a VTK file (no '# vtk DataFile' header)")
    if lines[2].strip().upper() != "ASCII":
        raise MeshError(f"{str(p)!r}: binary legacy VTK that meshio could not read either; convert it to .vtu or .vtk ASCII")
    tok = _VtkTokens(p, " ".join(lines[3:]).split())
    points, tris, cells_conn, tets = None, [], None, None
    while tok.more():
        key = tok.take(1, "a section name")[0].upper()
        if key == "DATASET":
            kind = tok.take(1, "DATASET")[0].upper()
            if kind not in ("POLYDATA", "UNSTRUCTURED_GRID"):
                raise MeshError(f"{str(p)!r}: VTK dataset {kind} is not a surface mesh (need POLYDATA or UNSTRUCTURED_GRID)")
        elif key == "POINTS":
            n = tok.count("POINTS")
            tok.take(1, "POINTS")  # data type
            points = tok.numbers(3 * n, "POINTS", float).reshape(n, 3)
        elif key in ("POLYGONS", "TRIANGLE_STRIPS", "CELLS", "VERTICES", "LINES"):
            rows = tok.cell_rows(key)
            if key == "POLYGONS":
                tris += _vtk_polygons(rows)
            elif key == "TRIANGLE_STRIPS":
                tris += _vtk_strips(rows)
            elif key == "CELLS":
                cells_conn = rows
        elif key == "CELL_TYPES":
            typed, tets = _vtk_typed_cells(p, cells_conn, tok.numbers(tok.count("CELL_TYPES"), "CELL_TYPES", np.int64))
            tris += typed
        elif key in ("POINT_DATA", "CELL_DATA", "FIELD", "METADATA"):
            break  # attributes follow; the geometry is complete
    if points is None:
        raise MeshError(f"{str(p)!r}: no POINTS section found")
    if tets is not None:
        return points, None, tets, {}
    if not tris:
        raise MeshError(f"{str(p)!r}: no POLYGONS, TRIANGLE_STRIPS or surface CELLS found")
    return points, np.concatenate(tris).astype(np.int64), None, {}


def mesh_cells(mesh) -> list[tuple[str, np.ndarray]]:
    """meshio cells of a TriMesh (triangles) or a TetMesh (tetra or tetra10, VTK order)."""
    from .tetmesh import TetMesh

    if isinstance(mesh, TetMesh):
        return [("tetra" if mesh.order == 1 else "tetra10", np.asarray(mesh.tets))]
    if isinstance(mesh, TriMesh):
        return [("triangle", np.asarray(mesh.triangles))]
    raise ModelError(f"mesh={validate.show(mesh)} must be an rtfem TriMesh or TetMesh")


def point_field(values, n: int, name: str) -> np.ndarray:
    """Per-vertex data: a finite numeric array with n rows."""
    a = validate.real_array(values, name)
    if a.ndim == 0 or a.shape[0] != n:
        raise ModelError(f"{name} must have {n} rows (one per vertex), got shape {a.shape}")
    return a
