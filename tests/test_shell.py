"""The shell triangle (OPT membrane + DKT bending) at element level: symmetry, the six
rigid-body motions as its exact null space, and element patch tests against closed forms."""

from __future__ import annotations

import numpy as np
import pytest

import rtfem as rt
from rtfem.fe import shell

MAT = rt.Material(E=2.0e5, nu=0.3, thickness=0.01, density=1000.0)


def _triangles(seed=0, n=6):
    """Random, well-shaped triangles in general 3D position."""
    rng = np.random.default_rng(seed)
    base = np.array([[0.0, 0.0, 0.0], [1.0, 0.1, 0.0], [0.3, 0.9, 0.0]])
    out = []
    for _ in range(n):
        A = rng.normal(size=(3, 3))
        Q, _ = np.linalg.qr(A)
        out.append((base + 0.1 * rng.normal(size=(3, 3))) @ Q.T * rng.uniform(0.5, 2.0) + rng.normal(size=3))
    return np.array(out)


def _rigid_modes(X):
    """(18, 6) nodal dofs (u, v, w, rx, ry, rz per corner) of 3 translations and 3 rotations."""
    R = np.zeros((18, 6))
    for a in range(3):
        for k in range(3):
            R[6 * a + k, k] = 1.0
            e = np.zeros(3)
            e[k] = 1.0
            R[6 * a : 6 * a + 3, 3 + k] = np.cross(e, X[a])
            R[6 * a + 3 + k, 3 + k] = 1.0
    return R


@pytest.mark.parametrize("membrane", shell.MEMBRANES)
def test_element_stiffness_is_symmetric_and_positive_semidefinite(membrane):
    K = shell.element_stiffness(_triangles(), MAT, membrane)
    for Ke in K:
        assert np.abs(Ke - Ke.T).max() <= 1e-12 * np.abs(Ke).max()
        lam = np.linalg.eigvalsh(0.5 * (Ke + Ke.T))
        assert lam.min() >= -1e-10 * lam.max()


def test_rigid_body_motions_are_the_exact_null_space():
    """OPT + DKT: K R = 0 for the six rigid motions, and nothing else is free: rank 18 - 6 = 12."""
    X = _triangles(1)
    K = shell.element_stiffness(X, MAT, "opt")
    for Xe, Ke in zip(X, K):
        R = _rigid_modes(Xe)
        scale = np.abs(Ke).max()
        assert np.abs(Ke @ R).max() <= 1e-9 * scale
        lam = np.linalg.eigvalsh(0.5 * (Ke + Ke.T))
        assert np.sum(lam > 1e-8 * lam.max()) == 12


def test_the_cst_drilling_spring_is_the_one_thing_that_resists_a_rigid_motion():
    """The CST's fictitious drilling spring acts on the absolute in-plane rotation (why it is
    for comparison only): translations are free, a rigid rotation is resisted, and only by
    the spring (drilling=0 makes every rigid motion free)."""
    X = _triangles(1, 2)
    R_, xy, area = shell.local_frames(X)
    for drilling, free in ((1e-3, 3), (0.0, 6)):
        k9 = shell.membrane_cst(xy, area, MAT, drilling)
        for e in range(2):
            p = xy[e]
            rig = np.zeros((9, 3))  # in-plane rigid motions: u, v, rotation about the normal
            for a in range(3):
                rig[3 * a, 0] = rig[3 * a + 1, 1] = 1.0
                rig[3 * a : 3 * a + 2, 2] = [-p[a, 1], p[a, 0]]
                rig[3 * a + 2, 2] = 1.0
            resid = np.abs(k9[e] @ rig).max(axis=0) / np.abs(k9[e]).max()
            assert np.all(resid[:2] < 1e-12)
            assert (resid[2] < 1e-12) == (free == 6)


def _flat_element():
    X = np.array([[[0.0, 0.0, 0.0], [2.0, 0.3, 0.0], [0.4, 1.5, 0.0]]])
    R, xy, area = shell.local_frames(X)
    return X[0], xy, area


