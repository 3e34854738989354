"""The scalpel (issue 57): a blade that cuts the full-order solid it sweeps through, its force loop at the
haptic rate.

The blade is a segment from its heel to its tip, placed by a device or a path each haptic tick
(:meth:`Scalpel.update`). Its organ steps on a physics thread (the multi-rate scheme of
:mod:`rtfem.interaction.multirate`) under gravity. At each physics step the blade's samples are taken
to the reference configuration (each point less the displacement about it) and, once the blade has
advanced by ``advance`` there, the strip between where it was and where it is is added to the cut
surface, cell by cell, where a cell reaches inside the solid and has not been swept before. A cutter
thread then has the model cut along the new strips and their neighbours (:func:`rtfem.cut`: tet4
and tet10 elements split, see docs/guide/cutting.md) and the cut model assembled, in a worker process
(:mod:`rtfem.interaction.cut_worker`) where the scalpel runs threaded; it builds the driver on the cut
model, and the physics thread swaps it in between two steps, the state carried over node by node
(:meth:`DirectSimulator.carry_over`). Ticks never wait for any of this.

The cutting resistance, a stated model: the energy a cut takes is the tissue's fracture toughness J
times the area it opens (Gokgol, Basdogan and Canadinc 2012 measured J = 164 +- 6 J/m^2 for liver;
blade cutting of porcine liver, 187-225 J/m^2). A blade advancing by ds that opens dA = L ds (L the
length of its edge in tissue not cut before) is held back by F = J dA / ds = J L, against its motion
across the blade: on the hand -F v / max(|v|, ``V_REG``) (v the blade's velocity across itself,
smoothed over ~10 ms; below ``V_REG`` = 1 mm/s the force fades with the speed, as a regularized
Coulomb force does, so that a blade held still feels nothing). The tissue takes the opposite force at
the nodes about the blade's edge, shared by their lumped masses (a body force over that region: the
small nodes a split leaves are not flung, as an equal share per node flung them). F follows J L
through a first-order lag of ``SMOOTHING`` = 20 ms of simulated time (the tissue's share, applied step
by step, otherwise pushed soft tissue off the blade and the force flickered between 0 and J L). A
blade drawn back along its own slit opens nothing and feels nothing (once the lag has let go). The cut
is undone only by rebuilding the model.
"""

from __future__ import annotations

import threading
import time

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from .. import validate
from ..errors import ModelError, RtfemError
from ..mesh.cut import on_surface
from .multirate import _PARAMETERS, _MultiRate

__all__ = ["Scalpel", "TOUGHNESS", "SMOOTHING"]

#: J/m^2: liver's fracture toughness (Gokgol, Basdogan, Canadinc 2012, needle insertion, bovine liver)
TOUGHNESS = 164.0
#: m/s: below this speed across the blade the cutting force fades with the speed
V_REG = 1e-3
#: s (simulated): the resistance follows J L through a first-order lag of this time constant
SMOOTHING = 0.02
#: points along the blade (the strip's cells are between neighbours)
SAMPLES = 9
_SMOOTH = 0.01  # s: the blade velocity's smoothing time
_SUB = (np.arange(4) + 0.5) / 4  # a cell's share inside the solid: its 4 x 4 sub-cells' centres
_EDGE = (np.arange(8) + 0.5) / 8  # the blade's edge in tissue: 8 points along each cell's front


def _check_law(model) -> None:
    """Refuse a solid of a relaxing (Prony) law, or with a region of one: its history is not carried to a
    cut mesh (every cut would be refused)."""
    from ..fe.viscoelastic import Prony

    laws = [getattr(model, "law", None), *(getattr(model, "materials", None) or {}).values()]
    if any(isinstance(law, Prony) for law in laws):
        raise ModelError("a viscoelastic (Prony) law's history is not carried to a cut mesh yet: a scalpel cuts a solid "
                         "of an elastic law (rt.Material or a hyperelastic law) in every region")


