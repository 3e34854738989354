"""Meshing a closed surface into tetrahedra with fTetWild (Hu et al., "Fast Tetrahedral Meshing
in the Wild", SIGGRAPH 2020; MPL-2.0) through the ``pytetwild`` wheel (the ``mesh`` extra).

fTetWild was chosen over TetGen (AGPL) and Gmsh (GPL) for its licence and its robustness: it
meshes the organ files with self-intersecting faces and slivers that constrained Delaunay
meshers refuse (measured in benchmarks/results/tetmesh.txt). Its output is an envelope
approximation of the input (within ``epsilon`` of the diagonal), so the surface nodes are new;
vertex groups are carried over to the nearest new surface nodes.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
from functools import lru_cache
from pathlib import Path

import numpy as np

from .. import validate
from ..errors import MeshError, RtfemError
from ..cache import cache_dir
from ..storage import load_versioned, save_versioned
from ._tetwild import find_wrapper
from .surface import TriMesh
from .tetmesh import TetMesh

__all__ = ["tetrahedralize", "mesher_available", "cached_tetrahedralize", "cache_dir"]

_EXTRA = "pip install 'rtfem[mesh]' (make installs it)"


@lru_cache(maxsize=1)
def _wrapper():
    """fTetWild's compiled entry point in this process, or None (whether the mesh extra is here)."""
    return find_wrapper()


def _remove_stale_scratch() -> None:
    """Remove the scratch folders of meshing processes that are gone (a process killed mid-mesh
    cannot remove its own)."""
    from ..storage import process_gone

    for path in Path(tempfile.gettempdir()).glob("rtfem-tetwild-*-*"):
        if process_gone(path.name.split("-")[2]):
            shutil.rmtree(path, ignore_errors=True)


