"""Haptic rendering: a probe touching the organ, a contact force, and a fixed-rate force loop.

Contact. The probe is a sphere (radius 0 for a point) at position c. Near it, the organ
surface is sampled at the vertices closest to c, at their *deformed* positions; the contact
vertex p is the one nearest to the probe, with outward normal n, and it is kept while the
contact lasts (under a frictionless load the surface slides sideways, and re-selecting the
nearest vertex every tick would hop to a neighbour and drop the force). Frictionless, unilateral
contact requires n . u_p <= g = n . (c - X_p) - radius (the probe stays outside).

Force. With the exact modal update the contact node obeys u_p(k+1) = u_free + W f_k
(:meth:`ModalSimulator.predict`, :meth:`ModalSimulator.step_compliance`), so the force
f = -lam n for the next step is found before stepping, implicitly:

* ``coupling="constraint"``: the displacement constraint n . u_p(k+1) = g (James & Pai's
  capacitance approach): lam = (n . u_free - g) / (n^T W n) when positive;
* ``coupling="spring"`` (default): a virtual coupling spring of stiffness k between probe
  and surface, lam = (n . u_free - g) / (n^T W n + 1/k): softer, bounded forces, stable for a
  real device whatever k.

Both are implicit in the organ's own dynamics, so the coupled loop is passive: no force
blow-up under a held contact. With an :class:`~rtfem.ImpedanceMap` the same formulas run
quasi-statically with the static point compliance G_pp as W.

HapticLoop runs the update on its own thread at a fixed rate (1 kHz by default), reading
probe positions from a device and handing forces back, and records the achieved rate,
per-step compute time and jitter. Call :meth:`Probe.prepare` for the region the probe can
reach before starting it: the first contact at an unprepared vertex costs a few sparse
solves inside the loop.
"""

from __future__ import annotations

import contextlib
import threading
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from scipy.linalg import lu_factor, lu_solve
from scipy.spatial import cKDTree

from .. import validate
from ..errors import ModelError, SolverError
from ..mesh.surface import TriMesh
from .contact import hold_patch, nodes_to_prepare, patch_system
from ..drivers.base import as_driver, check_driver_mesh, displacements_at, predictions, prepare, step_compliances

__all__ = ["Probe", "Grasp", "HapticLoop", "ScriptedDevice", "Press", "CallbackDevice", "SharedDevice", "LoopStats"]


class Probe:
    """Contact between a spherical probe and an organ driven by a ModalSimulator or an ImpedanceMap.

    Parameters
    ----------
    mesh : the organ surface.
    driver : a :class:`ModalSimulator` (dynamic), a Newmark :class:`DirectSimulator` (the full model,
        for comparison) or an :class:`ImpedanceMap` (quasi-static).
    radius : probe tip radius (m); 0 for a point probe.
    coupling : "spring" (virtual coupling, default) or "constraint" (hard displacement).
    stiffness : virtual coupling stiffness k (N/m).
    candidates : how many vertices near the probe are tested for contact.
    """

    def __init__(self, mesh: TriMesh, driver, *, radius: float = 0.0, coupling: str = "spring",
                 stiffness: float = 200.0, candidates: int = 8) -> None:
        driver = as_driver(driver, "probe")
        check_driver_mesh(mesh, driver, "probe")
        validate.choice(coupling, "coupling", ("spring", "constraint"))
        radius = validate.nonnegative(radius, "radius", "the probe tip radius in m")
        stiffness = validate.positive(stiffness, "stiffness", "the coupling stiffness in N/m")
        candidates = validate.count(candidates, "candidates", 1, 10_000)
        self.mesh = mesh
        self.driver = driver
        self.radius = float(radius)
        self.coupling = coupling
        self.stiffness = float(stiffness)
        self.X = np.asarray(mesh.vertices)
        self.normals = mesh.vertex_normals()
        self._touchable = mesh.used_vertices()  # the surface (a solid's interior nodes are never touched)
        self._tree = cKDTree(self.X[self._touchable])
        self._k = int(min(candidates, self._touchable.size))
        self._W: dict[int, np.ndarray] = {}
        self._cand: np.ndarray | None = None
        self._cand_at = np.zeros(3)
        edges = mesh.edges()
        self._requery = 0.25 * float(np.median(np.linalg.norm(self.X[edges[:, 0]] - self.X[edges[:, 1]], axis=1)))
        self.force = np.zeros(3)  # force on the probe (what the user feels), N
        self.contact_node: int | None = None
        self.penetration = 0.0

    def prepare(self, nodes=None, *, around=None, radius: float = 0.01) -> int:
        """Precompute the contact compliances W of the vertices the probe may touch.

        The first contact at a vertex otherwise computes W inside the force loop (with the
        static correction: three sparse solves, tens of milliseconds), a hiccup a 1 kHz loop
        cannot absorb. Give vertex indices, or a point ``around`` which every vertex within
        ``radius`` is prepared. Returns the number of vertices prepared.
        """
        nodes = nodes_to_prepare(self._touchable, self._tree, self.mesh.n_vertices, nodes, around, radius)
        for v in nodes.tolist():
            self._compliance(int(v))
        return int(nodes.size)

    def displacements(self) -> np.ndarray:
        """The organ's (n, 3) displacement field now (for drawing; O(n), not for the force loop)."""
        return self.driver.displacements()

    def _compliance(self, node: int) -> np.ndarray:
        return _cached_compliance(self.driver, self._W, node)

    def replay(self, positions, *, compiled: bool | None = None) -> np.ndarray:
        """Run :meth:`update` at each of ``positions`` (k, 3) back to back, offline (no clock):
        a recorded or scripted trajectory's forces (k, 3), and the state where it ends. With a
        linear ModalSimulator or a quasi-static ImpedanceDriver, and numba, the ticks run in the
        haptic loop's compiled code (``compiled``: None = when available), which gives the same
        forces as the Python ticks to round-off."""
        return _replay(self, positions, compiled, "probe")

    # ---------------------------------------------------------------- compiled loop support
    def _grid(self) -> tuple:
        """A uniform grid over the vertices for the compiled nearest-vertex search: lower corner,
        cell size, cells per axis, CSR-like cell starts and the vertices sorted by cell."""
        if getattr(self, "_grid_cache", None) is None:
            X = self.X[self._touchable]
            lo, hi = X.min(axis=0), X.max(axis=0)
            h = max(8.0 * self._requery, float((hi - lo).max()) / 64.0, 1e-12)  # about 2 edges, at most 64^3 cells
            dims = np.maximum(np.ceil((hi - lo) / h).astype(np.int64), 1)
            idx = np.minimum(((X - lo) / h).astype(np.int64), dims - 1)
            cell = (idx[:, 0] * dims[1] + idx[:, 1]) * dims[2] + idx[:, 2]
            order = np.argsort(cell, kind="stable").astype(np.int64)
            start = np.searchsorted(cell[order], np.arange(int(np.prod(dims)) + 1)).astype(np.int64)
            self._grid_cache = (lo.astype(float), float(h), dims, start, self._touchable[order].astype(np.int64))
        return self._grid_cache

    def _compliance_table(self) -> tuple[np.ndarray, np.ndarray]:
        """The cached step compliances as (slot per node, -1 when absent; (m, 3, 3) table)."""
        slot = np.full(self.X.shape[0], -1, dtype=np.int64)
        table = np.zeros((max(len(self._W), 1), 3, 3))
        for i, (node, W) in enumerate(self._W.items()):
            slot[node], table[i] = i, W
        return slot, table

    def _deformed(self, nodes: np.ndarray) -> np.ndarray:
        return self.X[nodes] + displacements_at(self.driver, nodes)

    def update(self, position) -> np.ndarray:
        """Advance one step with the probe at ``position``; returns the force on the probe (N)."""
        c = validate.point(position, "probe position")
        if self.contact_node is not None:
            # stay on the vertex in contact: under a frictionless load the surface slides
            # sideways and a nearest-vertex search would hop to a neighbour, dropping the force
            p = self.contact_node
        else:
            if self._cand is None or np.linalg.norm(c - self._cand_at) > self._requery:
                _, cand = self._tree.query(c, k=self._k)
                self._cand, self._cand_at = self._touchable[np.atleast_1d(cand)], c.copy()
            xd = self._deformed(self._cand)
            p = int(self._cand[np.argmin(np.einsum("ij,ij->i", xd - c, xd - c))])
        n = self.normals[p]
        g = float(n @ (c - self.X[p])) - self.radius
        d = self.driver
        lam = 0.0
        u_free = d.predict(p)
        if n @ u_free > g:  # the surface would pass the probe: contact
            W = self._compliance(p)
            denom = float(n @ W @ n) + (1.0 / self.stiffness if self.coupling == "spring" else 0.0)
            lam = (float(n @ u_free) - g) / denom
        f_organ = -lam * n
        d.step({p: (float(f_organ[0]), float(f_organ[1]), float(f_organ[2]))} if lam > 0 else None)
        self.contact_node = p if lam > 0 else None
        self.penetration = max(0.0, float(n @ u_free) - g) if lam > 0 else 0.0
        self.force = -f_organ
        return self.force


