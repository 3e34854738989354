"""The element-level terms of :class:`rtfem.reduction.reduced.ReducedNonlinearModel` (a mixin): the
elements' basis rows and kernel arguments, their forces and tangents (the compiled kernels of
:mod:`rtfem.reduction.cubature` and :mod:`rtfem.reduction.tet_kernels`, or a solid's hyperelastic
law), the cubature's rows and rest stiffness, and the tangent's change from rest that the reduced
nonlinear step is linearized about."""

from __future__ import annotations

import numpy as np

from .. import validate
from ..errors import ModelError

__all__ = ["ElementTerms"]


def _region_laws(system):
    """(each element's group (m,), the groups' laws: a hyperelastic law, or None for the corotated
    linear material) of a solid whose regions are not all rt.Material; else None."""
    laws = getattr(system.kernel, "laws", None)
    if not laws or all(law is None for _, law in laws):
        return None
    group = np.empty(sum(idx.size for idx, _ in laws), dtype=np.int64)
    for g, (idx, _) in enumerate(laws):
        group[idx] = g
    return group, [law for _, law in laws]


HELD_OUT = 4  # the poses the cubature's fit is checked on after it is trained (not fitted to)


class ElementTerms:
    """Needs ``system`` (the model's NonlinearSystem), ``model``, ``free``, ``basis``, ``size``, ``law``,
    ``_K0`` and, for the cubature's terms, ``_cubature`` (set by ``train_cubature``)."""

    def _element_data(self, elements: np.ndarray | None = None):
        """The compiled kernel's arguments for ``elements`` (default all), each indexed by element
        first: the basis rows of each element's dofs (E, nd, r), then on a shell the rest corners,
        frames, local coordinates and stiffnesses; on a solid the rest nodes (E, k, 3), the shape
        gradients (E, nq, k, 3) and weights (E, nq) of the quadrature points and the Lame
        constants (E, 2)."""
        kern, cells = self.system.kernel, self.system.cells
        idx = np.arange(cells.shape[0]) if elements is None else np.asarray(elements, int)
        pos = np.full(self.model.n_dofs, -1)
        pos[self.free] = np.arange(self.free.size)
        p = pos[self.system.dofs[idx]]
        Ue = np.zeros((idx.size, p.shape[1], self.size))
        Ue[p >= 0] = self.basis[p[p >= 0]]
        X = np.ascontiguousarray(np.asarray(self.model.mesh.vertices)[cells[idx]])
        if self.dpn == 3:
            G = np.ascontiguousarray(np.stack(kern.G, axis=1)[idx])
            wdet = np.ascontiguousarray(np.stack(kern.wdet, axis=1)[idx])
            lm = kern.lm[idx] if hasattr(kern, "lm") else np.tile([kern.lam, kern.mu], (idx.size, 1))  # regions: own
            regions = _region_laws(self.system)
            if regions is not None:  # regions of their own laws: each element's group, a sixth array
                return Ue, X, G, wdet, np.ascontiguousarray(lm), regions[0][idx]
            return Ue, X, G, wdet, np.ascontiguousarray(lm)
        return (Ue, X, np.ascontiguousarray(kern.R0[idx]), np.ascontiguousarray(kern.x2[idx]),
                np.ascontiguousarray(kern.x3[idx]), np.ascontiguousarray(kern.y3[idx]),
                np.ascontiguousarray(kern.k[idx]))

    def _region_groups(self, regions) -> list[np.ndarray] | None:
        """The elements of each region (the system's element order) where the cubature is fitted per
        region: ``regions`` True, or None on a solid of several regions; else None."""
        labels = np.asarray(self.model.tetmesh.labels) if getattr(self.model, "materials", None) else None
        if regions is None:
            regions = labels is not None
        if not validate.flag(regions, "regions"):
            return None
        if labels is None:
            raise ModelError("train_cubature(regions=True) needs a solid of several regions (a material per label)")
        return [np.flatnonzero(labels == k) for k in np.unique(labels)]

    def _kernel_forces(self, V: np.ndarray, data) -> np.ndarray:
        """Each element's forces (E, nd) at its dofs V (E, nd) (compiled where numba is): the
        corotational triangle's or, for data with a solid's five arrays, the corotated tet's (or
        the solid's hyperelastic law's, batched numpy)."""
        from . import cubature, tet_kernels

        F = np.empty(V.shape)
        if len(data) == 6:
            return self._by_region(V, data, F, tet_kernels.solid_element_forces, tet_kernels.law_forces)
        if len(data) == 5 and self.law is not None:
            tet_kernels.law_forces(np.ascontiguousarray(V), *data[1:4], self.law, F)
            return F
        kernel = tet_kernels.solid_element_forces if len(data) == 5 else cubature.element_forces
        kernel(np.ascontiguousarray(V), *data[1:], F)
        return F

    def _by_region(self, V: np.ndarray, data, out: np.ndarray, corotated, by_law) -> np.ndarray:
        """``out`` filled region by region (data's sixth array: each element's group): ``corotated``
        (V, X, G, wdet, lm, out) for the groups of the corotated material, ``by_law`` (V, X, G, wdet,
        law, out) for a hyperelastic law's."""
        from .tet_kernels import by_region

        groups = data[5]  # (the group array: data's, made once)
        parts = [(np.flatnonzero(groups == g), law) for g, (_, law) in enumerate(self.system.kernel.laws)]
        return by_region(parts, np.ascontiguousarray(V, dtype=float), *data[1:5], out, corotated, by_law)

    def _element_forces(self, q: np.ndarray, data, weights: np.ndarray, per_element: bool,
                        rest: np.ndarray | None = None, UT: np.ndarray | None = None,
                        U: np.ndarray | None = None) -> np.ndarray:
        """sum_e w_e U_e^T g_e(U_e q) over the elements of ``data`` ((1, r)), or each term (E, r).
        ``rest`` (E, nd, nd): subtract each element's rest tangent times its dofs (the nonlinear
        remainder g_e(v) - K_e v). ``UT``: the basis rows as (r, nd E) in C order (:func:`_projection_rows`),
        for the sum's projection; ``U`` (nd E, r): the rows for the dofs instead of data's. Either
        may be float32 (the products in single precision, the kernel in double)."""
        Ue = data[0] if U is None else U
        E, nd = data[0].shape[:2]
        V = np.asarray(Ue.reshape(-1, self.size) @ np.asarray(q, dtype=Ue.dtype), dtype=float).reshape(E, nd)
        F = self._kernel_forces(V, data)
        if rest is not None:
            F -= np.einsum("eij,ej->ei", rest, V)
        F *= np.asarray(weights, dtype=float)[:, None]
        if per_element:
            return np.einsum("eir,ei->er", Ue, F)
        if UT is not None:  # the projection as a row-major product: 0.5-0.6 times the time of F @ Ue
            return np.asarray(UT @ F.reshape(-1).astype(UT.dtype, copy=False), dtype=float)[None]
        return F.reshape(1, -1) @ Ue.reshape(-1, self.size)

    def cubature_rows(self, single: bool) -> tuple[np.ndarray | None, np.ndarray]:
        """The cubature elements' basis rows as the products take them (:func:`_projection_rows`),
        made once per cubature and precision."""
        if getattr(self, "_cubature_rows", None) is None or self._cubature_rows[0] is not self._cubature:
            self._cubature_rows = (self._cubature, {})
        rows = self._cubature_rows[1]
        if single not in rows:
            rows[single] = _projection_rows(self._cubature[0][0], single)
        return rows[single]

    def cubature_rest(self) -> tuple[np.ndarray, np.ndarray]:
        """The cubature elements' rest tangents K_e (E, nd, nd; central differences of the kernel,
        which is smooth) and the cubature's reduced rest stiffness sum_e w_e U_e^T K_e U_e (r, r)
        (with ``train_cubature(remainder=True)``: the exact U^T K U), computed once. They split the
        cubature forces into a linear part and the remainder g_e(v) - K_e v that
        :class:`ReducedNonlinearSimulator` refreshes a group at a time."""
        if getattr(self, "_cubature", None) is None:
            raise ModelError("no cubature yet: call train_cubature() first")
        if getattr(self, "_cubature_rest", None) is None or self._cubature_rest[0] is not self._cubature:
            data, w = self._cubature
            Ke = self._rest_tangents(data)
            Ue = data[0]
            K = np.einsum("eir,eij,ejs->rs", Ue * w[:, None, None], Ke, Ue, optimize=True)
            self._cubature_rest = (self._cubature, Ke, 0.5 * (K + K.T))
        return self._cubature_rest[1], self._cubature_rest[2]

    def _rest_tangents(self, data) -> np.ndarray:
        """The rest tangents K_e (E, nd, nd) of the elements of ``data`` (:meth:`_element_tangents`;
        at rest a shell's generalized moments' J = I)."""
        return self._element_tangents(np.zeros(data[0].shape[:2]), data)

    def _element_tangents(self, V: np.ndarray, data, central: bool = True, law=None) -> np.ndarray:
        """The tangents K_e (E, nd, nd) of the elements of ``data`` at their dofs V (E, nd),
        symmetric (the forces are an energy's gradient). The tets': the closed form
        (:func:`rtfem.reduction.tet_kernels.solid_element_tangents`), or the hyperelastic law's
        (:func:`rtfem.reduction.tet_kernels.law_tangents`). The shell triangles': differences
        of the kernel (smooth), central with a step of 1e-7 of the organ's size (truncation and
        round-off both ~1e-10 relative), or forward (half the kernel calls; ~1e-7 relative, for a
        step's linearization, which sets no equilibrium)."""
        E, nd = V.shape
        Ke = np.empty((E, nd, nd))
        if len(data) == 6:
            from .tet_kernels import law_tangents, solid_element_tangents

            return self._by_region(V, data, Ke, solid_element_tangents, law_tangents)
        if len(data) == 5:
            from .tet_kernels import law_tangents, solid_element_tangents

            law = self.law if law is None else law
            if law is not None:
                law_tangents(np.ascontiguousarray(V, dtype=float), *data[1:4], law, Ke)
            else:
                solid_element_tangents(np.ascontiguousarray(V, dtype=float), *data[1:], Ke)
            return Ke
        h = 1e-7 * self.system.size
        P = np.array(V, dtype=float)
        F0 = None if central else self._kernel_forces(P, data)
        for j in range(nd):
            P[:, j] = V[:, j] + h
            Fp = self._kernel_forces(P, data)
            if central:
                P[:, j] = V[:, j] - h
                Ke[:, :, j] = (Fp - self._kernel_forces(P, data)) / (2 * h)
            else:
                Ke[:, :, j] = (Fp - F0) / h
            P[:, j] = V[:, j]
        return 0.5 * (Ke + Ke.transpose(0, 2, 1))

    def tangent_change(self, q: np.ndarray, data, weights: np.ndarray, rest: np.ndarray,
                       rows: tuple | None = None, law=None) -> np.ndarray:
        """sum_e w_e U_e^T (K_e(U_e q) - K_e(0)) U_e (r, r): how far the tangent of the elements of
        ``data`` (weights ``weights``, rest tangents ``rest``) has moved from rest at q. Added to the
        cubature's rest stiffness (:meth:`cubature_rest`) it is the cubature forces' tangent at q,
        which :class:`ReducedNonlinearSimulator` linearizes its step about. ``rows``: the elements'
        rows in single precision (:func:`_projection_rows`), for the projection in float32 (half
        the time of its 2 r^2 nd E flops; ~1e-5 relative, as the single-precision forces). ``law``:
        as :meth:`_element_tangents`' (``rest`` then that law's rest tangents)."""
        Ue = data[0]
        E, nd, r = Ue.shape
        V = (Ue.reshape(-1, r) @ np.asarray(q, float)).reshape(E, nd)
        dK = (self._element_tangents(V, data, central=False, law=law) - rest) * np.asarray(weights, float)[:, None, None]
        if rows is not None and rows[0] is not None:
            U, UT = rows
            T = np.asarray(UT @ np.matmul(dK.astype(U.dtype), U.reshape(E, nd, r)).reshape(-1, r), dtype=float)
        else:
            T = Ue.reshape(-1, r).T @ np.matmul(dK, Ue).reshape(-1, r)
        return 0.5 * (T + T.T)

    def _training_poses(self, count: int, reach: float, rng) -> list[np.ndarray]:
        """``count`` random poses of the cubature's training (coordinates normal in the stiffness-orthonormal
        basis: the response to random loads), each scaled to move the organ by 0.25-1 ``reach`` times its size."""
        out = []
        for _ in range(count):
            q = rng.normal(size=self.size)
            out.append(q * rng.uniform(0.25, 1.0) * reach * self.system.size / np.abs(self.displacements(q)).max())
        return out

    def _held_out_error(self, poses: list, data, Ke, reach: float, elements: np.ndarray, weights: np.ndarray) -> float:
        """The cubature's relative force error on ``poses`` it was not fitted to (as the training error is
        measured: each pose's rows scaled to a unit sum): what it does away from its training set."""
        from .cubature import fit_error

        found = [self._pose_rows(q, data, Ke, reach) for q in poses]
        return fit_error(np.vstack([f[0] for f in found]), np.concatenate([f[1] for f in found]), elements, weights)

    def _pose_rows(self, q: np.ndarray, data, Ke, reach: float) -> tuple[np.ndarray, np.ndarray, int]:
        """One training pose of :meth:`rtfem.reduction.reduced.ReducedNonlinearModel.train_cubature`: (each element's reduced
        force (r, E) and their sum (r,), both scaled to a unit sum, the halvings it took): a pose that
        turns an element inside out (a law without energy there) is halved, up to 8 times."""
        E = data[0].shape[0]
        per = self._element_forces(q, data, np.ones(E), True, rest=Ke)  # (E, r)
        for shrunk in range(9):
            if np.isfinite(per).all():
                break
            if shrunk == 8:
                raise ModelError(f"cubature training: a pose turns elements inside out even at 1/256 of its size "
                                 f"(reach={reach:g}); the model's law ({self.law!r}) has no energy there")
            q = 0.5 * q
            per = self._element_forces(q, data, np.ones(E), True, rest=Ke)
        b = per.sum(axis=0)
        scale = 1.0 / np.linalg.norm(b)
        return per.T * scale, b * scale, shrunk

    # ---------------------------------------------------------------- a Prony law's step (rt.Prony)
    def viscous_forces(self, q: np.ndarray, data, weights: np.ndarray, history: np.ndarray,
                       dt: float, law=None) -> tuple[np.ndarray, np.ndarray]:
        """(sum_e w_e U_e^T f_e (r,), the history after the step): the step's algorithmic forces of
        the tets of ``data`` (a solid's five arrays) with the model's :class:`~rtfem.Prony` law at the
        end of a step dt from ``history`` (:func:`rtfem.fe.viscoelastic.prony_step`; its layout, for
        these elements in this order) at coordinates q, and the history that step leaves at q
        (:func:`rtfem.fe.viscoelastic.prony_commit`); compiled where it can be
        (:mod:`rtfem.reduction.prony_kernels`). ``law``: a region's Prony law instead of the model's."""
        from ..fe.viscoelastic import prony_commit, prony_step
        from .prony_kernels import prony_forces

        law = self.law if law is None else law

        Ue, X, G, wdet = data[:4]
        V = (Ue.reshape(-1, self.size) @ np.asarray(q, float)).reshape(Ue.shape[:2])
        F = np.empty(V.shape)
        new = prony_forces(V, X, G, wdet, law, history, dt, F)
        if new is None:
            x, Gs, ws = self._viscous_arguments(q, data)
            F, new = prony_step(law, x, Gs, ws, history, dt)[0], prony_commit(law, x, Gs, history, dt)
        F *= np.asarray(weights, float)[:, None]
        return F.reshape(-1) @ Ue.reshape(-1, self.size), new

    def _viscous_arguments(self, q: np.ndarray, data):
        """(deformed nodes (E, k, 3), each point's shape gradients (E, k, 3), each point's weights (E,))."""
        Ue, X, G, wdet = data[:4]
        E, k = X.shape[:2]
        x = X + (Ue.reshape(-1, self.size) @ np.asarray(q, float)).reshape(E, k, 3)
        return x, [np.ascontiguousarray(G[:, p]) for p in range(G.shape[1])], [wdet[:, p] for p in range(G.shape[1])]


def _projection_rows(Ue: np.ndarray, single: bool) -> tuple[np.ndarray | None, np.ndarray]:
    """The rows ``_element_forces`` takes for elements' basis rows Ue (E, nd, r): (U, UT), UT the
    (r, nd E) C-order copy that U^T F reads row-major; in single precision both float32 (U the
    (nd E, r) rows), in double U None (Ue itself is used)."""
    if single:
        U32 = Ue.reshape(-1, Ue.shape[2]).astype(np.float32)
        return U32, np.ascontiguousarray(U32.T)
    return None, np.ascontiguousarray(Ue.reshape(-1, Ue.shape[2]).T)
