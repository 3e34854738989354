"""Tool-tissue contact over patches: rigid tools against the deformed surface, with friction.

A tool is a convex "core" (a point, a segment or a rectangle) swept by a radius: a sphere, a
capsule (an instrument shaft) or a flat jaw. Its signed distance is d(x) = |x - core(x)| - R, with
unit gradient n(x) = (x - core(x)) / |x - core(x)|, the direction the tool pushes the tissue.

Contact points. Every surface vertex near the tool is a candidate, at its *predicted* position
(where it would be after one more step with no new load, :func:`~rtfem.drivers.base.predictions`), and
so is the one point of the deformed surface closest to the tool's core, on a triangle (barycentric
weights b): with the vertices alone a small probe would pass between them and feel the vertex
spacing. The gap of a contact point y = sum_k b_k x_k is d0 = d(y); its frame F = [n, t1, t2].

The solve (James & Pai's capacitance matrix). With the driver's one-step cross compliances W_SS
(:func:`~rtfem.drivers.base.step_compliances`) the contact points move as y(k+1) = y_free + B W_SS B^T f.
The tool is coupled to the device by a virtual spring of stiffness k (``coupling="spring"``; a
"constraint" is k = infinity): its proxy sits at x_t = x_d - (1/k) sum f. In each point's frame
(r_c = F_c^T f_c) the gap and the tangential slip of the step are

    w = b + A r,   A_cd = F_c^T (B W_SS B^T + 1/k)_cd F_d,
    b_c = [d0_c - n_c . (x_d(k+1) - x_e);  T_c^T ((y_free,c - y_c(k)) - (x_d(k+1) - x_t(k)))],

The contact points are found with the tool where it was, x_t(k) (a point stuck to the tool is
found at the same material point again), and their gaps d0 and frames F are evaluated against
the tool where it will end the step with last step's force, x_e = x_d(k+1) + (1/k) f_hand(k) (the
device itself for a constraint), so that the friction directions do not lag a step behind a
large quasi-static move; the coupling's change over the step is linear through A, and the slip
takes the tool's whole move over the step, x_d(k+1) - x_t(k). A direction the supports hold has
no compliance; the tangential diagonal gets 1e-9 of the point's compliance, so that the tool
slides on such a point with friction (the supports take the force) instead of dividing by zero.
With the Signorini conditions w_n >= 0, r_n >= 0, w_n r_n = 0 and Coulomb's law |r_t| <= mu r_n
(stick: w_t = 0; slip: r_t opposes w_t at |r_t| = mu r_n). This is solved by projected
Gauss-Seidel over the 3x3 contact blocks (the normal by its row, the tangential pair by its 2x2
block, a sliding pair on the friction circle opposite its slip), warm-started from the previous
step's forces, with subspace steps (Silcowitz, Niebe & Erleben's PGS-SM): once a sweep leaves
every contact's state (apart, sliding, stuck) unchanged, the equalities of those states are solved
directly, kept when they bring the forces closer to a solution (:func:`~rtfem.interaction.friction.pgs`, compiled when numba
is present). The step is then taken with the vertex forces B^T F r; the hand feels -sum f.

The compliances of the vertices touched lately are kept from step to step in one pool: when the
set changes only the rows and columns of newly touched vertices are computed, and the set's block
is read in place (for drivers whose W follows the motion, ``compliance_changes``, the whole block
each step). What a vertex needs from the driver first
(its static-correction or compliance columns: sparse solves, milliseconds) is prepared by a
background thread while the tool is still ``lookahead`` away, so a sliding tool does not stall
the force loop; a vertex not ready when touched is prepared in the loop, so the numbers never
depend on the timing.
"""

from __future__ import annotations


import numpy as np
from scipy.spatial import cKDTree

from .. import validate
from ..errors import ModelError
from ..mesh.surface import TriMesh
from ..drivers.base import as_driver, displacements_at, predictions
from .compliance import _ComplianceBlock
from .contact_points import _after, _faces, _gaps, _points, _rhs
from .friction import _diagonal, _solve

__all__ = ["Tool", "ToolContact", "hold_patch", "nodes_to_prepare"]


