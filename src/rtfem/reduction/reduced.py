"""A reduced geometrically nonlinear model: modes and modal derivatives (Barbic & James 2005).

The linear modes Phi span the small-motion response. A large motion also moves along directions
the modes leave out: a bending mode pulled far enough stretches the membrane, and a lobe swung
shortens along its arc. The modal derivatives

    Psi_ij = -K^-1 (d^2 g / dq_i dq_j)(0),     g(v): the internal forces at the dof vector v,

the second-order static response to the amplitudes of modes i and j, span those directions. The
reduced model is the Galerkin projection of the full corotational internal forces on
U = [Phi, Psi]: g_r(q) = U^T g(U q) and K_r(q) = U^T K(U q) U, exact for the motions U can hold
(no small-rotation assumption).

On a shell, a node's coordinates are its translation and its rotation vector theta (Q = exp([theta]x));
the corotational kernel gives moments m about the spin axes, and the generalized moment on theta is
J(theta)^T m with J the left Jacobian of SO(3) (dQ Q^T = [J dtheta]x). The modes' rotations are those
the condensation recovers (``model.rotation_field``).

The internal forces here are evaluated on every element, so a step costs about as much as one
full-order force evaluation: this is the accuracy model (and its static equilibrium); a haptic
rate needs the forces on a cubature subset of the elements (An, Kim & James 2008).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable, Mapping

import numpy as np
import scipy.sparse as sp

from .. import validate
from ..errors import ModelError, SolverError
from .element_terms import HELD_OUT, ElementTerms
from .modal import check_model_key, mesh_fingerprint
from ..fe.nonlinear import MIN_LOAD_STEP, Configuration
from ..fe.rotations import integrated_rotation, rotation

__all__ = ["build_bytes", "check_build_memory", "patch_nodes", "ReducedNonlinearModel", "ReducedStatic"]


@dataclass
class ReducedStatic:
    """What :meth:`ReducedNonlinearModel.solve_static` found: the reduced coordinates ``q``, the
    translations (n, 3), the load factors of the converged steps and the residual norms of each
    step's Newton iterations."""

    q: np.ndarray
    displacements: np.ndarray
    load_factors: list = field(default_factory=list)
    residuals: list = field(default_factory=list)
    seconds: float = 0.0

    @property
    def iterations(self) -> int:
        return sum(len(h) - 1 for h in self.residuals)


def patch_nodes(model, nodes: np.ndarray, radius: float) -> np.ndarray:
    """The nodes within ``radius`` (m) of any of ``nodes``: the patch a localized basis holds."""
    from scipy.spatial import cKDTree

    X = np.asarray(model.mesh.vertices)
    return np.flatnonzero(cKDTree(X[nodes]).query(X)[0] <= radius)


def build_bytes(model, base: int, local: tuple | None = None, poses: int = 16) -> tuple[int, int]:
    """(about the peak memory in bytes, the basis size r) of building a reduced nonlinear model whose
    basis has ``base`` columns before a patch (modes + d (d + 1) / 2 derivatives), localized on
    ``local`` = (nodes, radius), and of training its cubature on ``poses`` poses, before any of it is
    computed: the element basis rows (E nd r), the training matrix and its stacking (2 poses r E), the
    basis and its orthonormalization (2 N r) and a patch's columns (4 N p), 8 bytes each, for E
    elements of nd dofs, N free dofs and p patch dofs. Measured on the solid default liver (4,942
    tet10, 20 modes and the derivatives of 20) with a 2 / 5 cm patch: a peak of 2.4 / 10.7 GB above
    the start, estimated 1.9 / 10.0 GB; on a tet10 block 1.03-1.37 times tracemalloc's peak."""
    system = model.nonlinear()
    E, nd = system.dofs.shape
    N = system.free.size
    p = 0
    if local is not None:
        p = int(np.count_nonzero(~model.fixed[patch_nodes(model, *local)]))
    r = base + p
    return 8 * (E * nd * r + 2 * poses * r * E + 2 * N * r + 4 * N * p), r


