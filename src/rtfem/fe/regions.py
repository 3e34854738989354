"""Solids of several regions, each with its own material: a tumour stiffer than the liver around
it, a vessel wall, a layer of fat (issue 58).

A :class:`~rtfem.TetMesh` carries a region label per tet (``mesh.labels``; read from a Gmsh
physical group, a MEDIT reference, a VTU 'region' field or Abaqus element sets). A
:class:`~rtfem.SolidModel` given ``{label or region name: material or law}`` builds each region's
elements with its own law; the regions share their interface nodes, so the mesh stays one
conforming body. Every operator is a sum over elements, so a region is a subset of the elements
with its own constants:

- the linear stiffness and mass: each region's elements assembled with its Lame constants and
  density, the matrices summed (:func:`linear_materials`);
- the nonlinear solvers (full order, static and dynamic): :class:`RegionTets`, each region's
  elements evaluated by its own law's kernel (the corotated linear material for a
  :class:`~rtfem.Material`, the hyperelastic law's otherwise) and the results put back in the
  mesh's element order.

  A region of a :class:`~rtfem.Prony` law carries its own history (its quadrature points' Q_i and
  S_iso), a segment of the whole's, stepped by the full-order dynamics.
- the reduced nonlinear model: regions of :class:`~rtfem.Material` (Lame constants per element in
  its compiled kernels) and of hyperelastic laws (each region's elements by its law's kernels), its
  cubature fitted per region.

Not yet with regions (refused with the reason): the averaged-nodal-pressure tet4 (``tet4-anp``,
whose nodal pressure would mix two bulk moduli), Prony regions in the reduced nonlinear model.
"""

from __future__ import annotations

from typing import Mapping

import numpy as np

from ..errors import ModelError
from .hyperelastic import Hyperelastic
from .material import Material

__all__ = ["region_materials", "linear_materials", "RegionTets"]


def region_materials(materials: Mapping, mesh) -> dict[int, object]:
    """``{label: Material or law}`` for every region of ``mesh``, from a mapping by label (an int)
    or by region name (``mesh.region_names``); a text key is a region's name first, else the label
    it spells (a name that spells another region's label is refused as ambiguous). Raises ModelError for a region left without a
    material, a key that names no region, or a value that is not a material or law."""
    if not materials:
        raise ModelError("materials={} gives no material: give {label: rt.Material(...) or a law} for each region")
    names, present = dict(mesh.region_names), set(mesh.regions.tolist())
    out: dict[int, object] = {}
    for key, value in materials.items():
        spelled = int(key) if isinstance(key, str) and key.lstrip("-").isdigit() else None  # a file's or a CLI's "2"
        if isinstance(key, str) and key in names:
            label = names[key]
            if spelled is not None and spelled in present and spelled != label:
                raise ModelError(f"{key!r} is the name of region {label} and the label of another region: name that "
                                 "region by another of its names, or rename it in the file")
        elif spelled is not None:
            label = spelled
        elif isinstance(key, (int, np.integer)) and not isinstance(key, bool):
            label = int(key)
        else:
            known = ", ".join(f"{n!r} = {v}" for n, v in names.items()) or "none"
            raise ModelError(f"material key {key!r} names no region: give a region label (an int; this mesh has "
                             f"{sorted(present)}) or a region name (this mesh's: {known})")
        if label not in present:
            raise ModelError(f"material for region {key!r}: no tet of this mesh has label {label} (its labels: "
                             f"{sorted(present)})")
        if label in out:
            other = {v: k for k, v in names.items()}.get(label)
            raise ModelError(f"region {label}{f' ({other!r})' if other else ''} is given two materials (by its name and "
                             "its label, or twice)")
        if not isinstance(value, (Material, Hyperelastic)):
            raise ModelError(f"region {key!r}: the material must be an rt.Material or a hyperelastic law (rt.NeoHookean, "
                             f"rt.MooneyRivlin, rt.Ogden, or rt.Prony on one), got {type(value).__name__}")
        out[label] = value
    missing = sorted(present - set(out))
    if missing:
        raise ModelError(f"the mesh's regions {missing} have no material ({_count(mesh, missing)}): give one for every "
                         f"label in mesh.regions ({sorted(present)})")
    return dict(sorted(out.items()))


def _count(mesh, labels) -> str:
    return ", ".join(f"{int(np.sum(mesh.labels == k))} tets with label {k}" for k in labels)


def linear_materials(materials: Mapping[int, object]) -> dict[int, Material]:
    """Each region's linear material (a law's linearization at rest)."""
    return {k: (v.linearized() if isinstance(v, Hyperelastic) else v) for k, v in materials.items()}