class Tool:
    """A rigid tool: a convex core swept by a radius (sphere, capsule, flat jaw).

    The core is the box [-a, a] x [-b, b] x {0} in the tool's frame (``orientation``: the 3x3
    rotation whose columns are the frame's axes in the world): a = b = 0 a point (a sphere), b = 0 a
    segment along the first axis (a capsule), both > 0 a rectangle (a jaw, whose face normal is the
    third axis). Use the constructors :meth:`sphere`, :meth:`capsule` and :meth:`jaw`.

    Parameters
    ----------
    radius : the radius swept around the core (m); 0 with a point core is a point probe.
    half_extents : (a, b), the core's half-lengths along the frame's first two axes (m).
    orientation : the tool frame's rotation, a 3x3 matrix whose columns are its axes in the world; default identity.
    kind : a name for messages ("sphere", "capsule", "jaw" from the constructors).

    Raises
    ------
    ModelError
        A negative radius or half-length, half_extents that are not two numbers, an orientation
        that is not a rotation.
    """

    def __init__(self, radius: float, half_extents=(0.0, 0.0), orientation=None, *, kind: str = "tool") -> None:
        self.radius = validate.nonnegative(radius, "radius", "the tool's radius in m")
        if isinstance(half_extents, (str, bytes)) or np.ndim(half_extents) != 1 or len(half_extents) != 2:
            raise ModelError(f"half_extents={validate.show(half_extents)} must be two half-lengths (a, b) in m: the "
                             "core's segment (b = 0) or rectangle (0, 0: a point)")
        a, b = (validate.nonnegative(v, n, "a half-length in m") for v, n in zip(half_extents, ("a", "b")))
        self.half_extents = np.array([a, b, 0.0])
        self.orientation = np.ascontiguousarray(np.eye(3) if orientation is None else _rotation_matrix(orientation), dtype=float)
        self.kind = kind

    @classmethod
    def sphere(cls, radius: float) -> "Tool":
        """A sphere of ``radius`` (m); 0 is a point probe."""
        return cls(radius, kind="sphere")

    @classmethod
    def capsule(cls, radius: float, length: float, axis=(1.0, 0.0, 0.0)) -> "Tool":
        """A capsule (an instrument shaft): a segment of ``length`` along ``axis`` swept by ``radius``."""
        length = validate.positive(length, "length", "the capsule's length in m")
        return cls(radius, (0.5 * length, 0.0), _frame(axis), kind="capsule")

    @classmethod
    def jaw(cls, width: float, length: float, thickness: float, normal=(0.0, 0.0, 1.0), along=None) -> "Tool":
        """A flat jaw: a ``length`` x ``width`` plate of ``thickness`` (rounded edges) whose faces
        look along ``normal``; ``along`` the direction of its length (any direction across the normal
        when not given)."""
        width = validate.positive(width, "width", "the jaw's width in m")
        length = validate.positive(length, "length", "the jaw's length in m")
        thickness = validate.positive(thickness, "thickness", "the jaw's thickness in m")
        n = _unit(normal, "normal")
        t = _frame(n)[:, 1] if along is None else _unit(along, "along")
        t = t - (t @ n) * n
        if np.linalg.norm(t) < 1e-9:
            raise ModelError("the jaw's length direction `along` must not be parallel to its normal")
        t /= np.linalg.norm(t)
        R = np.column_stack([t, np.cross(n, t), n])
        return cls(0.5 * thickness, (0.5 * length, 0.5 * width), R, kind="jaw")

    @property
    def reach(self) -> float:
        """The radius of a ball around the tool's position that contains the tool."""
        return float(np.linalg.norm(self.half_extents) + self.radius)

    def core(self, points: np.ndarray, position: np.ndarray) -> np.ndarray:
        """The closest core point (k, 3) to each of ``points`` with the tool at ``position``."""
        R = self.orientation
        local = (points - position) @ R
        local = np.clip(local, -self.half_extents, self.half_extents)
        return position + local @ R.T

    def distance(self, points: np.ndarray, position: np.ndarray, outward: np.ndarray):
        """Signed gaps (k,) between surface ``points`` and the tool at ``position``, and the unit
        directions (k, 3) the tool pushes them along; ``outward`` (k, 3) the surface's outward
        normals there. Away from the core, |x - core(x)| - R; a point the core has passed (the core
        behind the surface, within R of the normal line) gets a negative gap and the inward normal,
        so that it is pushed on, not back; so does a point on the core itself. (The force loop's
        compiled :func:`_gaps` is this, with the normal line widened on a concave edge.)"""
        v = self.core(points, position) - points
        dist = np.sqrt(np.einsum("ij,ij->i", v, v))
        above = _outside(v, outward, self.radius)
        n = np.where((above & (dist > 1e-12))[:, None], -v / np.maximum(dist, 1e-300)[:, None], -outward)
        return np.where(above, dist, -dist) - self.radius, n

    def __repr__(self) -> str:
        a, b, _ = self.half_extents
        return f"Tool.{self.kind}(radius={self.radius:g}, half_extents=({a:g}, {b:g}))"