def _movable(nodes: np.ndarray, W: np.ndarray, node: int) -> tuple[np.ndarray, np.ndarray]:
    """The vertices of a patch that can move, and their rows in the (3m, 3m) block ``W``: a vertex
    held by the supports has a zero diagonal block (any driver), and a grip tied to it would anchor
    the jaw to the support, so it is left out (the grabbed ``node`` always stays)."""
    trace = np.diagonal(W).reshape(nodes.size, 3).sum(axis=1)
    free = (trace > 1e-9 * trace.max()) | (nodes == node)
    rows = np.flatnonzero(np.repeat(free, 3))
    return nodes[free], rows


class Grasp:
    """A grasp of the organ by a jaw held by the hand through a virtual spring: the viewer's drag.

    ``grab(node)`` closes the jaw on the vertex ``node`` and, with ``radius`` > 0, on every surface
    vertex within ``radius`` of it (a patch; the pull lifts a region instead of a cone); ``release``
    opens it. The jaw is rigid: each held vertex is tied to it by a stiff grip spring (``grip``
    N/m per vertex, default 100 k), the jaw to the hand at ``target`` by the grasp spring k. With
    the driver's one-step cross compliances W_SS of the held vertices (u_S(k+1) = u_free + W_SS f),
    the forces f and the jaw's translation delta are found implicitly before stepping:

        (W_SS + I/grip) f - E delta = u_S(grab) - u_free,   E^T f + k delta = k (target - x_jaw(grab)),

    (E the stacked identities: :func:`rtfem.interaction.contact.hold_patch`), so a stiff spring cannot make the
    coupled loop unstable. One vertex (radius 0) is the single-spring grab, (I + k W) f =
    k (target - X - u_free). Drivers: a ModalSimulator (linear or warped), a DirectSimulator
    (linear or large-deformation), an ImpedanceMap (quasi-static: W = static compliances,
    u_free = 0) or any Driver. ``max_force`` caps the total force (N), for a mouse that can be
    dragged anywhere; ``clipped`` says whether the last step's force was capped and ``demand`` is
    the force the spring asked for (N).
    """

    def __init__(self, mesh: TriMesh, driver, *, stiffness: float = 200.0, max_force: float | None = None,
                 radius: float = 0.0, grip: float | None = None) -> None:
        driver = as_driver(driver, "grasp")
        check_driver_mesh(mesh, driver, "grasp")
        stiffness = validate.positive(stiffness, "stiffness", "the grasp spring stiffness in N/m")
        if max_force is not None:
            max_force = validate.positive(max_force, "max_force", "a force cap in N, or None")
        self.radius = validate.nonnegative(radius, "radius", "the jaw's grab radius in m (0: one vertex)")
        self.grip = 100.0 * stiffness if grip is None else validate.positive(grip, "grip", "a stiffness in N/m")
        self.mesh, self.driver = mesh, driver
        self.stiffness = stiffness
        self.max_force = max_force
        self.X = np.asarray(mesh.vertices)
        self._touchable = mesh.used_vertices()
        self._tree = cKDTree(self.X[self._touchable])
        self.node: int | None = None
        self.nodes = np.zeros(0, dtype=np.int64)  # the held vertices
        self.force = np.zeros(3)  # total force on the organ (N); the hand feels -force
        self.forces = np.zeros((0, 3))  # the force on each held vertex (N)
        self.demand = 0.0  # |force| the spring asked for in the last step, before the cap (N)
        self.clipped = False  # whether the last step's force was capped at max_force
        self._W: dict[int, np.ndarray] = {}
        self._block = None
        self._patch_lu = None

    def compliance(self, node: int) -> np.ndarray:
        """The 3x3 step compliance W at ``node`` (the driver prepares the node the first time)."""
        return _cached_compliance(self.driver, self._W, node)

    def patch(self, node: int, radius: float | None = None) -> np.ndarray:
        """The vertices a jaw closed on ``node`` would hold: ``node`` and the surface vertices within
        ``radius`` (default: the grasp's) of its deformed position (sorted)."""
        node = validate.node(node, self.X.shape[0])
        radius = self.radius if radius is None else validate.nonnegative(radius, "radius", "a grab radius in m")
        nodes = np.array([node], dtype=np.int64)
        if radius > 0:
            x = self.X[node] + self.driver.displacement(node)
            near = self._touchable[np.asarray(self._tree.query_ball_point(x, 1.05 * radius + 1e-12), dtype=np.int64)]
            if near.size:
                xs = self.X[near] + displacements_at(self.driver, near)
                near = near[np.linalg.norm(xs - x, axis=1) <= radius]
            nodes = np.union1d(nodes, near)
        return nodes

    def grab(self, node: int, radius: float | None = None) -> np.ndarray:
        """Close the jaw on ``node`` and the surface vertices within ``radius`` (default: the
        grasp's) of its deformed position (:meth:`patch`), less those the supports hold (a grip on them
        would anchor the jaw); returns the held vertices. While a compiled HapticLoop runs this
        grasp, its ticks wait for the new grip (a few skipped slots)."""
        with _loop_paused(self):
            return self._grab(node, radius)

    def _grab(self, node: int, radius: float | None) -> np.ndarray:
        node = validate.node(node, self.X.shape[0])
        if not np.isin(node, self._touchable):
            raise ModelError(f"node {node} is not on the surface (an interior node of a solid): grab a surface vertex, "
                             "e.g. the nearest with model.nearest_free_node(point)")
        nodes = self.patch(node, radius)
        x = self.X[node] + self.driver.displacement(node)
        if nodes.size == 1:
            self.compliance(node)
            self._block = None
            self._patch_lu = None
        else:
            prepare(self.driver, nodes)
            W = step_compliances(self.driver, nodes)
            nodes, keep = _movable(nodes, W, node)
            W = W[np.ix_(keep, keep)]
            self._block = None if getattr(self.driver, "compliance_changes", False) else W
            self._patch_lu = None
        self.node, self.nodes = node, nodes
        self._hold = displacements_at(self.driver, nodes).reshape(-1)
        self._jaw = x
        return nodes

    def transferred(self, driver) -> "Grasp":
        """This grasp on another Driver of the same mesh in the same state (a driver swapped in
        mid-pull, e.g. :meth:`rtfem.drivers.reduced_nonlinear.ReducedNonlinearSimulator.localized`): the same springs,
        the jaw closed on the same vertices with the same grip references, so that the pull goes
        on where it was. The held vertices are prepared on ``driver`` here."""
        g = Grasp(self.mesh, driver, stiffness=self.stiffness, max_force=self.max_force, radius=self.radius,
                  grip=self.grip)
        if self.node is not None:
            nodes = self.nodes.copy()
            if nodes.size == 1:
                g.compliance(int(nodes[0]))
            else:
                prepare(g.driver, nodes)
                W = step_compliances(g.driver, nodes)
                g._block = None if getattr(g.driver, "compliance_changes", False) else W
            g.node, g.nodes = self.node, nodes
            g._hold, g._jaw = self._hold.copy(), self._jaw.copy()
            g.force, g.forces = self.force.copy(), self.forces.copy()
        return g

    def replay(self, targets, *, compiled: bool | None = None) -> np.ndarray:
        """Run :meth:`update` at each of the hand's ``targets`` (k, 3) back to back, offline (no
        clock), with the jaw as it is now: the total forces (k, 3), and the state where it ends.
        With a linear ModalSimulator or a quasi-static ImpedanceDriver, and numba, the ticks run in
        the haptic loop's compiled code (``compiled``: None = when available), which gives the same
        forces as the Python ticks to round-off."""
        return _replay(self, targets, compiled, "hand")

    def release(self) -> None:
        """Open the jaw."""
        with _loop_paused(self):
            self._release()

    def _release(self) -> None:
        self.node = None
        self.nodes = np.zeros(0, dtype=np.int64)
        self._block = None
        self._patch_lu = None

    def update(self, target=None) -> np.ndarray:
        """One step with the hand at ``target`` (None or no grab: the organ moves freely).

        Returns the total force on the organ (N). With an ImpedanceMap the step is quasi-static
        (the map's driver holds the force; its field is the superposed static responses).
        """
        d = self.driver
        c = None if target is None else validate.point(target, "grasp target")
        if self.node is None or c is None:
            d.step(None)
            self.force, self.forces = np.zeros(3), np.zeros((0, 3))
            self.demand, self.clipped = 0.0, False
            return self.force
        k = self.stiffness
        if self.nodes.size == 1:
            p = self.node
            f = np.linalg.solve(np.eye(3) + k * self.compliance(p), k * (c - self.X[p] - d.predict(p)))[None]
        else:
            h = self._hold - predictions(d, self.nodes).reshape(-1)
            if self._block is not None:  # a constant compliance: the jaw's system is factorized once per grip
                key = (k, self.grip)
                if self._patch_lu is None or self._patch_lu[0] != key:
                    self._patch_lu = (key, lu_factor(patch_system(self._block, k, self.grip)))
                f = lu_solve(self._patch_lu[1], np.concatenate([h, k * (c - self._jaw)]))[:-3].reshape(-1, 3)
            else:
                f, _ = hold_patch(step_compliances(d, self.nodes), h, k * (c - self._jaw), k, self.grip)
        total = f.sum(axis=0)
        self.demand = mag = float(np.linalg.norm(total))
        self.clipped = self.max_force is not None and mag > self.max_force
        if self.clipped:
            f = f * (self.max_force / mag)
            total = f.sum(axis=0)
        d.step({int(v): (float(g[0]), float(g[1]), float(g[2])) for v, g in zip(self.nodes.tolist(), f)})
        self.force, self.forces = total, f
        return total