def check_build_memory(model, base: int, local: tuple | None = None) -> None:
    """Refuse, before it is computed, a reduced model whose build (:func:`build_bytes`) would take
    over 3/4 of this machine's memory: a 5 cm patch on a fine liver ran out of memory after 93 s of
    modal derivatives (issue 53)."""
    from ..storage import physical_memory

    need, size = build_bytes(model, base, local)
    have = physical_memory()
    if need > 0.75 * have:
        patch = "" if local is None else f" with a {local[1] * 1e3:g} mm patch"
        raise ModelError(f"the reduced nonlinear model{patch} ({size} coordinates) needs about {need / 1e9:.1f} GB to "
                         f"build, more than 3/4 of this machine's {have / 1e9:.1f} GB: give a smaller --local radius "
                         "(local=), fewer modes or derivatives, or a coarser mesh")


class ReducedNonlinearModel(ElementTerms):
    """The Galerkin projection of a model's corotational forces on its modes and modal derivatives.

    Parameters
    ----------
    model : a ShellModel or SolidModel with its fixes (the same the modes were computed with).
    modes : its :class:`~rtfem.ModalBasis` (from :func:`rtfem.modal_analysis`).
    derivatives : the modal derivatives of the lowest ``derivatives`` modes are added
        (d (d + 1) / 2 columns); 0 gives the plain modal Galerkin model.
    size : keep only this many derivative directions, the largest after weighting Psi_ij by
        w_1^4 / (w_i^2 w_j^2) (Barbic & James' mass-PCA, in the stiffness norm here); default all.
    progress : ``progress(done, total, message)`` per derivative mode.
    scheduler : the derivatives' tangent differences on a Dask cluster (:mod:`rtfem.cluster`:
        "tcp://HOST:PORT", "local:N" or a Client; :meth:`derivatives`); None: here.

    ``basis`` (free dofs x r) is stiffness-orthonormal (basis^T K basis = I at rest); ``info``
    holds the sizes and the time split.

    Raises
    ------
    ModelError
        A model without corotational forces, modes of another model (mesh, supports or material:
        the basis's model key), a negative derivatives or size.
    SolverError
        A modal derivative's solve fails (a mechanism).
    """

    local = None  # a localized copy's patch (see :meth:`localize`)

    def __init__(self, model, modes, derivatives: int = 20, *, size: int | None = None,
                 progress: Callable[[int, int, str], None] | None = None, scheduler=None) -> None:
        from .modal import ModalBasis
        from ..fe.protocol import check_model

        t0 = time.perf_counter()
        check_model(model, "model")
        progress = validate.progress(progress)
        if not isinstance(modes, ModalBasis):
            raise ModelError(f"modes={validate.show(modes)} must be an rt.ModalBasis (from rt.modal_analysis(model, r))")
        if modes.fingerprint != mesh_fingerprint(model.mesh) or modes.shapes.shape[0] != model.n_nodes:
            raise ModelError("these modes were computed for another mesh: pass the model they came from, or "
                             "recompute them with rt.modal_analysis(model, ...)")
        check_model_key(modes.info, model, "the modal basis")
        n_modes = modes.omega.size
        derivatives = validate.count(derivatives, "derivatives", 0, n_modes)
        self._setup(model)
        n = model.n_nodes
        shapes = np.asarray(modes.shapes, float)
        if self.dpn == 6:
            shapes = np.concatenate([shapes, model.rotation_field(shapes)], axis=1)
        Phi = shapes.reshape(n * self.dpn, n_modes)[self.free]
        t1 = time.perf_counter()
        Psi = self.derivatives(Phi[:, :derivatives], progress=progress, scheduler=scheduler)
        t2 = time.perf_counter()
        if Psi.shape[1]:
            w2 = np.asarray(modes.omega[:derivatives], float) ** 2
            i, j = np.triu_indices(derivatives)
            Psi = Psi * (w2[0] ** 2 / (w2[i] * w2[j]))
        self.basis = self._orthonormal(Phi, Psi, size)
        self.n_modes = n_modes
        self.n_derivatives = self.basis.shape[1] - n_modes
        self.info = {"modes": n_modes, "derivative_modes": derivatives, "derivatives": self.n_derivatives,
                     "size": self.basis.shape[1], "seconds": {"derivatives": t2 - t1,
                                                              "total": time.perf_counter() - t0}}

    def _setup(self, model) -> None:
        """The model, its law, nonlinear system, free dofs and rest stiffness with its factorization."""
        self.model = model
        self.law = getattr(model, "law", None)  # a solid's hyperelastic law (else the corotated linear material)
        if getattr(model, "element", None) == "tet4-anp":
            raise ModelError("element='tet4-anp' couples each node's patch of tets, which the reduced nonlinear model's "
                             "element cubature cannot split: reduce a tet10 model, or step tet4-anp full order")
        self.system = model.nonlinear()
        self.dpn = model.dofs_per_node
        self.free = self.system.free
        self._K0 = self.system.evaluate(Configuration.rest(model.n_nodes, self.dpn == 6))[1]

    @property
    def _solver(self):
        """The factorization of the stiffness at rest, made when first needed (the derivatives, a
        static solve): a reduced model loaded from a file and only stepped never needs it (0.66 s of
        a launch's 2.2 s on the solid default liver)."""
        solver = self.__dict__.get("_solver_at_rest")
        if solver is None:
            solver = self.__dict__["_solver_at_rest"] = self.system.solver(self._K0, "the stiffness at rest")
        return solver

    def save(self, path):
        """Save the basis and the cubature as a versioned ``.npz`` (:mod:`rtfem.reduction.reduced_io`)."""
        from .reduced_io import save_reduced

        return save_reduced(self, path)

    @classmethod
    def load(cls, path, model) -> "ReducedNonlinearModel":
        """The reduced model saved at ``path``, on ``model`` (the same mesh, supports and material; it is
        checked), without computing the derivatives again (:mod:`rtfem.reduction.reduced_io`)."""
        from .reduced_io import load_reduced

        return load_reduced(cls, path, model)

    # ---------------------------------------------------------------- configurations and forces
    def _configuration(self, v: np.ndarray) -> tuple[Configuration, np.ndarray]:
        """The configuration of a free-dof vector v (translations; rotation vectors on a shell)."""
        full = self.system.expand(v)
        Q = rotation(full[:, 3:]) if self.dpn == 6 else None
        return Configuration(full[:, :3].copy(), Q), full

    def forces(self, v: np.ndarray, tangent: bool = True):
        """The generalized internal forces g(v) on the free dofs and their Jacobian dg/dv (sparse;
        None unless ``tangent``), for a free-dof vector v."""
        conf, full = self._configuration(v)
        f, K, _ = self.system.evaluate(conf, tangent)
        if self.dpn == 3:
            return f[self.free], K
        n = self.model.n_nodes
        f = f.reshape(n, 6).copy()
        theta = full[:, 3:]
        J = integrated_rotation(theta)  # the left Jacobian of SO(3)
        m = f[:, 3:].copy()
        f[:, 3:] = np.einsum("kji,kj->ki", J, m)
        if not tangent:
            return f.ravel()[self.free], None
        # d(J^T m)/dtheta with m held: the derivative of the Jacobian (central differences; J is smooth)
        h = 1e-7
        G = np.zeros((n, 3, 3))
        for c in range(3):
            e = np.zeros(3)
            e[c] = h
            G[:, :, c] = np.einsum("kji,kj->ki", integrated_rotation(theta + e) - integrated_rotation(theta - e), m) / (2 * h)
        B = np.zeros((n, 6, 6))
        B[:, :3, :3] = np.eye(3)
        B[:, 3:, 3:] = J
        Bf = _block_diagonal(B)[self.free][:, self.free]
        Gf = _block_diagonal(np.pad(G, ((0, 0), (3, 0), (3, 0))))[self.free][:, self.free]
        return f.ravel()[self.free], (Bf.T @ K @ Bf + Gf).tocsr()

    def derivatives(self, Phi: np.ndarray, *, progress=None, scheduler=None) -> np.ndarray:
        """The modal derivatives Psi_ij = -K^-1 (dK/dq_j) phi_i (i <= j) of the columns of Phi
        (free dofs), ordered as ``np.triu_indices``. dK/dq_j is the central difference of the
        tangent along phi_j (a step moving no node by more than 1e-5 of the model's size); the
        pair is symmetrized, ((dK/dq_j) phi_i + (dK/dq_i) phi_j) / 2. The m tangent differences
        (two tangent assemblies each: nearly all of the time) are independent: with ``scheduler``
        (:mod:`rtfem.cluster`) they run on a Dask cluster's workers, each rebuilding the model once;
        the solves stay here."""
        m = Phi.shape[1]
        if m == 0:
            return np.zeros((Phi.shape[0], 0))
        Y: list = [None] * m  # Y[j] = (dK/dq_j) Phi
        if scheduler is None:
            for j in range(m):
                Y[j] = _tangent_difference(self, Phi, j)
                if progress is not None:
                    progress(j + 1, m, f"tangent derivative {j + 1} of {m}")
        else:
            Y = _cluster_differences(self.model, Phi, scheduler, progress)
        i, j = np.triu_indices(m)
        rhs = np.column_stack([0.5 * (Y[b][:, a] + Y[a][:, b]) for a, b in zip(i, j)])
        return -self._solver.solve(rhs)

    def _orthonormal(self, Phi: np.ndarray, Psi: np.ndarray, size: int | None) -> np.ndarray:
        """[Phi, the kept directions of Psi], stiffness-orthonormal."""
        K = self._K0
        U = Phi / np.sqrt(np.einsum("ir,ir->r", Phi, K @ Phi))
        L = np.linalg.cholesky(U.T @ (K @ U))
        U = np.linalg.solve(L, U.T).T
        if Psi.shape[1] == 0:
            return U
        P = Psi - U @ (U.T @ (K @ Psi))  # the part the modes do not hold
        P = P - U @ (U.T @ (K @ P))
        G = P.T @ (K @ P)
        lam, V = np.linalg.eigh(0.5 * (G + G.T))
        keep = lam > 1e-12 * lam.max()
        order = np.argsort(lam[keep])[::-1]
        if size is not None:
            size = validate.count(size, "size", 0, int(keep.sum()))
            order = order[:size]
        V, lam = V[:, keep][:, order], lam[keep][order]
        return np.column_stack([U, (P @ V) / np.sqrt(lam)])

    # ---------------------------------------------------------------- the reduced model
    @property
    def size(self) -> int:
        return self.basis.shape[1]

    def displacements(self, q: np.ndarray) -> np.ndarray:
        """The nodal translations (n, 3) of reduced coordinates q."""
        return self.system.expand(self.basis @ q)[:, :3].copy()

    def reduced_forces(self, q: np.ndarray, tangent: bool = True):
        """g_r(q) = U^T g(U q) and K_r(q) = U^T K(U q) U (dense r x r; None unless ``tangent``)."""
        U = self.basis
        g, K = self.forces(U @ q, tangent)
        return U.T @ g, (None if K is None else U.T @ (K @ U))

    # ---------------------------------------------------------------- local enrichment
    def localize(self, nodes, radius: float) -> "ReducedNonlinearModel":
        """A copy whose basis also holds every free dof of the nodes within ``radius`` (m) of
        ``nodes`` (a grasped vertex, or all of a jaw's held nodes): the modes and derivatives
        carry the organ's global motion, the patch's own dofs the strongly nonlinear dent under
        the grasp, which a basis of global shapes cannot hold (a subspace with local deformations,
        after Harmon & Zorin, ACM TOG 32 (2013) 129: theirs are added at contacts at run time,
        these are the patch's nodal dofs). The basis stays stiffness-orthonormal; the cubature is
        not copied: call :meth:`train_cubature`, which then keeps every element touching the patch
        exactly (weight 1) and fits the others, and :class:`ReducedNonlinearSimulator` refreshes
        those elements every step (``remainder=True`` halved the solid liver's cubature and kept
        its pulls, but missed its 5 cm lobe lift: README). Measured on the solid liver, a vertex pulled 2 / 5 cm, the
        exact reduced static error against the corotational full order falls from 0.115 / 0.152
        of the pull (40 modes + derivatives of 20, static correction) to 0.029 / 0.050 with a
        2 cm patch (18 nodes, 54 more coordinates) and 0.007 / 0.013 with 3 cm (42 nodes)
        (``benchmarks/reduced_nonlinear.py --organ solid --local 0.02``)."""
        n = self.model.n_nodes
        nodes = validate.nodes(nodes, n)
        radius = validate.positive(radius, "radius", "a distance in m such as 0.02")
        near = patch_nodes(self.model, nodes, radius)
        parent = self if self.local is None else self.local["parent"]
        check_build_memory(self.model, parent.size, (nodes, radius))
        pos = np.full(self.model.n_dofs, -1)
        pos[self.free] = np.arange(self.free.size)
        rows = pos[(self.dpn * near[:, None] + np.arange(self.dpn)).ravel()]
        rows = rows[rows >= 0]
        if rows.size == 0:
            raise ModelError(f"no free node lies within {radius:g} m of nodes {nodes.tolist()}: pick a free node or a "
                             "larger radius")
        E = np.zeros((self.free.size, rows.size))
        E[rows, np.arange(rows.size)] = 1.0
        out = object.__new__(type(self))
        out.__dict__.update({k: v for k, v in parent.__dict__.items() if not k.startswith("_cubature")})
        out.basis = parent._orthonormal(parent.basis, E, None)
        elements = np.flatnonzero(np.isin(self.system.cells, near).any(axis=1))
        out.local = {"parent": parent, "nodes": near, "radius": radius, "columns": parent.size,
                     "elements": elements}
        out.info = dict(parent.info, size=out.basis.shape[1],
                        local={"nodes": int(near.size), "radius": radius, "coordinates": out.basis.shape[1] - parent.size,
                               "elements": int(elements.size)})
        return out

    # ---------------------------------------------------------------- elements and cubature
    def train_cubature(self, poses: int = 16, *, tol: float = 0.05, reach: float = 0.1, seed: int = 0,
                       remainder: bool = False, scheduler=None, regions: bool | None = None) -> dict:
        """Choose the elements and weights of the reduced forces (optimized cubature, An, Kim &
        James 2008) on ``poses`` random poses, each moving the organ by up to ``reach`` times its
        size. Afterwards :meth:`reduced_forces` with ``cubature=True`` sums those elements only.
        ``remainder``: the rest-linear part is kept exact (K_r q, K_r = U^T K U the reduced rest
        stiffness) and the cubature fits only the nonlinear remainder sum_e U_e^T (g_e(v) - K_e v),
        so the forces are exact to first order in the motion and ``tol`` bounds the error of the
        remainder alone. ``scheduler``: the poses' element forces on a Dask cluster (one pose a task;
        :mod:`rtfem.cluster`). ``regions`` (default: where the solid has several): each region's
        elements fitted to ``tol`` of that region's own forces and to ``tol`` / regions of the whole's
        (:func:`~rtfem.reduction.cubature.region_tol`), so that a small region is not averaged away in
        the whole's sum and the fits together are as close as one; ``False``: one fit over all elements.
        Returns what it found (``elements``, relative ``training_error``, ``held_out_error`` on
        ``held_out_poses`` more poses drawn alike but not fitted to, ``seconds``)."""
        from . import cubature

        t0 = time.perf_counter()
        poses = validate.count(poses, "poses", 1, 10**4)
        tol = validate.positive(tol, "tol", "a relative error such as 0.05")
        reach = validate.positive(reach, "reach", "a fraction of the model's size such as 0.1")
        remainder = validate.flag(remainder, "remainder")
        seed = validate.count(seed, "seed", 0, 2**63 - 1)
        data = self._element_data()
        E = data[0].shape[0]
        Ke = self._rest_tangents(data) if remainder else None
        rng = np.random.default_rng(seed)
        qs = self._training_poses(poses, reach, rng)
        if scheduler is None:
            found = [self._pose_rows(q, data, Ke, reach) for q in qs]
        else:
            from .reduced_io import cluster_poses

            found = cluster_poses(self, qs, remainder, reach, scheduler)
        rows, targets = [f[0] for f in found], [f[1] for f in found]
        shrunk = sum(f[2] for f in found)
        A, b = np.vstack(rows), np.concatenate(targets)
        pinned = np.zeros(0, int) if self.local is None else self.local["elements"]
        groups = self._region_groups(regions)
        if pinned.size:  # a localized model: the patch's elements exact, the others fitted to the rest
            others = np.setdiff1d(np.arange(E), pinned)
            rest = b - A[:, pinned].sum(axis=1)  # the same tolerance relative to the whole force
            chosen, w, _ = cubature.train(A[:, others], rest, tol * np.linalg.norm(b) / max(np.linalg.norm(rest), 1e-300))
            elements, weights = np.concatenate([pinned, others[chosen]]), np.concatenate([np.ones(pinned.size), w])
        elif groups is not None:  # each region to its own forces, and to its share of the whole's
            fits = [(g, *cubature.train(A[:, g], bg, cubature.region_tol(tol, bg, b, len(groups)), seed=seed)[:2])
                    for g, bg in ((g, A[:, g].sum(axis=1)) for g in groups)]
            elements, weights = np.concatenate([g[c] for g, c, _ in fits]), np.concatenate([w for _, _, w in fits])
        else:
            elements, weights, error = cubature.train(A, b, tol)
        error = cubature.fit_error(A, b, elements, weights)
        if elements.size == 0:
            raise ModelError(f"cubature training chose no element (training error {error:.3g}): the training forces "
                             "carry no information; train on larger poses (reach) or more of them")
        self._cubature_pinned = int(pinned.size)
        self._cubature = (self._element_data(elements), weights)
        self._cubature_elements = np.asarray(elements, int)
        if remainder:
            K = self.basis.T @ (self._K0 @ self.basis)
            self._cubature_rest = (self._cubature, Ke[elements], 0.5 * (K + K.T))
        self._cubature_remainder = remainder
        held_out = self._held_out_error(self._training_poses(HELD_OUT, reach, rng), data, Ke, reach, elements, weights)
        self.info["cubature"] = {"elements": int(elements.size), "of": int(E), "training_error": error,
                                 "held_out_error": held_out, "held_out_poses": HELD_OUT,
                                 "remainder": remainder, "pinned": int(pinned.size), "halved_poses": shrunk,
                                 "regions": 0 if groups is None else len(groups), "seconds": time.perf_counter() - t0}
        return dict(self.info["cubature"], elements=elements, weights=weights)

    def cubature_forces(self, q: np.ndarray, *, single: bool = False) -> np.ndarray:
        """The reduced forces g_r(q) summed over the cubature elements (compiled; see
        :meth:`train_cubature`). ``single``: the two products with the elements' basis rows in
        single precision (copies made once; half the memory read, the step's limit; forces
        within ~1e-5 relative), the element forces in double."""
        if getattr(self, "_cubature", None) is None:
            raise ModelError("no cubature yet: call train_cubature() first")
        data, weights = self._cubature
        single = single is True or validate.flag(single, "single")
        U, UT = self.cubature_rows(single)
        if not self._cubature_remainder:
            return self._element_forces(q, data, weights, False, UT=UT, U=U)[0]
        Ke, K = self.cubature_rest()
        return K @ q + self._element_forces(q, data, weights, False, rest=Ke, UT=UT, U=U)[0]

    def _rows(self, nodes: np.ndarray) -> np.ndarray:
        """Positions among the free dofs of the translations of ``nodes`` (3k,), refused if held."""
        pos = np.full(self.model.n_dofs, -1)
        pos[self.free] = np.arange(self.free.size)
        rows = pos[(self.dpn * nodes[:, None] + np.arange(3)).ravel()]
        if (rows < 0).any():
            raise ModelError("a pulled node is fixed in the model: pull free nodes")
        return rows

    def solve_static(self, forces=None, *, targets: Mapping[int, np.ndarray] | None = None, steps: int = 4,
                     tol: float = 1e-9, max_iterations: int = 30, max_cuts: int = 10,
                     cubature: bool = False, static_correction: bool = False) -> ReducedStatic:
        """The reduced nonlinear static equilibrium under dead ``forces`` ((n, 3) or {node: f}) with
        the nodes of ``targets`` ({node: displacement (3,)}) moved there exactly (Lagrange
        multipliers), by Newton's method with load steps halved on failure (like
        :func:`rtfem.fe.nonlinear.solve_static`). ``cubature``: the equilibrium of the cubature forces
        (:meth:`train_cubature`; the Newton matrix stays the all-element tangent, so the iterations
        converge linearly, at the rate of the cubature's error). ``static_correction``: the
        displacement is U q + D f, D = K^-1 - U U^T the static response the basis cannot hold
        (linear) to the loads f (the given forces and the pulled nodes' reactions), as
        :class:`ReducedNonlinearSimulator` adds it; a pulled node then reaches its target with
        U q + D f together."""
        t0 = time.perf_counter()
        static_correction = validate.flag(static_correction, "static_correction")
        cubature = validate.flag(cubature, "cubature")
        tol = validate.positive(tol, "tol", "a relative tolerance such as 1e-9")
        max_iterations = validate.count(max_iterations, "max_iterations", 1, 1000)
        max_cuts = validate.count(max_cuts, "max_cuts", 0, 60)
        if cubature and getattr(self, "_cubature", None) is None:
            raise ModelError("no cubature yet: call train_cubature() first")
        U = self.basis
        F = np.zeros(self.model.n_dofs) if forces is None else self.model.force_vector(forces)
        Fr = U.T @ F[self.free]
        targets = dict(targets or {})
        nodes = np.array([validate.node(k, self.model.n_nodes) for k in targets], dtype=int)
        C = U[self._rows(nodes)] if nodes.size else np.zeros((0, self.size))
        t = np.concatenate([validate.vector(v, "target displacement") for v in targets.values()]) if nodes.size \
            else np.zeros(0)
        if nodes.size and np.linalg.matrix_rank(C) < C.shape[0]:
            raise ModelError(f"the reduced basis cannot move the {nodes.size} pulled nodes independently: pull "
                             "fewer nodes, or add modes or derivatives")
        R, Dh, DF = None, None, None
        if static_correction:
            DF = self._residual(F[self.free])  # the given forces' part, at every free dof
            if nodes.size:  # the pulled nodes' columns of D, and its block there
                rows = self._rows(nodes)
                E = np.zeros((self.free.size, rows.size))
                E[rows, np.arange(rows.size)] = 1.0
                R = self._residual(E)
                Dh = R[rows]
                t = t - DF[rows]  # what the basis and the reactions' correction have to add
        q, lam, applied, step, cuts = np.zeros(self.size), np.zeros(t.size), 0.0, \
            1.0 / validate.count(steps, "steps", 1, 10**6), 0
        result = ReducedStatic(q, np.zeros((self.model.n_nodes, 3)))
        while applied < 1.0 - 1e-12:
            target = min(1.0, applied + step)
            trial, history, ok, trial_lam = self._newton(q, target * Fr, C, target * t, tol, max_iterations, cubature,
                                                         lam, Dh)
            if ok:
                q, applied, lam = trial, target, trial_lam
                result.load_factors.append(target)
                result.residuals.append(history)
                if cuts == 0 and len(history) <= 6:
                    step *= 2.0
                cuts = 0
                continue
            cuts += 1
            if cuts > max_cuts or step < MIN_LOAD_STEP:
                raise SolverError(f"the reduced Newton iterations did not converge past load factor {applied:.4g}: "
                                  "reduce the load or pass more steps")
            step *= 0.5
        result.q, result.displacements = q, self.displacements(q)
        if static_correction:  # the reactions on the pulled nodes are -lam
            v = DF if R is None else DF - R @ lam
            result.displacements += self.system.expand(v)[:, :3]
        result.seconds = time.perf_counter() - t0
        return result

    def _residual(self, B: np.ndarray) -> np.ndarray:
        """D B = K^-1 B - U U^T B for free-dof loads B (columns): the static response the basis
        cannot hold."""
        X = self._solver.solve(B if B.ndim == 2 else B[:, None])
        X = X - self.basis @ (self.basis.T @ (B if B.ndim == 2 else B[:, None]))
        return X if B.ndim == 2 else X[:, 0]

    def _newton(self, q, Fr, C, t, tol, max_iterations, cubature=False, lam=None, Dh=None):
        q = q.copy()
        k = C.shape[0]
        lam = np.zeros(k) if lam is None else lam.copy()
        Z = np.zeros((k, k)) if Dh is None else -Dh
        history = []
        for _ in range(max_iterations):
            g, A = self.reduced_forces(q)
            if cubature:
                g = self.cubature_forces(q)
            r = np.concatenate([g + C.T @ lam - Fr, C @ q + Z @ lam - t])
            rn = float(np.linalg.norm(r))
            history.append(rn)
            if not np.isfinite(rn):
                return q, history, False, lam
            if rn <= tol * (float(np.linalg.norm(Fr)) + float(np.linalg.norm(g)) + float(np.linalg.norm(C.T @ lam))) \
                    and np.abs(r[self.size:]).max(initial=0.0) <= 1e-12 * self.system.size:
                return q, history, True, lam
            KKT = np.block([[A, C.T], [C, Z]])
            try:
                dx = -np.linalg.solve(KKT, r)
            except np.linalg.LinAlgError:
                return q, history, False, lam
            q += dx[:self.size]
            lam += dx[self.size:]
            if np.abs(self.system.expand(self.basis @ dx[:self.size])[:, :3]).max() <= 1e-12 * self.system.size:
                return q, history, True, lam  # the round-off floor: no translation moves any more
        return q, history, False, lam


