"""FEModel, what shell and solid models share: sparse assembly of K and M, fixed nodes,
condensation and static solves.

Paper section 2: element matrices are assembled into the global stiffness (Eq. 3); fixed
nodes are imposed either by elimination (default) or by the paper's penalty method; the
rotations are condensed out of the static problem (Eq. 4-5), either through the paper's
explicit dense Schur complement (small models only) or, by default, through a sparse
factorization that never forms a dense (3n)^2 matrix.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import scipy.sparse as sp

from .. import validate
from ..errors import ModelError, RtfemWarning, SolverError
from .compliance import _DENSE_LIMIT, surface_compliance as _surface_compliance
from .linalg import Factorization, expand_node_order, factorize, nested_dissection
from .material import Material
from .protocol import DOF_NAMES, parse_dofs
from ..mesh.surface import TriMesh
from ..mesh.selection import select_nodes

__all__ = ["FEModel", "Condensation"]

_CHUNK = 16384  # elements per batch during assembly (bounds the temporary memory)


class FEModel:
    """What the assembled models share: fixes, loads, the constrained systems, the cached
    factorization, static solves and the condensation of rotations (Eq. 4-5).

    A subclass sets ``dofs_per_node`` (the first three are the translations), calls
    :meth:`_setup` from its constructor and implements ``_assemble`` (sets ``_K``, the sparse
    unconstrained stiffness, and ``_M``, the lumped mass per dof), ``_node_graph`` (node adjacency
    for the fill-reducing order), ``_pieces`` (connected pieces: label per node) and
    ``metadata``. ``mesh`` is the surface that is drawn and touched (a TriMesh over the model's
    node numbering).
    """

    dofs_per_node = 6

    def _setup(self, mesh: TriMesh, material: Material, constraints: str, penalty: float) -> None:
        self.mesh = mesh
        self.material = material
        self.constraints = constraints
        self.penalty = float(penalty)
        self.fixed = np.zeros((self.n_nodes, self.dofs_per_node), bool)
        self._K: sp.csr_matrix | None = None
        self._M: np.ndarray | None = None
        self._factor: Factorization | None = None
        self._condensation: Condensation | None = None
        self._cache: dict[str, np.ndarray] = {}
        self.timings: dict[str, float] = {}

    @staticmethod
    def _check_constraints(constraints: str, penalty) -> float:
        validate.choice(constraints, "constraints", ("elimination", "penalty"))
        penalty = validate.number(penalty, "penalty", "a large factor such as 1e8")
        if penalty <= 1.0:
            raise ModelError(f"penalty={validate.show(penalty)} must be a large factor (> 1, e.g. 1e8): it multiplies "
                             "the stiffness diagonal at fixed dofs")
        return penalty

    # ------------------------------------------------------------ sizes
    @property
    def n_nodes(self) -> int:
        return self.mesh.n_vertices

    @property
    def n_dofs(self) -> int:
        return self.dofs_per_node * self.mesh.n_vertices

    def _dof_mask(self, dofs) -> np.ndarray:
        """``parse_dofs`` restricted to this model's dofs; naming a dof it lacks is an error."""
        mask = parse_dofs(dofs)
        if self.dofs_per_node < 6 and mask[self.dofs_per_node:].any() and not mask.all():
            raise ModelError(f"dofs={validate.show(dofs)}: this model has only {', '.join(DOF_NAMES[:self.dofs_per_node])} "
                             "per node (a solid has no rotations); fix 'xyz' or 'all'")
        return mask[:self.dofs_per_node]

    # ------------------------------------------------------------ assembly
    @property
    def K(self) -> sp.csr_matrix:
        """Global stiffness (sparse, unconstrained), Eq. 3."""
        if self._K is None:
            self._assemble()
        return self._K  # type: ignore[return-value]

    @property
    def mass_diagonal(self) -> np.ndarray:
        """Lumped mass per dof (n_dofs,)."""
        if self._M is None:
            self._assemble()
        return self._M  # type: ignore[return-value]

    @property
    def M(self) -> sp.dia_matrix:
        """Lumped (diagonal) global mass matrix."""
        return sp.diags(self.mass_diagonal, format="csr")

    def _assemble(self) -> None:
        raise NotImplementedError

    # ------------------------------------------------------------ fixes
    def select_nodes(self, nodes) -> np.ndarray:
        """Node indices from indices, a boolean mask, a vertex group name, ``"z<0.01"``, ``"bottom:0.1"`` or
        ``"nodes:i,j"`` (:func:`rtfem.select_nodes`)."""
        return select_nodes(self.mesh, nodes)

    def fix(self, nodes, dofs: str | Sequence = "all") -> "FEModel":
        """Fix (zero displacement) the given dofs of the given nodes. Calls accumulate.

        ``nodes``: indices, a boolean mask, or the name of a mesh vertex group (e.g. "attachment").
        ``dofs``: "all", "xyz", "z", "rx", "xy,rz", ... (see :func:`parse_dofs`).
        """
        idx = self.select_nodes(nodes)
        if idx.size == 0:
            raise ModelError("fix() was given no nodes")
        mask = self._dof_mask(dofs)
        self.fixed[np.ix_(idx, np.flatnonzero(mask))] = True
        self._supports_changed()
        return self

    def release(self, nodes=None, dofs: str | Sequence = "all") -> "FEModel":
        """Undo fixes (all nodes when ``nodes`` is None)."""
        idx = np.arange(self.n_nodes) if nodes is None else self.select_nodes(nodes)
        mask = self._dof_mask(dofs)
        self.fixed[np.ix_(idx, np.flatnonzero(mask))] = False
        self._supports_changed()
        return self

    def complete_motion(self, P: np.ndarray) -> np.ndarray:
        """A prescribed motion of fixed dofs (n, dofs_per_node), completed where the model holds nodes
        the user did not name (a tet10 solid's mid-edge nodes follow their corners); here as given."""
        return np.array(P, dtype=float)

    def _supports_changed(self) -> None:
        self._factor = None
        self._condensation = None
        self.supports_version = getattr(self, "supports_version", 0) + 1

    supports_version = 0  # counts fix() and release() calls: what a driver built on the old supports checks

    @property
    def held_nodes(self) -> np.ndarray:
        """(n,) mask of the nodes whose three translations are all fixed: they cannot move."""
        return self.fixed[:, :3].all(axis=1)

    def nearest_free_node(self, point, displacements: np.ndarray | None = None) -> int:
        """The node nearest ``point`` among those that can move, on the surface displaced by
        ``displacements`` ((n, 3), default undeformed)."""
        p = validate.point(point, "point")
        X = np.asarray(self.mesh.vertices)
        if displacements is not None:
            u = validate.real_array(displacements, "displacements", 2)
            if u.shape != X.shape:
                raise ModelError(f"displacements must have shape {X.shape}, got {u.shape}")
            X = X + u
        self.check_not_all_fixed()
        d = np.full(X.shape[0], np.inf)
        touchable = self.mesh.used_vertices()  # the surface: a solid's interior nodes cannot be touched
        d[touchable] = np.linalg.norm(X[touchable] - p, axis=1)
        d[self.held_nodes] = np.inf
        if not np.isfinite(d).any():
            raise ModelError("every node of the surface is fixed: nothing on it can be moved; fix a smaller region")
        return int(np.argmin(d))

    @property
    def fixed_dofs(self) -> np.ndarray:
        return np.flatnonzero(self.fixed.ravel())

    @property
    def free_dofs(self) -> np.ndarray:
        return np.flatnonzero(~self.fixed.ravel())

    def check_not_all_fixed(self) -> None:
        """Raise ModelError when every node is held (nothing left to move or to solve for)."""
        if self.held_nodes.all():
            raise ModelError(
                f"every node is fixed (all {self.n_nodes} nodes have their translations held): nothing can "
                "move. Fix a smaller region (e.g. --fix bottom:0.05, or model.release(...) some nodes); a flat "
                "mesh lies entirely in its own 'bottom' slab"
            )

    #: nodes a spring outside the model holds (a scene's attachment or grasp on the body; ``rt.cut(held=...)``
    #: sets their copies): a piece of the mesh with one counts as restrained, as a dynamic step needs (its mass
    #: makes the step's system definite; the spring, the scene's, holds the piece). A static solve of the
    #: model alone finds such a piece free (its stiffness is singular, and the factorization says so).
    tethered = np.zeros(0, dtype=np.int64)

    def check_restrained(self, tethers: bool = True) -> None:
        """Raise ModelError when the fixes leave a rigid-body motion free, or hold every node.

        For each connected piece of the mesh, the six rigid-body motions (3 translations,
        3 rotations about its centroid) restricted to the fixed dofs must have rank 6; a piece with a
        :attr:`tethered` node (held by a spring outside the model) is restrained by it, unless ``tethers``
        is False (a static solve of the model alone, which has no spring).
        """
        self.check_not_all_fixed()
        n_comp, label = self._pieces()
        X = np.asarray(self.mesh.vertices)
        dpn = self.dofs_per_node
        tethered = np.zeros(self.n_nodes, dtype=bool)
        tethered[np.asarray(self.tethered, dtype=np.int64)] = True
        for c in range(n_comp):
            nodes = np.flatnonzero(label == c)
            if tethered[nodes].any():
                if tethers:
                    continue
                if not self.fixed[nodes].any():
                    raise ModelError(f"piece {c + 1} of {n_comp} ({nodes.size} nodes) is held only by springs outside the "
                                     "model (its tethered nodes: a scene's attachment or grasp); the model alone leaves "
                                     "it free. Step it in its scene, or fix a node of it for a static solve")
            where = f" (piece {c + 1} of {n_comp}, {nodes.size} nodes, e.g. node {nodes[0]})" if n_comp > 1 else ""
            fx = self.fixed[nodes]
            if not fx.any():
                raise ModelError(
                    f"nothing is fixed{where}: the model can move as a rigid body, so a static or "
                    "dynamic solve has no unique answer. Fix some nodes first, e.g. "
                    "model.fix(nodes, dofs='all') or model.fix('attachment')"
                )
            centre = X[nodes].mean(axis=0)
            P = X[nodes] - centre
            scale = max(np.abs(P).max(), 1e-300)
            P = P / scale
            Rb = np.zeros((nodes.size, 6, 6))  # rigid motion (t, theta) -> each node's dofs
            Rb[:, [0, 1, 2], [0, 1, 2]] = 1.0
            for k in range(3):
                e = np.zeros(3)
                e[k] = 1.0
                Rb[:, :3, 3 + k] = np.cross(e, P)
                Rb[:, 3 + k, 3 + k] = 1.0
            rows = Rb[:, :dpn][fx]  # (n_fixed_dofs, 6)
            # thin SVD: vt is 6 x 6 whenever there are >= 6 fixed dofs (the full one would form a
            # dense square of the fixed-dof count: 16 s for the 15,365-vertex OpenHELP liver)
            s, vt = np.linalg.svd(rows, full_matrices=rows.shape[0] < 6)[1:]
            rank = int(np.sum(s > 1e-9 * s[0])) if s.size else 0
            if rank < 6:
                motions = [_describe_rigid_motion(v, centre, scale) for v in vt[rank:]]
                raise ModelError(
                    f"the fixes leave {6 - rank} rigid-body motion(s) free{where}: "
                    f"{'; '.join(motions)}. Fix more dofs, e.g. all dofs of one node, "
                    "or 'xyz' of three nodes that are not on one line"
                )

    # ------------------------------------------------------------ forces
    def force_vector(self, forces, *, warn: bool = True) -> np.ndarray:
        """Validate forces and return the global load vector (6n,).

        ``forces``: (n, 3) nodal forces, (n, 6) forces and moments on a model with rotations, or a
        mapping ``{node: (fx, fy, fz)}`` (or 6 components) whose keys are integer node indices
        (Python or numpy integers; a float, a bool or a string is refused). Nothing is
        changed anywhere when the forces are refused. ``warn``: name loads on fixed dofs.
        """
        F = validate.forces(forces, self.n_nodes, tuple(sorted({3, self.dofs_per_node})))
        if warn:
            on_fixed = np.flatnonzero((self.fixed & (F != 0)).any(axis=1))
            if on_fixed.size:
                warnings.warn(
                    f"loads on fixed dofs at {on_fixed.size} node(s) (first: node {on_fixed[0]}, "
                    f"{F[on_fixed[0]][self.fixed[on_fixed[0]]].tolist()}) go straight into the supports "
                    "and move nothing; load free nodes instead",
                    RtfemWarning,
                    stacklevel=3,
                )
        return F.ravel()

    def pressure_forces(self, pressure: float, nodes=None) -> np.ndarray:
        """Nodal forces (n, 3) of a uniform pressure on the surface (or on the triangles whose
        corners are all in ``nodes``, a selection), along the face normals: positive pressure
        pushes against the normal, i.e. inward on an outward-oriented closed surface."""
        pressure = validate.number(pressure, "pressure", "a pressure in Pa")
        return self._surface_load(self.mesh.face_normals(unit=False) * (-0.5 * pressure), nodes)

    def traction_forces(self, traction, nodes=None) -> np.ndarray:
        """Nodal forces (n, 3) of a uniform traction vector (Pa) on the surface, or on the
        triangles whose corners are all in ``nodes`` (e.g. the free end of a cantilever)."""
        t = validate.point(traction, "traction")
        return self._surface_load(self.mesh.areas()[:, None] * t[None, :], nodes)

    def _surface_load(self, per_face: np.ndarray, nodes) -> np.ndarray:
        """Nodal forces of per-triangle resultants (f, 3), the triangles limited to ``nodes``."""
        T = np.asarray(self.mesh.triangles)
        if nodes is not None:
            inside = np.zeros(self.n_nodes, bool)
            inside[self.select_nodes(nodes)] = True
            keep = inside[T].all(axis=1)
            if not keep.any():
                raise ModelError(f"nodes={validate.show(nodes)} hold no whole surface triangle to load")
            T, per_face = T[keep], per_face[keep]
        return self._distribute(T, per_face)

    def _distribute(self, T: np.ndarray, per_face: np.ndarray) -> np.ndarray:
        """A uniform load's consistent nodal forces on linear triangles: a third to each corner."""
        out = np.zeros((self.n_nodes, 3))
        for k in range(3):
            np.add.at(out, T[:, k], per_face / 3.0)
        return out

    # ------------------------------------------------------------ constrained systems
    def constrained_stiffness(self) -> tuple[sp.csr_matrix, np.ndarray]:
        """The stiffness with the fixes applied and the dofs it acts on.

        Elimination: K restricted to the free dofs. Penalty: the full K with the diagonal of
        the fixed dofs multiplied by ``penalty`` (paper, section 2).
        """
        if self.constraints == "elimination":
            free = self.free_dofs
            return self.K[free][:, free].tocsr(), free
        K = self.K.copy()
        fd = self.fixed_dofs
        d = K.diagonal()
        d[fd] *= self.penalty
        K.setdiag(d)
        return K.tocsr(), np.arange(self.n_dofs)

    def constrained_mass(self) -> tuple[sp.csr_matrix, np.ndarray]:
        """The (lumped, diagonal) mass on the dofs of :meth:`constrained_stiffness`."""
        dofs = self.free_dofs if self.constraints == "elimination" else np.arange(self.n_dofs)
        return sp.diags(self.mass_diagonal[dofs], format="csr"), dofs

    def nodal_translations(self, values, dofs) -> np.ndarray:
        """Values on ``dofs`` ((len(dofs),) or (len(dofs), k)) as nodal translations (n, 3) or
        (n, 3, k); other dofs read zero."""
        values = np.asarray(values)
        full = np.zeros((self.n_dofs,) + values.shape[1:], dtype=values.dtype)
        full[dofs] = values
        return full.reshape((self.n_nodes, self.dofs_per_node) + values.shape[1:])[:, :3].copy()

    def translation_dofs(self, node: int) -> np.ndarray:
        """The global dofs (3,) of a node's x, y, z translations."""
        return self.dofs_per_node * validate.node(node, self.n_nodes) + np.arange(3)

    def factorization(self) -> Factorization:
        """The cached sparse factorization of the constrained stiffness."""
        if self._factor is None:
            self.check_restrained(tethers=False)
            t0 = time.perf_counter()
            Kc, dofs = self.constrained_stiffness()
            # the condition estimate uses the physical stiffness: the penalized diagonal
            # would make it grow with the penalty factor and refuse a well-posed model
            norm = float(abs(self.K).sum(axis=0).max())
            try:
                self._factor = factorize(Kc, spd=True, what="the constrained stiffness", order=lambda: self.dof_order(dofs),
                                         norm=norm)
            except SolverError as exc:
                if self.constraints == "penalty" and self._elimination_factorizes():
                    raise ModelError(
                        f"{exc}. With elimination the same fixes hold the model, so the penalty factor "
                        f"{self.penalty:g} is the problem: use a smaller one (1e6 .. 1e8) or constraints='elimination'"
                    ) from None
                raise ModelError(
                    f"{exc}. The fixes cannot hold the model: a part can move freely (a mechanism, "
                    "e.g. pieces joined at a single vertex). Fix more nodes"
                ) from None
            self.timings["factorize"] = time.perf_counter() - t0
        return self._factor

    def _elimination_factorizes(self) -> bool:
        free = self.free_dofs
        try:
            factorize(self.K[free][:, free], spd=True, what="K_ff", order=lambda: self.dof_order(free))
        except SolverError:
            return False
        return True

    def dof_order(self, dofs: np.ndarray) -> np.ndarray:
        """Fill-reducing order of the given dofs (nested dissection of the mesh nodes)."""
        if "nd" not in self._cache:
            self._cache["nd"] = nested_dissection(self._node_graph(), np.asarray(self.mesh.vertices))
        return expand_node_order(self._cache["nd"], self.dofs_per_node, dofs)

    def solve_static(self, forces, *, return_rotations: bool = False, warn: bool = True,
                     large_deformation: bool = False, **options) -> np.ndarray:
        """Static displacements under nodal loads: K U = F with the fixes applied.

        Returns (n, 3) translations, or all dofs (n, dofs_per_node: rotations too on a shell) when
        ``return_rotations``.
        ``warn=False`` silences the warning about loads on fixed dofs (for loads rtfem applies
        itself, such as the static correction's).
        Solving the full system with zero moments is exactly the condensed problem of Eq. 5
        (K_condensed U_t = F_t), without forming the condensed matrix.

        ``large_deformation=True``: the geometrically nonlinear (corotational) equilibrium under
        dead loads, by Newton with load steps (:func:`rtfem.fe.nonlinear.solve_static`, which takes
        ``options`` such as ``steps``, ``tol``, ``prescribed`` and returns the whole result);
        rotations come as rotation vectors.
        """
        large_deformation = validate.flag(large_deformation, "large_deformation")
        if large_deformation:
            from .nonlinear import solve_static

            res = solve_static(self, forces, **options)
            if return_rotations and res.rotations is not None:
                return np.hstack([res.displacements, res.rotations])
            return res.displacements
        if options:
            raise ModelError(f"solve_static got {', '.join(sorted(options))}: those options are for "
                             "large_deformation=True")
        F = self.force_vector(forces, warn=warn)
        return self._solve(F, return_rotations)

    def nonlinear(self):
        """The geometrically nonlinear (corotational) system of this model with its current fixes
        (:class:`rtfem.fe.nonlinear.NonlinearSystem`), cached until the fixes change."""
        from .nonlinear import NonlinearSystem

        key = self.fixed.tobytes()
        hit = self._cache.get("nonlinear")
        if hit is None or hit[0] != key:
            hit = self._cache["nonlinear"] = (key, NonlinearSystem(self))
        return hit[1]

    def unit_load_response(self, node: int, direction: int) -> np.ndarray:
        """Static (n, 3) displacements under a unit force at ``node`` along axis ``direction``.

        The columns of the static correction and of the impedance map: an internal load,
        applied without the warning about loads on fixed dofs that a user's load gets.
        """
        F = np.zeros(self.n_dofs)
        F[self.translation_dofs(node)[validate.count(direction, "direction", 0, 2)]] = 1.0
        return self._solve(F, False)

    def unit_load_responses(self, nodes, memory: float = 64 * 2**20) -> np.ndarray:
        """(k, n, 3, 3) :meth:`unit_load_response` of each of ``nodes`` in its three directions
        ([node, displaced node, displacement axis, load axis]), with multi-column solves of at most
        ``memory`` bytes of right-hand sides each: one solve of 30 columns costs about what 4 single
        ones do (MKL PARDISO, the 14,556-dof liver shell)."""
        nodes = validate.nodes(nodes, self.n_nodes)
        memory = validate.positive(memory, "memory", "a size in bytes")
        out = np.empty((nodes.size, self.n_nodes, 3, 3))
        per = max(1, int(memory // (8 * 3 * self.n_dofs)))
        for start in range(0, nodes.size, per):
            chunk = nodes[start:start + per]
            F = np.zeros((self.n_dofs, 3 * chunk.size))
            rows = (self.dofs_per_node * chunk[:, None] + np.arange(3)).reshape(-1)
            F[rows, np.arange(rows.size)] = 1.0
            U = self._solve(F).reshape(self.n_nodes, 3, chunk.size, 3)  # displaced node, axis, node, load axis
            out[start:start + chunk.size] = U.transpose(2, 0, 1, 3)
        return out

    def _solve(self, F: np.ndarray, return_rotations: bool = False) -> np.ndarray:
        """Static displacements (n, 3) (``return_rotations``: (n, dofs per node)) of a load vector
        (n_dofs,); a load matrix (n_dofs, m) gives (n, 3, m) (or (n, dofs per node, m))."""
        fac = self.factorization()
        t0 = time.perf_counter()
        U = np.zeros(F.shape)
        if self.constraints == "elimination":
            free = self.free_dofs
            U[free] = fac.solve(F[free])
        else:
            Fp = F.copy()
            Fp[self.fixed_dofs] *= self.penalty
            U = fac.solve(Fp).reshape(F.shape)
        self.timings["solve"] = time.perf_counter() - t0
        U = U.reshape((-1, self.dofs_per_node) + F.shape[1:])
        return U if return_rotations else U[:, :3].copy()

    # ------------------------------------------------------------ condensation (Eq. 4-5)
    def _partition(self) -> tuple[np.ndarray, np.ndarray]:
        """Free translational and free rotational dofs (global indices)."""
        free = ~self.fixed.ravel()
        kind = np.tile(np.arange(self.dofs_per_node) >= 3, self.n_nodes)
        return np.flatnonzero(free & ~kind), np.flatnonzero(free & kind)

    def condensation(self) -> "Condensation":
        """The blocks of Eq. 4 on the free dofs and a factorization of K_rr (Eq. 5, sparse route; a
        model without rotations has K_c = K_tt and no K_rr).

        Cached until the fixes change; shared by :meth:`condensed_stiffness`,
        :meth:`condensed_operator` and SLDM.
        """
        if self._condensation is None:
            t, r = self._partition()
            K = self.K
            Ktt = K[t][:, t].tocsr()
            Ktr = K[t][:, r].tocsr()
            Krr = factorize(K[r][:, r], spd=True, what="K_rr", order=lambda: self.dof_order(r)) if r.size else None
            self._condensation = Condensation(t, r, Ktt, Ktr, Ktr.T.tocsr(), Krr)
        return self._condensation

    def condensed_stiffness(self, *, allow_large: bool = False) -> np.ndarray:
        """The paper's explicit dense condensed stiffness (Eq. 5) on the free translations.

        K_c = K_tt - K_tr K_rr^-1 K_rt: a dense (n_t x n_t) matrix. Refused above 6,000
        translational dof unless ``allow_large``; use :meth:`condensed_operator` instead.
        """
        t, _ = self._partition()
        if t.size > _DENSE_LIMIT and not allow_large:
            raise ModelError(
                f"the dense condensed stiffness would be {t.size} x {t.size} "
                f"({t.size**2 * 8 / 2**30:.1f} GiB); use condensed_operator() or pass allow_large=True"
            )
        c = self.condensation()
        Ktt = c.Ktt.toarray()
        if c.Krr is None:
            return Ktt
        return Ktt - c.Ktr @ c.Krr.solve(c.Krt.toarray())

    def condensed_operator(self) -> "scipy.sparse.linalg.LinearOperator":  # noqa: F821
        """The condensed stiffness of Eq. 5 as a sparse operator (never formed densely).

        x -> K_tt x - K_tr (K_rr^-1 (K_rt x)), with K_rr factorized once.
        """
        c = self.condensation()
        import scipy.sparse.linalg as spla  # here: a model's other uses need not import it

        return spla.LinearOperator((c.t.size, c.t.size), matvec=c.apply, matmat=c.apply, dtype=float)

    def surface_compliance(self, nodes=None, *, method: str = "solves", memory: float = 256 * 2**20,
                           allow_large: bool = False, scheduler=None) -> tuple[np.ndarray, np.ndarray]:
        """The static compliance between the translations of ``nodes``: (nodes, C) with C (3s, 3s),
        C[3a + i, 3b + k] the displacement of ``nodes[a]`` along i per unit force on ``nodes[b]``
        along k: the block of K^-1 that a surface load and a surface display need (Bro-Nielsen &
        Cotin 1996 precompute it to render a volumetric organ from its surface). Default nodes: the
        surface's nodes that are not fully held. Fixed translations get zero rows and columns.

        ``method``: "solves" (default): the columns of K^-1 by multi-column solves with the model's
        factorization (``memory`` bytes of right-hand sides per solve); "condensation": Bro-Nielsen
        and Cotin's route, the Schur complement K* = K_SS - K_SI K_II^-1 K_IS of the other dofs
        (a factorization of K_II, solves with the columns of K_IS) and its dense Cholesky inverse.
        Both are exact; ``benchmarks/condensation.py`` measures which is faster. Dense: refused above
        6,000 rows unless ``allow_large``. ``scheduler``: the blocks of columns (the solves) on a Dask
        cluster (:mod:`rtfem.cluster`; :mod:`rtfem.fe.compliance`), each worker factorizing once."""
        return _surface_compliance(self, nodes, method, memory, allow_large, scheduler)

    def translational_free_dofs(self) -> np.ndarray:
        """Global indices of the free translational dofs (the rows of the condensed matrices)."""
        return self._partition()[0]


@dataclass(frozen=True)
class Condensation:
    """Eq. 4 partitioned on the free translations t and free rotations r, with K_rr factorized."""

    t: np.ndarray
    r: np.ndarray
    Ktt: sp.csr_matrix
    Ktr: sp.csr_matrix
    Krt: sp.csr_matrix
    Krr: Factorization | None  # None when no rotation is free

    def apply(self, x: np.ndarray) -> np.ndarray:
        """K_c x = K_tt x - K_tr K_rr^-1 K_rt x (x of length n_t, or n_t x k)."""
        x = np.asarray(x, dtype=float)
        w = self.Ktt @ x
        if self.Krr is not None:
            w = w - self.Ktr @ self.Krr.solve(self.Krt @ x)
        return w

    def load(self, F: np.ndarray) -> np.ndarray:
        """The condensed load F_t - K_tr K_rr^-1 F_r of a full load vector (6n,)."""
        Ft = F[self.t].copy()
        Fr = F[self.r]
        if self.Krr is not None and np.any(Fr != 0):
            Ft -= self.Ktr @ self.Krr.solve(Fr)
        return Ft


def _describe_rigid_motion(v: np.ndarray, centre: np.ndarray, scale: float) -> str:
    """Words for a rigid motion (t, theta) given about ``centre`` in coordinates scaled by ``scale``."""
    t, th = v[:3] * scale, v[3:]
    fmt = lambda a: "(" + ", ".join(f"{x:.3g}" for x in np.where(np.abs(a) < 1e-9, 0.0, a)) + ")"  # noqa: E731
    if np.linalg.norm(th) * scale < 1e-6 * np.linalg.norm(t):
        return f"translation along {fmt(t / np.linalg.norm(t))}"
    axis = th / np.linalg.norm(th)
    point = centre + np.cross(th, t) / np.dot(th, th)
    return f"rotation about the axis {fmt(axis)} through the point {fmt(point)}"