@dataclass
class LoopStats:
    """What a HapticLoop achieved."""

    steps: int = 0
    seconds: float = 0.0
    compute: list[float] = field(default_factory=list)  # per-step compute time (s)
    lateness: list[float] = field(default_factory=list)  # start time minus scheduled time (s)
    peak_force: float = 0.0
    missed: int = 0  # ticks skipped because the loop was more than a period behind its schedule
    slots: list[int] = field(default_factory=list)  # the schedule slot of each step (k: due at start + k / rate)
    compiled: bool = False  # True when the ticks ran in compiled code without the GIL

    def period_errors(self) -> np.ndarray:
        """|interval between consecutive ticks - period| (s), over pairs of adjacent slots: the
        jitter a device sees (the lateness difference of neighbouring ticks)."""
        late, slot = np.asarray(self.lateness), np.asarray(self.slots)
        if late.size < 2 or slot.size != late.size:
            return np.zeros(0)
        adjacent = np.diff(slot) == 1
        return np.abs(np.diff(late))[adjacent]

    def period_error(self, q: float) -> float:
        """The q-th percentile of :meth:`period_errors` (s)."""
        e = self.period_errors()
        return float(np.percentile(e, q)) if e.size else float("nan")

    @property
    def behind(self) -> bool:
        """True when the loop could not keep its rate (some ticks were skipped)."""
        return self.missed > 0

    @property
    def rate(self) -> float:
        return self.steps / self.seconds if self.seconds > 0 else 0.0

    def percentile(self, q: float) -> float:
        return float(np.percentile(self.compute, q)) if self.compute else float("nan")

    @property
    def jitter(self) -> float:
        """Standard deviation of the step start times around the schedule (s)."""
        return float(np.std(self.lateness)) if self.lateness else float("nan")

    def __str__(self) -> str:
        text = (f"{self.steps} steps in {self.seconds:.2f} s: {self.rate:.0f} Hz achieved; compute median "
                f"{self.percentile(50) * 1e6:.1f} us, 99th percentile {self.percentile(99) * 1e6:.1f} us; "
                f"jitter {self.jitter * 1e6:.1f} us; period error 99th percentile {self.period_error(99) * 1e6:.1f} us; "
                f"peak force {self.peak_force:.3f} N" + (" (compiled loop)" if self.compiled else ""))
        if self.missed:
            share = 100.0 * self.missed / (self.missed + self.steps)
            text += f"; FELL BEHIND: {self.missed} ticks skipped ({share:.1f} % of the schedule)"
        return text


