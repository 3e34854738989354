"""Fixed-mesh obstacles of scenes: a rigid triangle surface (a spine, a pelvis, an operating table's
pad, any mesh file) that bodies rest on and slide over.

A body's surface vertex within the scene's margin of the obstacle's surface (after the trial step)
is a contact point against the closest point of that surface, with the face's normal (the side the
triangles' winding makes outward is the free side; a closed surface's outside) and the vertex's own
slip (the obstacle does not move). A vertex beside the surface (its closest point on an edge with
the vertex off the face's normal line) or more than the margin behind it is not in contact, as
between bodies.
"""

from __future__ import annotations

import numpy as np

from .. import validate
from ..errors import ModelError
from ..mesh.surface import TriMesh

__all__ = ["MeshObstacle", "pair_search"]


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
        A mesh that is not a TriMesh with triangles, degenerate triangles, a negative friction.
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
        length = np.linalg.norm(normals, axis=1)
        if np.any(length <= 1e-12 * np.max(length)):
            raise ModelError(f"{name}: {int(np.sum(length <= 1e-12 * np.max(length)))} degenerate (zero-area) "
                             "triangles; repair the mesh (rtfem info reports them)")
        self.normals = normals / length[:, None]
        centres = self.Y.mean(axis=1)
        self.reach = float(np.max(np.linalg.norm(self.Y - centres[:, None], axis=2)))
        self.tree = cKDTree(centres)
        self.lo, self.hi = self.Y.reshape(-1, 3).min(axis=0), self.Y.reshape(-1, 3).max(axis=0)
        self.edge = float(np.median(np.linalg.norm(self.Y[:, 1] - self.Y[:, 0], axis=1)))

    def contacts(self, x: np.ndarray, margin: float):
        """The points x (k, 3) in contact: (their indices, gaps (m), the obstacle's normals there)."""
        from .contact_points import closest_points_on_triangles

        inside = np.flatnonzero(np.all((x >= self.lo - margin) & (x <= self.hi + margin), axis=1))
        none = (np.zeros(0, dtype=np.int64), np.zeros(0), np.zeros((0, 3)))
        if inside.size == 0:
            return none
        k = min(8, len(self.Y))
        dist, near = self.tree.query(x[inside], k=k, distance_upper_bound=self.reach + margin)
        near, dist = near.reshape(inside.size, k), dist.reshape(inside.size, k)
        hit = np.flatnonzero(np.isfinite(dist).any(axis=1))
        if hit.size == 0:
            return none
        valid = near[hit] < len(self.Y)
        tris = np.where(valid, near[hit], 0)
        P = np.repeat(x[inside[hit]], k, axis=0)
        Yt = self.Y[tris.ravel()]
        q, _ = closest_points_on_triangles(P, Yt[:, 0], Yt[:, 1], Yt[:, 2])
        d = np.where(valid.ravel(), np.linalg.norm(q - P, axis=1), np.inf).reshape(tris.shape)
        best = np.argmin(d, axis=1)
        rows = np.arange(hit.size) * k + best
        n = self.normals[tris[np.arange(hit.size), best]]
        delta = P[rows] - q[rows]
        gap = np.einsum("ij,ij->i", delta, n)
        lateral = np.linalg.norm(delta - gap[:, None] * n, axis=1)
        keep = (np.abs(gap) < margin) & (lateral <= 1e-3 * self.edge + 1e-12)
        return inside[hit][keep], gap[keep], n[keep]


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
    inside = np.flatnonzero(np.all((x >= lo) & (x <= hi), axis=1))  # b's box
    k = min(8, len(centres))
    if inside.size == 0:
        return np.zeros(0, dtype=np.int64), np.zeros((0, k), dtype=np.int64), np.zeros((0, k), dtype=bool)
    dist, near = cKDTree(centres).query(x[inside], k=k, distance_upper_bound=reach)
    near, dist = near.reshape(inside.size, k), dist.reshape(inside.size, k)
    hit = np.flatnonzero(np.isfinite(dist).any(axis=1))
    valid = near[hit] < len(centres)
    tris = np.where(valid, near[hit], 0)
    # kept: the vertices whose closest point on b is within the margin and the slack now
    from .contact_points import closest_points_on_triangles

    P = np.repeat(x[inside[hit]], k, axis=0)
    q, _ = closest_points_on_triangles(P, *(Y[tris.ravel(), c] for c in range(3)))
    d = np.where(valid.ravel(), np.linalg.norm(q - P, axis=1), np.inf).reshape(tris.shape)
    close = d.min(axis=1) < reach_beyond
    return inside[hit][close], tris[close], valid[close]
