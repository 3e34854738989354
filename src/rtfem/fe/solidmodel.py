"""SolidModel: a tetrahedral solid (3 translations per node) through the Model protocol.

The same fixes, loads, constrained systems, factorization and static solves as the shell
(:class:`rtfem.fe.model.FEModel`); the element math is in :mod:`rtfem.fe.solid`. The surface that is
drawn and touched is the tet mesh's boundary over the model's own node numbering.
"""

from __future__ import annotations

import time
from typing import Mapping

import numpy as np
import scipy.sparse as sp

from . import solid
from .assembly import assemble_blocks, assemble_solid
from .. import validate
from ..errors import ModelError
from .hyperelastic import Hyperelastic
from .material import Material
from .model import FEModel
from .regions import RegionTets, linear_materials, region_materials
from ..mesh.tetmesh import TET10_EDGES, TetMesh

__all__ = ["SolidModel"]

_CHUNK = 8192  # tets per batch during assembly (a 10-node tet's stiffness is 30 x 30)


class SolidModel(FEModel):
    """Linear elastic tetrahedral finite-element model of a volume (3 dof per node).

    Parameters
    ----------
    mesh : a :class:`~rtfem.TetMesh` (``rt.load_mesh`` of a volume file, or ``rt.tetrahedralize``).
    material : :class:`~rtfem.Material` (E, nu, density; the thickness is not used), or a
        hyperelastic law (:class:`~rtfem.NeoHookean`, :class:`~rtfem.MooneyRivlin`,
        :class:`~rtfem.Ogden`): the full-order nonlinear solvers (``rt.nonlinear.solve_static``,
        the corotational and Newmark simulators) use the law, the linear ones (modes, statics,
        SLDM, maps) its linearization at rest (``law.linearized()``, kept as ``model.material``).
        Or, for a mesh of several regions (``mesh.labels``), ``{label or region name: material or
        law}``, one for each region (:mod:`rtfem.fe.regions`): kept as :attr:`materials`; such a
        model has no single ``material``.
    element : "tet4" (linear, constant strain; stiff in bending and near incompressibility),
        "tet10" (quadratic; a 4-node mesh gets mid-edge nodes added, :meth:`TetMesh.quadratic`) or
        "tet4-anp" (tet4 with an averaged nodal pressure, :func:`rtfem.fe.solid.anp_volumetric`:
        no volumetric locking on the 4-node mesh; in the full-order nonlinear solvers with a
        hyperelastic law, :mod:`rtfem.fe.anp`; not in the reduced nonlinear model).
    mass : "lumped" (diagonal, the paper's M; default) or "consistent" (rho int N^T N). With a
        consistent mass the modal route uses it as it is (the eigen-solve takes ARPACK's
        generalized mode); SLDM and the central-difference simulator need a diagonal M and ask
        for ``mass='lumped'``.
    constraints, penalty : as for :class:`~rtfem.ShellModel`.

    Raises
    ------
    ModelError
        A mesh that is not a TetMesh, a material that is not a Material, an unknown element,
        mass or constraints.
    MeshError
        Inverted or degenerate tets (a non-positive Jacobian at a quadrature point).
    """

    dofs_per_node = 3  # x, y, z

    def __init__(self, mesh: TetMesh, material: Material, *, element: str = "tet4", mass: str = "lumped",
                 constraints: str = "elimination", penalty: float = 1e8) -> None:
        if not isinstance(mesh, TetMesh):
            raise ModelError(f"mesh must be an rtfem TetMesh, got {type(mesh).__name__}; use rt.load_mesh on a volume "
                             "file or rt.tetrahedralize(surface)")
        self.law = None  # a hyperelastic law (full-order nonlinear solves), its linear twin the Material
        self.materials = None  # {label: Material or law} of a model of several regions
        if isinstance(material, Mapping) and isinstance(mesh, TetMesh):
            material = self._regions(mesh, material, element)
        if isinstance(material, Hyperelastic):
            self.law, material = material, material.linearized()
        if not isinstance(material, Material):
            raise ModelError(f"material must be an rtfem Material or a hyperelastic law (rt.NeoHookean, "
                             f"rt.MooneyRivlin, rt.Ogden), got {type(material).__name__}")
        validate.choice(element, "element", solid.ELEMENTS)
        validate.choice(mass, "mass", solid.MASSES)
        penalty = self._check_constraints(constraints, penalty)
        if element == "tet10":
            mesh = mesh.quadratic()
        elif mesh.order == 2:
            raise ModelError("element='tet4' on a mesh of 10-node tets: use element='tet10', or mesh.linear() for the "
                             "4-node mesh of its corners")
        self.tetmesh = mesh
        self.element = element
        self.mass = mass
        self._setup(mesh.surface, material, constraints, penalty)

    def _regions(self, mesh: TetMesh, materials: Mapping, element: str):
        """Keep a mesh's regions' materials (:attr:`materials`); the one material of a mesh of one region."""
        given = region_materials(materials, mesh)
        if len(given) == 1:
            return next(iter(given.values()))
        if element == "tet4-anp":
            raise ModelError("element='tet4-anp' averages the pressure at the nodes, which would mix the regions' bulk "
                             "moduli at their interface: a mesh of several regions takes element='tet10' (or 'tet4')")
        self.materials = given
        return linear_materials(given)[next(iter(given))]  # what FEModel keeps; `material` refuses to answer

    @property
    def material(self) -> Material:
        """The model's linear material (a law's linearization at rest). A model of several regions
        has none: its regions' are in :attr:`materials` (a ModelError says so)."""
        if self.materials is not None:
            raise ModelError(f"this solid has {len(self.materials)} regions, each with its own material: read "
                             "model.materials[label] (what needs one material for the whole model does not take a "
                             "model of several regions)")
        return self._material

    @material.setter
    def material(self, value: Material) -> None:
        self._material = value

    def _linear_regions(self) -> list[tuple[np.ndarray | None, Material]]:
        """(tets, linear material) per region; (None, material) for a model of one material."""
        if self.materials is None:
            return [(None, self._material)]
        labels = np.asarray(self.tetmesh.labels)
        return [(np.flatnonzero(labels == k), mat) for k, mat in linear_materials(self.materials).items()]

    @property
    def metadata(self) -> dict:
        """What a saved basis or map records about the model."""
        out = {"model": "solid", "element": self.element, "mass": self.mass, "constraints": self.constraints}
        if self.materials is not None:
            out["regions"] = {str(k): repr(v) for k, v in self.materials.items()}
        return out

    def __repr__(self) -> str:
        nf = int(self.fixed.any(axis=1).sum())
        return (f"SolidModel({self.n_nodes} nodes, {self.tetmesh.n_tets} {self.element} tets, {self.n_dofs} dof, "
                f"{nf} nodes fixed, mass={self.mass!r}, constraints={self.constraints!r})")

    # ------------------------------------------------------------ assembly
    def _assemble(self) -> None:
        t0 = time.perf_counter()
        X = np.asarray(self.tetmesh.vertices)
        K, lumped, Mc = None, np.zeros(self.n_nodes), None
        for tets, material in self._linear_regions():  # a region's elements with its constants, summed
            T = np.asarray(self.tetmesh.tets) if tets is None else np.asarray(self.tetmesh.tets)[tets]
            done = self._assemble_compiled(X, T, material) if self.mass == "lumped" else None
            Kr, lumped_r, Mr = done if done is not None else self._assemble_numpy(X, T, material)
            K, lumped = (Kr if K is None else (K + Kr).tocsr()), lumped + lumped_r
            Mc = Mr if Mc is None else Mc + Mr
        if self.element == "tet4-anp":  # the volumetric part: one pressure per node
            K = K + solid.anp_volumetric(X, np.asarray(self.tetmesh.tets), self.material, self.n_nodes)
            K = ((K + K.T) * 0.5).tocsr()
        if Mc is not None:
            Mc = ((Mc + Mc.T) * 0.5).tocsr()
            self._Mc = sp.kron(Mc, sp.identity(3), format="csr")
        self._K, self._M = K, np.repeat(lumped, 3)
        self.timings["assemble"] = time.perf_counter() - t0

    def _assemble_numpy(self, X: np.ndarray, T: np.ndarray, material: Material):
        """The stiffness, the lumped nodal masses and the consistent node mass matrix (None unless
        asked for) of the tets T of one material, from batched element matrices."""
        ne, k = T.shape
        kdata, mdata = [], []
        lumped = np.zeros(self.n_nodes)
        for s in range(0, ne, _CHUNK):
            c = slice(s, min(s + _CHUNK, ne))
            Ke, Me = solid.element_matrices(X[T[c]], material, self.element, self.mass)
            kdata.append(Ke)
            if self.mass == "consistent":
                mdata.append(Me.reshape(-1))
                lumped_e = _hrz(Me) if self.element == "tet10" else Me.sum(axis=2)
            else:
                lumped_e = np.einsum("mii->mi", Me)
            lumped += np.bincount(T[c].ravel(), lumped_e.ravel(), minlength=self.n_nodes)
        Mn = None
        if self.mass == "consistent":
            r = np.repeat(T, k, axis=1).ravel()
            c = np.tile(T, (1, k)).ravel()
            Mn = sp.coo_matrix((np.concatenate(mdata), (r, c)), shape=(self.n_nodes, self.n_nodes)).tocsr()
        return assemble_blocks(T, np.concatenate(kdata), self.n_nodes, 3), lumped, Mn  # exactly symmetric

    def _assemble_compiled(self, X: np.ndarray, T: np.ndarray, material: Material):
        """The stiffness of the tets T of one material in one compiled pass and the lumped nodal
        masses (and None: no consistent mass), or None where numba does not run."""
        done = assemble_solid(X, T, *solid.stiffness_rule(self.element), *solid.element_lame(material, self.element),
                              self.n_nodes)
        if done is None:
            return None
        K, vol = done
        lumped = np.zeros(self.n_nodes)
        for s in range(0, T.shape[0], _CHUNK):
            c = slice(s, min(s + _CHUNK, T.shape[0]))
            Me = solid.element_mass(X[T[c]], material, self.element, "lumped", vol[c])
            lumped += np.bincount(T[c].ravel(), np.einsum("mii->mi", Me).ravel(), minlength=self.n_nodes)
        return K, lumped, None

    @property
    def M(self) -> sp.csr_matrix:
        """The global mass matrix: diagonal (lumped) or the consistent one."""
        if self.mass == "lumped":
            return sp.diags(self.mass_diagonal, format="csr")
        if self._K is None:
            self._assemble()
        return self._Mc

    def constrained_mass(self) -> tuple[sp.csr_matrix, np.ndarray]:
        """The mass (lumped or consistent, as built) on the dofs of :meth:`constrained_stiffness`."""
        dofs = self.free_dofs if self.constraints == "elimination" else np.arange(self.n_dofs)
        return self.M[dofs][:, dofs].tocsr(), dofs

    def _distribute(self, T: np.ndarray, per_face: np.ndarray) -> np.ndarray:
        """Consistent nodal forces of a uniform load: a third to each corner of a linear face; on a
        6-node face (tet10) nothing to the corners and a third to each mid-edge node."""
        if self.element != "tet10":
            return super()._distribute(T, per_face)
        out = np.zeros((self.n_nodes, 3))
        for a, b in ((0, 1), (1, 2), (2, 0)):
            np.add.at(out, self._mid_node(T[:, a], T[:, b]), per_face / 3.0)
        return out

    def _edge_mids(self) -> tuple[np.ndarray, np.ndarray]:
        """(keys, mids) of the tet10 corner edges: key i n + j (i < j), and its mid-edge node."""
        if "mid" not in self._cache:
            T = np.asarray(self.tetmesh.tets)
            e = np.sort(T[:, TET10_EDGES].reshape(-1, 2), axis=1)
            keys, first = np.unique(e[:, 0] * self.n_nodes + e[:, 1], return_index=True)
            self._cache["mid"] = (keys, T[:, 4:].ravel()[first])
        return self._cache["mid"]

    def _mid_node(self, i: np.ndarray, j: np.ndarray) -> np.ndarray:
        """The mid-edge nodes (tet10) of the corner edges (i, j)."""
        keys, mids = self._edge_mids()
        want = np.minimum(i, j) * self.n_nodes + np.maximum(i, j)
        return mids[np.searchsorted(keys, want)]

    def fix(self, nodes, dofs="all") -> "SolidModel":
        """As :meth:`ShellModel.fix`; on tet10 a mid-edge node whose two corners are both fixed in a
        dof is fixed in it too (a face clamped by its corner indices, e.g. those of the 4-node mesh
        it was made from, is clamped along its edges, not left with free mid-edge nodes: a
        cantilever clamped so deflected 11 % more than one clamped by region)."""
        super().fix(nodes, dofs)
        if self.element == "tet10":
            keys, mids = self._edge_mids()
            i, j = keys // self.n_nodes, keys % self.n_nodes
            for d in np.flatnonzero(self._dof_mask(dofs)):
                self.fixed[mids[self.fixed[i, d] & self.fixed[j, d]], d] = True
        return self

    def complete_motion(self, P: np.ndarray) -> np.ndarray:
        """A prescribed motion (n, 3) of fixed dofs, completed where :meth:`fix` held nodes the user did
        not name: on tet10, a mid-edge node held because its two corners are held (and given no motion
        of its own, zero) moves with the mean of its corners' motions in that dof, the straight edge
        a quadratic element keeps under a motion given at its corners. Without this a jaw's corners
        moved 2.25 mm pulled against mid-edge nodes left at rest: 13.6 N against CalculiX's 0.09 N.
        A mid-edge node given a motion of its own keeps it. Returns a new array."""
        P = np.array(P, dtype=float)
        if self.element != "tet10" or not P.any():
            return P
        keys, mids = self._edge_mids()
        i, j = keys // self.n_nodes, keys % self.n_nodes
        for d in range(3):
            follow = self.fixed[i, d] & self.fixed[j, d] & self.fixed[mids, d] & (P[mids, d] == 0.0)
            P[mids[follow], d] = 0.5 * (P[i[follow], d] + P[j[follow], d])
        return P

    def _node_graph(self) -> sp.csr_matrix:
        return self.tetmesh.adjacency()

    def rotation_field(self, U: np.ndarray) -> np.ndarray:
        """The infinitesimal rotations (n, 3, k) of translation fields U (n, 3, k): half the curl,
        per tet at its centroid, averaged to the nodes by volume."""
        U = np.asarray(U, float)
        if "curl" not in self._cache:
            T = np.asarray(self.tetmesh.tets)
            X = np.asarray(self.tetmesh.vertices)[T]
            dN = solid.shape_functions(self.element, np.full((1, 3), 0.25))[1][0]
            G, det = solid._gradients(X, dN)
            w = np.bincount(T.ravel(), weights=np.repeat(det, T.shape[1]), minlength=self.n_nodes)
            self._cache["curl"] = (T, G, det, w)
        T, G, det, w = self._cache["curl"]
        H = np.einsum("miar,mib->mabr", U[T], G)  # du_a / dX_b per tet and field
        curl = 0.5 * np.stack([H[:, 2, 1] - H[:, 1, 2], H[:, 0, 2] - H[:, 2, 0], H[:, 1, 0] - H[:, 0, 1]], axis=1)
        out = np.zeros_like(U)
        for i in range(T.shape[1]):
            np.add.at(out, T[:, i], det[:, None, None] * curl)
        return out / np.maximum(w, 1e-300)[:, None, None]

    def _corotational(self) -> tuple[solid.CorotationalTets, np.ndarray]:
        """The corotational element kernel and the cells (tets) it acts on."""
        T = np.asarray(self.tetmesh.tets)
        X = np.asarray(self.tetmesh.vertices)[T]
        if self.element == "tet4-anp":
            from .anp import AnpTets
            from .viscoelastic import Prony

            if self.law is None or isinstance(self.law, Prony):
                raise ModelError("element='tet4-anp' in the nonlinear solvers averages a hyperelastic law's volumetric "
                                 "energy kappa / 2 (J - 1)^2 at the nodes: give rt.NeoHookean, rt.MooneyRivlin or "
                                 "rt.Ogden (a linear material's twin: rt.NeoHookean(mu=E / (2 (1 + nu)), kappa=E / "
                                 "(3 (1 - 2 nu)))), or take element='tet10' (no locking either)")
            return AnpTets(X, self.law, T, self.n_nodes), T
        if self.materials is not None:
            return RegionTets(X, np.asarray(self.tetmesh.labels), self.materials, self.element), T
        if self.law is not None:
            return self.law.tets(X, self.element), T
        return solid.CorotationalTets(X, self.material, self.element), T

    def _pieces(self) -> tuple[int, np.ndarray]:
        return self.tetmesh.components()


def _hrz(Me: np.ndarray) -> np.ndarray:
    """HRZ lumping of consistent element masses (m, k, k): the diagonal scaled to the element mass."""
    d = np.einsum("mii->mi", Me)
    return d * (Me.sum(axis=(1, 2)) / d.sum(axis=1))[:, None]