def _run_mesher(V: np.ndarray, F: np.ndarray, fac: float, epsilon: float, optimize: bool,
                threads: int) -> tuple[np.ndarray, np.ndarray]:
    """fTetWild on unit-sized V, F in a child process (:mod:`rtfem.mesh._tetwild`, run as a script)
    working in a scratch folder of its own: fTetWild's debug surface does not litter the user's
    folder, and Ctrl-C (its own SIGINT handler ended the whole process, leaving that folder) ends
    the child; here it is a KeyboardInterrupt after the child is gone and the folder removed."""
    _remove_stale_scratch()
    args = json.dumps({"fac": float(fac), "epsilon": float(epsilon), "optimize": bool(optimize), "threads": int(threads)})
    with tempfile.TemporaryDirectory(prefix=f"rtfem-tetwild-{os.getpid()}-") as scratch:
        folder = Path(scratch)
        np.save(folder / "V.npy", V)
        np.save(folder / "F.npy", F)
        child = subprocess.Popen([sys.executable, str(Path(__file__).with_name("_tetwild.py")), scratch, args],
                                 cwd=scratch, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        try:
            _, err = child.communicate()
        except BaseException:  # Ctrl-C (or anything else) while it meshes: the child goes first
            child.kill()
            child.wait()
            raise
        if child.returncode != 0:
            lines = [line for line in err.splitlines() if line.strip()]
            why = lines[-1] if lines else f"the mesher stopped (exit status {child.returncode})"
            raise MeshError(f"fTetWild could not mesh the surface: {why}")
        return np.load(folder / "X.npy"), np.load(folder / "T.npy")


MAX_TETS = 3_000_000  # about what fTetWild meshes within this machine's memory (24 GB, a few kB a tet)


def mesher_available() -> bool:
    """Whether :func:`tetrahedralize` can run (the ``mesh`` extra is installed)."""
    return _wrapper() is not None


def tetrahedralize(surface: TriMesh, edge_length: float | None = None, *, epsilon: float = 1e-3,
                   optimize: bool = True, threads: int = 1) -> TetMesh:
    """Tetrahedra filling the closed ``surface``.

    Parameters
    ----------
    surface : TriMesh
        A closed surface (every edge shared by two triangles).
    edge_length : float, optional
        Target edge length in metres (default: 5 % of the bounding-box diagonal).
    epsilon : float
        How far the result's boundary may stray from the input surface, as a fraction of the
        diagonal (fTetWild's envelope; 1e-3 by default).
    optimize : bool
        Improve the tets' quality (fTetWild's AMIPS optimization); False is faster.
    threads : int
        fTetWild's threads; 0 for all cores. The result differs from run to run on one thread
        too (SOFA's liver2 at 8 mm: 4,389 to 4,447 nodes in three runs); keep a mesh with
        :func:`cached_tetrahedralize` or by saving it.

    Returns
    -------
    TetMesh
        The tets, whose vertex groups are the input's carried to the nearest new surface nodes.

    Raises
    ------
    MeshError
        For an open surface, or when the mesher is missing or fails.
    """
    if not isinstance(surface, TriMesh):
        raise MeshError(f"tetrahedralize needs a TriMesh surface, got {type(surface).__name__}")
    diag = surface.diagonal()
    if edge_length is None:
        fac = 0.05
    else:
        edge_length = validate.positive(edge_length, "edge_length", "a target edge length in m", error=MeshError)
        fac = edge_length / diag
        if not 1e-3 <= fac <= 0.5:
            raise MeshError(f"edge_length={edge_length:.3g} m is {fac:.2g} of the organ's diagonal ({diag:.3g} m); "
                            "give 0.001 .. 0.5 of it")
    epsilon = validate.in_range(epsilon, "epsilon", 1e-5, 0.1, what="a fraction of the diagonal", error=MeshError)
    threads = int(validate.count(threads, "threads", 0, 1024))
    optimize = validate.flag(optimize, "optimize", error=MeshError)
    if not surface.report.closed:
        raise MeshError(f"the surface has {surface.report.n_boundary_edges} boundary edges (holes): a volume needs a "
                        "closed surface. Close the holes (e.g. MeshLab's 'Close Holes', Blender's 'Fill') and try again")
    if surface.report.n_components > 1:
        raise MeshError(f"the surface has {surface.report.n_components} separate pieces; mesh one organ at a time "
                        "(or they would be meshed as one body)")
    wrapper = _wrapper()
    if wrapper is None:
        raise MeshError(f"rt.tetrahedralize needs the fTetWild mesher: {_EXTRA}")
    volume = abs(surface.volume())
    estimate = 8.5 * volume / (fac * diag) ** 3  # regular tets of the target edge: l^3 / (6 sqrt 2) each
    if estimate > MAX_TETS:
        least = (8.5 * volume / MAX_TETS) ** (1 / 3)
        raise MeshError(f"an edge length of {fac * diag:.3g} m would make about {estimate:.3g} tets in this "
                        f"{volume:.3g} m^3 volume, more than the {MAX_TETS:,} the mesher can hold in memory here: give "
                        f"edge_length >= {least:.2g} m")
    # the mesher works in absolute units (its tolerances fail on a body of micrometres): at unit size
    centre = 0.5 * (np.min(surface.vertices, axis=0) + np.max(surface.vertices, axis=0))
    V = np.array((np.asarray(surface.vertices) - centre) / diag, dtype=np.float64, order="C")
    F = np.array(surface.triangles, dtype=np.uint32, order="C")
    X, T = _run_mesher(V, F, fac, epsilon, optimize, threads)
    if len(T) == 0:
        raise MeshError("fTetWild produced no tets: the surface encloses no volume the mesher could find "
                        "(is it flat, or made of sheets?)")
    mesh = TetMesh(np.asarray(X, dtype=float) * diag + centre, np.asarray(T, dtype=np.int64))
    return _carry_groups(surface, mesh)


def _carry_groups(surface: TriMesh, mesh: TetMesh) -> TetMesh:
    """``mesh`` with the surface's groups: each new surface node joins the groups of its nearest
    old vertex; a single-vertex group (a probe point) becomes the nearest new surface node."""
    if not surface.groups:
        return mesh
    new = mesh.surface_nodes()
    old = np.asarray(surface.vertices)
    from scipy.spatial import cKDTree  # here: loading a mesh need not import scipy.spatial

    _, nearest = cKDTree(old).query(np.asarray(mesh.vertices)[new])
    groups = {}
    for name, idx in surface.groups.items():
        idx = np.asarray(idx)
        if idx.size == 1:
            d = np.linalg.norm(np.asarray(mesh.vertices)[new] - old[idx[0]], axis=1)
            groups[name] = new[[int(np.argmin(d))]]
        else:
            groups[name] = new[np.isin(nearest, idx)]
    return TetMesh(mesh.vertices, mesh.tets, repair=False, groups=groups)


def _cache_entry(surface: TriMesh, edge_length: float | None) -> tuple[str, Path]:
    h = hashlib.sha1()
    h.update(np.ascontiguousarray(surface.vertices).tobytes())
    h.update(np.ascontiguousarray(surface.triangles, dtype=np.int64).tobytes())
    h.update(repr(edge_length).encode())
    key = h.hexdigest()
    return key, cache_dir() / f"tets-{key[:20]}.npz"


def is_cached(surface: TriMesh, edge_length: float | None = None) -> bool:
    """Whether :func:`cached_tetrahedralize` has this surface's tets on disk (no meshing to wait for)."""
    return _cache_entry(surface, edge_length)[1].is_file()


def cached_tetrahedralize(surface: TriMesh, edge_length: float | None = None) -> TetMesh:
    """:func:`tetrahedralize`, kept on disk (:func:`cache_dir`) under a hash of the surface and
    the edge length. fTetWild's result differs from run to run, so a generated organ (the solid
    default liver) would otherwise get a new mesh, and saved results a new fingerprint, in every
    process; with the cache it is made once per machine. A cache file that does not read back
    as a valid mesh is replaced."""
    key, path = _cache_entry(surface, edge_length)
    if path.is_file():
        try:  # checksummed, and made from this surface (a file swapped in from another key is not)
            z, info = load_versioned(path, "rtfem.TetCache", 1, ["vertices", "tets"], "tet mesh cache")
            if info.get("key") == key:
                groups = {g: np.asarray(info["groups"][g], dtype=np.int64) for g in info.get("groups", {})}
                return TetMesh(z["vertices"], z["tets"], repair=False, groups=groups)
        except RtfemError:  # a broken, altered or foreign cache file is regenerated
            pass
    mesh = tetrahedralize(surface, edge_length)
    try:
        save_versioned(path, "rtfem.TetCache", 1, {"vertices": mesh.vertices, "tets": mesh.tets},
                       {"key": key, "groups": {k: np.asarray(v).tolist() for k, v in mesh.groups.items()}})
    except RtfemError:
        pass  # a read-only home: the mesh is still returned, only not kept
    return mesh
