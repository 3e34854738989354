"""Modal warping: the rotation maps, the rotation modes of both models, the warped simulator.

References: Rodrigues' formula against scipy's rotations; the integrated rotation against the
closed form of a rigid rotation (a linear rigid-rotation field warped is the exact rotated one);
rotation modes of rigid infinitesimal rotations (shell: through the condensation; solid: half
the curl); the warped strip against the corotational full order (ALGORITHMS.md's elastica).
"""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import rtfem as rt
from rtfem.drivers.warping import integrated_rotation, rotation


def test_rotation_is_rodrigues():
    w = np.random.default_rng(3).standard_normal((20, 3))
    w[0] = 0.0
    w[1] = [1e-6, 0.0, 2e-6]
    np.testing.assert_allclose(rotation(w), Rotation.from_rotvec(w).as_matrix(), atol=1e-14)


@pytest.mark.parametrize("angle", [1e-5, 0.3, 1.5, 3.0])
def test_the_integrated_rotation_turns_a_linear_rigid_rotation_into_the_exact_one(angle):
    axis = np.array([0.2, -0.5, 1.0]) / np.linalg.norm([0.2, -0.5, 1.0])
    rho = np.array([0.3, 0.7, -0.2])
    w = angle * axis
    linear = np.cross(w, rho)  # the small-rotation displacement of a point at rho
    exact = Rotation.from_rotvec(w).apply(rho) - rho
    np.testing.assert_allclose(integrated_rotation(w) @ linear, exact, atol=1e-13)


def test_shell_rotation_modes_of_a_rigid_rotation():
    model = rt.ShellModel(rt.meshes.plate(1.0, 1.0, nx=4), rt.Material(E=1e5, nu=0.3, thickness=0.01))
    model.fix("y0", dofs="xyz")  # on the x axis: a rotation about it moves none of them
    X = np.asarray(model.mesh.vertices)
    omega = np.array([1e-3, 0.0, 0.0])
    U = np.cross(omega, X)[:, :, None]
    psi = model.rotation_field(U)[:, :, 0]
    np.testing.assert_allclose(psi, np.tile(omega, (model.n_nodes, 1)), atol=1e-12)


@pytest.mark.parametrize("element", ["tet4", "tet10"])
def test_solid_rotation_modes_are_half_the_curl(element):
    model = rt.SolidModel(rt.meshes.box(1.0, 0.5, 0.5, 3, 2, 2), rt.Material(E=1e5, nu=0.3), element=element)
    X = np.asarray(model.tetmesh.vertices)
    omega = np.array([1e-3, -2e-3, 0.5e-3])
    shear = np.column_stack([X[:, 1], X[:, 0], 0 * X[:, 0]]) * 1e-3  # symmetric gradient: no rotation
    U = np.stack([np.cross(omega, X), shear], axis=2)
    psi = model.rotation_field(U)
    np.testing.assert_allclose(psi[:, :, 0], np.tile(omega, (model.n_nodes, 1)), atol=1e-15)
    np.testing.assert_allclose(psi[:, :, 1], 0.0, atol=1e-15)


def test_warping_needs_the_model():
    model = rt.ShellModel(rt.meshes.plate(1.0, 1.0, nx=4), rt.Material(E=1e5, nu=0.3, thickness=0.01)).fix("x0")
    modes = rt.modal_analysis(model, 4)
    sim = rt.ModalSimulator(modes, 1e-3, warping=True)
    assert isinstance(sim, rt.drivers.warping.WarpedModalSimulator) and sim.warping and not sim.compiled
    modes.model = None
    with pytest.raises(rt.ModelError, match="model"):
        rt.ModalSimulator(modes, 1e-3, warping=True)
    with pytest.raises(rt.ModelError, match="warping"):
        rt.ModalSimulator(modes, 1e-3, warping="yes")


def test_warped_strip_against_the_full_order_model():
    """Settled under a dead end load, the warped reduced strip is within 30 % of the linear
    one's error of the corotational answer (measured: 1.2 % of L against 5.6 % at P L^2/EI = 1,
    4.4 % against 17 % at 2)."""
    model = rt.ShellModel(rt.meshes.plate(10.0, 1.0, nx=40, ny=2),
                          rt.Material(E=1.2e6, nu=0.0, thickness=0.1, density=1.0)).fix("x0")
    end = model.select_nodes("x1")
    modes = rt.modal_analysis(model, 20)
    for k in (1, 2):
        F = np.zeros((model.n_nodes, 3))
        F[end, 2] = k / end.size
        ref = rt.nonlinear.solve_static(model, F).displacements[end]
        errors = []
        for warping in (False, True):
            sim = rt.ModalSimulator(modes, 0.01, rt.Damping(zeta=1.0), static_correction=True, warping=warping)
            loads = {int(i): F[i] for i in end}
            for _ in range(1500):
                sim.step(loads)
            errors.append(np.abs(sim.displacements()[end] - ref).max() / 10.0)
        assert errors[1] < 0.3 * errors[0] and errors[1] < 0.015 * k**2, (k, errors)
