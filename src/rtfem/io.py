"""Exports for ParaView and friends: VTU snapshots and PVD time series (through meshio)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Iterable
from xml.sax.saxutils import quoteattr

import numpy as np

from .errors import ModelError
from .mesh import TriMesh

__all__ = ["write_vtu", "write_pvd", "save_versioned", "load_versioned"]


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


def save_versioned(path: str | os.PathLike, kind: str, version: int, arrays: dict[str, np.ndarray], info: dict) -> Path:
    """Save arrays as a compressed ``.npz`` tagged with a format name and version (no pickle).

    ``info`` keeps its plain scalar entries (numbers, strings, booleans) as text.
    """
    path = Path(path)
    if path.suffix != ".npz":
        path = path.with_name(path.name + ".npz")
    info = {k: v for k, v in info.items() if isinstance(v, (int, float, str, bool))}
    np.savez_compressed(path, format=np.array(kind), version=np.array(version), **arrays,
                        info_keys=np.array(list(info), dtype=str),
                        info_values=np.array([str(v) for v in info.values()], dtype=str))
    return path


def load_versioned(path: str | os.PathLike, kind: str, version: int, names: list[str],
                   what: str) -> tuple[dict[str, np.ndarray], dict]:
    """Load what :func:`save_versioned` wrote, checking the format name, the version and the arrays.

    ``what`` names the content in error messages ("modal basis").
    """
    path = Path(path)
    if not path.exists():
        raise ModelError(f"{what} file {str(path)!r} does not exist")
    try:
        with np.load(path, allow_pickle=False) as z:
            if "format" not in z or str(z["format"]) != kind:
                raise ModelError(f"{str(path)!r} is not an rtfem {what} file")
            v = int(z["version"])
            if v > version:
                raise ModelError(f"{str(path)!r} has format version {v}; this rtfem reads up to {version}: upgrade rtfem")
            missing = [n for n in names if n not in z]
            if missing:
                raise ModelError(f"{str(path)!r} lacks {', '.join(missing)}: the file is damaged")
            arrays = {n: z[n] for n in names}
            info = dict(zip(z["info_keys"].tolist(), z["info_values"].tolist()))
    except ModelError:
        raise
    except Exception as exc:
        raise ModelError(f"could not read {what} {str(path)!r}: {exc}") from None
    return arrays, info
