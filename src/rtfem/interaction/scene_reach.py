"""Which bodies of a :class:`~rtfem.Scene` nothing can touch this step, so that their trial step (the
contact search's look ahead, a whole nonlinear step for a full-order body) is not taken: a body on no
spring whose bounding sphere, grown by how far its surface moved over the last step (four times, and
the contact margin), is apart from every plane, obstacle, other body and tool. Such a body's contact
search would find nothing, so its step is the same with or without the trial (tested bit for bit)."""

from __future__ import annotations

import numpy as np

from ..drivers.base import displacements_at

__all__ = ["untouched"]

SQRT3 = 1.7321  # a displacement's length is at most sqrt(3) times its largest component


def untouched(scene, spring_nodes: dict) -> list[np.ndarray | None]:
    """For each body: its surface displacements now (s, 3) where nothing can touch it this step (its trial
    step may be skipped: the trial's surface is then taken to be where it is now), else None. Only bodies
    whose trial is a step of their own (a driver whose compliances follow its motion) are looked at."""
    bodies = scene.bodies
    out: list[np.ndarray | None] = [None] * len(bodies)
    own = [getattr(b.driver, "compliance_changes", True) for b in bodies]
    look = [k for k, b in enumerate(bodies) if own[k] and k not in spring_nodes and getattr(b, "_last_now", None) is not None]
    # (with none to look at, only the bodies that may be looked at next step need where they are)
    now = [displacements_at(b.driver, b.surface) if look or own[k] else None for k, b in enumerate(bodies)]
    if look:
        spheres = []
        for b, u in zip(bodies, now):
            last = getattr(b, "_last_now", None)
            moved = np.abs(u - last).max() if last is not None and last.shape == u.shape else np.inf
            spheres.append((b.centre, b.radius + SQRT3 * (np.abs(u).max() + 4.0 * moved) + scene.margin * b.edge
                            + b.longest))
        for k in look:
            c, r = spheres[k]
            if np.isfinite(r) and _apart(scene, k, c, r, spheres):
                out[k] = now[k]
    for b, u in zip(bodies, now):
        if u is not None:
            b._last_now = u
    return out


def _apart(scene, k: int, c: np.ndarray, r: float, spheres) -> bool:
    """Whether the sphere (c, r) of body k is apart from every plane, obstacle, other body and tool."""
    for obstacle in scene.obstacles:
        if hasattr(obstacle, "normal"):
            if float((c - obstacle.point) @ obstacle.normal) <= r:
                return False
        elif np.linalg.norm(c - 0.5 * (obstacle.lo + obstacle.hi)) <= r + 0.5 * np.linalg.norm(obstacle.hi - obstacle.lo):
            return False
    for j, (cj, rj) in enumerate(spheres):
        if j != k and np.linalg.norm(c - cj) <= r + rj:
            return False
    for tool in scene.tools:
        extent = max(float(tool.radius), float(getattr(tool.shape, "reach", 0.0)))
        for x in (tool.target, tool.proxy):
            if x is None or np.linalg.norm(np.asarray(x) - c) <= r + extent:
                return False
    return True
