"""A reduced organ cut while it runs goes full order (issue 57): ReducedNonlinearSimulator.carry_over(
cut_model, transfer) gives a full-order rt.DirectSimulator (the lagged corotational step) holding the
reduced state on the cut mesh. The issue's tet4 block 0.1 x 0.02 x 0.02 m clamped at x = 0, swinging
under a tip load on its reduced nonlinear model (12 modes + derivatives of 4, cubature), is slit from
its top halfway down at mid-length (rt.cut, on element faces):

- at the swap the full order's field is the reduced one node for node (a slit node's copies take their
  parent's displacement) and its kinetic energy is the reduced model's (a node's copies share its
  lumped mass), to 1e-12;
- settled under the same load, its tip is where rt.nonlinear.solve_static puts the tip of a slit mesh
  built by index arithmetic (test_cut._slit_box, not the cut's graph): measured 5e-13 of the tip's
  deflection, bound 1e-6; the uncut block's tip is 21 % of it away (the slit is in effect).
"""

from __future__ import annotations

import numpy as np
import pytest

import rtfem as rt
from rtfem.drivers.reduced_nonlinear import reduced_nonlinear_driver
from rtfem.errors import ModelError

from test_cut import MAT, QUAD, SLIT, L, _slit_box

LOAD = 0.01  # N down on the tip face, shared by its nodes


def _block(mesh: rt.TetMesh) -> rt.SolidModel:
    return rt.SolidModel(mesh, MAT, element="tet4").fix(np.flatnonzero(np.asarray(mesh.vertices)[:, 0] <= 1e-12))


def _tip_load(model) -> dict:
    tip = np.flatnonzero(np.isclose(np.asarray(model.tetmesh.vertices)[:, 0], L))
    return {int(i): (0.0, 0.0, -LOAD / tip.size) for i in tip}


def test_a_cut_reduced_block_goes_full_order_with_its_state_and_settles_on_the_slit_meshs_equilibrium():
    model = _block(rt.meshes.box(L, 0.02, 0.02, nx=20, ny=4, nz=4))
    sim = reduced_nonlinear_driver(model, rt.modal_analysis(model, 12), 1e-3, rt.Damping(alpha=20.0), derivatives=4)
    loads = _tip_load(model)
    for _ in range(150):  # swinging down
        sim.step(loads)
    cut = rt.cut(model, SLIT, QUAD)
    P = cut.cut_info.transfer()
    full = sim.carry_over(cut, P)
    assert isinstance(full, rt.DirectSimulator) and full.large_deformation and full.steps == sim.steps
    U = sim.displacements()
    assert np.abs(full.displacements() - P @ U).max() <= 1e-12 * np.abs(U).max()
    v = full.get_state()["v"]
    m_full = np.asarray(cut.mass_diagonal)[full._solved]
    red = sim.reduced
    m_old = np.asarray(model.mass_diagonal)[red.free]
    vr = red.basis @ sim._v
    kinetic_full, kinetic_red = 0.5 * v @ (m_full * v), 0.5 * vr @ (m_old * vr)
    assert kinetic_red > 0 and abs(kinetic_full - kinetic_red) <= 1e-12 * kinetic_red
    assert sim.carry_over(cut, P, into=full) is full  # only the state again
    cut_loads = _tip_load(cut)
    for _ in range(2500):
        full.step(cut_loads)
    slit = _block(_slit_box())
    ref = rt.nonlinear.solve_static(slit, _tip_load(slit), steps=4).displacements
    uncut = rt.nonlinear.solve_static(model, loads, steps=4).displacements
    tip_ref = ref[np.isclose(np.asarray(slit.tetmesh.vertices)[:, 0], L)]
    tip = full.displacements()[np.isclose(np.asarray(cut.tetmesh.vertices)[:, 0], L)]
    tip_uncut = uncut[np.isclose(np.asarray(model.tetmesh.vertices)[:, 0], L)]
    scale = np.abs(tip_ref[:, 2]).max()
    assert scale > 0.005  # m: a large deflection (5 % of the length)
    assert np.abs(np.sort(tip[:, 2]) - np.sort(tip_ref[:, 2])).max() < 1e-6 * scale
    assert np.abs(np.sort(tip_uncut[:, 2]) - np.sort(tip_ref[:, 2])).max() > 0.1 * scale