def _tangent_difference(owner, Phi: np.ndarray, j: int) -> np.ndarray:
    """(dK/dq_j) Phi (free dofs, m): the central difference of ``owner.forces``' tangent along Phi's
    column j (see :meth:`ReducedNonlinearModel.derivatives`) times Phi."""
    b = Phi[:, j]
    scale = np.abs(owner.system.expand(b)[:, :3]).max()
    eps = 1e-5 * owner.system.size / max(scale, 1e-300)
    Kp, Km = owner.forces(eps * b)[1], owner.forces(-eps * b)[1]
    return ((Kp - Km) / (2 * eps)) @ Phi


class _Forces:
    """What :meth:`ReducedNonlinearModel.forces` needs, on a cluster's worker: the model rebuilt
    from its recipe and its nonlinear system."""

    _configuration = ReducedNonlinearModel._configuration
    forces = ReducedNonlinearModel.forces

    def __init__(self, model) -> None:
        self.model, self.system = model, model.nonlinear()
        self.dpn, self.free = model.dofs_per_node, self.system.free


def _difference_task(recipe, Phi: np.ndarray, js) -> list:
    """On a worker: [(j, (dK/dq_j) Phi)] for the columns js, the model built once per worker."""
    from ..cluster import worker_cached

    owner = worker_cached(recipe.key + ":forces", lambda: _Forces(recipe.build()))
    return [(int(j), _tangent_difference(owner, Phi, int(j))) for j in js]


