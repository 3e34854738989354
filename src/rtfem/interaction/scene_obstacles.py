"""Rigid obstacles of scenes: planes, and fixed meshes: a rigid triangle surface (a spine, a pelvis, an operating table's
pad, any mesh file) that bodies rest on and slide over.

A body's surface vertex within the scene's margin of the obstacle's surface (after the trial step)
is a contact point against the closest point of that surface, with the face's normal (the side the
triangles' winding makes outward is the free side; a closed surface's outside) and the vertex's own
slip (the obstacle does not move). A vertex beside the surface (its closest point on an edge with
the vertex off the face's normal line) or more than the margin behind it is not in contact, as
between bodies.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .. import validate
from ..errors import ModelError
from ..mesh.surface import TriMesh
from .scene_tools import _frame

__all__ = ["Plane", "MeshObstacle", "pair_search"]


@dataclass
class Plane:
    """A rigid plane: the half-space behind ``normal`` is solid.

    Parameters
    ----------
    name : its name in the contact records.
    point : a point on it (m).
    normal : its outward normal (any length > 0).
    friction : Coulomb's coefficient against it (0: frictionless).

    Raises
    ------
    ModelError
        A point that is not one, a zero normal, a negative friction.
    """

    name: str
    point: np.ndarray
    normal: np.ndarray
    friction: float = 0.0

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name:
            raise ModelError(f"an obstacle's name must be a non-empty string, got {validate.show(self.name)}")
        self.point = np.array(validate.point(self.point, f"{self.name}: point"), dtype=float)
        n = validate.vector(self.normal, f"{self.name}: normal", 3)
        if not np.linalg.norm(n) > 0:
            raise ModelError(f"{self.name}: normal must be a non-zero vector (the plane's outward normal)")
        self.normal = n / np.linalg.norm(n)
        self.friction = validate.in_range(self.friction, f"{self.name}: friction", 0.0, 10.0,
                                          what="Coulomb's friction coefficient")
        self.frame = _frame(self.normal)

    def gaps(self, x: np.ndarray) -> np.ndarray:
        """Signed distances (m) of points x (k, 3) in front of the plane."""
        return (x - self.point) @ self.normal

    def contacts(self, x: np.ndarray, margin: float):
        """The points x (k, 3) within ``margin`` of the plane or behind it: (indices, gaps, normals)."""
        gaps = self.gaps(x)
        i = np.flatnonzero(gaps < margin)
        return i, gaps[i], np.broadcast_to(self.normal, (i.size, 3))


class MeshObstacle:
    """A rigid obstacle given by a triangle surface, fixed in the scene's frame.

    Parameters
    ----------
    name : its name in the contact records.
    mesh : a :class:`~rtfem.TriMesh` (its triangles' winding gives the free side).
    friction : Coulomb's coefficient against it (0: frictionless).

    Raises
    ------
    ModelError
        A mesh that is not a TriMesh with triangles, a negative friction.
    """

    def __init__(self, name: str, mesh: TriMesh, friction: float = 0.0) -> None:
        from scipy.spatial import cKDTree

        if not isinstance(name, str) or not name:
            raise ModelError(f"an obstacle's name must be a non-empty string, got {validate.show(name)}")
        if not isinstance(mesh, TriMesh) or len(mesh.triangles) == 0:
            raise ModelError(f"{name}: mesh must be an rt.TriMesh with triangles (a surface), got {validate.show(mesh)}")
        self.name, self.mesh = name, mesh
        self.friction = validate.in_range(friction, f"{name}: friction", 0.0, 10.0, what="Coulomb's friction coefficient")
        self.Y = np.asarray(mesh.vertices, dtype=float)[np.asarray(mesh.triangles)]  # (t, 3, 3)
        normals = np.cross(self.Y[:, 1] - self.Y[:, 0], self.Y[:, 2] - self.Y[:, 0])
        self.normals = normals / np.linalg.norm(normals, axis=1)[:, None]  # a TriMesh has no zero-area triangle
        centres = self.Y.mean(axis=1)
        self.reach = float(np.max(np.linalg.norm(self.Y - centres[:, None], axis=2)))
        self.tree = cKDTree(centres)
        self.lo, self.hi = self.Y.reshape(-1, 3).min(axis=0), self.Y.reshape(-1, 3).max(axis=0)
        self.edge = float(np.median(np.linalg.norm(self.Y[:, 1] - self.Y[:, 0], axis=1)))

    def contacts(self, x: np.ndarray, margin: float):
        """The points x (k, 3) in contact: (their indices, gaps (m), the obstacle's normals there)."""
        idx, tris, valid = candidate_faces(x, self.tree, self.reach + margin, self.lo - margin, self.hi + margin)
        if idx.size == 0:
            return np.zeros(0, dtype=np.int64), np.zeros(0), np.zeros((0, 3))
        best, q, _, _ = nearest_face_points(x[idx], self.Y, tris, valid)
        n = self.normals[tris[np.arange(idx.size), best]]
        gap, on = on_faces(x[idx], q, n, margin, self.edge)
        return idx[on], gap[on], n[on]


def candidate_faces(x: np.ndarray, tree, reach: float, lo: np.ndarray, hi: np.ndarray, k: int = 8):
    """The points x (m, 3) inside the box [lo, hi] with a triangle centre (``tree``) within ``reach``,
    and for each the (up to) k triangles with the nearest centres: (indices into x, triangles (c, k),
    valid (c, k): False where fewer than k were within reach)."""
    inside = np.flatnonzero(np.all((x >= lo) & (x <= hi), axis=1))
    k = min(k, tree.n)
    if inside.size == 0:
        return np.zeros(0, dtype=np.int64), np.zeros((0, k), dtype=np.int64), np.zeros((0, k), dtype=bool)
    dist, near = tree.query(x[inside], k=k, distance_upper_bound=reach)
    near, dist = near.reshape(inside.size, k), dist.reshape(inside.size, k)
    hit = np.flatnonzero(np.isfinite(dist).any(axis=1))
    valid = near[hit] < tree.n
    return inside[hit], np.where(valid, near[hit], 0), valid


def nearest_face_points(x: np.ndarray, Y: np.ndarray, tris: np.ndarray, valid: np.ndarray):
    """For points x (c, 3) and their candidate triangles ``tris`` (c, k) of the triangles Y (t, 3, 3):
    (the nearest candidate's column (c,), its closest points (c, 3), their barycentric weights (c, 3),
    the distances (c,))."""
    from .contact_points import closest_points_on_triangles

    k = tris.shape[1]
    P = np.repeat(x, k, axis=0)
    q, w = closest_points_on_triangles(P, *(Y[tris.ravel(), c] for c in range(3)))
    d = np.where(valid.ravel(), np.linalg.norm(q - P, axis=1), np.inf).reshape(tris.shape)
    best = np.argmin(d, axis=1)
    rows = np.arange(x.shape[0]) * k + best
    return best, q[rows], w[rows], d[np.arange(x.shape[0]), best]


def on_faces(x: np.ndarray, q: np.ndarray, n: np.ndarray, margin: float, edge: float):
    """The gaps (c,) of points x from their face points q along the faces' unit normals n, and
    whether each is a contact: within ``margin`` of the face and on its normal line (a point beside
    the surface, or through the body, is not this face's contact)."""
    delta = x - q
    gap = np.einsum("ij,ij->i", delta, n)
    lateral = np.linalg.norm(delta - gap[:, None] * n, axis=1)
    return gap, (np.abs(gap) < margin) & (lateral <= 1e-3 * edge + 1e-12)


def pair_search(a, b, trial_a, trial_b, reach_beyond: float):
    """a's surface vertices (indices into a.surface) within ``reach_beyond`` of b's deformed
    surface, each with b's triangles whose centres are the eight nearest within b's largest
    triangle radius + ``reach_beyond``: (cand, tris, valid)."""
    from scipy.spatial import cKDTree

    tri = np.asarray(b.mesh.triangles)
    Y = b.X[tri] + trial_b[b.local[tri]]
    centres = Y.mean(axis=1)
    reach = float(np.max(np.linalg.norm(Y - centres[:, None], axis=2))) + reach_beyond
    lo, hi = Y.reshape(-1, 3).min(axis=0) - reach_beyond, Y.reshape(-1, 3).max(axis=0) + reach_beyond
    x = a.X[a.surface] + trial_a
    idx, tris, valid = candidate_faces(x, cKDTree(centres), reach, lo, hi)
    if idx.size == 0:
        return idx, tris, valid
    # kept: the vertices whose closest point on b is within the margin and the slack now
    close = nearest_face_points(x[idx], Y, tris, valid)[3] < reach_beyond
    return idx[close], tris[close], valid[close]