def _bilinear(corners: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Points (c, len(s)^2, 3) of each quad (c, 4, 3) at the parameters s x s."""
    u, v = (a.ravel()[None, :, None] for a in np.meshgrid(s, s))
    q = corners[:, None]
    return (1 - u) * (1 - v) * q[:, :, 0] + u * (1 - v) * q[:, :, 1] + u * v * q[:, :, 2] + (1 - u) * v * q[:, :, 3]


class _Solid:
    """What a physics step reads of the model: its reference nodes and corner tets, the weight, and a
    search for the tet holding a point (in the reference or a deformed configuration)."""

    def __init__(self, model, gravity: np.ndarray) -> None:
        from ..drivers.carry import lumped_nodal_masses

        self.model = model
        self.X = np.asarray(model.tetmesh.vertices, dtype=float)
        self.C = np.asarray(model.tetmesh.tets)[:, :4]
        P = self.X[self.C]
        self.tree = cKDTree(P.mean(axis=1))
        m = lumped_nodal_masses(model)
        self.weights = m[:, None] * gravity[None, :]
        self.mass = np.maximum(m, 0.0)  # (what the tissue's share of the cutting force is spread by)
        edges = np.linalg.norm(P[:, [1, 2, 3, 2, 3, 3]] - P[:, [0, 0, 0, 1, 1, 2]], axis=2)
        self.edge = float(np.mean(edges))

    def locate(self, points: np.ndarray, X=None, around=None):
        """For each point (k, 3), a corner tet holding it (faces included; -1: none) and its
        barycentric coordinates (k, 4), with the nodes at ``X`` (default: the reference): among the
        tets whose reference centres are the 12 nearest ``around`` (default: the points; for a
        deformed ``X``, a guess of the points' reference places), then the 64 nearest."""
        X = self.X if X is None else X
        around = points if around is None else around
        tet, bary, gap = self._among(points, X, around, 12)
        lost = np.flatnonzero((tet < 0) & (gap < self.edge))  # far from every centre: outside, no second look
        if lost.size and self.C.shape[0] > 12:
            tet[lost], bary[lost], _ = self._among(points[lost], X, around[lost], 64)
        return tet, bary

    def _among(self, points: np.ndarray, X: np.ndarray, around: np.ndarray, k: int):
        k = min(k, self.C.shape[0])
        gap, cand = self.tree.query(around, k=k)
        cand = cand.reshape(points.shape[0], k)
        P = X[self.C[cand]]  # (p, k, 4, 3)
        J = np.transpose(P[:, :, 1:] - P[:, :, :1], (0, 1, 3, 2))
        ok = np.abs(np.linalg.det(J)) > 0
        J[~ok] = np.eye(3)
        lam = np.linalg.solve(J, (points[:, None, :] - P[:, :, 0])[..., None])[..., 0]
        bary = np.concatenate([1.0 - lam.sum(axis=2, keepdims=True), lam], axis=2)
        inside = ok & (bary.min(axis=2) >= -1e-9)
        first = np.argmax(inside, axis=1)
        rows = np.arange(points.shape[0])
        return np.where(inside[rows, first], cand[rows, first], -1), bary[rows, first], gap.reshape(points.shape[0], k)[:, 0]

    def inside(self, points: np.ndarray) -> np.ndarray:
        """(k,) True where a reference point lies in a tet (its faces included)."""
        return self.locate(points)[0] >= 0


class Scalpel(_MultiRate):
    __doc__ = f"""A blade that cuts the full-order solid it sweeps through (see the module): each haptic
    tick, :meth:`update` places it and returns the cutting resistance on the hand, from the last
    physics step; the organ steps on a physics thread under gravity, and the cut follows the blade
    one swept strip at a time, applied between two steps by a cutter thread.

    What it keeps: ``model`` (the model as cut so far), ``driver``, ``transfer`` (the interpolation
    from the first model's nodes to the cut model's), ``cuts`` (cuts applied), ``latencies`` (s, each
    strip's from its sweep to the model holding it), ``cut_frames`` (s, each physics step that swapped a cut
    in: the frame of a cut), ``refused`` (why the last cut job was refused, or
    None), ``removed_mass`` (kg of pieces cut free), ``resistance`` (N, the last physics step's J L),
    ``vertices`` and ``triangles`` (the surface swept, reference coordinates), ``lifted`` (the blade out
    of the tissue: :meth:`lift`), :meth:`stats`.

    Parameters
    ----------
    driver : a full-order :class:`~rtfem.DirectSimulator` on an rt.SolidModel (tet4 or tet10; an
        elastic law), at rest or running.
    blade : (3,) m, from the blade's tip to its heel, where :meth:`update` is given the tip alone (a
        device's point; default (0, 0, 0.03): a 3 cm blade held upright).
    gravity : (3,) m/s^2 on the organ (default (0, 0, -9.81)).
    toughness : J/m^2, the energy a cut takes per unit area opened (default :data:`TOUGHNESS`, liver);
        0 cuts without resistance.
    advance : m, how far (in the reference configuration) the blade moves before its strip is added
        to the cut (default half the mean element edge).
    worker : cut and assemble in a worker process (default: with ``thread``, the real-time setting:
        there that work would hold Python's lock while the ticks wait); False: in the cutter thread.
    smoothing : s of simulated time, the lag through which the resistance follows J L (default
        :data:`SMOOTHING`, 20 ms; 0: none). Without it the tissue's share, applied step by step, pushed
        soft tissue off the blade, the edge in uncut tissue read zero at the next step and the force
        flickered between 0 and J L (a third of the steps at zero on a 30 kPa beam at 5 ms steps).
{_PARAMETERS}

    Raises
    ------
    ModelError
        A driver that is not a full-order one on a solid; a gravity, toughness or advance out of
        range; in :meth:`update`, a blade of no length or a position that is not a point, and what
        the physics thread raised (the scalpel is stopped; the force is zero from then on).
    """

    WHAT = "scalpel"

    def __init__(self, driver, *, blade=(0.0, 0.0, 0.03), gravity=(0.0, 0.0, -9.81), toughness: float = TOUGHNESS,
                 advance=None, rate: float = 1000.0, pace: bool = True, thread: bool = True,
                 worker: bool | None = None, smoothing: float = SMOOTHING) -> None:
        if not (hasattr(driver, "carry_over") and hasattr(getattr(driver, "model", None), "tetmesh")):
            raise ModelError(f"driver={validate.show(driver)}: a scalpel cuts a full-order solid: give "
                             "rt.DirectSimulator(solid_model, dt, ...) (a reduced or shell driver cannot be cut yet)")
        _check_law(driver.model)
        self.blade = np.array(validate.vector(blade, "blade", 3), dtype=float)
        if not np.linalg.norm(self.blade) > 0:
            raise ModelError("blade=(0, 0, 0): give the vector from the blade's tip to its heel (m), e.g. (0, 0, 0.03)")
        self.gravity = np.array(validate.vector(gravity, "gravity", 3), dtype=float)
        self.toughness = validate.nonnegative(toughness, "toughness", "J/m^2, a number >= 0 (liver: 164)")
        self.smoothing = validate.in_range(smoothing, "smoothing", 0.0, 1.0, what="a time in s (0: none)")
        self._setup(driver, rate, pace, thread)
        self.solid = _Solid(driver.model, self.gravity)
        self.advance = (0.5 * self.solid.edge if advance is None
                        else validate.positive(advance, "advance", "a distance in metres > 0"))
        self.vertices = np.zeros((0, 3))  # the cut surface swept so far (reference coordinates) ...
        self.triangles = np.zeros((0, 3), dtype=np.int64)  # ... and its triangles
        self._blade = None  # (tip, heel) in the world, the last tick's
        self.lifted = False  # the blade out of the tissue (lift()): the organ steps on, nothing is swept
        self._t_tick = None
        self._lifts: list = []  # the blades at lifts the physics has not taken yet (None: none was down)
        self._new_stroke()
        # (model, (n, 3) displacements) for drawing: a running driver's state until the first physics step
        self.shown = (driver.model, np.asarray(driver.displacements(), dtype=float))
        self.cuts, self.latencies, self.refused = 0, [], None
        self.cut_frames: list = []  # s, each physics step that swapped a cut in (threaded: the cut's frame)
        self.removed_mass = 0.0  # kg of pieces cut free (nothing held them): they fall away, out of the model
        self.transfer = sp.identity(driver.n_nodes, format="csr")  # from the first model's nodes to the cut's
        self.last_transfer = self.transfer  # the last cut's alone (from the model before it)
        #: nodes of the model that hold the piece they are in as a fix does (a scene's springs and grasps on it)
        self.held = np.zeros(0, dtype=np.int64)
        self._added: list = []  # (triangles after, perf_counter) of each strip not yet in the model
        self._tried = 0  # triangles the last cut job had
        self._applied = 0  # triangles the model holds (the first ones of ``triangles``)
        self._job: threading.Thread | None = None
        self._ready = None
        self.worker_note = None  # why the cut worker process stopped, if it did
        self._worker = None
        if self.threaded if worker is None else validate.flag(worker, "worker"):
            from .cut_worker import CutWorker

            self._worker = CutWorker(warm=driver.model)

    # ------------------------------------------------------------------ the haptic side
    def update(self, tip, heel=None, *, t: float | None = None) -> np.ndarray:
        """One haptic tick with the blade from ``heel`` (default: ``tip`` + ``blade``, a device's
        point being the tip) to ``tip`` (m, world): the force on the hand (N), the cutting resistance
        against the blade's motion across itself (see the module). ``t``: the tick's time (s) for the
        blade's velocity (default the wall clock; a scene gives its simulated time)."""
        c = validate.point(tip, "scalpel tip")
        h = c + self.blade if heel is None else validate.point(heel, "scalpel heel")
        now = time.perf_counter() if t is None else validate.number(t, "t", "a time in s")
        along = c - h
        length = float(np.linalg.norm(along))
        if not length > 0:
            self.force = np.zeros(3)
            raise ModelError(f"the blade's tip {c.tolist()} and heel {h.tolist()} coincide: give a blade of some length")
        self._blade = (c, h)
        self.lifted = False
        self._tick(c)
        if self._restroke:  # lifted since the last tick: this one begins a stroke (the blade's motion is the ticks' own)
            self._restroke = False
            self._velocity, self._mid = np.zeros(3), None
        mid, last = 0.5 * (c + h), self._mid
        if last is not None and now > self._t_tick:
            w = min(1.0, (now - self._t_tick) / _SMOOTH)
            self._velocity = (1 - w) * self._velocity + w * (mid - last) / (now - self._t_tick)
        self._mid, self._t_tick = mid, now
        b = along / length
        v = self._velocity - (self._velocity @ b) * b
        resistance = 0.0 if self._lifts else self.resistance  # (a lift the physics has not taken: the last stroke's)
        self.force = -resistance * v / max(float(np.linalg.norm(v)), V_REG)
        return self.force

    def lift(self) -> None:
        """The blade out of the tissue (a stroke's end): the organ steps on under gravity, nothing is swept
        and the hand feels nothing until :meth:`update` places the blade again, which starts a new strip
        there (not one from where it was lifted). The blade's last strip, shorter than ``advance``, joins
        the cut surface first: the cut reaches where the blade was lifted, not the strip before. With the
        physics on its thread, that thread sweeps it at its next step (or :meth:`finish`): the caller waits
        for nothing and the hand's force is zero at once (0.01 ms; lift() took the physics' lock, which the
        thread stepping flat out took again first, step after step, and swept: it returned after 7-283 ms,
        median 175 ms, 32 ms beside a busy core, on the 9k-tet liver of benchmarks/scalpel.py, the ticks
        meanwhile giving the cutting force)."""
        blade = None if self.lifted else self._blade
        # lifted first: a step that takes the lift below sees it (else it would start a stroke where this one ended)
        self.lifted, self.force, self._restroke = True, np.zeros(3), True
        self._lifts.append(blade)
        if self._thread is None:  # no physics thread: taken here
            with self._between_steps():
                self._take_lifts(self.shown)

    def _take_lifts(self, shown) -> None:
        """The physics side of the lifts asked since the last step (under the lock): each blade's last strip
        swept on ``shown`` = (model, U) (where that is the model now) and a new stroke begun. A lift leaves
        the queue once its stroke is reset: until then a tick reads the resistance as zero."""
        while self._lifts:
            blade = self._lifts[0]
            if blade is not None and shown[0] is self.solid.model:
                self._sweep(shown[1], final=True, blade=blade)
            self._new_stroke(haptic=False)
            self._lifts.pop(0)

    def _new_stroke(self, haptic: bool = True) -> None:
        """No strip, resistance or (``haptic``) blade motion yet: a stroke's start."""
        none = np.zeros(SAMPLES - 1, dtype=bool)
        self._last = (None, none, none, none)  # the last strip: cells, beside the solid, taken, fresh
        self._anchor = None  # the blade's samples in the reference configuration where its last strip ended
        if haptic:
            self._velocity, self._mid, self._restroke = np.zeros(3), None, False
        self.resistance = 0.0  # N: J times the edge length in uncut tissue, the last strip's
        self._push = np.zeros(0, dtype=np.int64)  # the tissue's nodes at the edge: the hand's force, opposite, on them

    def displacements(self) -> np.ndarray:
        """The organ's (n, 3) displacements at the last physics step, on the mesh of ``shown[0]``."""
        return self.shown[1].copy()

    # ------------------------------------------------------------------ the physics thread
    def physics_step(self) -> None:
        """Swap in a cut model if one is ready, step the organ (gravity and the tissue's share of the
        cutting force), add the blade's strip to the cut surface and start a cut job when it grew."""
        if self._blade is None and not self.lifted:
            raise ModelError("no blade position yet: call update(tip, heel) first (or lift() it)")
        super().physics_step()

    def _advance(self) -> None:
        t = time.perf_counter()
        swapped = self.take_cut()
        self.driver.step(self.solid.weights + self.tissue_loads())
        self.follow(np.asarray(self.driver.displacements(), dtype=float))
        if swapped:  # the frame of a cut: its swap, the first step on the cut model, the next strip
            self.cut_frames.append(time.perf_counter() - t)

    def take_cut(self) -> bool:
        """Swap in the cut model a job has ready (between two steps; the physics step does): True when
        the model changed (``driver`` and ``model`` are the cut's, ``last_transfer`` its interpolation)."""
        model = self.solid.model
        self._swap()
        return self.solid.model is not model

    def tissue_loads(self) -> np.ndarray:
        """(n, 3) N: the tissue's share of the cutting force, the opposite of the hand's (the last tick's),
        spread over the nodes about the blade's edge where it cuts by their lumped masses (a body force over
        that region; the same share each where they have none). An equal share each flung the nodes of the
        slivers a split leaves (0.01-0.1 % of the median tet's volume on strokes through the clamped block
        of the viewer's test, 2-3 mm in a 2 ms step) and turned their tets inside out."""
        F = np.zeros((self.driver.n_nodes, 3))
        nodes = self._push
        if nodes.size:
            m = self.solid.mass[nodes]
            total = float(m.sum())
            w = m / total if total > 0 else np.full(nodes.size, 1.0 / nodes.size)
            F[nodes] = -w[:, None] * self.force[None, :]
        return F

    def follow(self, U: np.ndarray) -> None:
        """After a step of the organ to displacements ``U`` (n, 3): the blade's strip swept (unless it is
        lifted) and a cut job started when the surface grew (the physics step does this; a scene calls it
        after stepping the body itself)."""
        self._take_lifts((self.solid.model, U))
        if not self.lifted:  # (read after the lifts: a blade placed again after a lift starts its stroke here)
            self._sweep(U)
        self._start_cut()
        self.shown = (self.solid.model, U)

    def join(self, timeout: float | None = None) -> None:
        """Wait for the cut job in progress, if any (its model is then swapped in by the next step)."""
        job = self._job
        if job is not None:
            job.join(timeout)

    def _reference(self, points: np.ndarray, U: np.ndarray):
        """World points in the reference configuration: inside the deformed solid, the reference point
        of the same barycentric coordinates in the same tet (the exact inverse of the tet4 map; the
        tet sought about the guess below); outside it, the point less the displacements of the four
        nearest nodes weighted by inverse distance. Returns them and a search over the deformed nodes."""
        x = self.solid.X + U
        nodes = cKDTree(x)
        dist, near = nodes.query(points, k=4)
        w = 1.0 / np.maximum(dist, 1e-12)
        w /= w.sum(axis=1, keepdims=True)
        ref = points - np.einsum("pk,pkj->pj", w, U[near])
        tet, bary = self.solid.locate(points, x, around=ref)  # candidates about the guess
        held = tet >= 0
        ref[held] = np.einsum("pk,pkj->pj", bary[held], self.solid.X[self.solid.C[tet[held]]])
        return ref, nodes

    def _sweep(self, U: np.ndarray, final: bool = False, blade=None) -> None:
        """The blade's strip since its last one (reference configuration): the resistance from its edge
        in the uncut tissue the strip reaches, the tissue's share of the force, and, once it advanced by
        ``advance`` (``final``, the stroke's end: by a tenth of that), its cells added to the cut surface
        (see :meth:`_cells`). ``blade``: (tip, heel) (default: the last tick's)."""
        tip, heel = self._blade if blade is None else blade
        world = heel + np.linspace(0.0, 1.0, SAMPLES)[:, None] * (tip - heel)
        ref, tree = self._reference(world, U)
        if self._anchor is None:
            self._anchor = ref
            return
        a = self._anchor
        move = (ref - a).mean(axis=0)
        step = float(np.linalg.norm(move))
        if step < 0.1 * self.advance:  # too short a strip to tell the opening rate by: the last one holds
            return
        # J times the blade's edge in uncut tissue: its points inside the solid and not in the slit already
        front = (ref[:-1, None] + _EDGE[None, :, None] * (ref[1:] - ref[:-1])[:, None]).reshape(-1, 3)
        edge = (self.solid.inside(front) & self._fresh(front)).reshape(ref.shape[0] - 1, -1)
        raw = self.toughness * float((np.linalg.norm(ref[1:] - ref[:-1], axis=1) * edge.mean(axis=1)).sum())
        lag = min(1.0, self.driver.dt / self.smoothing) if self.smoothing > 0 else 1.0
        self.resistance += lag * (raw - self.resistance)
        cut = edge.any(axis=1)
        if cut.any():  # the tissue's share: on the nodes within an element edge of the blade where it cuts
            at = np.unique(np.concatenate([np.flatnonzero(cut), np.flatnonzero(cut) + 1]))
            near = tree.query_ball_point(world[at], r=self.solid.edge)
            self._push = np.unique(np.concatenate([np.asarray(k, dtype=np.int64) for k in near]))
        else:
            self._push = np.zeros(0, dtype=np.int64)
        if step >= self.advance or final:  # the strip joins the cut surface
            corners = np.stack([a[:-1], a[1:], ref[1:], ref[:-1]], axis=1)  # (S - 1, 4, 3) cells
            share = self.solid.inside(_bilinear(corners, _SUB).reshape(-1, 3)).reshape(corners.shape[0], -1).mean(axis=1)
            self._anchor = ref
            self._cells(corners, share > 0, self._fresh(0.5 * (ref[1:] + ref[:-1])))

    def _fresh(self, front: np.ndarray) -> np.ndarray:
        """(c,) True for cells whose front (the blade's edge now) is not in the slit swept before: within
        half an element edge of its surface (the tissue moved since: the blade slides into its slit)
        and not past its edges by a twentieth of an advance. A blade drawn back along its slit opens
        nothing."""
        if not self.triangles.shape[0]:
            return np.ones(front.shape[0], dtype=bool)
        return ~on_surface(front, self.vertices[self.triangles], 0.5 * self.solid.edge, 0.05 * self.advance)

    def _cells(self, corners: np.ndarray, inside: np.ndarray, fresh: np.ndarray) -> None:
        """Add to the cut surface the strip's cells that reach into the solid and the cells beside them,
        along the blade and in the strips before and after (so that the surface passes the solid's
        outside: a face on it is cut only if the surface covers it whole); never a cell swept before."""
        near = inside | np.r_[inside[1:], False] | np.r_[False, inside[:-1]]
        last_corners, last_near, last_taken, last_fresh = self._last
        take = (near | last_near) & fresh
        add = corners[take]
        if last_corners is not None:  # the strip before, where it now has tissue beside it
            add = np.concatenate([last_corners[near & ~last_taken & last_fresh], add])
        self._last = (corners, near, take, fresh)
        if add.shape[0]:
            self._add_cells(add)

    def _add_cells(self, corners: np.ndarray) -> None:
        base = self.vertices.shape[0] + 4 * np.arange(corners.shape[0])[:, None]
        tris = np.concatenate([base + [0, 1, 2], base + [0, 2, 3]])
        self.vertices = np.concatenate([self.vertices, corners.reshape(-1, 3)])
        self.triangles = np.concatenate([self.triangles, tris])
        self._added.append((self.triangles.shape[0], time.perf_counter()))

    def _start_cut(self) -> None:
        n = self.triangles.shape[0]
        if n == self._tried or self._ready is not None or (self._job is not None and self._job.is_alive()):
            return
        from ..mesh.cut import NothingToCut
        from ..threads import leave_realtime, raise_priority

        V, T, driver, held = self.vertices, self._to_cut(), self.driver, self.held
        self._tried = n

        def work() -> None:
            leave_realtime()  # (not at the physics thread's real-time priority, where it has one: raised)
            raise_priority()
            try:
                new = self._cut(driver.model, V, T, held)
                P = new.cut_info.transfer()
                prepared = driver.carry_over(new, P)
                if hasattr(prepared, "factorize"):  # the lagged step's factor made here, not in the cut's frame
                    prepared.factorize()
                self._ready = (driver.model, new, P, prepared, _Solid(new, self.gravity), n)
            except NothingToCut:  # no new face swept whole yet: the next strip retries
                pass
            except RtfemError as exc:  # refused (rt.cut says why): the next strip retries with more surface
                self.refused = str(exc)
            except BaseException as exc:  # noqa: BLE001 - surfaced by the next tick, as a physics error
                self.error = exc

        self._job = threading.Thread(target=work, name="rtfem-scalpel-cut", daemon=True)
        self._job.start()

    def _cut(self, model, V: np.ndarray, T: np.ndarray, held=None):
        """The model cut along the triangles and assembled: in the worker process where there is one (see
        :mod:`rtfem.interaction.cut_worker`), else here. Tet4 and tet10 elements are split (no node of the running
        solid moves); a piece cut free (nothing fixed in it, none of ``held``) falls away."""
        from .cut_worker import WorkerGone, cut_and_assemble

        worker = self._worker  # (snap="split", tet4 and tet10: no node moves by over a fifth of an edge)
        if worker is not None:
            try:
                return worker.cut(model, V, T, "split", held)
            except WorkerGone as exc:
                self.worker_note, self._worker = str(exc), None
        return cut_and_assemble(model, V, T, "split", held)

    def close(self, timeout: float = 10.0) -> None:
        """Stop the physics thread (after the step it is in) and the cut worker process; :meth:`finish`
        still cuts, in this process."""
        super().close(timeout)
        if self._lifts:  # a lift the physics thread did not take (its ticks had stopped): its strip joins the surface
            try:
                with self._between_steps():
                    self._take_lifts(self.shown)
            except Exception as exc:  # noqa: BLE001 - a close on its way to zero force ends all the same
                self._lifts.clear()
                self.refused = f"the last stroke's end was not added to the cut ({type(exc).__name__}: {exc})"
        worker, self._worker = self._worker, None
        if worker is not None:  # never waits: a tick that failed closes the scalpel on its way to zero force
            worker.close(wait=False)

    def _to_cut(self) -> np.ndarray:
        """The triangles a cut job takes: those the model does not hold yet, and the older ones within
        two element edges of them (a face half on an old strip and half on a new one is covered whole
        only by both); the faces cut before are the solid's outside now. A job's cost so stays that of
        the new strips, not of the whole stroke."""
        T = self.triangles
        new = T[self._applied:]
        old = T[:self._applied]
        if not old.size:
            return new.copy()
        pts = self.vertices[new].reshape(-1, 3)
        reach = 2.0 * self.solid.edge
        lo, hi = pts.min(axis=0) - reach, pts.max(axis=0) + reach
        near = ((self.vertices[old] >= lo) & (self.vertices[old] <= hi)).all(axis=2).any(axis=1)
        return np.concatenate([old[near], new])

    def _swap(self) -> None:
        ready, self._ready = self._ready, None
        if ready is None:
            return
        model, new, P, prepared, solid, n = ready
        if model is not self.solid.model:
            return
        self.driver = self.driver.carry_over(new, P, into=prepared)
        self.transfer, self.last_transfer = (P @ self.transfer).tocsr(), P
        self.solid = solid
        self.shown = (new, np.asarray(self.driver.displacements(), dtype=float))
        self._push = np.zeros(0, dtype=np.int64)
        self.cuts += 1
        self._applied = max(self._applied, n)
        self.removed_mass += new.cut_info.removed_mass
        self.refused = None
        now = time.perf_counter()
        self.latencies += [now - t for k, t in self._added if k <= n]  # each strip: swept -> in the model
        self._added = [(k, t) for k, t in self._added if k > n]

    def finish(self, timeout: float = 60.0) -> "Scalpel":
        """Wait for the cut job in progress, start one for the strips it did not have, and swap the cut
        model in (between physics steps): the model then holds every strip swept so far (an offline
        stroke's end, a test's check). Returns the scalpel."""
        for _ in range(2):
            job = self._job
            if job is not None:
                job.join(timeout)
            with self._between_steps():
                self._swap()
                self._take_lifts(self.shown)
                self._start_cut()
        return self

    @property
    def model(self):
        """The model as cut so far (``model.cut_info``: the last cut)."""
        return self.solid.model