class ScriptedDevice:
    """A probe that follows a trajectory: ``trajectory(t) -> (3,)`` position in metres."""

    def __init__(self, trajectory: Callable[[float], np.ndarray]) -> None:
        if not callable(trajectory):
            raise ModelError(f"trajectory={validate.show(trajectory)} must be a callable t -> (3,) position")
        self.trajectory = trajectory
        self.forces: list[np.ndarray] = []
        self.times: list[float] = []

    @classmethod
    def press(cls, point, normal, depth: float, duration: float, *, approach: float = 0.002, ramp: float = 0.2,
              release: float = 0.6, repeat: bool = False) -> "ScriptedDevice":
        """A press along the inward normal: from ``approach`` (m) outside the surface point to
        ``depth`` (m) inside over ``ramp * duration``, held until ``release * duration``, backed
        out over ``ramp * duration`` and left outside; ``repeat`` starts again every ``duration``.
        The one scripted press of the CLI, the demo, the examples and the benchmarks."""
        return cls(Press(point, normal, depth, duration, approach, ramp, release, repeat))

    def position(self, t: float) -> np.ndarray:
        return np.asarray(self.trajectory(t), dtype=float)

    def set_force(self, t: float, force: np.ndarray) -> None:
        self.times.append(t)
        self.forces.append(np.array(force))


class Press:
    """The trajectory of :meth:`ScriptedDevice.press`: ``press(t)`` is the probe position (3,) and
    ``press.depth_at(t)`` how far inside the undeformed surface it is (m; negative outside)."""

    def __init__(self, point, normal, depth, duration, approach=0.002, ramp=0.2, release=0.6, repeat=False) -> None:
        self.point = validate.point(point, "point")
        n = validate.vector(normal, "normal", 3)
        if not np.linalg.norm(n) > 0:
            raise ModelError("normal must be a non-zero vector (the surface's outward normal)")
        self.normal = n / np.linalg.norm(n)
        self.depth = validate.number(depth, "depth", "a press depth in m")
        self.duration = validate.positive(duration, "duration", "a time in s")
        self.approach = validate.nonnegative(approach, "approach", "a distance in m")
        self.ramp = validate.in_range(ramp, "ramp", 0.0, 0.5, lo_open=True, what="a fraction of the duration")
        self.release = validate.in_range(release, "release", self.ramp, 1.0 - self.ramp, what="a fraction of the duration")
        self.repeat = validate.flag(repeat, "repeat")

    def depth_at(self, t: float) -> float:
        s = (t % self.duration if self.repeat else t) / self.duration
        if s < self.release:
            level = min(s / self.ramp, 1.0)
        else:
            level = max(0.0, 1.0 - (s - self.release) / self.ramp)
        return -self.approach + (self.depth + self.approach) * level

    def __call__(self, t: float) -> np.ndarray:
        return self.point - self.depth_at(t) * self.normal


class CallbackDevice:
    """Plug a real device driver (or the viewer) in: ``get_position() -> (3,)``, ``set_force(f)``."""

    def __init__(self, get_position: Callable[[], np.ndarray], set_force: Callable[[np.ndarray], None]) -> None:
        for name, fn in (("get_position", get_position), ("set_force", set_force)):
            if not callable(fn):
                raise ModelError(f"{name}={validate.show(fn)} must be a callable")
        self._get, self._set = get_position, set_force

    def position(self, t: float) -> np.ndarray:
        return validate.point(self._get(), "the device's position (get_position())")

    def set_force(self, t: float, force: np.ndarray) -> None:
        self._set(force)


class SharedDevice:
    """A device whose position any thread writes (:meth:`move_to`: a device driver's thread, the
    viewer's mouse) and whose force any thread reads (:attr:`force`), through one shared array,
    so a compiled HapticLoop reads and writes it without the GIL."""

    def __init__(self, position=(0.0, 0.0, 0.0)) -> None:
        self.mailbox = np.zeros(6)  # position (3), force on the probe (3)
        self.move_to(position)

    def move_to(self, position) -> None:
        self.mailbox[:3] = validate.point(position, "device position")

    @property
    def force(self) -> np.ndarray:
        """The last force handed to the device (N): what the hand feels."""
        return self.mailbox[3:6].copy()

    def position(self, t: float) -> np.ndarray:
        return self.mailbox[:3].copy()

    def set_force(self, t: float, force: np.ndarray) -> None:
        self.mailbox[3:6] = force


MAX_PRESAMPLED = 2_000_000  # ticks of a ScriptedDevice a compiled loop samples in advance (48 MB)