def _unit(v, name: str) -> np.ndarray:
    v = validate.vector(v, name, 3)
    n = float(np.linalg.norm(v))
    if n < 1e-300:
        raise ModelError(f"{name} must be a nonzero direction")
    return v / n


def _frame(axis) -> np.ndarray:
    """A rotation whose first column is ``axis``."""
    e = _unit(axis, "axis")
    helper = np.eye(3)[int(np.argmin(np.abs(e)))]
    t1 = np.cross(e, helper)
    t1 /= np.linalg.norm(t1)
    return np.column_stack([e, t1, np.cross(e, t1)])


def _rotation_matrix(R) -> np.ndarray:
    R = validate.real_array(R, "orientation", 2)
    if R.shape != (3, 3) or np.abs(R.T @ R - np.eye(3)).max() > 1e-6 or np.linalg.det(R) < 0:
        raise ModelError("orientation must be a 3x3 rotation matrix (orthonormal columns, determinant +1)")
    return R


# ------------------------------------------------------------------------------ compiled geometry


class ToolContact:
    """A rigid :class:`Tool` in frictional contact with an organ through any Driver, coupled to a
    haptic device by a virtual spring. ``update(position)`` is one haptic step (a HapticLoop drives
    it like a Probe); it returns the force on the device (N).

    Parameters
    ----------
    mesh : the organ surface (the driver's mesh).
    driver : a ModalSimulator (linear or warped), a DirectSimulator (linear or large-deformation),
        an ImpedanceMap or any Driver.
    tool : a :class:`Tool` (default: a 5 mm sphere).
    coupling : "spring" (virtual coupling of ``stiffness`` N/m, default) or "constraint" (the tool
        sits at the device; points the supports hold, which a rigid tool cannot move, are left out
        of its contacts).
    friction : Coulomb's coefficient mu (0: frictionless).
    margin : candidates within this distance of the tool (m) enter the solve (default: a quarter of
        the median edge), so that a point about to touch is in the set.
    surface_point : also the surface point closest to the tool's core, on a triangle (default True;
        False: vertices only, for a tool much larger than the edges).
    lookahead : vertices within this distance beyond the tool's reach (m; default two median edges)
        are prepared on a background thread before the tool touches them (their static-correction
        or compliance columns: a few ms each), so that a tool sliding onto new vertices does not
        stall the force loop; 0: prepared in the loop when touched. Either way the same numbers.

    Raises
    ------
    ModelError
        A driver that is not one or is of another mesh, a tool that is not a Tool, an unknown
        coupling, a non-positive stiffness, a negative friction, margin or lookahead; in
        :meth:`update`, a position that is not a finite point within 1e6 m or a tool starting
        deeper in the tissue than its radius or an edge.
    """

    def __init__(self, mesh: TriMesh, driver, tool: Tool | None = None, *, coupling: str = "spring",
                 stiffness: float = 200.0, friction: float = 0.0, margin: float | None = None,
                 surface_point: bool = True, lookahead: float | None = None, max_sweeps: int = 500,
                 tol: float = 1e-10) -> None:
        from ..drivers.base import check_driver_mesh

        driver = as_driver(driver, "tool")
        check_driver_mesh(mesh, driver, "tool")
        self.tool = Tool.sphere(0.005) if tool is None else tool
        if not isinstance(self.tool, Tool):
            raise ModelError(f"tool={validate.show(tool)} must be an rt.Tool (Tool.sphere, Tool.capsule, Tool.jaw)")
        self.coupling = validate.choice(coupling, "coupling", ("spring", "constraint"))
        self.stiffness = validate.positive(stiffness, "stiffness", "the coupling stiffness in N/m")
        self.friction = friction
        self.surface_point = validate.flag(surface_point, "surface_point")
        self.max_sweeps = validate.count(max_sweeps, "max_sweeps", 1, 10**6)
        self.tol = validate.positive(tol, "tol", "a relative tolerance")
        self.mesh, self.driver = mesh, driver
        touched = mesh.contact_surface()  # quadratic faces: their corner and mid-edge triangles
        self.X = np.asarray(touched.vertices, dtype=float)
        self.normals = touched.vertex_normals()
        self._touchable = touched.used_vertices()
        self._tree = cKDTree(self.X[self._touchable])
        T = np.asarray(touched.triangles, dtype=np.int64)
        self._tri = T  # vertex -> triangles (CSR): _vt_tris[_vt_start[v]:_vt_start[v + 1]]
        order = np.argsort(T.reshape(-1), kind="stable")
        self._vt_tris = order // 3
        self._vt_start = np.searchsorted(T.reshape(-1)[order], np.arange(self.X.shape[0] + 1))
        edges = touched.edges()
        self.edge = float(np.median(np.linalg.norm(self.X[edges[:, 0]] - self.X[edges[:, 1]], axis=1)))
        self.margin = 0.25 * self.edge if margin is None else validate.nonnegative(margin, "margin", "a distance in m")
        self.lookahead = 2 * self.edge if lookahead is None else validate.nonnegative(lookahead, "lookahead",
                                                                                      "a distance in m")
        self._block = _ComplianceBlock(driver)
        self._ahead = getattr(driver, "prepare", None) is not None and not getattr(driver, "compliance_changes", False)
        self._asked_at: np.ndarray | None = None  # where the tool was when the vertices ahead were last named
        self._warm_ids, self._warm_r = np.zeros(0, dtype=np.int64), np.zeros((0, 3))  # last step's forces
        self._cand: np.ndarray | None = None  # the candidate vertices (see _candidates)
        self._cand_at = np.zeros(3)
        self._buf: tuple | None = None  # the contact set's arrays (see _contact_set), reused
        self._A = np.empty(0)  # the contact operator's buffer (see _operator)
        self._offset = np.zeros(3)
        self.proxy: np.ndarray | None = None  # the tool's position after the coupling (m)
        self.force = np.zeros(3)  # force on the device (N); the organ gets -force in total
        self.contacts = 0  # active contact points (positive normal force) in the last step
        self.sweeps = 0  # PGS sweeps of the last step
        self.points = np.zeros((0, 3))  # the active contact points after the last step (deformed, m)
        self.contact_forces = np.zeros((0, 3))  # and the force on the organ at each (N)
        self.contact_normals = np.zeros((0, 3))  # and the direction the tool pushes at each

    @property
    def friction(self) -> float:
        """Coulomb's coefficient mu (0: frictionless); may be changed between steps, mid-contact
        (checked: a finite number from 0 to 10, else ModelError and the old value kept)."""
        return self._friction

    @friction.setter
    def friction(self, mu) -> None:
        self._friction = validate.in_range(mu, "friction", 0.0, 10.0, what="Coulomb's friction coefficient")

    # ---------------------------------------------------------------- preparation
    def prepare(self, nodes=None, *, around=None, radius: float = 0.01) -> int:
        """Compute what contacts at these vertices will need (static-correction columns, compliance
        columns, maps) before the force loop; as :meth:`Probe.prepare`. Returns how many."""
        nodes = nodes_to_prepare(self._touchable, self._tree, self.X.shape[0], nodes, around, radius)
        if nodes.size:
            self._block.preparer.ensure(nodes)
        return int(nodes.size)

    def displacements(self) -> np.ndarray:
        return self.driver.displacements()

    # ---------------------------------------------------------------- the contact set
    def _candidates(self, c: np.ndarray) -> np.ndarray:
        """The surface vertices that may touch the tool at ``c`` (ascending), from a ball query
        one edge wider than needed, kept until the tool has moved that edge (relative to the
        vertices' mean motion)."""
        at = c - self._offset
        if self._cand is None or np.sum((at - self._cand_at) ** 2) > self.edge**2:
            reach = self.tool.reach + self.margin + 2 * self.edge
            verts = self._touchable[np.asarray(self._tree.query_ball_point(at, reach), dtype=np.int64)]
            verts.sort()
            self._cand, self._cand_at = verts, at
        return self._cand

    def _contact_set(self, c: np.ndarray, ahead: np.ndarray):
        """Contact points near the tool at ``c`` (where it was: a stuck face point is found at the
        same material point again), their gaps and frames against the tool at ``ahead`` (where it
        will end the step): (nodes S, corners Bi (m, 3) (rows of S) and weights Bv, frames
        (m, 3, 3), gaps (m,), free positions (m, 3), current positions (m, 3), ids (m,)), or None."""
        verts = self._candidates(c)
        if verts.size == 0:
            return None
        tool = self.tool
        R, half, radius = tool.orientation, tool.half_extents, float(tool.radius)
        k = verts.size
        d, n, O = np.empty(k), np.empty((k, 3)), self.normals[verts]
        # the triangles around the candidate nearest the tool, by the rest shape moved by the
        # candidates' mean motion (a stable choice: by the deformed shape a flat jaw over many
        # vertices at one gap would pick another ring each step)
        X = self.X[verts]
        P = X + self._offset
        _gaps(P, P, O, np.zeros(k), c, R, half, radius, d, n)
        v = int(verts[np.argmin(d)])
        ring = self._vt_tris[self._vt_start[v]:self._vt_start[v + 1]]
        corners = self._tri[ring]
        loc = np.searchsorted(verts, corners)
        if np.any(verts[np.minimum(loc, k - 1)] != corners):  # the ring reaches past the candidates
            self._cand = np.union1d(verts, corners)
            return self._contact_set(c, ahead)
        u_free = predictions(self.driver, verts)
        u_now = displacements_at(self.driver, verts)
        self._offset = u_now.mean(axis=0)
        # the geometry of the surface now (continuous from step to step), its free motion linearly
        Y, Yf = X + u_now, X + u_free
        _gaps(Y, Y, O, np.zeros(k), ahead, R, half, radius, d, n)
        g = d + np.einsum("ki,ki->k", n, Yf - Y)  # each gap moved on to the free position, linearly
        f = ring.size if self.surface_point else 0
        bw, nf, df, keep = np.empty((f, 3)), np.empty((f, 3)), np.empty(f), np.empty(f, dtype=np.int64)
        if f:  # a face point within 1e-3 edge of a vertex contact or of another kept point is the
            # same contact twice (a probe sitting on a vertex): dropped
            kept = _faces(Y, Yf, loc, c, ahead, R, half, radius, 1 if not half.any() else 4,
                          self.margin + 2 * self.edge, self.margin, 1e-3 * self.edge, Y[g < self.margin], bw, nf, df,
                          keep)
            keep = keep[:kept]
        loc, bw, nf, df, fid = loc[keep], bw[keep], nf[keep], df[keep], -1 - ring[keep]
        size = k + loc.shape[0]
        if self._buf is None or self._buf[0].size < size:
            cap = 2 * size
            self._buf = (np.empty(cap, dtype=np.int64), np.empty(cap, dtype=np.int64), np.empty((cap, 3), dtype=np.int64),
                         np.empty((cap, 3)), np.empty((cap, 3, 3)), np.empty(cap), np.empty((cap, 3)),
                         np.empty((cap, 3)), np.empty(cap, dtype=np.int64))
        pos, S, Bi, Bv, F, gaps, y_free, y_now, ids = self._buf
        m, ns = _points(g, n, Y, Yf, verts, self.margin, np.ascontiguousarray(loc), np.ascontiguousarray(bw), nf, df,
                        np.ascontiguousarray(fid), pos, S, Bi, Bv, F, gaps, y_free, y_now, ids)
        if m == 0:
            return None
        return verts[S[:ns]], Bi[:m], Bv[:m], F[:m], gaps[:m], y_free[:m], y_now[:m], ids[:m]

    # ---------------------------------------------------------------- the step
    def update(self, position) -> np.ndarray:
        """One step with the device at ``position``; returns the force on the device (N)."""
        c = validate.point(position, "tool position")
        inv_k = 1.0 / self.stiffness if self.coupling == "spring" else 0.0
        # the geometry (gaps, frames) where the tool will end the step with last step's force (at the
        # device for a constraint), so that large steps bring no lag in the friction directions; the
        # coupling's change over the step is linear in the solve, and the slip takes the tool's whole
        # move over the step, x_d(k+1) - x_t(k)
        ahead = c + inv_k * self.force
        last = c if self.proxy is None else self.proxy
        if self.lookahead > 0 and self._ahead:
            self._look_ahead(c)
        found = self._contact_set(last, ahead)
        if found is None:
            return self._apart(c)
        S, Bi, Bv, F, gaps, y_free, y_now, ids = found
        deepest = -float(gaps.min())
        if deepest > max(self.tool.radius, self.edge):  # nothing stepped: the state is as it was
            raise ModelError(f"the tool would be {deepest * 1e3:.3g} mm inside the organ at once, more than its radius "
                             f"({self.tool.radius * 1e3:.3g} mm) and an edge ({1e3 * self.edge:.3g} mm): a jump of the "
                             "device (or a tool placed inside the organ) has no contact answer. Move it there in steps "
                             "from outside")
        m = gaps.size
        W, slots = self._block.block(S)
        Bs = slots[Bi]  # the points' corners as the pool's slots
        A = self._operator(m)  # the contact operator (see _pgs), filled as the solve needs it
        if inv_k == 0.0:  # a rigid tool cannot press a point the supports hold (zero compliance): left out
            _diagonal(W, Bs, Bv, F, inv_k, A)
            normal = np.diagonal(A)[::3]
            soft = normal > 1e-12 * max(float(normal.max()), 1e-300)
            if not soft.all():
                if not soft.any():
                    return self._apart(c)
                Bi, Bs, Bv, F, gaps, y_free, y_now, ids = (np.ascontiguousarray(x[soft]) for x in
                                                           (Bi, Bs, Bv, F, gaps, y_free, y_now, ids))
                m = gaps.size
                A = self._operator(m)
        b, r = np.empty((m, 3)), np.empty((m, 3))
        _rhs(F, gaps, y_free, y_now, c - ahead, c - last, ids, self._warm_ids, self._warm_r, b, r)
        r, sweeps = _solve(A, np.zeros(m, dtype=bool), W, Bs, Bv, F, inv_k, b.reshape(-1), np.full(m, self.friction),
                           r.reshape(-1), self.max_sweeps, self.tol)
        r = r.reshape(m, 3)
        f_points, f_nodes, y_after = np.empty((m, 3)), np.empty((S.size, 3)), np.empty((m, 3))
        _after(W, slots, Bi, Bv, F, r, y_free, f_points, f_nodes, y_after)
        pushed = np.flatnonzero(f_nodes.any(axis=1))
        loads = dict(zip(S[pushed].tolist(), map(tuple, f_nodes[pushed].tolist())))
        self.driver.step(loads or None)
        total = f_points.sum(axis=0)
        self.proxy = c - inv_k * total
        self.force = -total
        self.sweeps = sweeps
        active = r[:, 0] > 0
        self.contacts = int(np.count_nonzero(active))
        self._warm_ids, self._warm_r = ids[active], r[active]
        self.points, self.contact_forces, self.contact_normals = y_after[active], f_points[active], F[active, :, 0]
        return self.force

    def _operator(self, m: int) -> np.ndarray:
        """A (3m, 3m) for the solve, in a buffer kept between steps (filled by the solve itself)."""
        if self._A.size < 9 * m * m:
            self._A = np.empty(max(9 * m * m, 2 * self._A.size))
        return self._A[:9 * m * m].reshape(3 * m, 3 * m)

    def _look_ahead(self, c: np.ndarray) -> None:
        """Name the vertices within the lookahead to the background preparer, when the tool has
        moved a quarter edge since it last did (a ball query, some 10-50 us)."""
        at = c - self._offset
        if self._asked_at is not None and np.sum((at - self._asked_at) ** 2) < (0.25 * self.edge) ** 2:
            return
        self._asked_at = at
        reach = self.tool.reach + self.margin + self.edge + self.lookahead
        verts = self._touchable[np.asarray(self._tree.query_ball_point(at, reach), dtype=np.int64)]
        if verts.size:
            self._block.preparer.want(verts, self.X[verts], at)

    def _apart(self, c: np.ndarray) -> np.ndarray:
        """A step with nothing touched: the organ moves freely, the tool sits at the device."""
        self.driver.step(None)
        self.proxy, self.force, self.contacts, self.sweeps = c.copy(), np.zeros(3), 0, 0
        self.points = self.contact_forces = self.contact_normals = np.zeros((0, 3))
        self._warm_ids, self._warm_r = np.zeros(0, dtype=np.int64), np.zeros((0, 3))
        return self.force