def _cluster_differences(model, Phi: np.ndarray, scheduler, progress) -> list:
    """[(dK/dq_j) Phi for every column j] on a Dask cluster, one column a task."""
    from ..cluster import connect, run_tasks
    from ..fe.recipe import ModelRecipe

    m = Phi.shape[1]
    Y: list = [None] * m

    def collect(batch) -> None:
        for j, y in batch:
            Y[j] = y
        if progress is not None:
            done = sum(y is not None for y in Y)
            progress(done, m, f"tangent derivative {done} of {m} (cluster)")

    with connect(scheduler) as client:
        stage = None if progress is None else (lambda message: progress(sum(y is not None for y in Y), m, message))
        why = run_tasks(client, _difference_task, (ModelRecipe.of(model), Phi), [[j] for j in range(m)], collect,
                        stage=stage)
    if why:
        if why == "interrupted":
            raise KeyboardInterrupt
        raise SolverError(f"the modal derivatives on the cluster stopped: {why}")
    return Y


def _block_diagonal(B: np.ndarray) -> sp.csr_matrix:
    """The block-diagonal sparse matrix of blocks B (n, d, d)."""
    n, d, _ = B.shape
    rows = (d * np.arange(n)[:, None, None] + np.arange(d)[None, :, None]).repeat(d, axis=2)
    cols = (d * np.arange(n)[:, None, None] + np.arange(d)[None, None, :]).repeat(d, axis=1)
    return sp.csr_matrix((B.ravel(), (rows.ravel(), cols.ravel())), shape=(n * d, n * d))
