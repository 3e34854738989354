"""Hyperelastic solids against CalculiX (issue 41 item 5): a block compressed 30 % between bonded
platens (base clamped, top moved down with its x, y held: the sides barrel, the field is not
homogeneous), each law as ccx's ``*HYPERELASTIC`` (NEO HOOKE, MOONEY-RIVLIN, OGDEN N=2) with
NLGEOM on the same mesh and nodes. C3D4 integrates with one point in both codes, so the discrete
problems are the same: the platen's total force and every node's displacement agree to the digits
ccx prints (measured: 7 digits, the force within 1e-7). ccx's convergence tolerances are tightened
to 1e-8 (*CONTROLS, PARAMETERS=FIELD; its defaults stop at 0.5 % of the average force).
The ccx fixture (skip without ccx, fail under RTFEM_REQUIRE_CCX=1) is test_calculix's."""

from __future__ import annotations

import numpy as np
import pytest

import rtfem as rt
from test_calculix import _need_ccx, last_displacements, mesh_lines, run_ccx  # noqa: F401 - the autouse fixture

LAWS = {
    "neo-hookean": (rt.NeoHookean(mu=2000.0, kappa=1e5, density=1000.0), "NEO HOOKE"),
    "mooney-rivlin": (rt.MooneyRivlin(c10=700.0, c01=300.0, kappa=1e5, density=1000.0), "MOONEY-RIVLIN"),
    "ogden": (rt.Ogden(mu=[1500.0, 500.0], alpha=[8.0, -2.0], kappa=1e5, density=1000.0), "OGDEN,N=2"),
}


def _constants(law) -> list[float]:
    D1 = 2.0 / law.kappa
    if isinstance(law, rt.Ogden):
        # ccx reads D1, D2 for N = 2 and divides by D2 ((J - 1)^4 / D2): a D2 of 0 is not "no term" there
        # (the platen force came out 370 times too large), 1e30 is
        return [v for m, a in zip(law.mus, law.alphas) for v in (float(m), float(a))] + [D1, 1e30]
    if isinstance(law, rt.MooneyRivlin):
        return [law.c10, law.c01, D1]
    return [law.c10, D1]


def ccx_platens(model, law, keyword: str, base, top, squeeze: float, folder):
    """ccx's (total force on the top set (3,), displacements (n, 3)) of ``model``'s mesh: ``base``
    clamped, ``top`` held in x, y and moved by -squeeze in z."""
    lines = mesh_lines(model, "rtfem hyperelastic verification")
    lines += ["*NSET,NSET=BASE"] + [f"{i + 1}," for i in base.tolist()]
    lines += ["*NSET,NSET=TOP"] + [f"{i + 1}," for i in top.tolist()]
    lines += ["*MATERIAL,NAME=M", f"*HYPERELASTIC,{keyword}", ",".join(repr(float(c)) for c in _constants(law)),
              "*SOLID SECTION,ELSET=EALL,MATERIAL=M", "*BOUNDARY", "BASE,1,3", "TOP,1,2",
              "*STEP,NLGEOM,INC=1000", "*STATIC", "0.1,1.0", "*CONTROLS,PARAMETERS=FIELD", ",".join(["1e-8"] * 7),
              "*BOUNDARY", f"TOP,3,3,{-squeeze!r}", "*NODE PRINT,NSET=TOP,TOTALS=ONLY", "RF",
              "*NODE PRINT,NSET=NALL", "U", "*END STEP"]
    text = run_ccx(lines, folder)
    force = np.array([float(v) for v in text.split("total force (fx,fy,fz)")[-1].splitlines()[2].split()])
    return force, last_displacements(text, model.n_nodes)


@pytest.mark.parametrize("name", list(LAWS))
def test_a_block_squeezed_between_platens_equals_calculix(name, tmp_path):
    law, keyword = LAWS[name]
    model = rt.SolidModel(rt.meshes.box(1.0, 1.0, 1.0, nx=4, ny=4, nz=4), law, element="tet4")
    X = np.asarray(model.tetmesh.vertices)
    base, top = np.flatnonzero(X[:, 2] == 0.0), np.flatnonzero(X[:, 2] == 1.0)
    model.fix(base)
    model.fix(top)
    prescribed = np.zeros((model.n_nodes, 3))
    prescribed[top, 2] = -0.3
    result = rt.nonlinear.solve_static(model, prescribed=prescribed, steps=4)
    force, U = ccx_platens(model, law, keyword, base, top, 0.3, tmp_path)
    ours = result.reactions[top].sum(axis=0)
    assert np.abs(ours - force).max() < 1e-6 * abs(force[2]), (ours, force)
    assert np.abs(result.displacements - U).max() < 1e-6 * np.abs(U).max()
    side = np.flatnonzero((X[:, 0] == 1.0) & (X[:, 2] == 0.5))
    assert result.displacements[side, 0].max() > 0.05  # the sides barrel: not a homogeneous field