def nodes_to_prepare(touchable: np.ndarray, tree: cKDTree, n_nodes: int, nodes=None, around=None,
                     radius: float = 0.01) -> np.ndarray:
    """The vertices a tool's ``prepare`` names: ``nodes`` (checked indices), or the surface vertices
    (``touchable``, indexed by ``tree`` at their rest positions) within ``radius`` of ``around``."""
    if nodes is not None:
        return validate.nodes(nodes, n_nodes)
    if around is None:
        raise ModelError("give nodes, or a point around which to prepare the contact compliances")
    centre = validate.point(around, "around")
    radius = validate.positive(radius, "radius", "a distance in m")
    return touchable[np.asarray(tree.query_ball_point(centre, radius), dtype=np.int64)]


def _outside(v: np.ndarray, outward: np.ndarray, radius: float) -> np.ndarray:
    """Whether the tool's core is outside the tissue, given v (k, 3) from a surface point to its
    closest core point and the surface's outward normals: it has passed the surface only when it is
    behind it and within the tool's radius of the normal line (a core merely beside the point, as a
    shaft lying on the surface, is not through it)."""
    vn = np.einsum("ij,ij->i", v, outward)
    lateral = np.sqrt(np.maximum(np.einsum("ij,ij->i", v, v) - vn * vn, 0.0))
    return (vn >= 0) | (lateral > radius + 1e-12)


