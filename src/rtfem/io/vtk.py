"""Exports for ParaView and friends: VTU snapshots and PVD time series (through meshio)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Iterable
from xml.sax.saxutils import quoteattr

import numpy as np

from .. import validate
from ..errors import ModelError
from ..mesh.files import mesh_cells, point_field
from ..storage import atomic_target

__all__ = ["write_vtu", "write_pvd"]


def write_vtu(
    path: str | os.PathLike,
    mesh,
    displacements: np.ndarray | None = None,
    *,
    deformed: bool = False,
    point_data: dict[str, np.ndarray] | None = None,
) -> Path:
    """Write a mesh (a TriMesh, or a TetMesh: the volume with its tets) and a displacement
    field (n, 3) as a VTU file.

    The points are the mesh's reference (undeformed) positions and the field is point data
    ``displacement`` (with ``displacement_magnitude``): ParaView's convention, so that its Warp By
    Vector (scale 1) shows the deformed organ, deformed = points + displacement. The file says so
    in its field data: ``rtfem_reference_points`` = 1. ``deformed=True`` writes the displaced points
    instead (``rtfem_reference_points`` = 0): then warping by the field counts it twice.
    """
    import meshio

    path = Path(validate.path_like(path, "path"))
    deformed = validate.flag(deformed, "deformed")
    cells = mesh_cells(mesh)
    X = np.asarray(mesh.vertices, dtype=float)
    data = {}
    for name, values in (point_data or {}).items():
        data[str(name)] = point_field(values, X.shape[0], f"point_data[{name!r}]")
    if displacements is not None:
        u = point_field(displacements, X.shape[0], "displacements")
        if u.ndim != 2 or u.shape[1] < 3:
            raise ModelError(f"displacements must be an ({X.shape[0]}, 3) array, got shape {u.shape}")
        u = u[:, :3]
        data["displacement"] = u
        data["displacement_magnitude"] = np.linalg.norm(u, axis=1)
        if deformed:
            X = X + u
    reference = not (deformed and displacements is not None)
    with atomic_target(path, "VTU file") as tmp:
        meshio.write_points_cells(str(tmp), X, cells, point_data=data, binary=True, file_format="vtu")
        _mark_points(tmp, reference)
    return path


def _mark_points(path: Path, reference: bool) -> None:
    """Add the field data ``rtfem_reference_points`` (1: the points are at rest, 0: displaced) to the
    VTU meshio wrote at ``path`` (meshio's VTU writer writes no field data): the first element of the
    ``UnstructuredGrid``, where VTK reads a dataset's field data."""
    text = path.read_bytes()
    mark = (b'<UnstructuredGrid>\n<FieldData>\n<DataArray type="Int8" Name="rtfem_reference_points" '
            b'NumberOfTuples="1" format="ascii">' + (b"1" if reference else b"0") + b"</DataArray>\n</FieldData>")
    path.write_bytes(text.replace(b"<UnstructuredGrid>", mark, 1))


def write_pvd(path: str | os.PathLike, frames: Iterable[tuple[float, str | os.PathLike]]) -> Path:
    """Write a ParaView collection (.pvd) that lists (time, vtu file) frames."""
    path = Path(validate.path_like(path, "path"))
    rows = []
    for item in validate.entries(frames, "frames", "frame", 2, "a (time, vtu file) pair"):
        t = validate.number(item[0], "frame time", "a time in seconds")
        rows.append((t, Path(validate.path_like(item[1], "frame file"))))
    lines = ['<?xml version="1.0"?>', '<VTKFile type="Collection" version="0.1" byte_order="LittleEndian">', "  <Collection>"]
    for t, f in rows:
        rel = os.path.relpath(f, path.parent)
        lines.append(f'    <DataSet timestep="{t:.9g}" group="" part="0" file={quoteattr(rel)}/>')
    lines += ["  </Collection>", "</VTKFile>", ""]
    with atomic_target(path, "PVD file") as tmp:
        tmp.write_text("\n".join(lines))
    return path
