"""The averaged-nodal-pressure tet4 at finite strain (issue 41, item 2: no volumetric locking in the
nonlinear solvers), against a second element, the linear tet4-anp, a closed form and invariants.

- A bonded punch pressed 10 % into a nearly incompressible neo-Hookean block (kappa / mu = 500,
  nu = 0.499): the punch force of tet4-anp is within 6 % of tet10's on the same mesh (measured
  4.4 %), plain tet4 locks (9.9x).
- Consistency: at a tiny tip load on a nu = 0.499 cantilever the nonlinear tet4-anp equals the
  linear solvers' tet4-anp (rt.fe.solid.anp_volumetric, verified against beam theory) to 1e-5.
- A homogeneous deformation keeps every node's volume ratio equal to the tets': the 30 % cube
  compression meets the closed-form uniaxial stress as plain tet4 does (1e-9).
- The tangent (element terms plus the patches' C^T diag(kappa / V_a) C) against central
  differences of the forces, and the forces against the energy's differences.
"""

from __future__ import annotations

import numpy as np
import pytest

import rtfem as rt
from rtfem.errors import ModelError

MU = 1000.0


def _block(element, ratio=500.0):
    law = rt.NeoHookean(MU, MU * ratio, 1000.0)
    model = rt.SolidModel(rt.meshes.box(1.0, 1.0, 0.5, nx=6, ny=6, nz=3), law, element=element)
    X = np.asarray(model.tetmesh.vertices)
    base = np.flatnonzero(X[:, 2] == 0.0)
    top = np.flatnonzero(np.isclose(X[:, 2], 0.5) & (np.hypot(X[:, 0] - 0.5, X[:, 1] - 0.5) < 0.26))
    model.fix(np.concatenate([base, top]))
    pressed = np.zeros((model.n_nodes, 3))
    pressed[top, 2] = -0.05
    result = rt.nonlinear.solve_static(model, prescribed=pressed, steps=2)
    return result.reactions[top, 2].sum()


def test_a_punch_into_a_nearly_incompressible_block_does_not_lock():
    anp, tet10, tet4 = _block("tet4-anp"), _block("tet10"), _block("tet4")
    assert abs(anp - tet10) < 0.06 * abs(tet10), (anp, tet10)
    assert abs(tet4) > 5 * abs(tet10)  # plain tet4 locks


def test_at_a_tiny_load_the_nonlinear_anp_is_the_linear_one():
    law = rt.NeoHookean(MU, 500 * MU, 1000.0)
    mesh = rt.meshes.box(1.0, 0.1, 0.1, nx=20, ny=2, nz=2)
    tips = []
    for material in (law, law.linearized()):
        model = rt.SolidModel(mesh, material, element="tet4-anp")
        model.fix("x0")
        tip = model.select_nodes("x1")
        F = np.zeros((model.n_nodes, 3))
        F[tip, 2] = 1e-6 / tip.size
        u = rt.nonlinear.solve_static(model, F).displacements if material is law else model.solve_static(F)
        tips.append(u[tip, 2].mean())
    assert abs(tips[0] - tips[1]) < 1e-5 * abs(tips[1])
    E = 9 * law.kappa * MU / (3 * law.kappa + MU)
    assert 0.4 < tips[1] / (1e-6 / (3 * E * 0.1**4 / 12)) < 0.7  # 0.51 of beam theory (tet4's own bending)


def test_a_homogeneous_compression_meets_the_closed_form():
    law = rt.NeoHookean(mu=2000.0, kappa=100000.0, density=1000.0)
    forces = []
    for element in ("tet4", "tet4-anp"):
        model = rt.SolidModel(rt.meshes.box(1.0, 1.0, 1.0, nx=2, ny=2, nz=2), law, element=element)
        X = np.asarray(model.tetmesh.vertices)
        base, top = np.flatnonzero(X[:, 2] == 0.0), np.flatnonzero(X[:, 2] == 1.0)
        model.fix(base, dofs=[2])
        model.fix(np.flatnonzero(np.all(X == 0.0, axis=1)), dofs=[0, 1])
        model.fix(np.flatnonzero((X[:, 0] == 1.0) & (X[:, 1] == 0.0) & (X[:, 2] == 0.0)), dofs=[1])
        model.fix(top, dofs=[2])
        pressed = np.zeros((model.n_nodes, 3))
        pressed[top, 2] = -0.3
        forces.append(rt.nonlinear.solve_static(model, prescribed=pressed, steps=3).reactions[top, 2].sum())
    assert abs(forces[1] - forces[0]) < 1e-9 * abs(forces[0])


def test_the_tangent_and_the_forces_are_the_energys_derivatives():
    from rtfem.fe.nonlinear import Configuration

    law = rt.MooneyRivlin(c10=400.0, c01=100.0, kappa=50000.0, density=1000.0)
    model = rt.SolidModel(rt.meshes.box(0.1, 0.05, 0.05, nx=3, ny=2, nz=2), law, element="tet4-anp")
    model.fix("x0")
    system = model.nonlinear()
    rng = np.random.default_rng(6)
    u = system.expand(0.003 * rng.normal(size=system.free.size))
    conf = Configuration.rest(model.n_nodes, False)
    conf.update(u)
    f, K, energy = system.evaluate(conf)
    ff = f[system.free]
    eps = 1e-7
    for j in rng.choice(system.free.size, 12, replace=False):
        d = np.zeros(system.free.size)
        d[j] = eps
        cp, cm = conf.copy(), conf.copy()
        cp.update(system.expand(d))
        cm.update(system.expand(-d))
        fp, fm = system.evaluate(cp, False)[0][system.free], system.evaluate(cm, False)[0][system.free]
        np.testing.assert_allclose((fp - fm) / (2 * eps), K[:, j].toarray().ravel(), rtol=1e-5,
                                   atol=1e-6 * abs(K).max())
        ep, em = system.energy(cp), system.energy(cm)
        assert abs((ep - em) / (2 * eps) - ff[j]) < 1e-5 * np.abs(ff).max()


def test_anp_refusals():
    mesh = rt.meshes.box(0.1, 0.05, 0.05, nx=2, ny=1, nz=1)
    model = rt.SolidModel(mesh, rt.Material(E=3e4, nu=0.49, density=1000.0), element="tet4-anp")
    model.fix("x0")
    with pytest.raises(ModelError, match="hyperelastic law's volumetric energy"):
        model.nonlinear()
    law = rt.NeoHookean(MU, 50 * MU, 1000.0)
    model = rt.SolidModel(mesh, law, element="tet4-anp")
    model.fix("x0")
    with pytest.raises(ModelError, match="reduced nonlinear model's element cubature"):
        rt.ReducedNonlinearModel(model, rt.modal_analysis(model, 4), derivatives=2)
