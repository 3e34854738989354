"""Solids of several regions, each with its own material (issue 58), against CalculiX with one element
set and one material per region (``*ELSET``, ``*SOLID SECTION`` each) on the same mesh, nodes and
nodal forces: a 30 mm soft cube (E 30 kPa) with a 10 mm stiff cubic inclusion (E 300 kPa) at its
centre, the base clamped and the top pushed down.

- Linear statics, C3D4 and C3D10: every displacement agrees with ccx's to the digits it prints.
- A neo-Hookean law per region (shear and bulk moduli ten times apart) under a dead top load that squeezes
  the cube by a fifth, ccx with NLGEOM: C3D4 integrates with one point in both codes, so the
  discrete problems are the same and every displacement agrees to 1e-6 of the largest.

Both are checked to differ from the homogeneous cube by far more than the tolerance (the inclusion
matters), and the model's stiffness is checked to be the sum of its regions' (an invariant).
The ccx fixture (skip without ccx, fail under RTFEM_REQUIRE_CCX=1) is test_calculix's.
"""

from __future__ import annotations

import numpy as np
import pytest

import rtfem as rt
from test_calculix import _need_ccx, last_displacements, mesh_lines, run_ccx  # noqa: F401 - the autouse fixture
from test_calculix_hyperelastic import _constants

SIDE = 0.03
SOFT, STIFF = 3e4, 3e5


def _cube(element: str = "tet4", materials=None):
    """The cube (6 x 6 x 6 cells of 5 mm, 6 tets each) with the central 2 x 2 x 2 cells labelled 1,
    the rest 0 (named 'soft' and 'stiff'); base clamped. Returns the model, the base nodes and the
    nodal forces of a -z traction on the top."""
    box = rt.meshes.box(SIDE, SIDE, SIDE, nx=6, ny=6, nz=6)
    c = np.asarray(box.vertices)[np.asarray(box.corner_tets)].mean(axis=1)
    inside = np.all((c > SIDE / 3) & (c < 2 * SIDE / 3), axis=1)
    mesh = rt.TetMesh(box.vertices, box.tets, labels=inside.astype(int), region_names={"soft": 0, "stiff": 1})
    if materials is None:
        materials = {"soft": rt.Material(E=SOFT, nu=0.45), "stiff": rt.Material(E=STIFF, nu=0.45)}
    model = rt.SolidModel(mesh, materials, element=element)
    X = np.asarray(model.tetmesh.vertices)
    base = np.flatnonzero(np.isclose(X[:, 2], 0.0))
    model.fix(base)
    return model, base, model.traction_forces((0.0, 0.0, -1.0), f"z>{SIDE * 0.9999}")


def _region_lines(model, sections: list[str]) -> list[str]:
    """The deck's mesh, one ELSET per region (R<label>) and each region's material lines (its
    ``*MATERIAL`` block from ``sections``, in the order of the labels), each with its section."""
    labels = np.asarray(model.tetmesh.labels)
    lines = mesh_lines(model, "rtfem regions verification")
    for k, block in zip(np.unique(labels).tolist(), sections):
        lines += [f"*ELSET,ELSET=R{k}"] + [f"{e + 1}," for e in np.flatnonzero(labels == k).tolist()]
        lines += [f"*MATERIAL,NAME=M{k}", *block.split("\n"), f"*SOLID SECTION,ELSET=R{k},MATERIAL=M{k}"]
    return lines


def _ccx(model, sections, base, F, folder, nlgeom: bool) -> np.ndarray:
    lines = _region_lines(model, sections)
    lines += ["*NSET,NSET=FIX"] + [f"{i + 1}," for i in base.tolist()] + ["*BOUNDARY", "FIX,1,3"]
    if nlgeom:
        lines += ["*STEP,NLGEOM,INC=1000", "*STATIC", "0.1,1.0", "*CONTROLS,PARAMETERS=FIELD", ",".join(["1e-8"] * 7)]
    else:
        lines += ["*STEP", "*STATIC"]
    lines += ["*CLOAD"] + [f"{i + 1},{d + 1},{float(F[i, d])!r}" for i, d in zip(*np.nonzero(F))]
    lines += ["*NODE PRINT,NSET=NALL", "U", "*END STEP"]
    return last_displacements(run_ccx(lines, folder), model.n_nodes)


