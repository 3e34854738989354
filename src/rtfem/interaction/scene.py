"""Scenes: several bodies under gravity, touching rigid obstacles and each other (issue 40, in part).

A :class:`Scene` holds bodies (any Driver with the surface it is touched on) and rigid planes, and
steps them together. Each step of each body:

1. the body's trial step under its weight (and any loads held), from its saved state: where its
   surface would be with no contact (the step is affine in the loads, so this is exact);
2. the contact points: the surface vertices within ``margin`` of a plane there, and of another
   body's surface (against its closest point, in both directions of every pair), each with its
   gap, its slip over the step relative to the other side and a frame (the normal from the other
   side, two tangents);
3. the frictional contact problem w = b + A r of all the points together, A = G^T (sum_k P_k W_k
   P_k^T) G with W_k each body's one-step compliances of its nodes in contact (so both bodies'
   compliances add for their relative motion), solved by the projected Gauss-Seidel of
   :mod:`rtfem.interaction.friction` (Signorini's conditions and Coulomb's law); a point's force acts
   on its vertex and, opposite, on the other body's triangle (momentum is kept);
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
from ..drivers.base import (as_driver, check_driver_mesh, displacements_at, predictions, step_compliances,
                             trial_displacements)
from ..mesh.surface import TriMesh
from .scene_obstacles import MeshObstacle, Plane, pair_search
from .scene_points import PointSet, contact_solve
from .scene_reach import untouched
from .scene_search import pair_block, probe_block
from .scene_springs import spring_key, spring_system, warm_springs
from .scene_scalpel import SceneScalpel, recut
from .scene_tools import SceneTool

__all__ = ["Scene", "Plane", "Body", "Attachment"]


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
        self.normals = self.mesh.vertex_normals()[self.surface]
        self.local = np.full(self.X.shape[0], -1, dtype=np.int64)  # a node's place in surface, -1 off it
        self.local[self.surface] = np.arange(self.surface.size)
        self.tri_local = np.ascontiguousarray(self.local[np.asarray(self.mesh.triangles)])  # corners in surface order
        edges = np.linalg.norm(np.diff(self.X[np.asarray(self.mesh.triangles)][:, [0, 1]], axis=1)[:, 0], axis=1)
        self.edge = float(np.median(edges))
        rest = self.X[self.surface]
        self.centre = 0.5 * (rest.min(axis=0) + rest.max(axis=0))  # a sphere holding the surface at rest
        self.radius = float(np.linalg.norm(rest - self.centre, axis=1).max())
        self.longest = float(np.max(np.linalg.norm(self.X[np.asarray(self.mesh.triangles)]
                                                   - np.roll(self.X[np.asarray(self.mesh.triangles)], 1, axis=1), axis=2)))
        self.loads = np.zeros((n, 3))

    @property
    def mass(self) -> float:
        return float(self.masses.sum())


@dataclass
class Attachment:
    """Springs holding nodes of a body to the world, or to nodes of another body (ligaments, vessels):
    each pair keeps its rest offset, the force k (x_b - x_a - (X_b - X_a)) on a's node and its opposite
    on b's (to the world: the node's rest position). Implicit: the forces are those at the end of the
    step, solved with the bodies' one-step compliances (the step is affine in the loads), so a spring
    of any stiffness is stable and an undamped one keeps its energy.

    Parameters
    ----------
    name : its name in the contact records.
    a : the body whose nodes are held; nodes_a : their indices.
    b : the other body, or None: the world; nodes_b : b's nodes paired with nodes_a (default: the
        nearest node of b's surface to each, at rest).
    stiffness : each spring's stiffness (N/m).

    Raises
    ------
    ModelError
        Nodes off a body, pairs of different lengths, a non-positive stiffness.
    """

    name: str
    a: "Body"
    nodes_a: np.ndarray
    b: "Body | None"
    nodes_b: np.ndarray | None
    stiffness: float

    def __post_init__(self) -> None:
        self.nodes_a = validate.nodes(self.nodes_a, self.a.driver.n_nodes, f"attachment {self.name}: nodes")
        self.stiffness = validate.positive(self.stiffness, f"attachment {self.name}: stiffness", "a spring in N/m")
        if self.b is None:
            self.anchor = self.a.X[self.nodes_a].copy()
            return
        if self.nodes_b is None:
            from scipy.spatial import cKDTree

            surface = self.b.surface
            self.nodes_b = surface[cKDTree(self.b.X[surface]).query(self.a.X[self.nodes_a])[1]]
        self.nodes_b = validate.nodes(self.nodes_b, self.b.driver.n_nodes, f"attachment {self.name}: nodes of {self.b.name}")
        if self.nodes_b.shape != self.nodes_a.shape:
            raise ModelError(f"attachment {self.name}: {self.nodes_a.size} nodes of {self.a.name} against "
                             f"{self.nodes_b.size} of {self.b.name}: give pairs")
        self.rest = self.b.X[self.nodes_b] - self.a.X[self.nodes_a]


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
    margin : points within this fraction of a body's median edge of an obstacle or of another body
        (after the trial steps) enter the contact problem (default 0.5).
    friction : Coulomb's coefficient between bodies (each plane has its own).

    Raises
    ------
    ModelError
        A gravity that is not three finite numbers, a non-positive margin, a negative friction; from :meth:`add_body`
        and :meth:`add_plane`, their checks, a name used twice, bodies with different time steps.
    """

    def __init__(self, gravity=(0.0, 0.0, -9.81), *, margin: float = 0.5, friction: float = 0.0) -> None:
        self.gravity = np.array(validate.vector(gravity, "gravity", 3), dtype=float)
        self.margin = validate.positive(margin, "margin", "a fraction of an edge")
        self.friction = validate.in_range(friction, "friction", 0.0, 10.0, what="Coulomb's coefficient between bodies")
        self.bodies: list[Body] = []
        self.obstacles: list[Plane | MeshObstacle] = []
        self.attachments: list[Attachment] = []
        self.tools: list[SceneTool] = []
        self.scalpels: list = []  # SceneScalpel: blades cutting a body each (add_scalpel)
        self.view = None  # the viewer's camera direction from the scene's centre (a scene file's view)
        self.time = 0.0
        self.steps = 0
        #: the force (N) of each obstacle on each body in the last step: {(body, obstacle): (3,)}
        self.contacts: dict[tuple[str, str], np.ndarray] = {}
        self.sweeps = 0
        self.compiled = True  # the compiled contact search where numba is present (False: numpy)
        self.skip_trials = True  # a full-order body nothing can touch takes no trial step (scene_reach; False: all do)
        self._spring_forces: dict = {}  # each spring set's forces (S, 3) in the last step, by name: scene_springs.warm_springs

    def _name_free(self, name: str) -> None:
        if any(x.name == name for x in (*self.bodies, *self.obstacles, *self.attachments, *self.tools, *self.scalpels)):
            raise ModelError(f"the scene already has a body, obstacle, attachment, tool or scalpel named {name!r}: "
                             "give each its own name")

    def add_body(self, name: str, driver, mesh: TriMesh, masses=None) -> Body:
        """A body (see :class:`Body`); all bodies step with the same dt."""
        self._name_free(name)
        body = Body(name, driver, mesh, masses)
        if self.bodies and abs(body.driver.dt - self.dt) > 1e-12 * self.dt:
            raise ModelError(f"body {name}: dt = {body.driver.dt:g} s, the scene's bodies step with {self.dt:g} s")
        self.bodies.append(body)
        return body

    def attach(self, name: str, a: str, nodes, b: str | None = None, nodes_b=None, *,
               stiffness: float = 500.0) -> Attachment:
        """Springs from ``nodes`` of body ``a`` to the world (``b`` None) or to body ``b`` (see
        :class:`Attachment`; ``nodes`` also a selection as :func:`rtfem.select_nodes` takes)."""
        from ..mesh.selection import select_nodes

        self._name_free(name)
        body = self.body(a)
        spec = nodes
        nodes = select_nodes(body.mesh, nodes, f"attachment {name}")  # the surface numbers all the nodes
        if nodes.size == 0:
            raise ModelError(f"attachment {name}: {validate.show(spec)} selects no node of {a}")
        other = None if b is None else self.body(b)
        if other is body:
            raise ModelError(f"attachment {name}: a body attached to itself; give b another body or None (the world)")
        att = Attachment(name, body, nodes, other, nodes_b, stiffness)
        self.attachments.append(att)
        return att

    def add_plane(self, name: str, point, normal, friction: float = 0.0) -> Plane:
        """A rigid plane (see :class:`Plane`)."""
        self._name_free(name)
        plane = Plane(name, point, normal, friction)
        self.obstacles.append(plane)
        return plane

    def add_obstacle(self, name: str, mesh: TriMesh, friction: float = 0.0) -> MeshObstacle:
        """A rigid obstacle given by a triangle surface (see
        :class:`~rtfem.interaction.scene_obstacles.MeshObstacle`)."""
        self._name_free(name)
        obstacle = MeshObstacle(name, mesh, friction)
        self.obstacles.append(obstacle)
        return obstacle

    def add_tool(self, name: str, device, *, kind: str = "probe", radius: float = 0.005, shape=None,
                 stiffness: float | None = None, friction: float = 0.0) -> SceneTool:
        """A probe or a grasper following ``device`` (see :class:`~rtfem.interaction.scene_tools.SceneTool`)."""
        self._name_free(name)
        tool = SceneTool(name, device, kind=kind, radius=radius, shape=shape, stiffness=stiffness, friction=friction)
        self.tools.append(tool)
        return tool

    def add_scalpel(self, name: str, body: str, device, **options):
        """A blade cutting body ``body`` (a full-order solid), following ``device`` (see
        :class:`~rtfem.interaction.scene_scalpel.SceneScalpel`, which takes ``options``); one a body."""
        self._name_free(name)
        for other in self.scalpels:
            if other.body == body:
                raise ModelError(f"scalpel {name}: body {body} is cut by scalpel {other.name} already; a body takes one "
                                 "scalpel (each cut makes the model the next cut starts from)")
        scalpel = SceneScalpel(name, self.body(body), device, gravity=self.gravity, **options)
        self.scalpels.append(scalpel)
        return scalpel

    def _holding(self, body: Body) -> np.ndarray:
        """The body's nodes on springs (attachments, grasps): a piece a cut frees is kept while one holds it."""
        held = [att.nodes_a for att in self.attachments if att.a is body]
        held += [att.nodes_b for att in self.attachments if att.b is body]
        held += [t.held.nodes_a for t in self.tools if t.held is not None and t.held.a is body]
        return np.unique(np.concatenate(held)) if held else np.zeros(0, dtype=np.int64)

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
        """One step of every body (see the module's docstring), their contacts solved together. A scalpel's cut
        job that failed (an error of its own, not rt.cut's refusal) raises ModelError after the step is taken."""
        if not self.bodies:
            raise ModelError("the scene has no body: add_body first")
        t1 = (self.steps + 1) * self.dt
        for scalpel in self.scalpels:
            if scalpel.begin(t1):
                recut(self, scalpel)
        for tool in self.tools:
            tool.begin(t1, self.bodies)
        springs = self.attachments + [tool.held for tool in self.tools if tool.held is not None]
        weights = [b.masses[:, None] * self.gravity[None, :] + b.loads for b in self.bodies]  # and the loads held
        for scalpel in self.scalpels:  # and the tissue's share of the cutting force
            weights[self.bodies.index(self.body(scalpel.body))] += scalpel.loads()
        warm = warm_springs(self, springs, weights)
        spring_nodes = self._spring_nodes(springs)
        alone = untouched(self, spring_nodes) if self.skip_trials else [None] * len(self.bodies)
        base = [self._trial(b, weights[k], spring_nodes.get(k)) if alone[k] is None else (weights[k], alone[k], alone[k], None)
                for k, b in enumerate(self.bodies)]
        held = self._attachment_loads(springs, base, spring_nodes, warm)
        trials = [self._held_trial(k, base[k], held[k], spring_nodes.get(k)) for k in range(len(self.bodies))]
        points = PointSet()
        Xs = [b.X[b.surface] + trial for b, (_, _, trial) in zip(self.bodies, trials)]  # the surfaces, a step on
        self._plane_points(Xs, points)
        self._pair_points(trials, Xs, points)
        self._tool_points(trials, Xs, points)
        points = points.join(self.compiled)
        loads = [F.copy() for F, _, _ in trials]
        pairs = [(a.name, other.name) for a in self.bodies for other in (*self.obstacles, *self.bodies, *self.tools)
                 if other is not a]
        contacts = dict(zip(pairs, np.zeros((len(pairs), 3))))  # each pair's row of one array
        for att in springs:
            contacts[(att.a.name, att.name)] = self._held_force[att.name].copy()
            if att.b is not None:
                contacts[(att.b.name, att.name)] = -self._held_force[att.name]
        if points is not None:
            self._solve(points, trials, loads, contacts)
        for body, F in zip(self.bodies, loads):
            body.driver.step(F)
        for tool in self.tools:
            tool.end(t1, sum((contacts[(b.name, tool.name)] for b in self.bodies), np.zeros(3)))
        for scalpel in self.scalpels:
            body = self.body(scalpel.body)
            contacts[(body.name, scalpel.name)] = scalpel.applied
            scalpel.end(t1, np.asarray(body.driver.displacements(), dtype=float), self._holding(body))
        self.contacts = contacts
        self.steps += 1
        self.time = self.steps * self.dt
        for scalpel in self.scalpels:  # a cut job's failure, said with the step taken
            scalpel.raise_failure()

    def run(self, n_steps: int) -> None:
        for _ in range(validate.count(n_steps, "n_steps", 0, 10**9)):
            self.step()

    def _spring_nodes(self, springs) -> dict[int, np.ndarray]:
        """{body index: the nodes its springs hold (sorted)} for the bodies with springs (kept while
        the springs are the same)."""
        key = tuple((att.name, att.a.name, att.nodes_a.tobytes(), None if att.b is None else att.b.name,
                     None if att.b is None else att.nodes_b.tobytes()) for att in springs)
        kept = getattr(self, "_spring_nodes_kept", None)
        if kept is not None and kept[0] == key:
            return kept[1]
        index = {b.name: k for k, b in enumerate(self.bodies)}
        ends: dict[int, list] = {}
        for att in springs:
            ends.setdefault(index[att.a.name], []).append(att.nodes_a)
            if att.b is not None:
                ends.setdefault(index[att.b.name], []).append(att.nodes_b)
        self._spring_nodes_kept = (key, {k: np.unique(np.concatenate(v)) for k, v in ends.items()})
        return self._spring_nodes_kept[1]

    def _attachment_loads(self, springs, base, spring_nodes, warm) -> list[np.ndarray]:
        """Each body's attachment forces (n, 3) in this step beyond ``warm`` (the last step's, in the
        loads already: :func:`~rtfem.interaction.scene_springs.warm_springs`), of the attachments' and
        the graspers' springs; the total of each set on its first body in :attr:`_held_force`.

        With e the springs' stretch after a step under the weights, loads and ``warm`` forces (a's node
        past its anchor or its pair's; ``base``: each body's trial step under them, with the
        displacements of its springs' nodes ``spring_nodes``, :meth:`_spring_nodes`), and A = J (sum_k
        W_k) J^T the stretch per unit spring force (J: +1 on a's node, -1 on b's), the correction d of
        the forces f = warm + d is f = -k (e + A d): (I / k + A) d = -(e + warm / k)."""
        out = [np.zeros((b.driver.n_nodes, 3)) for b in self.bodies]
        self._held_force, self._spring_forces = {}, {}
        if not springs:
            return out
        index = {b.name: k for k, b in enumerate(self.bodies)}
        sizes = [att.nodes_a.size for att in springs]
        start = np.concatenate([[0], np.cumsum(sizes)])
        e = np.concatenate([att.rest if att.b is not None else -att.anchor for att in springs])
        J, solve = spring_system(self, springs, index, start, sizes, spring_nodes)
        for k, (nodes, Jk) in J.items():
            x = self.bodies[k].X[nodes] + base[k][3]  # the body's spring nodes, as its trial took them
            e += (Jk @ x.reshape(-1)).reshape(-1, 3)
        f0 = np.concatenate(warm)
        e += f0 / np.repeat([att.stiffness for att in springs], sizes)[:, None]
        d = solve(-e.reshape(-1)).reshape(-1, 3)
        for a_index, att in enumerate(springs):
            da = d[start[a_index]:start[a_index + 1]]
            np.add.at(out[index[att.a.name]], att.nodes_a, da)
            if att.b is not None:
                np.add.at(out[index[att.b.name]], att.nodes_b, -da)
            fa = warm[a_index] + da
            self._held_force[att.name] = fa.sum(axis=0)
            self._spring_forces[att.name] = (spring_key(att), fa)
        return out

    @staticmethod
    def _trial(body: Body, F: np.ndarray, extra: np.ndarray | None = None):
        """The body's loads F, its surface's displacements now (None where the driver's own trial
        step leaves it as it is: asked at the contacts' nodes only, in :meth:`_solve`) and after a
        step under F alone, and (with ``extra`` nodes) those nodes' displacements after that step."""
        d = body.driver
        nodes = body.surface if extra is None else np.concatenate([body.surface, extra])  # one set: the
        ns = body.surface.size                                                            # driver keeps its rows
        now = None if getattr(d, "trial_displacements", None) is not None else displacements_at(d, body.surface)
        if now is None and not getattr(d, "compliance_changes", True):
            # affine in the loads with a constant linear part: the free step plus the load's response, kept
            # while the load and the nodes are the same (a body's weight, step after step)
            key, kept = (F.tobytes(), nodes.tobytes()), body.__dict__.get("_load_response")
            if kept is None or kept[0] != key:
                kept = body._load_response = (key, trial_displacements(d, F, nodes) - predictions(d, nodes))
            after = predictions(d, nodes) + kept[1]
        else:
            after = trial_displacements(d, F, nodes)
        return F, now, after[:ns], (None if extra is None else after[ns:])

    def _held_trial(self, k: int, base, held: np.ndarray, nodes: np.ndarray | None):
        """Body k's trial (loads, now, a step on) under its weight and loads and the springs' forces
        ``held`` on ``nodes``: the trial under the weight plus the springs' response, W (surface,
        nodes) held (the step is affine in the loads; W kept while the nodes are the same), or for a
        driver whose compliances follow its motion a trial step of its own."""
        F, now, trial, _ = base
        if nodes is None:
            return F, now, trial
        body = self.bodies[k]
        if getattr(body.driver, "compliance_changes", True):
            return self._trial(body, F + held)[:3]
        cache = self.__dict__.setdefault("_held_cache", {})
        kept = cache.get(k)
        if kept is None or not np.array_equal(kept[0], nodes):
            kept = cache[k] = (nodes.copy(), step_compliances(body.driver, body.surface, nodes))
        return F + held, now, trial + (kept[1] @ held[nodes].reshape(-1)).reshape(-1, 3)

    def _names(self) -> list[str]:
        """The bodies', obstacles' and tools' names: a point's pair (a, b) indexes them."""
        return [x.name for x in (*self.bodies, *self.obstacles, *self.tools)]

    def _plane_points(self, Xs, points: PointSet) -> None:
        nb = len(self.bodies)
        for k, (body, x) in enumerate(zip(self.bodies, Xs)):
            for o, obstacle in enumerate(self.obstacles):
                idx, gaps, normals = obstacle.contacts(x, self.margin * body.edge)
                if idx.size:
                    points.vertices(normals, gaps, obstacle.friction, k, nb + o, k, body.surface[idx])

    #: a body pair's candidate lists (which vertices of a near which triangles of b) are searched
    #: again once the two surfaces moved this fraction of the margin since the last search
    SLACK = 0.25

    def _pair_points(self, trials, Xs, points: PointSet) -> None:
        """Each body's surface vertices within ``margin`` edges of another body's surface (after the
        trial steps), against the closest point of that surface: both directions of every pair.

        The candidates (a's vertices and the eight triangles of b with the nearest centres within
        reach + margin + slack) are kept from step to step while the two surfaces move less than
        the slack since they were searched (Verlet lists): a vertex left out was then further than
        the margin plus the slack, and cannot have come within the margin."""
        if len(self.bodies) < 2:
            return
        cache = self.__dict__.setdefault("_pair_cache", {})
        for kb, (b, (_, _, trial_b)) in enumerate(zip(self.bodies, trials)):
            for ka, (a, (_, _, trial_a)) in enumerate(zip(self.bodies, trials)):
                if a is b:
                    continue
                margin = self.margin * max(a.edge, b.edge)
                slack = self.SLACK * margin
                kept = cache.get((ka, kb))
                if kept is None or (np.abs(trial_a - kept[0]).max() + np.abs(trial_b - kept[1]).max()) * 1.7321 > slack:
                    kept = cache[(ka, kb)] = (trial_a.copy(), trial_b.copy(), *pair_search(a, b, trial_a, trial_b,
                                                                                               margin + slack))
                cand, tris, valid = kept[2:]
                if cand.size == 0:
                    continue
                normal, gap, sn, sw = pair_block(Xs[ka][cand], Xs[kb], b.tri_local, tris, valid, margin, b.edge,
                                                 a.surface[cand], b.surface, self.compiled)
                points.add(normal, gap, self.friction, ka, kb, -1, (ka, kb), sn, sw)

    def _compliances(self, k: int, nodes: np.ndarray) -> np.ndarray:
        """Body k's one-step compliances of ``nodes`` (3n, 3n), the last set's kept while it is the
        same and the driver's compliances do not change with its motion."""
        driver = self.bodies[k].driver
        kept = self.__dict__.setdefault("_compliance_cache", {}).get(k)
        if kept is not None and np.array_equal(kept[0], nodes):
            return kept[1]
        W = step_compliances(driver, nodes)
        if not getattr(driver, "compliance_changes", True):
            self._compliance_cache[k] = (nodes.copy(), W)
        return W

    def _tool_points(self, trials, Xs, points: PointSet) -> None:
        """Each body's surface vertices within ``margin`` of a probe (after the trial steps), against
        the tool where last step's force leaves it (their slip relative to its move: :meth:`_solve`)."""
        nb, no = len(self.bodies), len(self.obstacles)
        probes = [(j, tool) for j, tool in enumerate(self.tools) if tool.kind == "probe"]
        if not probes:
            return
        spheres = [body.radius + 1.7321 * np.abs(trial).max() for body, (_, _, trial) in zip(self.bodies, trials)]
        for j, tool in probes:
            x_e, reach = tool.expected(), tool.shape.reach
            for k, body in enumerate(self.bodies):
                margin = self.margin * body.edge
                # vertices within an edge beyond reach: the face point between them may touch
                cutoff = reach + margin + body.longest
                if np.linalg.norm(x_e - body.centre) > spheres[k] + cutoff:
                    continue  # beyond the body's bounding sphere (a parked tool)
                normal, gap, sn, sw = probe_block(Xs[k], body.normals, body.tri_local, tool.shape, x_e, cutoff, margin,
                                                  body.surface, self.compiled)
                points.add(normal, gap, tool.friction, k, nb + no + j, j, (k, -1), sn, sw)

    def _solve(self, P: dict, trials, loads, contacts) -> None:
        """The contact forces of all points together: w = b + A r, A = G^T (sum_k P_k W_k P_k^T) G
        (G: the points' frames; P_k: each point's displacement per unit displacement of body k's
        nodes); b: the gaps and the slips over the trial step (relative to the other side, or to a
        probe's move)."""
        F = P["frame"]  # (m, 3, 3): G's diagonal blocks
        sk, sn, sw = P["sk"], P["sn"], P["sw"]
        on = (sk >= 0)[:, :, None] & (sw != 0.0)  # the sides' nodes that move the points
        stride = 1 + max(body.driver.n_nodes for body in self.bodies)
        keys = (sk[:, :, None] * stride + sn)[on]
        used = np.unique(keys)  # sorted body by body
        slot = np.searchsorted(used, keys)
        slots = np.full(sn.shape, -1, dtype=np.int64)
        slots[on] = slot
        W = np.zeros((3 * used.size, 3 * used.size))  # the bodies' compliances of those nodes, block diagonal
        maps = []
        owner = used // stride
        for k in np.unique(owner).tolist():
            at = np.flatnonzero(owner == k)
            nodes = used[at] % stride
            block = slice(3 * at[0], 3 * at[-1] + 3)
            W[block, block] = self._compliances(k, nodes)
            maps.append((k, nodes, at))
        moved = np.empty((used.size, 3))  # each node's displacement over the trial step
        for k, nodes, at in maps:
            _, now, trial = trials[k]
            local = self.bodies[k].local[nodes]
            moved[at] = trial[local] - (now[local] if now is not None else displacements_at(self.bodies[k].driver, nodes))
        tools = self.tools
        inv_k = np.array([0.0 if t.stiffness is None or t.kind != "probe" else 1.0 / t.stiffness for t in tools] or [0.0])
        move, force = np.zeros((max(len(tools), 1), 3)), np.zeros((max(len(tools), 1), 3))
        for j, t in enumerate(tools):
            move[j], force[j] = t.target - t.proxy, t.force
        f, node_force, self.sweeps = contact_solve(F, slots, sw, W, P["tool"], inv_k, move, force, moved, P["gap"],
                                                   P["mu"], self.compiled)  # each point's force on its first
        for k, nodes, at in maps:                                              # side, -w f on its second
            loads[k][nodes] += node_force[at]
        names, nb = self._names(), len(self.bodies)
        ne = len(names)
        between = P["b"] < nb  # a body on a body: the reaction on the other
        index = np.concatenate([P["a"] * ne + P["b"], P["b"][between] * ne + P["a"][between]])
        forces = np.concatenate([f, -f[between]])
        total = np.stack([np.bincount(index, weights=forces[:, c], minlength=nb * ne) for c in range(3)], axis=1)
        for i in np.unique(index).tolist():
            contacts[(names[i // ne], names[i % ne])] += total[i]