class HapticLoop:
    """Runs ``probe.update`` on its own thread at a fixed rate (default 1 kHz).

    Each tick reads the device position, computes the contact force and hands it back. The
    schedule is absolute (tick k at start + k/rate): a late tick does not shift later ones.
    Waiting sleeps until shortly before the tick and spins for the rest (sleep alone is
    too coarse for 1 ms periods). A tick that starts more than a period late does not burst
    through the ticks it owes: they are skipped, counted in ``stats.missed`` (``stats.behind``,
    and said by ``str(stats)``), and the loop resumes on the current slot of the schedule, so
    ``stats.rate`` is the rate actually achieved and the device's time stays the wall time.

    With numba, a Probe or a Grasp on a linear ModalSimulator or on a quasi-static
    ImpedanceDriver, read from a ScriptedDevice (with ``seconds``) or a SharedDevice, ticks in
    compiled code without the GIL (``compiled``: None = when it can, True = insist, False = the
    Python ticks); ``loop.compiled`` and ``stats.compiled`` say which ran.
    """

    MAX_RATE = 1e5  # Hz: beyond this a Python-level tick cannot be scheduled (the OS clock alone jitters ~us)

    def __init__(self, probe: Probe, device, rate: float = 1000.0, spin: float = 3e-4, *,
                 compiled: bool | None = None) -> None:
        if not callable(getattr(probe, "update", None)) or not hasattr(probe, "driver"):
            raise ModelError(f"probe={validate.show(probe)} must be an rt.Probe (or an rt.Grasp): an object with "
                             "update(position) and a driver")
        if not (callable(getattr(device, "position", None)) and callable(getattr(device, "set_force", None))):
            raise ModelError(f"device={validate.show(device)} must have position(t) and set_force(t, f) methods "
                             "(rt.ScriptedDevice, rt.CallbackDevice)")
        rate = validate.positive(rate, "rate", "ticks per second, in Hz")
        if rate > self.MAX_RATE:
            raise ModelError(f"rate={rate:g} Hz is above the {self.MAX_RATE:g} Hz a loop can be scheduled at; "
                             "haptic devices run at 1 .. 10 kHz")
        spin = validate.in_range(spin, "spin", 0.0, 0.1, what="seconds of busy-waiting before each tick")
        self.probe, self.device = probe, device
        self.rate = rate
        self.period = 1.0 / rate
        self.spin = spin
        self.stats = LoopStats()
        self._stop = threading.Event()
        self._owned: list[int] = []  # ids of the probe and its driver while this loop runs them
        self._ctl = np.zeros(1, dtype=np.int64)  # the compiled loop's flag: 1 stop, 2 pause
        self._paused, self._resume = threading.Event(), threading.Event()
        self._pause_lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self.error: BaseException | None = None
        self._kernels = None
        why = self._compiled_refusal()
        self._required = compiled is not None and validate.flag(compiled, "compiled")
        if compiled is None:
            compiled = why is None
        elif self._required and why is not None:
            raise ModelError(f"compiled=True: {why}")
        self.compiled = bool(compiled)  # ticks in compiled code where the run allows it (see start)
        if self.compiled:
            self._kernels = _compiled_loop()

    def _compiled_refusal(self) -> str | None:
        """Why the ticks cannot run in compiled code here (None: they can)."""
        if _compiled_loop() is None:
            return "the compiled loop needs numba (rtfem[fast]) and a monotonic clock (Linux, macOS)"
        if type(self.probe) not in (Probe, Grasp):
            return "only an rt.Probe or an rt.Grasp runs in the compiled loop (another object runs in Python)"
        if not _compiled_driver(self.probe.driver):
            return ("only a (linear) ModalSimulator with its compiled step, or a quasi-static ImpedanceDriver "
                    "(dynamic=False: a dynamic one keeps its force history in Python), drives the compiled loop")
        if type(self.device) not in (ScriptedDevice, SharedDevice):
            return "the compiled loop reads an rt.ScriptedDevice (sampled in advance) or an rt.SharedDevice"
        return None

    def _run(self, stats: LoopStats, max_steps: int | None, seconds: float | None) -> None:
        with _spare_core():
            self._ticks(stats, max_steps, seconds)

    def _ticks(self, stats: LoopStats, max_steps: int | None, seconds: float | None) -> None:
        st = stats
        t0 = time.perf_counter()
        deadline = None if seconds is None else t0 + seconds
        k = 0
        try:
            while not self._stop.is_set() and (max_steps is None or k - st.missed < max_steps):
                target = t0 + k * self.period
                if deadline is not None and target >= deadline:
                    break
                while True:
                    now = time.perf_counter()
                    wait = target - now
                    if wait <= 0:
                        break
                    if wait > self.spin:
                        time.sleep(wait - self.spin)
                start = time.perf_counter()
                if deadline is not None and start >= deadline:  # a loop that cannot keep the rate stops on
                    while t0 + k * self.period < deadline:  # time; the slots still due are skipped, and counted
                        k += 1
                        st.missed += 1
                    break
                if start - target > self.period:  # behind by whole ticks: skip them, do not burst
                    skip = int((start - target) / self.period)
                    k += skip
                    st.missed += skip
                    target = t0 + k * self.period
                t = k * self.period
                f = self.probe.update(self.device.position(t))
                self.device.set_force(t, f)
                st.lateness.append(start - target)
                st.slots.append(k)
                st.compute.append(time.perf_counter() - start)
                st.peak_force = max(st.peak_force, float(np.linalg.norm(f)))
                k += 1
                st.steps = k - st.missed
                st.seconds = time.perf_counter() - t0
        except BaseException as exc:  # surfaced by stop()/join()
            self.error = exc
        finally:
            st.seconds = time.perf_counter() - t0
            self._disown()

    def _run_compiled(self, stats: LoopStats, max_steps: int | None, seconds: float | None) -> None:
        """The loop with every tick in compiled code (kernels.loop_kernels): the GIL is released
        for whole runs of ticks, taken back only to prepare a newly touched vertex (its static
        correction: sparse solves), to empty a full record, and at the end."""
        dev = self.device
        t0 = time.perf_counter()
        try:
            scripted = type(dev) is ScriptedDevice
            n_slots = int(np.ceil(seconds * self.rate)) if seconds is not None else 0
            if scripted:
                positions = np.array([dev.position(k * self.period) for k in range(n_slots)], dtype=float).reshape(-1, 3)
                if not np.all(np.isfinite(positions)):
                    raise ModelError("the scripted device's trajectory gave NaN or infinite positions")
                mailbox = np.zeros(6)
            else:
                positions, mailbox = np.zeros((0, 3)), dev.mailbox
            capacity = n_slots if seconds is not None else int(10 * self.rate)
            if max_steps is not None:
                capacity = min(capacity, max_steps) if capacity else max_steps
            if type(self.probe) is Grasp:
                run = _CompiledGrasp(self.probe, self._kernels[2])
            else:
                run = _CompiledProbe(self.probe, self._kernels[0])
            run.pause = self._pause_point
            with _spare_core():
                t0 = time.perf_counter()
                deadline = t0 + seconds if seconds is not None else np.inf
                run.ticks(np.array([t0, self.period, deadline, self.spin]), positions, mailbox, self._ctl, capacity,
                          max_steps, lambda *rec: self._keep(stats, *rec, dev if scripted else None))
            stats.missed = run.missed
            stats.steps = len(stats.compute)
            stats.seconds = run.ended - t0
        except BaseException as exc:  # surfaced by stop()/join()
            self.error = exc
        finally:
            stats.seconds = stats.seconds or time.perf_counter() - t0
            self._disown()

    def _disown(self) -> None:
        """Let go of the probe and its driver (see :meth:`start`)."""
        with _OWNERS_LOCK:
            for key in self._owned:
                if _OWNERS.get(key) is self:
                    del _OWNERS[key]

    def _keep(self, stats: LoopStats, late, comp, forces, slots, scripted) -> None:
        """Move compiled-loop records into the statistics (and a scripted device's force log)."""
        stats.lateness.extend(late.tolist())
        stats.compute.extend(comp.tolist())
        stats.slots.extend(slots.tolist())
        if len(forces):
            stats.peak_force = max(stats.peak_force, float(np.linalg.norm(forces, axis=1).max()))
        if scripted is not None:
            scripted.times.extend((slots * self.period).tolist())
            scripted.forces.extend(forces.copy())

    def start(self, max_steps: int | None = None, *, seconds: float | None = None) -> "HapticLoop":
        """Start the loop on its own thread (fresh statistics); stop with :meth:`stop`.

        One loop per probe and per simulator: a second loop on a probe, or on another probe or tool
        of the same simulator, that is already driven is refused (two loops would step the same
        simulator twice per tick).
        """
        if max_steps is not None:
            max_steps = validate.count(max_steps, "max_steps", 1)
        if seconds is not None:
            seconds = validate.positive(seconds, "seconds", "a duration in seconds")
        if self._thread is not None and self._thread.is_alive():
            raise ModelError("this haptic loop is already running; stop() it first")
        compiled = self.compiled
        if compiled and type(self.device) is ScriptedDevice and seconds is None:
            if self._required:
                raise ModelError("a compiled loop samples a ScriptedDevice in advance: give seconds= (or compiled=False)")
            compiled = False  # an open-ended scripted run: the Python ticks (stats.compiled says so)
        if compiled and type(self.device) is ScriptedDevice and seconds * self.rate > MAX_PRESAMPLED:
            if self._required:  # (an hour at 10 kHz would be 36 million positions sampled before the first tick)
                raise ModelError(f"a compiled loop samples a ScriptedDevice in advance: {seconds * self.rate:.3g} ticks is "
                                 f"more than {MAX_PRESAMPLED:,}; run it in parts, or pass compiled=False")
            compiled = False
        try:  # the device's first answer, here: a device giving text or NaN fails now, not at stop()
            validate.point(self.device.position(0.0), "the device's position")
        except ModelError as exc:
            raise ModelError(f"{exc} (from {type(self.device).__name__}.position(0.0)); the loop was not started") \
                from None
        if compiled and _foreign_loads(self.probe):
            if self._required:
                raise ModelError(f"compiled=True: {_foreign_loads(self.probe)}")
            compiled = False
        driver = getattr(self.probe, "driver", None)
        owned = [(id(self.probe), "probe")] + ([] if driver is None else [(id(driver), "probe's simulator")])
        with _OWNERS_LOCK:
            for key, what in owned:
                owner = _OWNERS.get(key)
                if owner is not None and owner is not self:
                    raise ModelError(f"this {what} is already driven by another running HapticLoop (it would step twice "
                                     "per tick); stop that one first")
            for key, _ in owned:
                _OWNERS[key] = self
        self._owned = [key for key, _ in owned]
        self._stop.clear()
        self._ctl[0] = 0
        self._paused.clear()
        self._resume.clear()
        self.error = None
        self.stats = LoopStats(compiled=compiled)
        run = self._run_compiled if compiled else self._run
        self._thread = threading.Thread(target=run, args=(self.stats, max_steps, seconds),
                                        name="rtfem-haptic-loop", daemon=True)
        from ..threads import background

        background(self._thread, self._signal_stop)
        self._thread.start()
        return self

    def _signal_stop(self) -> None:
        """Tell the ticks to end (Python and compiled), without waiting."""
        self._stop.set()
        self._ctl[0] = 1
        self._resume.set()  # a loop waiting for a grab or release goes on to stop

    def _pause_point(self) -> None:
        """The loop thread, its ticks stopped for a waiting grab or release: wait until it is done."""
        self._paused.set()
        self._resume.wait()
        self._resume.clear()

    @contextlib.contextmanager
    def _held(self):
        """For a grab or a release from another thread while the compiled ticks run: the ticks
        stop (the slots meanwhile are skipped and counted), the grasp's state is handed back to
        it, and the ticks go on with the new grip when the block ends."""
        with self._pause_lock:
            self._paused.clear()
            self._ctl[0] = 2
            paused = False
            while not paused:
                paused = self._paused.wait(0.002)
                if not paused and (self._thread is None or not self._thread.is_alive() or self._ctl[0] == 1):
                    break  # the loop ended meanwhile: nothing to pause
            try:
                yield
            finally:
                if paused:
                    self._paused.clear()
                    self._resume.set()
                elif self._ctl[0] == 2:
                    self._ctl[0] = 0

    def stop(self, timeout: float = 5.0) -> LoopStats:
        """Stop the loop and return its statistics (raising what stopped it, if anything). A loop
        that does not end within ``timeout`` s (a device whose position() never returns) is left
        to end by itself and a SolverError says so, instead of waiting forever."""
        timeout = validate.positive(timeout, "timeout", "seconds to wait for the loop's thread")
        self._signal_stop()
        if self._thread is not None:
            self._thread.join(timeout)
            if self._thread.is_alive():
                raise SolverError(f"the haptic loop did not stop within {timeout:g} s: its tick is blocked, most likely "
                                  f"in {type(self.device).__name__}.position() (a device read that never returns); it "
                                  "stops at its next tick. Make the device's read return (or time out)")
        if self.error is not None:
            err, self.error = self.error, None
            raise err
        return self.stats

    def run(self, seconds: float) -> LoopStats:
        """Run for ``seconds`` of wall-clock time (blocking) and return the statistics.

        A loop that cannot keep its rate still stops on time; its statistics show how many
        ticks it managed and how late they were.
        """
        seconds = validate.positive(seconds, "seconds", "a duration in seconds")
        if seconds > 1e6:
            raise ModelError(f"seconds={seconds:g} is more than 11 days; use start() and stop() for an open-ended loop")
        self.start(seconds=seconds)
        self._thread.join()  # type: ignore[union-attr]
        return self.stop()


