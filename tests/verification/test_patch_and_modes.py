"""Patch tests and rigid-body modes.

Patch test (Irons): on an irregular patch, the exact nodal values of a constant-strain
(membrane) or constant-curvature (bending) field must be in equilibrium at every interior
node, i.e. (K d_exact) vanishes there, so the interior solution reproduces the field exactly.
An unconstrained model must have exactly six zero-energy modes: the rigid-body motions.
"""

import numpy as np
import pytest
import scipy.linalg as sla

import rtfem as rt
from conftest import rigid_body_modes


def irregular_patch(seed: int = 1, rotate: bool = False) -> rt.TriMesh:
    base = rt.meshes.plate(1.0, 0.8, 4, 4)
    V = np.asarray(base.vertices).copy()
    inner = np.setdiff1d(np.arange(base.n_vertices), base.groups["boundary"])
    V[inner, :2] += np.random.default_rng(seed).uniform(-0.07, 0.07, (inner.size, 2))
    if rotate:  # an arbitrarily oriented plane in space
        Q = np.linalg.qr(np.random.default_rng(seed + 1).normal(size=(3, 3)))[0]
        V = V @ Q.T + [0.3, -0.2, 0.5]
    return rt.TriMesh(V, base.triangles, repair=False, groups=base.groups)


def local_to_global_field(mesh, field_local):
    """Evaluate a field given in plate coordinates on a possibly rotated patch."""
    V = np.asarray(mesh.vertices)
    c = V[0]
    e1 = (V[mesh.groups["x1"][0]] - c)
    e1 /= np.linalg.norm(e1)
    e3 = mesh.face_normals()[0]
    e2 = np.cross(e3, e1)
    R = np.stack([e1, e2, e3])
    xy = (V - c) @ R.T
    d_local = field_local(xy[:, 0], xy[:, 1])  # (n, 6) in the plate frame
    d = np.zeros_like(d_local)
    d[:, :3] = d_local[:, :3] @ R
    d[:, 3:] = d_local[:, 3:] @ R
    return d.ravel()


def membrane_field(x, y, ex=1e-3, ey=-2e-3, gxy=1.5e-3, w=4e-3):
    d = np.zeros((x.size, 6))
    d[:, 0] = ex * x + 0.5 * gxy * y - w * y + 0.01
    d[:, 1] = ey * y + 0.5 * gxy * x + w * x - 0.02
    d[:, 5] = w  # drilling rotation = rigid rotation of the constant-strain field
    return d


def bending_field(x, y, kx=0.3, ky=-0.2, kxy=0.25):
    # w = -(kx x^2 + ky y^2 + kxy x y)/2 has curvatures (kx, ky, kxy); theta_x = w,y, theta_y = -w,x
    d = np.zeros((x.size, 6))
    d[:, 2] = -(kx * x**2 + ky * y**2 + kxy * x * y) / 2 + 0.1 * x - 0.05
    d[:, 3] = -(ky * y + kxy * x / 2)
    d[:, 4] = kx * x + kxy * y / 2 - 0.1
    return d


@pytest.mark.parametrize("rotate", [False, True])
@pytest.mark.parametrize("field", [membrane_field, bending_field], ids=["membrane", "bending"])
def test_patch_test_constant_strain_and_curvature(field, rotate, plate_material):
    mesh = irregular_patch(rotate=rotate)
    model = rt.ShellModel(mesh, plate_material)
    d = local_to_global_field(mesh, field)
    r = (model.K @ d).reshape(-1, 6)
    inner = np.setdiff1d(np.arange(mesh.n_vertices), mesh.groups["boundary"])
    scale = np.abs(model.K).max() * np.abs(d).max()
    assert np.abs(r[inner]).max() < 1e-12 * scale
    # the field really strains the patch: its boundary forces are far from round-off
    assert np.abs(r[mesh.groups["boundary"]]).max() > 1e6 * np.abs(r[inner]).max()


@pytest.mark.parametrize("field", [membrane_field, bending_field], ids=["membrane", "bending"])
def test_patch_solution_reproduces_field(field, plate_material):
    """Solve the patch with the boundary held at the exact values (by elimination)."""
    mesh = irregular_patch(seed=3, rotate=True)
    model = rt.ShellModel(mesh, plate_material)
    d = local_to_global_field(mesh, field)
    nodes_b = mesh.groups["boundary"]
    fixed = np.zeros((mesh.n_vertices, 6), bool)
    fixed[nodes_b] = True
    f, b = np.flatnonzero(~fixed.ravel()), np.flatnonzero(fixed.ravel())
    K = model.K
    Kff = K[f][:, f].toarray()
    u_f = np.linalg.solve(Kff, -(K[f][:, b] @ d[b]))
    # exact up to round-off amplified by the conditioning of K_ff (about 4e5 here)
    roundoff = np.linalg.cond(Kff) * np.finfo(float).eps
    assert np.abs(u_f - d[f]).max() < 100 * roundoff * np.abs(d).max()


def _zero_modes(mesh, material):
    K = rt.ShellModel(mesh, material).K.toarray()
    w = sla.eigvalsh(K)
    return K, w


@pytest.mark.parametrize(
    "mesh",
    [
        pytest.param(irregular_patch(), id="flat-plate"),
        pytest.param(irregular_patch(rotate=True), id="tilted-plate"),
        pytest.param(rt.meshes.hemisphere(0.05, 4), id="hemisphere"),
        pytest.param(rt.meshes.cylinder(0.05, 0.1, 8, 3), id="cylinder"),
        pytest.param(rt.meshes.icosphere(0.05, 1), id="closed-sphere"),
    ],
)
def test_unconstrained_model_has_exactly_six_zero_energy_modes(mesh):
    # thickness comparable to the element size, so that bending and membrane eigenvalues
    # are both far from round-off and the count is unambiguous
    material = rt.Material(E=1.0e6, nu=0.3, thickness=0.2 * np.sqrt(mesh.areas().mean()), density=1000.0)
    K, w = _zero_modes(mesh, material)
    assert np.abs(K - K.T).max() <= 1e-14 * np.abs(K).max()
    zero = np.abs(w) < 1e-10 * w.max()
    assert zero.sum() == 6, w[:8] / w.max()
    # the first elastic mode is far above the round-off of the six zero ones
    assert w[6] > 1e6 * np.abs(w[:6]).max()
    R = rigid_body_modes(np.asarray(mesh.vertices))
    assert np.abs(K @ R).max() < 1e-11 * np.abs(K).max() * np.abs(R).max()


def test_cst_option_also_has_six_zero_modes():
    mesh = irregular_patch(rotate=True)
    material = rt.Material(E=1.0e6, nu=0.3, thickness=0.05, density=1000.0)
    K = rt.ShellModel(mesh, material, membrane="cst").K.toarray()
    w = sla.eigvalsh(K)
    assert np.sum(np.abs(w) < 1e-10 * w.max()) == 6
