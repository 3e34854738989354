"""Exports for ParaView and friends: VTU snapshots and PVD time series (through meshio)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Iterable
from xml.sax.saxutils import quoteattr

import numpy as np

from .mesh import TriMesh

__all__ = ["write_vtu", "write_pvd"]


def write_vtu(
    path: str | os.PathLike,
    mesh: TriMesh,
    displacements: np.ndarray | None = None,
    *,
    deformed: bool = True,
    point_data: dict[str, np.ndarray] | None = None,
) -> Path:
    """Write a mesh and a displacement field (n, 3) as a VTU file.

    With ``deformed`` the points are written at their displaced positions, so the file shows
    the deformed organ as it is; the field is stored as point data ``displacement`` and
    ``displacement_magnitude`` either way (ParaView: colour by it, or Warp By Vector).
    """
    import meshio

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    X = np.asarray(mesh.vertices, dtype=float)
    data = dict(point_data or {})
    if displacements is not None:
        u = np.asarray(displacements, dtype=float).reshape(X.shape[0], -1)[:, :3]
        data["displacement"] = u
        data["displacement_magnitude"] = np.linalg.norm(u, axis=1)
        if deformed:
            X = X + u
    meshio.write_points_cells(str(path), X, [("triangle", np.asarray(mesh.triangles))], point_data=data, binary=True)
    return path


def write_pvd(path: str | os.PathLike, frames: Iterable[tuple[float, str | os.PathLike]]) -> Path:
    """Write a ParaView collection (.pvd) that lists (time, vtu file) frames."""
    path = Path(path)
    lines = ['<?xml version="1.0"?>', '<VTKFile type="Collection" version="0.1" byte_order="LittleEndian">', "  <Collection>"]
    for t, f in frames:
        rel = os.path.relpath(Path(f), path.parent)
        lines.append(f'    <DataSet timestep="{float(t):.9g}" group="" part="0" file={quoteattr(rel)}/>')
    lines += ["  </Collection>", "</VTKFile>", ""]
    path.write_text("\n".join(lines))
    return path
