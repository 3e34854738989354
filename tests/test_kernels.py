"""The compiled haptic step (rtfem.drivers.kernels) against the numpy path and against its own Python
definition: the same states, step after step, for both integrators, with and without loads."""

from __future__ import annotations

import numpy as np
import pytest

import rtfem as rt
from rtfem.drivers import kernels


@pytest.fixture(scope="module")
def basis():
    model = rt.ShellModel(rt.meshes.liver(2), rt.Material()).fix("attachment")
    return model, rt.modal_analysis(model, 12)


def _run(sim, node, steps=300):
    rng = np.random.default_rng(7)
    out = []
    for k in range(steps):
        f = None if k % 7 == 3 else {node: tuple(float(v) for v in rng.normal(scale=0.1, size=3))}
        sim.step(f)
        out.append(sim.displacement(node))
    return np.array(out), sim.get_state()


@pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba is not installed (pip install rtfem[fast])")
@pytest.mark.parametrize("integrator", ["exact", "newmark"])
@pytest.mark.parametrize("correction", [False, True])
def test_the_compiled_step_gives_the_numpy_states(basis, integrator, correction):
    model, modes = basis
    node = int(model.mesh.groups["probe"][0])
    a = rt.ModalSimulator(modes, 1e-3, rt.Damping(alpha=5.0), integrator=integrator, static_correction=correction)
    b = rt.ModalSimulator(modes, 1e-3, rt.Damping(alpha=5.0), integrator=integrator, static_correction=correction)
    assert a.compiled
    b.compiled = False
    ua, sa = _run(a, node)
    ub, sb = _run(b, node)
    scale = np.abs(ub).max()
    np.testing.assert_allclose(ua, ub, rtol=0, atol=1e-13 * scale)
    for key in ("q", "qdot", "f_old"):
        np.testing.assert_allclose(sa[key], sb[key], rtol=0, atol=1e-13 * max(np.abs(sb[key]).max(), 1e-300))


def test_the_python_definition_of_the_kernel_is_the_simulator_step(basis):
    """kernels.reference_step (plain Python, what numba compiles) advances the state exactly as
    ModalSimulator's numpy path does."""
    model, modes = basis
    node = int(model.mesh.groups["probe"][0])
    sim = rt.ModalSimulator(modes, 1e-3, rt.Damping(alpha=5.0), integrator="newmark")
    sim.compiled = False
    S = np.zeros((2, modes.n_modes))
    f_old = np.zeros(modes.n_modes)
    phi = np.ascontiguousarray(modes.shapes)
    for k in range(50):
        f = (0.01 * k, -0.02, 0.05)
        sim.step({node: f})
        kernels.reference_step(sim._coef, S, f_old, phi, node, f, True)
        np.testing.assert_allclose(S[0], sim.q, rtol=1e-12, atol=1e-14 * np.abs(sim.q).max())
