"""Square Kirchhoff plates against Timoshenko & Woinowsky-Krieger, "Theory of Plates and Shells"
(2nd ed., 1959): centre deflection w = alpha q a^4 / D (uniform load) or alpha P a^2 / D
(central point load), nu = 0.3.

Published coefficients (Tables 8, 23 and 35, Sec. 44): simply supported 0.00406 (uniform) and
0.01160 (point); clamped 0.00126 (uniform) and 0.00560 (point). The simply supported values
are also computed here from the Navier double series, the analytic solution.
"""

import numpy as np
import pytest

import rtfem as rt

TIMOSHENKO = {("simply", "uniform"): 0.00406, ("simply", "point"): 0.01160,
              ("clamped", "uniform"): 0.00126, ("clamped", "point"): 0.00560}
# more digits for the convergence study: Navier series (simply supported) and
# Taylor & Govindjee, "Solution of clamped rectangular plate problems" (2004) for clamped
PRECISE = {("clamped", "uniform"): 0.00126532, ("clamped", "point"): 0.00561210}


def navier_centre(load: str, terms: int = 401) -> float:
    """Centre deflection coefficient of a simply supported unit square plate (Navier series)."""
    m = np.arange(1, terms + 1, 2)[:, None]
    n = np.arange(1, terms + 1, 2)[None, :]
    s = np.sin(m * np.pi / 2) * np.sin(n * np.pi / 2)
    if load == "uniform":
        return float(np.sum(16 / np.pi**6 * s / (m * n * (m**2 + n**2) ** 2)))
    return float(np.sum(4 / np.pi**4 * s**2 / (m**2 + n**2) ** 2))


def centre_coefficient(support: str, load: str, divisions: int, material: rt.Material) -> float:
    a = 0.5
    mesh = rt.meshes.plate(a, a, divisions)
    model = rt.ShellModel(mesh, material)
    model.fix("boundary", "z" if support == "simply" else "all")
    # the in-plane problem is decoupled on a flat plate: hold it
    model.fix(np.arange(mesh.n_vertices), "x,y,rz")
    centre = int(mesh.groups["center"][0])
    if load == "uniform":
        q = 2.0e3
        F = model.pressure_forces(-q)
        F[mesh.groups["boundary"]] = 0.0  # carried by the supports
        scale = q * a**4 / material.bending_rigidity
    else:
        P = 10.0
        F = np.zeros((mesh.n_vertices, 3))
        F[centre, 2] = P
        scale = P * a**2 / material.bending_rigidity
    return model.solve_static(F)[centre, 2] / scale


def test_navier_series_matches_timoshenko_table():
    assert navier_centre("uniform") == pytest.approx(TIMOSHENKO[("simply", "uniform")], rel=2e-3)
    assert navier_centre("point") == pytest.approx(TIMOSHENKO[("simply", "point")], rel=2e-3)


@pytest.mark.parametrize("support", ["simply", "clamped"])
@pytest.mark.parametrize("load", ["uniform", "point"])
def test_centre_deflection_within_2_percent_at_16x16(support, load, plate_material):
    alpha = centre_coefficient(support, load, 16, plate_material)
    assert alpha == pytest.approx(TIMOSHENKO[(support, load)], rel=0.02)


@pytest.mark.parametrize("support", ["simply", "clamped"])
@pytest.mark.parametrize("load", ["uniform", "point"])
def test_centre_deflection_converges(support, load, plate_material):
    exact = navier_centre(load) if support == "simply" else PRECISE[(support, load)]
    errors = [abs(centre_coefficient(support, load, n, plate_material) / exact - 1) for n in (4, 8, 16, 32)]
    assert all(e2 < e1 for e1, e2 in zip(errors, errors[1:])), errors
    # DKT converges at O(h^2) in deflection: each halving of h cuts the error by about 4
    assert errors[-1] < errors[-2] / 2.5
    assert errors[-1] < 0.008
