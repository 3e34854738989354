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


import numpy as np
from scipy.spatial import cKDTree

from .. import validate
from ..errors import ModelError
from ..mesh.surface import TriMesh
from .contact import nodes_to_prepare, patch_system
from ..drivers.base import as_driver, check_driver_mesh, displacements_at, predictions, prepare, step_compliances

from .ticks import _cached_compliance, _compiled_driver, _compiled_loop, _CompiledTicks, _is_impedance, _loop_paused

__all__ = ["Probe", "Grasp"]


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

    Raises
    ------
    ModelError
        A driver that is not one or is of another mesh, an unknown coupling, a negative radius, a
        non-positive stiffness or candidates; in :meth:`update`, a position that is not a finite
        point within 1e6 m.
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

    Parameters
    ----------
    mesh : the organ's :class:`~rtfem.TriMesh` (a solid's boundary surface: ``model.mesh``).
    driver : any Driver on that mesh (an :class:`~rtfem.ImpedanceMap` is wrapped as its driver).
    stiffness : the grasp spring k between hand and jaw (N/m).
    max_force : a cap on the total force (N); None: no cap.
    radius : the jaw holds the surface vertices within this of the grabbed one (m); 0: one vertex.
    grip : each held vertex's spring to the jaw (N/m; default 100 k).

    Raises
    ------
    ModelError
        A driver that is not one or is of another mesh, a non-positive stiffness, max_force or
        grip, a negative radius; in :meth:`grab`, a node off the surface or held by the supports.
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
        self._patch_inv = None

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
            self._patch_inv = None
        else:
            prepare(self.driver, nodes)
            W = step_compliances(self.driver, nodes)
            nodes, keep = _movable(nodes, W, node)
            W = W[np.ix_(keep, keep)]
            self._block = None if getattr(self.driver, "compliance_changes", False) else W
            self._patch_inv = None
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
        self._patch_inv = None

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
            # the jaw's system (contact.hold_patch) inverted once per grip and compliance, as in the compiled
            # tick: a constant compliance (_block), or the driver's until it changes (a reduced nonlinear
            # driver's, at a tangent refresh); a (3m + 3) product per step
            W = self._block if self._block is not None else step_compliances(d, self.nodes)
            key = (k, self.grip)
            inv = self._patch_inv
            if inv is None or inv[0] != key or (inv[2] is not W and not np.array_equal(inv[2], W)):
                self._patch_inv = inv = (key, np.linalg.inv(patch_system(W, k, self.grip)), W)
            f = (inv[1] @ np.concatenate([h, k * (c - self._jaw)]))[:-3].reshape(-1, 3)
        total = f.sum(axis=0)
        self.demand = mag = float(np.linalg.norm(total))
        self.clipped = self.max_force is not None and mag > self.max_force
        if self.clipped:
            f = f * (self.max_force / mag)
            total = f.sum(axis=0)
        d.step({int(v): (float(g[0]), float(g[1]), float(g[2])) for v, g in zip(self.nodes.tolist(), f)})
        self.force, self.forces = total, f
        return total




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




def _foreign_loads(obj) -> str | None:
    """Why the compiled ticks would not match the Python ones for ``obj`` now, else None: a Probe
    out of contact on an ImpedanceDriver that holds loads the probe did not apply (the compiled
    nearest-vertex search takes the surface at rest, which is where the probe's own loads leave it)."""
    d = obj.driver
    if type(obj) is Probe and _is_impedance(d) and obj.contact_node is None and d._loads:
        return ("the impedance driver holds loads the probe did not apply (its field moves the surface the "
                "probe searches): step(None) it first, or run the Python ticks")
    return None


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