@pytest.mark.parametrize("element", ["tet4", "tet10"])
def test_a_stiff_inclusion_in_a_soft_cube_equals_calculix_linear(element, tmp_path):
    """Linear statics under 300 Pa on the top: every node within 1e-6 of the largest displacement of
    ccx's (it prints 7 digits; the issue asks 1e-5; measured 1.8e-7 on both), while the cube all soft
    is 24-25 % off: the inclusion is seen."""
    model, base, F = _cube(element)
    F = F * 300.0
    u = model.solve_static(F)
    sections = [f"*ELASTIC\n{SOFT!r},0.45", f"*ELASTIC\n{STIFF!r},0.45"]
    ref = _ccx(model, sections, base, F, tmp_path, nlgeom=False)
    scale = np.abs(ref).max()
    assert np.abs(u - ref).max() < 1e-6 * scale, np.abs(u - ref).max() / scale
    soft, _, _ = _cube(element, {0: rt.Material(E=SOFT, nu=0.45), 1: rt.Material(E=SOFT, nu=0.45)})
    assert np.abs(soft.solve_static(F) - ref).max() > 0.2 * scale


def test_the_stiffness_is_the_sum_of_the_regions():
    """K of the two-region cube = K of the cube all soft + the inclusion's elements' (stiff minus soft)
    stiffness (each region assembled with its own Lame constants; an invariant, 1e-12); the lumped
    mass likewise with two densities; the rigid motions are still in K's null space."""
    lo, hi = rt.Material(E=SOFT, nu=0.45, density=1000.0), rt.Material(E=STIFF, nu=0.3, density=1100.0)
    model, _, _ = _cube("tet10", {0: lo, 1: hi})
    soft, _, _ = _cube("tet10", {0: lo, 1: lo})
    labels = np.asarray(model.tetmesh.labels)
    part = rt.TetMesh(model.tetmesh.vertices, np.asarray(model.tetmesh.tets)[labels == 1], repair=False)
    a = rt.SolidModel(part, hi, element="tet10")
    b = rt.SolidModel(part, lo, element="tet10")
    dK = model.K - soft.K - (a.K - b.K)
    assert abs(dK).max() < 1e-12 * abs(model.K).max()
    dM = model.mass_diagonal - soft.mass_diagonal - (a.mass_diagonal - b.mass_diagonal)
    assert np.abs(dM).max() < 1e-12 * model.mass_diagonal.max()
    X = np.asarray(model.tetmesh.vertices)
    rigid = np.cross([0.3, -0.2, 1.0], X) + [0.1, 0.2, 0.3]
    assert np.abs(model.K @ rigid.ravel()).max() < 1e-9 * abs(model.K).max() * np.abs(rigid).max()


def test_a_neo_hookean_region_each_equals_calculix_nlgeom(tmp_path):
    """A neo-Hookean law per region (mu 10 / 100 kPa, kappa 0.1 / 1 MPa: E 29 / 290 kPa, nu 0.45; round
    numbers, as ccx reads 20 characters a number) under a dead top load of 6 kPa, which squeezes the
    cube by a fifth: every node within 1e-6 of ccx NLGEOM's largest displacement (the issue asks
    1e-4; measured 3.5e-7), the linear answer 19 % off."""
    laws = {0: rt.NeoHookean(mu=1e4, kappa=1e5), 1: rt.NeoHookean(mu=1e5, kappa=1e6)}
    model, base, F = _cube("tet4", laws)
    F = F * 6000.0
    res = rt.nonlinear.solve_static(model, F, tol=1e-10, steps=4)
    sections = [f"*HYPERELASTIC,NEO HOOKE\n{','.join(repr(float(c)) for c in _constants(law))}" for law in laws.values()]
    ref = _ccx(model, sections, base, F, tmp_path, nlgeom=True)
    scale = np.abs(ref).max()
    assert scale > 0.15 * SIDE  # a large deformation
    assert np.abs(res.displacements - ref).max() < 1e-6 * scale, np.abs(res.displacements - ref).max() / scale
    assert np.abs(model.solve_static(F) - ref).max() > 0.1 * scale