class _CompiledTicks:
    """A haptic object (Probe or Grasp) and its ModalSimulator packed into the arrays of a compiled
    loop (kernels.loop_kernels), and unpacked back into them when the ticks end. ``pause``, set
    by the loop, is called when the ticks stop for a waiting grab or release (status 3)."""

    def __init__(self, obj, chunk) -> None:
        self.sim, self.chunk = obj.driver, chunk
        self.impedance = _is_impedance(self.sim)
        self.fout = np.zeros(3)
        self.missed = 0
        self.pause = None

    def ticks(self, sched, positions, mailbox, ctl, capacity: int, max_steps, keep) -> None:
        """Run the compiled ticks; ``keep(lateness, compute, forces, slots)`` receives the records
        each time the record of ``capacity`` ticks fills and at the end."""
        sim = self.sim
        late, comp = np.zeros(capacity), np.zeros(capacity)
        forces, slots = np.zeros((capacity, 3)), np.zeros(capacity, dtype=np.int64)
        counters = np.array([0, 0, 0, -1 if max_steps is None else max_steps, 0], dtype=np.int64)
        clock = np.zeros(2, dtype=np.int64)
        steps0 = sim.steps
        if self.impedance:  # the driver's field follows the ticks' loads (a drawing thread reads them)
            sim._live = self._live_loads
        try:
            while True:
                status = self.chunk(self.arguments(), self.fout, sched, positions, mailbox, ctl, late, comp, forces,
                                    slots, counters, clock)
                if status == 1:  # a vertex touched for the first time: its compliance, then on
                    self.prepare()
                    continue
                if status == 3:  # a grab or release waits: hand over the state, take it back after
                    self._unpack(steps0 + int(counters[1]))
                    steps0, counters[1] = sim.steps, 0
                    ctl[0] = 0
                    self.pause()
                    self.pack()
                    continue
                n = int(counters[4])
                if status == 0 and n == capacity and (max_steps is None or counters[1] < max_steps):
                    keep(late[:n], comp[:n], forces[:n], slots[:n])  # the record is full: empty it and go on
                    counters[4] = 0
                    continue
                break
        finally:
            self.ended = time.perf_counter()
            n = int(counters[4])
            keep(late[:n], comp[:n], forces[:n], slots[:n])
            self.missed = int(counters[2])
            self._unpack(steps0 + int(counters[1]))
            if self.impedance:
                sim._live = None

    def _sim_arguments(self) -> tuple:
        sim = self.sim
        if self.impedance:  # quasi-static: no modes, so predict is 0 and the step moves nothing; the
            # contact compliance is the map's static one (the compliance table) and the loads are
            # read off the ticks' forces (_live_loads, _unpack)
            if getattr(self, "_none", None) is None:
                self._none = (np.zeros((8, 0)), np.zeros((2, 0)), np.zeros(0), np.zeros((sim.n_nodes, 3, 0)), False)
            return self._none
        return sim._coef, sim._S, sim._f_old, sim._phi, sim._G0 is not None

    def _steps_done(self, steps: int) -> None:
        self.sim.steps = steps
        self.sim.time = steps * self.sim.dt