def hold_patch(W: np.ndarray, h: np.ndarray, g: np.ndarray, k: float, grip: float) -> tuple[np.ndarray, np.ndarray]:
    """The forces (m, 3) of a jaw holding m vertices and the jaw's translation delta (3,).

    Each held vertex is tied to the jaw by a grip spring (stiffness ``grip``), the jaw to the hand
    by the grasp spring k: (W + I/grip) f - E delta = h (h = displacements at the grab minus the
    free prediction), E^T f + k delta = g (g = k (hand - jaw's grab position)), E the stacked 3x3
    identities; one symmetric (3m + 3) solve."""
    m = h.size // 3
    sol = np.linalg.solve(patch_system(W, k, grip), np.concatenate([h, g]))
    return sol[:-3].reshape(m, 3), sol[-3:]


def patch_system(W: np.ndarray, k: float, grip: float) -> np.ndarray:
    """The (3m + 3) matrix of :func:`hold_patch`: [[W + I/grip, -E], [E^T, k I]]."""
    n = W.shape[0]
    A = np.zeros((n + 3, n + 3))
    A[:n, :n] = W
    A[np.arange(n), np.arange(n)] += 1.0 / grip
    E = np.arange(n)
    A[E, n + E % 3] = -1.0
    A[n + E % 3, E] = 1.0
    A[n:, n:] = k * np.eye(3)
    return A
