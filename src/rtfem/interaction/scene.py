"""Scenes: several bodies under gravity against rigid obstacles (issue 40's first part).

A :class:`Scene` holds bodies (any Driver with the surface it is touched on) and rigid planes, and
steps them together. Each step of each body:

1. the body's trial step under its weight (and any loads held), from its saved state: where its
   surface would be with no contact (the step is affine in the loads, so this is exact);
2. the contact points: the surface vertices within ``margin`` of a plane there, each with its gap,
   its slip over the step and the plane's frame (normal, two tangents);
3. the frictional contact problem w = b + A r of those points (A = F^T W F, W the driver's one-step
   compliances of their nodes), solved by the projected Gauss-Seidel of
   :mod:`rtfem.interaction.friction` (Signorini's conditions and Coulomb's law);
4. the body's step from its state under its weight and the contact forces.

The force of each obstacle on each body is recorded every step (:attr:`Scene.contacts`).
A free body (nothing fixed) is simulated on its modes with the six rigid-body ones among them
(:func:`rtfem.modal_analysis` shifts below zero for it): its weight goes to the obstacles.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .. import validate
from ..errors import ModelError
from ..drivers.base import as_driver, check_driver_mesh, displacements_at, step_compliances
from ..mesh.surface import TriMesh
from .friction import pgs

__all__ = ["Scene", "Plane", "Body"]


def _frame(normal: np.ndarray) -> np.ndarray:
    """(3, 3) columns: the unit normal and two unit tangents."""
    n = normal / np.linalg.norm(normal)
    a = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    t1 = np.cross(n, a)
    t1 /= np.linalg.norm(t1)
    return np.column_stack([n, t1, np.cross(n, t1)])


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


@dataclass
class Body:
    """A deformable body of a scene: a Driver, the surface it is touched on and its weight.

    Parameters
    ----------
    name : its name in the contact records.
    driver : any Driver (linear or reduced modal, full order).
    mesh : the surface (:class:`~rtfem.TriMesh`) over the driver's nodes (a solid's ``model.mesh``).
    masses : (n,) each node's mass (kg) for its weight; default the driver's model's lumped masses.

    Raises
    ------
    ModelError
        A driver that is not one or is of another mesh, masses of the wrong size or negative.
    """

    name: str
    driver: object
    mesh: TriMesh
    masses: np.ndarray | None = None
    loads: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name:
            raise ModelError(f"a body's name must be a non-empty string, got {validate.show(self.name)}")
        self.driver = as_driver(self.driver, f"body {self.name}")
        check_driver_mesh(self.mesh, self.driver, f"body {self.name}")
        n = self.driver.n_nodes
        if self.masses is None:
            model = _model_of(self.driver)
            if model is None:
                raise ModelError(f"body {self.name}: give masses= (the driver does not say its model's masses)")
            diag = np.asarray(model.mass_diagonal, dtype=float)
            self.masses = diag.reshape(n, -1)[:, 0]
        self.masses = validate.real_array(self.masses, f"body {self.name}: masses")
        if self.masses.shape != (n,) or np.any(self.masses < 0):
            raise ModelError(f"body {self.name}: masses must be ({n},) values >= 0, got {self.masses.shape}")
        self.surface = self.mesh.used_vertices()
        self.X = np.asarray(self.mesh.vertices)
        edges = np.linalg.norm(np.diff(self.X[np.asarray(self.mesh.triangles)][:, [0, 1]], axis=1)[:, 0], axis=1)
        self.edge = float(np.median(edges))
        self.loads = np.zeros((n, 3))

    @property
    def mass(self) -> float:
        return float(self.masses.sum())


def _model_of(driver):
    for path in (("model",), ("modes", "model"), ("reduced", "model")):
        obj = driver
        for name in path:
            obj = getattr(obj, name, None)
        if obj is not None and hasattr(obj, "mass_diagonal"):
            return obj
    return None


class Scene:
    """Bodies under gravity against rigid obstacles, stepped together.

    Parameters
    ----------
    gravity : (3,) m/s^2 (default (0, 0, -9.81): +z up).
    margin : points within this fraction of a body's median edge of an obstacle (after the trial
        step) enter its contact problem (default 0.5).

    Raises
    ------
    ModelError
        A gravity that is not three finite numbers, a non-positive margin; from :meth:`add_body`
        and :meth:`add_plane`, their checks, a name used twice, bodies with different time steps.
    """

    def __init__(self, gravity=(0.0, 0.0, -9.81), *, margin: float = 0.5) -> None:
        self.gravity = np.array(validate.vector(gravity, "gravity", 3), dtype=float)
        self.margin = validate.positive(margin, "margin", "a fraction of an edge")
        self.bodies: list[Body] = []
        self.obstacles: list[Plane] = []
        self.time = 0.0
        self.steps = 0
        #: the force (N) of each obstacle on each body in the last step: {(body, obstacle): (3,)}
        self.contacts: dict[tuple[str, str], np.ndarray] = {}
        self.sweeps = 0

    def _name_free(self, name: str) -> None:
        if any(x.name == name for x in (*self.bodies, *self.obstacles)):
            raise ModelError(f"the scene already has a body or obstacle named {name!r}: give each its own name")

    def add_body(self, name: str, driver, mesh: TriMesh, masses=None) -> Body:
        """A body (see :class:`Body`); all bodies step with the same dt."""
        self._name_free(name)
        body = Body(name, driver, mesh, masses)
        if self.bodies and abs(body.driver.dt - self.dt) > 1e-12 * self.dt:
            raise ModelError(f"body {name}: dt = {body.driver.dt:g} s, the scene's bodies step with {self.dt:g} s")
        self.bodies.append(body)
        return body

    def add_plane(self, name: str, point, normal, friction: float = 0.0) -> Plane:
        """A rigid plane (see :class:`Plane`)."""
        self._name_free(name)
        plane = Plane(name, point, normal, friction)
        self.obstacles.append(plane)
        return plane

    @property
    def dt(self) -> float:
        if not self.bodies:
            raise ModelError("the scene has no body yet: add_body first")
        return float(self.bodies[0].driver.dt)

    def body(self, name: str) -> Body:
        for b in self.bodies:
            if b.name == name:
                return b
        raise ModelError(f"no body named {name!r} (bodies: {', '.join(b.name for b in self.bodies) or 'none'})")

    def step(self) -> None:
        """One step of every body (see the module's docstring)."""
        if not self.bodies:
            raise ModelError("the scene has no body: add_body first")
        contacts = {}
        for body in self.bodies:
            contacts.update(self._step_body(body))
        self.contacts = contacts
        self.steps += 1
        self.time = self.steps * self.dt

    def run(self, n_steps: int) -> None:
        for _ in range(validate.count(n_steps, "n_steps", 0, 10**9)):
            self.step()

    def _weight(self, body: Body) -> np.ndarray:
        return body.masses[:, None] * self.gravity[None, :] + body.loads

    def _step_body(self, body: Body) -> dict:
        d = body.driver
        F = self._weight(body)
        state = d.get_state()
        now = displacements_at(d, body.surface)
        d.step(F)
        trial = displacements_at(d, body.surface)
        d.set_state(state)
        x = body.X[body.surface] + trial
        points = []  # (obstacle index, surface row, gap)
        for k, obstacle in enumerate(self.obstacles):
            gaps = obstacle.gaps(x)
            near = np.flatnonzero(gaps < self.margin * body.edge)
            points += [(k, int(i), float(gaps[i])) for i in near]
        out = {(body.name, o.name): np.zeros(3) for o in self.obstacles}
        if not points:
            d.step(F)
            return out
        nodes = np.array([body.surface[i] for _, i, _ in points], dtype=np.int64)
        unique, slot = np.unique(nodes, return_inverse=True)
        W = step_compliances(d, unique)
        m = len(points)
        frames = np.stack([self.obstacles[k].frame for k, _, _ in points])  # (m, 3, 3)
        rows = (3 * slot[:, None] + np.arange(3)).ravel()
        G = np.zeros((3 * m, 3 * m))  # the points' frames on the diagonal
        for a in range(m):
            G[3 * a:3 * a + 3, 3 * a:3 * a + 3] = frames[a]
        A = G.T @ W[np.ix_(rows, rows)] @ G  # F^T W F
        slip = trial - now
        b = np.empty((m, 3))
        for a, (k, i, gap) in enumerate(points):
            b[a, 0] = gap
            b[a, 1:] = frames[a][:, 1:].T @ slip[i]
        mu = np.array([self.obstacles[k].friction for k, _, _ in points])
        warm = getattr(body, "_warm", None)
        r0 = warm.get(tuple(nodes.tolist())) if warm else None
        r, self.sweeps = pgs(A, b.reshape(-1), mu, r0)
        r = r.reshape(m, 3)
        body._warm = {tuple(nodes.tolist()): r.reshape(-1)}
        f = np.einsum("mij,mj->mi", frames, r)  # each point's force on the body
        for a, (k, i, _) in enumerate(points):
            F[body.surface[i]] += f[a]
            out[(body.name, self.obstacles[k].name)] += f[a]
        d.step(F)
        return out
