"""Reading and writing surface meshes: OBJ, STL, PLY, OFF, VTK/VTU, Gmsh and more via meshio.

Legacy ASCII VTK files (``# vtk DataFile Version 1.0 .. 3.0``, POLYDATA or
UNSTRUCTURED_GRID) that meshio cannot read are parsed here. Quads and polygons are split
into triangles; a tetrahedral volume mesh is reduced to its boundary surface.
"""

from __future__ import annotations

import contextlib
import io
import os
import warnings
from pathlib import Path

import numpy as np

from .errors import MeshError
from .mesh import TriMesh

__all__ = ["load_mesh", "save_mesh"]

_SURFACE_FORMATS = ".obj .stl .ply .off .vtk .vtu .msh .mesh .xdmf .med .inp"


def load_mesh(path: str | os.PathLike, *, scale: float = 1.0, repair: bool = True, merge_tol: float = 1e-10) -> TriMesh:
    """Load a triangle surface mesh from a file.

    Parameters
    ----------
    path : mesh file (OBJ, STL, PLY, OFF, VTK legacy or XML, VTU, Gmsh MSH, ...).
    scale : factor applied to the coordinates; organ meshes are usually in millimetres and
        the model works in SI units, so ``scale=1e-3`` turns mm into m.
    repair, merge_tol : see :class:`TriMesh`; the repairs are listed in ``mesh.report``.
    """
    p = Path(path)
    if not p.exists():
        raise MeshError(f"mesh file {str(p)!r} does not exist")
    if p.is_dir():
        raise MeshError(f"{str(p)!r} is a directory, not a mesh file")
    try:
        s = float(scale)
    except (TypeError, ValueError):
        raise MeshError(f"scale={scale!r} is not a number") from None
    if not np.isfinite(s) or s <= 0:
        raise MeshError(f"scale={scale!r} must be a finite number > 0 (1e-3 turns mm into m)")
    points, triangles, groups = _read(p)
    mesh = TriMesh(points * s, triangles, repair=repair, merge_tol=merge_tol, groups=groups)
    if s != 1.0:
        mesh.report.notes.append(f"coordinates scaled by {s:g}")
    return mesh


def save_mesh(mesh: TriMesh, path: str | os.PathLike, point_data: dict | None = None) -> None:
    """Write a mesh (optionally with per-vertex data) in the format the file suffix names."""
    import meshio

    meshio.write_points_cells(
        str(path), np.asarray(mesh.vertices), [("triangle", np.asarray(mesh.triangles))], point_data=point_data or {}
    )


def _read(p: Path) -> tuple[np.ndarray, np.ndarray, dict]:
    import meshio

    err: Exception | None = None
    if p.suffix.lower() == ".vtk" and _is_legacy_ascii_vtk(p):
        return _read_legacy_vtk(p)
    try:
        with contextlib.redirect_stdout(io.StringIO()), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # meshio's STL size probe overflows harmlessly
            m = meshio.read(str(p))
    except (Exception, SystemExit) as exc:  # meshio raises many kinds (and may sys.exit); report one clear error
        err = exc
    if err is not None:
        if p.suffix.lower() == ".vtk":
            return _read_legacy_vtk(p)
        known = "" if p.suffix.lower() in _SURFACE_FORMATS.split() else f" (suffix {p.suffix!r} is not a known mesh format)"
        raise MeshError(
            f"could not read {str(p)!r} as a mesh{known}: {type(err).__name__}: {err}. "
            f"Readable formats include {_SURFACE_FORMATS}"
        )
    tris = _triangles_from_cells([(c.type, np.asarray(c.data)) for c in m.cells], p)
    groups = {k: np.asarray(v).ravel() for k, v in (m.point_sets or {}).items()}
    return np.asarray(m.points, dtype=float), tris, groups


def _split_polygons(cells: np.ndarray) -> np.ndarray:
    """Fan-split k-gons into triangles; quads split along their shorter diagonal elsewhere."""
    k = cells.shape[1]
    parts = [cells[:, [0, i, i + 1]] for i in range(1, k - 1)]
    return np.concatenate(parts)


def _tet_boundary(tets: np.ndarray) -> np.ndarray:
    faces = np.concatenate([tets[:, [0, 2, 1]], tets[:, [0, 1, 3]], tets[:, [1, 2, 3]], tets[:, [0, 3, 2]]])
    key = np.sort(faces, axis=1)
    _, idx, cnt = np.unique(key, axis=0, return_index=True, return_counts=True)
    return faces[idx[cnt == 1]]