class _CompiledProbe(_CompiledTicks):
    """A Probe in the compiled loop (kernels.probe_chunk)."""

    def __init__(self, probe: Probe, chunk) -> None:
        super().__init__(probe, chunk)
        self.probe = probe
        self.grid = probe._grid()
        # writable, C order
        self.X, self.normals = np.array(probe.X, dtype=float, order="C"), np.array(probe.normals, dtype=float, order="C")
        self.slot, self.table = probe._compliance_table()
        inv_k = 1.0 / probe.stiffness if probe.coupling == "spring" else 0.0
        self.fpar = np.array([probe.radius, inv_k, probe._requery])
        self.ist = np.array([-1 if probe.contact_node is None else probe.contact_node, 0, -1], dtype=np.int64)
        self.cand = np.zeros(probe._k, dtype=np.int64)
        self.fst = np.zeros(7)
        if probe._cand is not None and probe._cand.size == probe._k:
            self.cand[:], self.ist[1], self.fst[:3] = probe._cand, probe._k, probe._cand_at
        self.fst[3:6], self.fst[6] = probe.force, probe.penetration
        self._args = None

    def arguments(self) -> tuple:
        from ..drivers.kernels import probe_arguments

        if self._args is None:
            self._args = probe_arguments(*self._sim_arguments(), self.X, self.normals, *self.grid, self.fpar, self.ist,
                                         self.cand, self.fst, self.slot, self.table)
        return self._args

    def prepare(self) -> None:
        self.probe._compliance(int(self.ist[2]))
        self.slot, self.table = self.probe._compliance_table()
        self._args = None

    def _unpack(self, steps: int) -> None:
        probe, sim, ist, fst = self.probe, self.sim, self.ist, self.fst
        self._steps_done(steps)
        p = int(ist[0])
        probe.contact_node = p if p >= 0 else None
        probe.force = fst[3:6].copy()
        probe.penetration = float(fst[6])
        if ist[1]:
            probe._cand, probe._cand_at = self.cand[: ist[1]].copy(), fst[:3].copy()
        if self.impedance:
            sim._loads = self._live_loads()
        elif sim.static_correction:
            sim._loads = {p: -fst[3:6].copy()} if p >= 0 else {}
            sim._load_array = None

    def _live_loads(self) -> dict:
        """The load the ticks apply: an ImpedanceDriver's ``_loads`` as its step would hold them."""
        p, f = int(self.ist[0]), -self.fst[3:6]
        return {p: f} if p >= 0 and f.any() else {}


