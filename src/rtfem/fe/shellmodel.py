"""ShellModel: the linear shell model of a triangulated surface (6 dof per node) on
:class:`~rtfem.fe.model.FEModel`'s assembly, supports, condensation and static solves."""

from __future__ import annotations

import time

import numpy as np
import scipy.sparse as sp

from . import shell
from .assembly import assemble_blocks, assemble_shell
from .. import validate
from ..errors import ModelError
from .material import Material
from ..mesh.surface import TriMesh

from .model import _CHUNK, FEModel

__all__ = ["ShellModel"]


class ShellModel(FEModel):
    """Linear shell finite-element model of a triangulated surface (6 dof per node).

    Parameters
    ----------
    mesh : the surface.
    material : :class:`~rtfem.Material`.
    membrane : "opt" (Felippa's optimal drilling triangle, default) or "cst" (constant strain +
        fictitious drilling spring; for comparison only, it locks in in-plane bending).
    rotary_inertia : give the rotations mass rho t^3/12 * A/3 (default: massless rotations,
        as the paper's condensation assumes).
    constraints : "elimination" (fixed dofs removed, default) or "penalty" (the paper's method:
        diagonal of K and rows of F at fixed dofs multiplied by ``penalty``).
    penalty : the penalty factor. It multiplies each fixed dof's own diagonal stiffness, so it
        is relative and scales with the organ's stiffness by construction: the default 1e8
        leaves ~1e-8 relative motion at the supports on any mesh, and 1e4 .. 1e16 agree with
        elimination to that order.

    Raises
    ------
    ModelError
        A mesh that is not a TriMesh, a material that is not a Material, an unknown membrane or
        constraints, a penalty that is not a factor > 1. (Degenerate triangles never get here:
        :class:`~rtfem.TriMesh` removes or refuses them.)
    """

    def __init__(
        self,
        mesh: TriMesh,
        material: Material,
        *,
        membrane: str = "opt",
        rotary_inertia: bool = False,
        constraints: str = "elimination",
        penalty: float = 1e8,
    ) -> None:
        if not isinstance(mesh, TriMesh):
            raise ModelError(f"mesh must be an rtfem TriMesh, got {type(mesh).__name__}; use rt.load_mesh or rt.TriMesh")
        if not isinstance(material, Material):
            hint = (": the hyperelastic laws are for solids (rt.SolidModel of a tet mesh, or --solid); a shell takes "
                    "an rt.Material (law.linearized() for its linear twin)") if hasattr(material, "linearized") else ""
            raise ModelError(f"material must be an rtfem Material, got {type(material).__name__}{hint}")
        validate.choice(membrane, "membrane", shell.MEMBRANES)
        penalty = self._check_constraints(constraints, penalty)
        rotary_inertia = validate.flag(rotary_inertia, "rotary_inertia")
        self.membrane = membrane
        self.rotary_inertia = bool(rotary_inertia)
        self._setup(mesh, material, constraints, penalty)

    # ------------------------------------------------------------ sizes
    dofs_per_node = 6  # x, y, z, rx, ry, rz

    @property
    def metadata(self) -> dict:
        """What a saved basis or map records about the model."""
        return {"model": "shell", "membrane": self.membrane, "constraints": self.constraints}

    def __repr__(self) -> str:
        nf = int(self.fixed.any(axis=1).sum())
        return (
            f"ShellModel({self.n_nodes} nodes, {self.mesh.n_triangles} triangles, {self.n_dofs} dof, "
            f"{nf} nodes fixed, membrane={self.membrane!r}, constraints={self.constraints!r})"
        )

    # ------------------------------------------------------------ assembly (Eq. 3)
    def _assemble(self) -> None:
        t0 = time.perf_counter()
        T = np.asarray(self.mesh.triangles)
        X = np.asarray(self.mesh.vertices)
        done = assemble_shell(X, T, self.material, self.n_nodes) if self.membrane == "opt" else None
        self._K, area = done if done is not None else self._assemble_numpy(X, T)  # compiled: straight into CSR
        dofs = 6 * T[:, :, None] + np.arange(6)[None, None, :]
        me = shell.element_mass(area, self.material, self.rotary_inertia)
        self._M = np.bincount(dofs.ravel(), np.tile(me, (1, 3)).ravel(), minlength=self.n_dofs)
        self.timings["assemble"] = time.perf_counter() - t0

    def _assemble_numpy(self, X: np.ndarray, T: np.ndarray) -> tuple[sp.csr_matrix, np.ndarray]:
        """The stiffness from batched element matrices, and the triangles' areas."""
        data, areas = [], []
        for s in range(0, T.shape[0], _CHUNK):
            R, xy, area = shell.local_frames(X[T[s:s + _CHUNK]])
            data.append(shell.to_global(shell.local_stiffness(xy, area, self.material, self.membrane), R))
            areas.append(area)
        return assemble_blocks(T, np.concatenate(data), self.n_nodes, 6), np.concatenate(areas)  # exactly symmetric

    def _node_graph(self) -> sp.csr_matrix:
        return self.mesh.adjacency()

    def rotation_field(self, U: np.ndarray) -> np.ndarray:
        """The nodal rotations (n, 3, k) that go with translation fields U (n, 3, k) (mode shapes)
        when the moments are zero: the rotations the condensation eliminates (Eq. 4),
        -K_rr^-1 K_rt U_t. Fixed rotations read zero."""
        c = self.condensation()
        U = np.asarray(U, float)
        out = np.zeros_like(U)
        if c.Krr is None:
            return out
        Ut = U[c.t // 6, c.t % 6]
        out[c.r // 6, c.r % 6 - 3] = -c.Krr.solve(c.Krt @ Ut)
        return out

    def _corotational(self) -> tuple[shell.CorotationalTriangles, np.ndarray]:
        """The corotational element kernel and the cells (triangles) it acts on."""
        T = np.asarray(self.mesh.triangles)
        return shell.CorotationalTriangles(np.asarray(self.mesh.vertices)[T], self.material, self.membrane), T

    def _pieces(self) -> tuple[int, np.ndarray]:
        return self.mesh.components()