class RegionTets:
    """The tets of a mesh of several regions, each region's evaluated by its own kernel (the
    corotated linear material, :class:`~rtfem.fe.solid.CorotationalTets`, or a law's tets), in the
    mesh's element order.

    ``parts``: (element indices, kernel) per region; ``laws``: (element indices, law or None for
    the corotated linear material); ``G``, ``wdet``: per quadrature point, every element's shape
    gradients (m, k, 3) and weights (m,); ``lm`` (m, 2): every element's Lame constants (a law's at
    rest)."""

    def __init__(self, X: np.ndarray, labels: np.ndarray, materials: Mapping[int, object], element: str) -> None:
        from .solid import CorotationalTets, _lame

        m = X.shape[0]
        self.parts, self.laws = [], []
        self.lm = np.zeros((m, 2))
        for label, law in materials.items():
            idx = np.flatnonzero(labels == label)
            lin = law.linearized() if isinstance(law, Hyperelastic) else law
            kern = law.tets(X[idx], element) if isinstance(law, Hyperelastic) else CorotationalTets(X[idx], lin, element)
            self.parts.append((idx, kern))
            self.laws.append((idx, law if isinstance(law, Hyperelastic) else None))
            self.lm[idx] = _lame(lin)
        self.G = [self._spread(lambda k, q=q: k.G[q], (X.shape[1], 3)) for q in range(len(self.parts[0][1].G))]
        self.wdet = [self._spread(lambda k, q=q: k.wdet[q], ()) for q in range(len(self.parts[0][1].wdet))]

    def _spread(self, part_array, shape: tuple) -> np.ndarray:
        """An array over all elements from each part's (its elements' rows)."""
        out = np.zeros((sum(idx.size for idx, _ in self.parts),) + shape)
        for idx, kern in self.parts:
            out[idx] = part_array(kern)
        return out

    def check_gradients(self, k: int) -> list[np.ndarray]:
        """The gradients the inversion check looks at (quadrature points, a tet10's corners too), the
        regions' spread over all elements."""
        n = len(self.parts[0][1].check_gradients(k))
        return [self._spread(lambda kern, q=q: kern.check_gradients(k)[q], self.G[0].shape[1:]) for q in range(n)]

    def inverted(self, x: np.ndarray) -> np.ndarray:
        """(m,) mask of the elements turned inside out in deformed nodes x (m, k, 3)."""
        bad = np.zeros(x.shape[0], dtype=bool)
        for idx, kern in self.parts:
            bad[idx] = kern.inverted(x[idx])
        return bad

    @property
    def history_size(self) -> int:
        """The floats of the regions' viscoelastic histories (:class:`~rtfem.Prony` regions; 0 if none):
        each region's, one after another in the order of ``parts``."""
        return int(sum(getattr(kern, "history_size", 0) for _, kern in self.parts))

    def _histories(self, history):
        """Each part's (history segment, dt), or None for a part without one (or no history given)."""
        if history is None:
            return [None] * len(self.parts)
        h, dt = history
        if h.size != self.history_size:
            raise ModelError(f"a viscoelastic history of {h.size} values for regions of {self.history_size}")
        out, at = [], 0
        for _, kern in self.parts:
            n = getattr(kern, "history_size", 0)
            out.append((h[at:at + n], dt) if n else None)
            at += n
        return out

    def evaluate(self, x: np.ndarray, tangent: bool = True, history=None):
        """Element forces (m, 3k), tangents (m, 3k, 3k) (None unless ``tangent``) and energies (m,)
        for deformed nodes x (m, k, 3), each region's by its own law; ``history`` (h, dt): the
        regions' viscoelastic histories (:attr:`history_size`), each Prony region's step from its
        segment (none: a Prony region's long-term law)."""
        m, k = x.shape[:2]
        f = np.zeros((m, 3 * k))
        K = np.zeros((m, 3 * k, 3 * k)) if tangent else None
        energy = np.zeros(m)
        for (idx, kern), h in zip(self.parts, self._histories(history)):
            fe, Ke, e = kern.evaluate(x[idx], tangent) if h is None else kern.evaluate(x[idx], tangent, h)
            f[idx], energy[idx] = fe, e
            if tangent:
                K[idx] = Ke
        return f, K, energy

    def committed(self, x: np.ndarray, history) -> np.ndarray:
        """The regions' histories after a step that ended at deformed nodes x (m, k, 3)."""
        parts = [kern.committed(x[idx], h) for (idx, kern), h in zip(self.parts, self._histories(history))
                 if h is not None]
        return np.concatenate(parts) if parts else np.zeros(0)