class _CompiledGrasp(_CompiledTicks):
    """A Grasp in the compiled loop (kernels.grasp_chunk): the jaw's system, which does not
    change while the grip holds (a linear ModalSimulator's compliances are constant), is
    inverted once when the jaw closes, and each tick is a prediction at the held vertices, one
    small matrix-vector product and the modal step."""

    def __init__(self, grasp: "Grasp", chunk) -> None:
        super().__init__(grasp, chunk)
        self.grasp = grasp
        self.pack()

    def pack(self) -> None:
        g, sim = self.grasp, self.sim
        r = self._sim_arguments()[3].shape[2]
        if g.node is None:
            nodes, A, base = np.zeros(0, dtype=np.int64), np.zeros((3, 3)), np.zeros(3)
        elif g.nodes.size == 1:
            nodes = np.array([g.node], dtype=np.int64)
            A = np.linalg.inv(np.eye(3) + g.stiffness * g.compliance(g.node))
            base = np.array(g.X[g.node], dtype=float)
        else:
            nodes = np.asarray(g.nodes, dtype=np.int64)
            W = g._block if g._block is not None else step_compliances(sim, nodes)
            A = np.linalg.inv(patch_system(W, g.stiffness, g.grip))
            base = np.concatenate([g._hold, g._jaw])
        m = nodes.size
        self.nodes, self.F = nodes, np.zeros((m, 3))
        gpar = np.array([g.stiffness, np.inf if g.max_force is None else g.max_force])
        from ..drivers.kernels import grasp_arguments

        self._args = grasp_arguments(*self._sim_arguments(), nodes, np.ascontiguousarray(A), base, gpar, self.F,
                                     np.zeros(3 * m + 3), np.zeros(r))

    def arguments(self) -> tuple:
        return self._args

    def _unpack(self, steps: int) -> None:
        g, sim = self.grasp, self.sim
        ticked = steps > sim.steps  # the simulator's count moves only here: ticks ran since the last pack
        self._steps_done(steps)
        if self.nodes.size and ticked:
            g.forces = self.F.copy()
            g.force = g.forces.sum(axis=0)
        else:
            g.force, g.forces = np.zeros(3), np.zeros((0, 3))
        if self.impedance:
            if ticked:
                sim._loads = self._live_loads()
        elif sim.static_correction:
            sim._loads = {int(v): f.copy() for v, f in zip(self.nodes.tolist(), self.F)} if self.nodes.size else {}
            sim._load_array = None


    def _live_loads(self) -> dict:
        """The loads the ticks apply (the nonzero forces on the held vertices), as an
        ImpedanceDriver's step would hold them."""
        return {int(v): f.copy() for v, f in zip(self.nodes.tolist(), self.F) if f.any()}


_OWNERS: dict[int, HapticLoop] = {}  # id(probe) -> the loop driving it


def _compiled_loop():
    from ..drivers.kernels import loop_kernels

    return loop_kernels()


def _spare_core():
    """While a loop runs, BLAS (numpy's and MKL's thread pools) is held to one thread
    (:func:`rtfem.threads.runtime`), so that a drawing thread's field product cannot take the
    loop's core: on 2 cores a two-thread product pre-empted the loop for 5 ms at a time
    (benchmarks/haptic_loop.py, "busy viewer"). Needs threadpoolctl (rtfem[fast]); without it,
    nothing is limited."""
    from ..threads import runtime

    return runtime()


def _is_impedance(driver) -> bool:
    from ..drivers.impedance import ImpedanceDriver

    return type(driver) is ImpedanceDriver


def _compiled_driver(driver) -> bool:
    """Whether the compiled ticks can drive ``driver``: a linear ModalSimulator with its compiled
    step, or a quasi-static ImpedanceDriver (its ticks are the modal ones with no modes)."""
    from ..drivers.modal import ModalSimulator

    if _is_impedance(driver):
        return not driver.dynamic
    return type(driver) is ModalSimulator and bool(driver.compiled)


def _foreign_loads(obj) -> str | None:
    """Why the compiled ticks would not match the Python ones for ``obj`` now, else None: a Probe
    out of contact on an ImpedanceDriver that holds loads the probe did not apply (the compiled
    nearest-vertex search takes the surface at rest, which is where the probe's own loads leave it)."""
    d = obj.driver
    if type(obj) is Probe and _is_impedance(d) and obj.contact_node is None and d._loads:
        return ("the impedance driver holds loads the probe did not apply (its field moves the surface the "
                "probe searches): step(None) it first, or run the Python ticks")
    return None
_OWNERS_LOCK = threading.Lock()


def _replay(obj, positions, compiled, what: str) -> np.ndarray:
    """Probe.replay and Grasp.replay: ``obj.update`` at each position, in Python or in the
    compiled loop's ticks with no schedule."""
    P = validate.real_array(positions, "positions", 2)
    if P.shape[1] != 3:
        raise ModelError(f"positions must be a (k, 3) array of {what} positions in m, got shape {P.shape}")
    usable = _compiled_loop() is not None and _compiled_driver(obj.driver) and not _foreign_loads(obj)
    if compiled is None:
        compiled = usable
    elif validate.flag(compiled, "compiled") and not usable:
        raise ModelError("compiled=True needs numba (rtfem[fast]) and a linear ModalSimulator with its compiled step "
                         "or a quasi-static ImpedanceDriver" + (f"; {_foreign_loads(obj)}" if _foreign_loads(obj) else ""))
    if not compiled:
        return np.array([obj.update(c).copy() for c in P]).reshape(-1, 3)
    out = []
    kernels = _compiled_loop()
    run = _CompiledGrasp(obj, kernels[2]) if isinstance(obj, Grasp) else _CompiledProbe(obj, kernels[0])
    run.ticks(np.array([0.0, 0.0, np.inf, 0.0]), np.ascontiguousarray(P, dtype=float), np.zeros(6),
              np.zeros(1, dtype=np.int64), max(len(P), 1), None, lambda late, comp, f, slots: out.append(f.copy()))
    return np.concatenate(out).reshape(-1, 3)


def _loop_paused(obj):
    """The compiled loop driving ``obj`` paused (from another thread), or nothing to pause."""
    with _OWNERS_LOCK:
        loop = _OWNERS.get(id(obj))
    if loop is None or not loop.stats.compiled or threading.current_thread() is loop._thread:
        return contextlib.nullcontext()
    return loop._held()


def _cached_compliance(driver, cache: dict, node: int) -> np.ndarray:
    """The driver's 3x3 step compliance at ``node``, kept in ``cache``; the first time the driver
    prepares the node (static-correction or compliance columns, an impedance map)."""
    W = cache.get(node)
    if W is None:
        prepare(driver, [node])
        W = cache[node] = np.asarray(driver.step_compliance(node), dtype=float)
    elif getattr(driver, "compliance_changes", False):  # warped or nonlinear: it follows the motion
        W = np.asarray(driver.step_compliance(node), dtype=float)
    return W