def _triangles_from_cells(cells: list[tuple[str, np.ndarray]], p: Path) -> np.ndarray:
    out: list[np.ndarray] = []
    tets: list[np.ndarray] = []
    for ctype, data in cells:
        if ctype in ("triangle", "triangle6", "triangle7"):
            out.append(data[:, :3])
        elif ctype in ("quad", "quad8", "quad9"):
            out.append(_split_polygons(data[:, :4]))
        elif ctype.startswith("polygon"):
            out.append(_split_polygons(data))
        elif ctype in ("tetra", "tetra10"):
            tets.append(data[:, :4])
    if not out and tets:
        out.append(_tet_boundary(np.concatenate(tets)))
    if not out:
        found = ", ".join(sorted({c for c, _ in cells})) or "no cells"
        raise MeshError(f"{str(p)!r} holds no surface cells (found: {found}); rtfem needs triangles, quads or polygons")
    return np.concatenate(out).astype(np.int64)


def _is_legacy_ascii_vtk(p: Path) -> bool:
    with open(p, "rb") as fh:
        head = fh.read(256).decode("latin-1").splitlines()
    return len(head) >= 3 and head[0].startswith("# vtk DataFile") and head[2].strip().upper() == "ASCII"


def _read_legacy_vtk(p: Path) -> tuple[np.ndarray, np.ndarray, dict]:
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
    tokens = " ".join(lines[3:]).split()
    pos = 0

    def take(k: int, what: str) -> list[str]:
        nonlocal pos
        if pos + k > len(tokens):
            raise MeshError(f"{str(p)!r} is truncated: expected {k} more values in {what}")
        out = tokens[pos : pos + k]
        pos += k
        return out

    def numbers(k: int, what: str, dtype) -> np.ndarray:
        values = take(k, what)
        try:
            return np.array(values, dtype=dtype)
        except ValueError:
            raise MeshError(f"{str(p)!r}: non-numeric value in {what}") from None

    points = None
    tris: list[np.ndarray] = []
    cells_conn = None
    while pos < len(tokens):
        key = tokens[pos].upper()
        pos += 1
        if key == "DATASET":
            kind = take(1, "DATASET")[0].upper()
            if kind not in ("POLYDATA", "UNSTRUCTURED_GRID"):
                raise MeshError(f"{str(p)!r}: VTK dataset {kind} is not a surface mesh (need POLYDATA or UNSTRUCTURED_GRID)")
        elif key == "POINTS":
            n = int(take(1, "POINTS")[0])
            take(1, "POINTS")  # data type
            points = numbers(3 * n, "POINTS", float).reshape(n, 3)
        elif key in ("POLYGONS", "TRIANGLE_STRIPS", "CELLS", "VERTICES", "LINES"):
            n, size = (int(x) for x in take(2, key))
            flat = numbers(size, key, np.int64)
            rows, i = [], 0
            for _ in range(n):
                k = int(flat[i])
                rows.append(flat[i + 1 : i + 1 + k])
                i += k + 1
            if key == "POLYGONS":
                for k in sorted({len(r) for r in rows}):
                    if k >= 3:
                        tris.append(_split_polygons(np.array([r for r in rows if len(r) == k])))
            elif key == "TRIANGLE_STRIPS":
                for r in rows:
                    for j in range(len(r) - 2):
                        tris.append((r[[j, j + 1, j + 2]] if j % 2 == 0 else r[[j + 1, j, j + 2]])[None, :])
            elif key == "CELLS":
                cells_conn = rows
        elif key == "CELL_TYPES":
            n = int(take(1, "CELL_TYPES")[0])
            types = numbers(n, "CELL_TYPES", np.int64)
            if cells_conn is None or len(cells_conn) != n:
                raise MeshError(f"{str(p)!r}: CELL_TYPES does not match CELLS")
            typed = {5: "triangle", 9: "quad", 7: "polygon", 10: "tetra"}
            cells = []
            for t, name in typed.items():
                sel = [np.asarray(cells_conn[i]) for i in np.flatnonzero(types == t)]
                if sel and name != "polygon":
                    cells.append((name, np.array(sel)))
                elif sel:
                    for s in sel:
                        cells.append(("polygon", s[None, :]))
            if cells:
                tris.append(_triangles_from_cells(cells, p))
        elif key in ("POINT_DATA", "CELL_DATA", "FIELD", "METADATA"):
            break  # attributes follow; the geometry is complete
    if points is None:
        raise MeshError(f"{str(p)!r}: no POINTS section found")
    if not tris:
        raise MeshError(f"{str(p)!r}: no POLYGONS, TRIANGLE_STRIPS or surface CELLS found")
    return points, np.concatenate(tris).astype(np.int64), {}
