"""Slender cantilevers against beam theory.

In-plane: a cantilever L/h = 10 under a parabolic end shear P (membrane action). Timoshenko
beam theory gives v = P L^3 / (3 E I) + P L / (kappa G A), kappa = 5/6. A plain constant-strain
membrane locks here; the drilling membrane (OPT) must not.
Out-of-plane: a plate strip (nu = 0) under a tip load, v = P L^3 / (3 E I) (bending action).
"""

import numpy as np
import pytest

import rtfem as rt
from rtfem.fe import shell


def inplane_tip_ratio(membrane: str, nx: int, ny: int, nu: float) -> float:
    L, h = 10.0, 1.0
    mat = rt.Material(E=1.0e6, nu=nu, thickness=0.1, density=1000.0)
    base = rt.meshes.plate(L, h, nx, ny)
    V = np.asarray(base.vertices).copy()
    V[:, 1] -= h / 2
    mesh = rt.TriMesh(V, base.triangles, repair=False, groups=base.groups)
    model = rt.ShellModel(mesh, mat, membrane=membrane)
    model.fix(np.arange(mesh.n_vertices), "z,rx,ry")  # membrane problem only
    model.fix("x0", "x,y")
    tip = mesh.groups["x1"][np.argsort(V[mesh.groups["x1"], 1])]
    ys = V[tip, 1]
    P = 1.0
    tau = lambda y: 1.5 * P / h * (1 - 4 * y**2 / h**2)  # noqa: E731
    F = np.zeros((mesh.n_vertices, 3))
    for k in range(len(ys) - 1):  # consistent loads of the parabolic traction (Simpson, exact)
        y0, y1 = ys[k], ys[k + 1]
        ym, l = (y0 + y1) / 2, y1 - y0
        F[tip[k], 1] += l / 6 * (tau(y0) + 2 * tau(ym))
        F[tip[k + 1], 1] += l / 6 * (2 * tau(ym) + tau(y1))
    assert F[:, 1].sum() == pytest.approx(P)
    v = model.solve_static(F)[tip, 1].mean()
    I = mat.thickness * h**3 / 12
    beam = P * L**3 / (3 * mat.E * I) + P * L / (5 / 6 * mat.G * h * mat.thickness)
    return v / beam


@pytest.mark.parametrize("nu", [0.0, 0.25])
def test_inplane_cantilever_opt_matches_beam_theory(nu):
    assert inplane_tip_ratio("opt", 40, 4, nu) == pytest.approx(1.0, abs=0.01)
    assert inplane_tip_ratio("opt", 80, 8, nu) == pytest.approx(1.0, abs=0.005)


def test_inplane_cantilever_cst_locks():
    # the reason the membrane needs drilling freedoms: CST is >10 % too stiff at the same mesh
    assert inplane_tip_ratio("cst", 40, 4, 0.25) < 0.9
    assert inplane_tip_ratio("opt", 40, 4, 0.25) > 0.99


@pytest.mark.parametrize("nu", [0.0, 0.25, 0.45])
@pytest.mark.parametrize("a,b", [(1.0, 1.0), (2.0, 1.0), (4.0, 1.0), (1.0, 3.0)])
def test_opt_exact_energy_in_pure_bending(nu, a, b):
    """Felippa (2003): OPT gives the exact energy of pure in-plane bending on rectangles of any aspect ratio."""
    mat = rt.Material(E=2.0, nu=nu, thickness=0.5, density=1.0)
    P = np.array([[0, -b / 2], [a, -b / 2], [a, b / 2], [0, b / 2]], float)
    energy = 0.0
    kap = 0.3  # exact field: u = k x y, v = -k (x^2 + nu y^2) / 2, theta_z = -k x
    for tri in ([0, 1, 2], [0, 2, 3]):
        xy = P[tri][None]
        area = np.array([0.5 * abs(np.linalg.det(np.c_[xy[0, 1:] - xy[0, 0]]))])
        k = shell.membrane_opt(xy, area, mat)[0]
        x, y = xy[0, :, 0], xy[0, :, 1]
        d = np.zeros(9)
        d[0::3], d[1::3], d[2::3] = kap * x * y, -kap * (x**2 + nu * y**2) / 2, -kap * x
        energy += 0.5 * d @ k @ d
    exact = 0.5 * mat.E * kap**2 * mat.thickness * a * b**3 / 12
    assert energy == pytest.approx(exact, rel=1e-12)


@pytest.mark.parametrize("nx,ny,tol", [(10, 1, 2e-3), (20, 2, 5e-4)])
def test_out_of_plane_cantilever_strip(nx, ny, tol):
    L, b = 1.0, 0.1
    mat = rt.Material(E=1.0e6, nu=0.0, thickness=0.01, density=1000.0)
    mesh = rt.meshes.plate(L, b, nx, ny)
    model = rt.ShellModel(mesh, mat)
    model.fix("x0", "all")
    tip = mesh.groups["x1"]
    F = np.zeros((mesh.n_vertices, 3))
    F[tip, 2] = 1.0
    F[tip[[0, -1]], 2] = 0.5  # uniform line load, lumped
    F[:, 2] /= F[:, 2].sum()
    w = model.solve_static(F)[tip, 2].mean()
    beam = L**3 / (3 * mat.E * b * mat.thickness**3 / 12)
    assert w == pytest.approx(beam, rel=tol)