def test_carry_over_refuses_what_is_not_a_remesh_of_its_model():
    model = _block(rt.meshes.box(L, 0.02, 0.02, nx=10, ny=2, nz=2))
    sim = reduced_nonlinear_driver(model, rt.modal_analysis(model, 6), 1e-3, rt.Damping(alpha=20.0), derivatives=2)
    cut = rt.cut(model, SLIT, QUAD)
    other = rt.SolidModel(cut.tetmesh, rt.Material(E=5e4, nu=0.45, density=1060.0), element="tet4").fix(
        np.flatnonzero(np.asarray(cut.tetmesh.vertices)[:, 0] <= 1e-12))
    with pytest.raises(ModelError, match="material"):
        sim.carry_over(other, cut.cut_info.transfer())
    with pytest.raises(ModelError, match="transfer"):
        sim.carry_over(cut, np.arange(3))
    with pytest.raises(ModelError, match="into="):
        sim.carry_over(cut, cut.cut_info.transfer(), into=rt.DirectSimulator(cut, 2e-3, rt.Damping(alpha=20.0)))


def test_a_reduced_model_of_the_cut_mesh_takes_the_full_order_over_again():
    """The way back (ReducedNonlinearSimulator.take_over): once a reduced model of the cut block is
    built, it takes the running full order's state over, projected on its basis in the stiffness
    inner product. A field the basis holds is kept exactly: the full order started from the reduced
    model's own state (carried over the identity) gives that state back to 1e-10. From the swinging
    cut block's full order the field moves by what the basis cannot hold (under 1 % of the motion at
    the swap), and the reduced model then settles on its own equilibrium (1.3e-10), whose basis holds
    the slit block's within 1 % (exact forces; the cubature puts the tip 11 % lower)."""
    model = _block(rt.meshes.box(L, 0.02, 0.02, nx=20, ny=4, nz=4))
    cut = rt.cut(model, SLIT, QUAD)
    loads = _tip_load(cut)
    sim = reduced_nonlinear_driver(cut, rt.modal_analysis(cut, 12), 1e-3, rt.Damping(alpha=20.0), derivatives=4,
                                   precision="double")
    for _ in range(100):
        sim.step(loads)
    identity = np.arange(cut.n_nodes)
    full = sim.carry_over(cut, identity)
    back = reduced_nonlinear_driver(cut, rt.modal_analysis(cut, 12), 1e-3, rt.Damping(alpha=20.0), derivatives=4,
                                    precision="double")
    back.take_over(full)
    assert back.steps == sim.steps
    for a, b in ((back._q, sim._q), (back._v, sim._v)):
        assert np.abs(a - b).max() < 1e-10 * np.abs(b).max()
    for _ in range(200):  # the full order swings on by itself, then the reduced model takes over
        full.step(loads)
    back.take_over(full)
    U, R = full.displacements(), back.displacements()
    assert np.abs(R - U).max() < 0.01 * np.abs(U).max(), np.abs(R - U).max() / np.abs(U).max()
    for _ in range(3000):
        back.step(loads)
    own = back.reduced.solve_static(loads, cubature=True, static_correction=True).displacements
    assert np.abs(back.displacements() - own).max() < 1e-6 * np.abs(own).max()  # measured 1.3e-10
    # the basis of the cut block holds the slit block's equilibrium (exact forces: 0.1 % of the tip's, measured);
    # its cubature (trained to 5 %) puts the tip 11 % lower
    exact = back.reduced.solve_static(loads, cubature=False, static_correction=True).displacements
    slit = _block(_slit_box())
    ref = rt.nonlinear.solve_static(slit, _tip_load(slit), steps=4).displacements
    tip_ref = np.sort(ref[np.isclose(np.asarray(slit.tetmesh.vertices)[:, 0], L)][:, 2])
    tip = np.sort(exact[np.isclose(np.asarray(cut.tetmesh.vertices)[:, 0], L)][:, 2])
    assert np.abs(tip - tip_ref).max() < 0.01 * np.abs(tip_ref).max(), np.abs(tip - tip_ref).max() / np.abs(tip_ref).max()
    before = back.get_state()
    with pytest.raises(ModelError, match="full-order"):
        back.take_over(sim)
    with pytest.raises(ModelError, match="tangent"):
        back.continue_from(sim, tangent="sometimes")
    after = back.get_state()  # refused: the state as it was
    assert set(after) == set(before) and all(np.array_equal(after[k], before[k]) for k in before)