@pytest.mark.parametrize("membrane", shell.MEMBRANES)
def test_membrane_patch_test_constant_stress_gives_the_traction_resultants(membrane):
    """u = eps_x x (with v = -nu eps_x y... any linear field): the nodal forces equal the edge
    tractions of the constant plane stress sigma = D eps lumped to the corners (consistent
    loads of a linear field on a straight edge), so the element reproduces the exact state."""
    X, xy, area = _flat_element()
    K = shell.local_stiffness(xy, area, MAT, membrane)[0]
    exx, eyy, gxy = 1e-3, -4e-4, 6e-4
    E, nu, t = MAT.E, MAT.nu, MAT.thickness
    D = E / (1 - nu**2) * np.array([[1, nu, 0], [nu, 1, 0], [0, 0, (1 - nu) / 2]])
    sxx, syy, sxy = D @ np.array([exx, eyy, gxy])
    p = xy[0]  # local corner coordinates (3, 2)
    d = np.zeros(18)
    for a in range(3):
        x, y = p[a]
        d[6 * a] = exx * x + 0.5 * gxy * y
        d[6 * a + 1] = eyy * y + 0.5 * gxy * x
        d[6 * a + 5] = 0.0  # no rigid rotation in this field (antisymmetric part zero)
    f = K @ d
    # exact: corner force = t/2 * sum over its two edges of sigma . n_edge * length (outward)
    sigma = np.array([[sxx, sxy], [sxy, syy]])
    exact = np.zeros((3, 2))
    for a in range(3):
        b = (a + 1) % 3
        edge = p[b] - p[a]
        n_out = np.array([edge[1], -edge[0]])  # outward for a counter-clockwise triangle, times length
        traction = t * sigma @ n_out
        exact[a] += 0.5 * traction
        exact[b] += 0.5 * traction
    got = np.stack([f[0::6], f[1::6]], axis=1)
    np.testing.assert_allclose(got, exact, rtol=1e-10, atol=1e-12 * np.abs(exact).max())
    assert np.abs(f[2::6]).max() <= 1e-12 * np.abs(exact).max()  # no out-of-plane force


def test_dkt_constant_curvature_patch_test_gives_the_bending_moment_resultants():
    """w = (kx x^2 + ky y^2 + kxy x y) / 2 with the Kirchhoff rotations: the DKT nodal forces
    are those of the constant moments M = D_b kappa (the DKT passes the constant-curvature
    patch test): their work on any field equals the exact bending energy integral."""
    X, xy, area = _flat_element()
    K = shell.local_stiffness(xy, area, MAT, "opt")[0]
    kx, ky, kxy = 0.02, -0.01, 0.015
    p = xy[0]

    def field(kx, ky, kxy):
        d = np.zeros(18)
        for a in range(3):
            x, y = p[a]
            w = 0.5 * (kx * x * x + ky * y * y + kxy * x * y)
            wx, wy = kx * x + 0.5 * kxy * y, ky * y + 0.5 * kxy * x
            d[6 * a + 2] = w
            d[6 * a + 3] = wy  # theta_x = dw/dy
            d[6 * a + 4] = -wx  # theta_y = -dw/dx
        return d

    E, nu, t = MAT.E, MAT.nu, MAT.thickness
    Db = E * t**3 / (12 * (1 - nu**2)) * np.array([[1, nu, 0], [nu, 1, 0], [0, 0, (1 - nu) / 2]])
    for k1, k2 in [((kx, ky, kxy), (kx, ky, kxy)), ((kx, ky, kxy), (-0.01, 0.03, 0.0)), ((0.0, 0.0, 0.02), (0.01, 0, 0))]:
        d1, d2 = field(*k1), field(*k2)
        c1 = np.array([k1[0], k1[1], k1[2]])  # curvatures (w_xx, w_yy, 2 w_xy) = (kx, ky, kxy)
        c2 = np.array([k2[0], k2[1], k2[2]])
        exact = area[0] * c1 @ Db @ c2
        scale = area[0] * np.linalg.norm(c1) * np.linalg.norm(c2) * np.abs(Db).max()
        np.testing.assert_allclose(d1 @ K @ d2, exact, rtol=1e-10, atol=1e-12 * scale)


def test_lumped_mass_is_a_third_of_the_element_mass_per_corner():
    X = _triangles(2, 3)
    R, xy, area = shell.local_frames(X)
    m = shell.element_mass(area, MAT)
    np.testing.assert_allclose(m[:, :3].sum(axis=1) * 3, 3 * MAT.density * MAT.thickness * area, rtol=1e-14)
    assert not np.any(m[:, 3:])  # massless rotations (the paper's condensation)
