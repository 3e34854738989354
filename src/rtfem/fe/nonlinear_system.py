"""The geometrically nonlinear system of a model: its corotational (or hyperelastic) internal forces
and consistent tangent on the free dofs over a :class:`Configuration`, and the limits of what its
elements describe (an element turned inside out, a shell triad turned too far), which no solver
accepts. Built by ``model.nonlinear()``; solved by :func:`rtfem.fe.nonlinear.solve_static` and
:class:`rtfem.drivers.nonlinear_newmark.NonlinearNewmarkSimulator`."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.spatial.transform import Rotation

from .assembly_kernels import _slot, node_pattern
from .jit import compiled
from .linalg import factorize
from .protocol import check_model
from .rotations import rotation
from ..errors import SolverError

__all__ = ["Configuration", "NonlinearSystem", "free_pattern", "LOCAL_ROTATION_LIMIT", "turn_refused", "inversion_refused"]


def free_pattern(cells: np.ndarray, dpn: int, free: np.ndarray, n_nodes: int):
    """The CSR pattern (indices, indptr; int32, sorted) on the free dofs ``free`` (sorted) of the elements
    ``cells`` (E, k) with ``dpn`` dofs per node numbered node-major, ``keep`` (the entries of the elements'
    (E, k dpn, k dpn) matrices, flattened, whose row and column are both free) and ``slot`` (each kept
    entry's place in the CSR data). Built from the node pattern (the pairs of nodes sharing an element,
    k^2 per element): free dof (a, i) holds, neighbour b by neighbour b (sorted), b's free dofs, so an
    entry's place is arithmetic (no sort of the E (k dpn)^2 entries: the 9k-tet liver's system 108 -> 26 ms).
    Where numba runs, the node pattern and the entries' places are compiled loops (a scalpel's cut model
    builds this at every cut: on that liver 37 -> 19 ms, medians of 7 alternating runs on 2 cores); numpy's
    otherwise, the same arrays (tests/verification/test_cut_zone.py)."""
    E, k = cells.shape
    cells = np.ascontiguousarray(cells, dtype=np.int64)
    isfree = np.zeros(n_nodes * dpn, dtype=bool)
    isfree[free] = True
    isfree = isfree.reshape(n_nodes, dpn)
    pos = np.full(n_nodes * dpn, -1, dtype=np.int64)
    pos[free] = np.arange(free.size)
    pos = pos.reshape(n_nodes, dpn)
    nfree = isfree.sum(axis=1)
    rank = np.cumsum(isfree, axis=1) - isfree  # a free dof's place among its node's free dofs
    kernel = compiled("free-slots", _free_slots, _slot)
    if kernel is not None:
        nptr, b_of = node_pattern(cells, n_nodes)  # the node pattern, row-major
        inverse = None
    else:
        pairs = (cells[:, :, None] * n_nodes + cells[:, None, :]).ravel()
        keys, inverse = np.unique(pairs, return_inverse=True)
        b_of = keys % n_nodes
        nptr = np.searchsorted(keys // n_nodes, np.arange(n_nodes + 1))
    deg = np.diff(nptr)
    width = nfree[b_of]  # each node pair's columns in its node row
    seen = np.concatenate([[0], np.cumsum(width)])
    row_len = seen[nptr[1:]] - seen[nptr[:-1]]
    col_off = seen[:-1] - np.repeat(seen[nptr[:-1]], deg)  # a pair's first column within its node row
    base = np.cumsum(nfree * row_len) - nfree * row_len  # where node a's first free row starts
    indptr = np.zeros(free.size + 1, dtype=np.int64)
    np.cumsum(np.repeat(row_len, nfree), out=indptr[1:])
    L = pos[b_of][isfree[b_of]]  # the columns of every node row, node row after node row
    L_start = np.cumsum(row_len) - row_len
    lens = np.repeat(row_len, nfree)
    take = np.repeat(np.repeat(L_start, nfree) - indptr[:-1], lens) + np.arange(int(indptr[-1]))
    indices = L[take]
    small = np.int32 if E * (k * dpn) ** 2 < 2**31 else np.int64  # (half the memory, and of a cut model sent between processes)
    if inverse is None:
        count = int((nfree[cells].sum(axis=1) ** 2).sum())
        keep, slot = np.empty(count, dtype=small), np.empty(count, dtype=small)
        kernel(cells, dpn, isfree, rank, row_len, base, nptr, b_of, col_off, keep, slot)
        return indices.astype(np.int32), indptr.astype(np.int32), keep, slot
    q = inverse.reshape(E, k, 1, k, 1)  # (e, la, i, lb, j) -> its node pair
    A = cells[:, :, None, None, None]
    B = cells[:, None, None, :, None]
    I, J = np.arange(dpn)[None, None, :, None, None], np.arange(dpn)[None, None, None, None, :]
    both = (isfree[A, I] & isfree[B, J]).ravel()
    slot = (base[A] + rank[A, I] * row_len[A] + col_off[q] + rank[B, J]).ravel()
    keep = np.flatnonzero(both)
    return indices.astype(np.int32), indptr.astype(np.int32), keep.astype(small), slot[keep].astype(small)


def _free_slots(cells, dpn, isfree, rank, row_len, base, nptr, b_of, col_off, keep, slot):
    """keep and slot of :func:`free_pattern` (in the order of the flattened element matrices), compiled."""
    E, k = cells.shape
    nd = k * dpn
    off = np.empty(k, np.int64)
    m = 0
    for e in range(E):
        for la in range(k):
            a = cells[e, la]
            for lb in range(k):  # where each neighbour's columns start in a's node row
                off[lb] = col_off[_slot(b_of, nptr[a], nptr[a + 1], cells[e, lb])]
            for i in range(dpn):
                if not isfree[a, i]:
                    continue
                row = base[a] + rank[a, i] * row_len[a]
                flat = (e * nd + la * dpn + i) * nd
                for lb in range(k):
                    b = cells[e, lb]
                    for j in range(dpn):
                        if isfree[b, j]:
                            keep[m] = flat + lb * dpn + j
                            slot[m] = row + off[lb] + rank[b, j]
                            m += 1


@dataclass
class Configuration:
    """A deformed state: translations u (n, 3) and, on a model with rotations, the nodal
    rotation matrices Q (n, 3, 3) (None on a solid)."""

    u: np.ndarray
    Q: np.ndarray | None

    @classmethod
    def rest(cls, n_nodes: int, rotations: bool) -> "Configuration":
        return cls(np.zeros((n_nodes, 3)), np.tile(np.eye(3), (n_nodes, 1, 1)) if rotations else None)

    def copy(self) -> "Configuration":
        return Configuration(self.u.copy(), None if self.Q is None else self.Q.copy())

    def update(self, delta: np.ndarray) -> None:
        """Add an increment of all dofs (n, dofs_per_node): translations add, rotations compose
        (Q <- exp([w]x) Q with the spins w)."""
        self.u += delta[:, :3]
        if self.Q is not None:
            moved = np.flatnonzero(np.any(delta[:, 3:] != 0, axis=1))
            if moved.size:
                self.Q[moved] = rotation(delta[moved, 3:]) @ self.Q[moved]

    def rotation_vectors(self) -> np.ndarray | None:
        """The nodal rotations as rotation vectors (n, 3) (None on a solid)."""
        return None if self.Q is None else Rotation.from_matrix(self.Q).as_rotvec()


class NonlinearSystem:
    """The assembled corotational internal forces and consistent tangent of a model on its
    free dofs (fixed dofs are eliminated; prescribed motions of them enter through the
    configuration). Built by ``model.nonlinear()``; the element kernel and connectivity come
    from the model's ``_corotational()``."""

    def __init__(self, model) -> None:
        check_model(model)
        model.check_restrained()
        self.model = model
        self.kernel, self.cells = model._corotational()
        self.dpn = model.dofs_per_node
        self.rotations = self.dpn == 6
        ne, k = self.cells.shape
        nd = k * self.dpn
        self.dofs = (self.dpn * self.cells[:, :, None] + np.arange(self.dpn)).reshape(ne, nd)
        self.free = model.free_dofs
        indices, indptr, self._keep, self._slot = free_pattern(self.cells, self.dpn, self.free, model.n_nodes)
        nf = self.free.size
        self._pattern = (indices, indptr, nf)
        self.size = float(np.ptp(model.mesh.vertices, axis=0).max())  # the model's extent (m)
        self.turned = 0.0  # the largest local rotation (degrees) a solve refused
        self.inverted = 0  # the most elements turned inside out in a configuration a solve refused

    def expand(self, values: np.ndarray) -> np.ndarray:
        """Values on the free dofs as (n, dofs_per_node), zero on the fixed ones."""
        full = np.zeros(self.model.n_dofs)
        full[self.free] = values
        return full.reshape(self.model.n_nodes, self.dpn)

    def evaluate(self, conf: Configuration, tangent: bool = True, history=None):
        """Internal forces on all dofs (n_dofs,), the tangent on the free dofs (sparse; None
        unless ``tangent``) and the strain energy. ``history``: a viscoelastic law's (the
        simulation's internal variables and its dt; :class:`rtfem.fe.viscoelastic.ViscoelasticTets`)."""
        X = np.asarray(self.model.mesh.vertices)
        x = (X + conf.u)[self.cells]
        if self.rotations:
            fe, Ke, energy = self.kernel.evaluate(x, conf.Q[self.cells], tangent)
        elif history is not None:
            fe, Ke, energy = self.kernel.evaluate(x, tangent, history)
        else:
            fe, Ke, energy = self.kernel.evaluate(x, tangent)
        f = self.gather(fe)
        K = None
        if tangent:
            K = self.tangent_matrix(Ke)
            patch = getattr(self.kernel, "patch_tangent", None)  # tet4-anp: the nodes' patches couple
            if patch is not None:
                K = (K + patch(x)[self.free][:, self.free]).tocsr()
        return f, K, float(energy.sum())

    def gather(self, fe: np.ndarray) -> np.ndarray:
        """The element forces (m, k dofs_per_node) summed at the model's dofs (n_dofs,)."""
        return np.bincount(self.dofs.ravel(), weights=fe.ravel(), minlength=self.model.n_dofs)

    def tangent_matrix(self, Ke: np.ndarray) -> sp.csr_matrix:
        """The element tangents (m, nd, nd) assembled on the free dofs (CSR, the system's pattern, its
        ``indices`` and ``indptr`` arrays themselves): compiled, the GIL released (np.bincount holds it
        for the whole sum, 1.3M entries on a 9k-tet liver: a haptic tick's wait beside a refreshing step)."""
        indices, indptr, nf = self._pattern
        fn = compiled("assemble-slots", _add_at_slots)
        if fn is None:
            data = np.bincount(self._slot, weights=Ke.reshape(-1)[self._keep], minlength=indices.size)
        else:
            data = np.zeros(indices.size)
            fn(self._slot, self._keep, np.ascontiguousarray(Ke).reshape(-1), data)
        return sp.csr_matrix((data, indices, indptr), shape=(nf, nf))

    def deformed(self, conf: Configuration) -> np.ndarray:
        """The elements' deformed nodes (m, k, 3) of a configuration."""
        return (np.asarray(self.model.mesh.vertices) + conf.u)[self.cells]

    def resolution(self, conf: Configuration) -> float:
        """The smallest correction that still moves a node (m): 1e-12 of the model's extent, or a few
        units in the last place of its farthest coordinate where that is coarser (a model carried 1 km
        from the origin is resolved to 1e-12 m at best)."""
        far = float(np.abs(np.asarray(self.model.mesh.vertices) + conf.u).max())
        return max(1e-12 * self.size, 8.0 * np.finfo(float).eps * far)

    def energy(self, conf: Configuration) -> float:
        """The strain energy of a configuration."""
        return self.evaluate(conf, tangent=False)[2]

    def local_rotation(self, conf: Configuration) -> float:
        """The largest rotation (degrees) of a shell's nodal triad relative to an element's
        corotated frame (0 on a solid, whose polar decomposition has no such limit)."""
        if not self.rotations:
            return 0.0
        X = np.asarray(self.model.mesh.vertices)
        return float(self.kernel.local_rotations((X + conf.u)[self.cells], conf.Q[self.cells]).max())

    def within_limit(self, conf: Configuration) -> bool:
        """Whether the elements describe the configuration: no solid element turned inside out
        (det F <= 0 at a quadrature point or a tet10 corner) and no shell triad turned
        :data:`LOCAL_ROTATION_LIMIT` degrees from an element frame. The most elements inverted and the
        largest turn refused are kept in ``inverted`` and ``turned`` (for the error message). No solver
        reports convergence on a configuration outside the limit."""
        if not self.rotations:
            bad = int(np.count_nonzero(self.kernel.inverted(self.deformed(conf))))
            self.inverted = max(self.inverted, bad)
            return bad == 0
        angle = self.local_rotation(conf)
        if angle >= LOCAL_ROTATION_LIMIT:
            self.turned = max(self.turned, angle)
            return False
        return True

    def solver(self, K: sp.csr_matrix, what: str, spd_only: bool = False, refactorable: bool = False, dofs=None):
        """A factorization of a tangent: Cholesky when it is symmetric (solids, and shells at
        rest), LU otherwise (a shell's spin tangent off equilibrium). ``spd_only``: Cholesky or a
        SolverError (a symmetric matrix that must be positive definite). ``dofs``: the model dofs K
        is over, when fewer than the free ones (for the fill-reducing order)."""
        on = self.free if dofs is None else dofs
        order = lambda: self.model.dof_order(on)  # noqa: E731
        if spd_only:
            return factorize(K, spd=True, what=what, order=order, refactorable=refactorable)
        sym = abs(K - K.T).max() <= 1e-12 * abs(K).max()
        if sym:
            try:
                return factorize(K, spd=True, what=what, order=order, refactorable=refactorable)
            except SolverError:
                pass  # indefinite (past a limit point, or compressed): LU below
        return factorize(K, spd=False, what=what, order=order)


