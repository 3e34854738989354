import numpy as np
import pytest
from scipy.integrate import solve_ivp

from rtfem.reduction.oscillator import _expm_blocks, step_response, transition

CASES = [(100.0, 2.0), (100.0, 20.0), (100.0, 40.0), (0.0, 3.0), (1e-9, 0.5), (1e4, 0.0), (25.0, 10.0 + 1e-7),
         (4e6, 5000.0), (1e-3, 5000.0), (0.0, 0.0)]


def ode(lam, a, t_end, x0=0.0, v0=0.0, f=1.0, t_eval=None):
    sol = solve_ivp(lambda t, y: [y[1], f - a * y[1] - lam * y[0]], (0, t_end), [x0, v0], t_eval=t_eval,
                    method="DOP853", rtol=1e-13, atol=1e-16)
    return sol.y


@pytest.mark.parametrize("lam,a", CASES)
def test_step_response_against_ode(lam, a):
    t = np.array([1e-5, 0.013, 0.1, 0.7])
    x = step_response(lam, a, t)
    ref = ode(lam, a, 0.7, t_eval=t)[0]
    assert np.abs(x - ref).max() <= 1e-9 * np.abs(ref).max() + 1e-18


@pytest.mark.parametrize("lam,a", CASES)
def test_transition_against_ode(lam, a):
    dt = 0.05
    P, G = transition(lam, a, dt)
    ref = ode(lam, a, dt, x0=0.3, v0=-1.2, f=2.0)[:, -1]
    assert np.abs(P @ [0.3, -1.2] + 2.0 * G - ref).max() <= 1e-9 * np.abs(ref).max()


def test_vectorized_expm_matches_scipy():
    """Over the regime it serves (lam t^2 < 1e-3 in the library) and well beyond it."""
    import scipy.linalg as sla

    rng = np.random.default_rng(0)
    t = 10 ** rng.uniform(-6, 0, 200)
    lam = 10 ** rng.uniform(-6, 1, 200) / t**2  # lam t^2 from 1e-6 to 10
    a = 10 ** rng.uniform(-3, 4, 200)
    E = _expm_blocks(lam, a, t)
    for k in range(0, 200, 7):
        A = np.array([[0, 1, 0], [-lam[k], -a[k], 1], [0, 0, 0]]) * t[k]
        R = sla.expm(A)
        assert np.abs(E[k] - R).max() <= 1e-12 * np.abs(R).max()


def test_broadcasting_shapes():
    lam = np.array([1.0, 100.0, 1e4])[:, None]
    t = np.linspace(0, 1, 7)[None, :]
    assert step_response(lam, 2.0, t).shape == (3, 7)
    assert np.all(step_response(lam, 2.0, np.zeros((1, 1))) == 0)