# a shell triad may turn at most this far (degrees) from an element's corotated frame: the
# element's rotational deformation is the rotation vector (log map) of that turn, exact up to 180
# degrees, where its axis flips and a turn beyond costs less than it should (its derivatives grow
# without bound on the way); an equilibrium beyond is not accepted
LOCAL_ROTATION_LIMIT = 150.0


def turn_refused(turned: float) -> str:
    """Why a step that turns a shell triad ``turned`` degrees is refused, and what to do (the static
    solver's and the corotational Newmark simulator's messages)."""
    return (f"shell triad turned {turned:.0f} degrees from an element's frame, past the {LOCAL_ROTATION_LIMIT:.0f} the "
            "corotational shell describes: a kink sharper than the mesh can turn, as at a vertex pulled alone; spread "
            "the load over more nodes or refine the mesh there")


def inversion_refused(count: int) -> str:
    """Why a state with ``count`` elements turned inside out is refused, and what to do (the static
    solver's and the corotational Newmark simulator's messages)."""
    return (f"{count} element{'s' if count != 1 else ''} turned inside out (det F <= 0): no equilibrium of the "
            "material there; a support or tool moved through the tissue, or a load too concentrated for the mesh. "
            "Move it less, spread it over more nodes, or refine the mesh there")


def _add_at_slots(slot, keep, values, data):
    """data[slot[i]] += values[keep[i]]: the element tangents' entries summed into the pattern's slots, in
    order (np.bincount's sums)."""
    for i in range(slot.shape[0]):
        data[slot[i]] += values[keep[i]]
