"""The plotted comparisons are right before they are pretty: direct -> SLDM as dt -> 0, modal -> SLDM as r grows."""

from __future__ import annotations

import numpy as np
import pytest

import rtfem as rt

pytest.importorskip("matplotlib")
from rtfem.cli import plots  # noqa: E402


@pytest.fixture(scope="module")
def case():
    mesh = rt.meshes.hemisphere(radius=0.05, n_rings=8)
    model = rt.ShellModel(mesh, rt.Material(E=1e5, nu=0.45, thickness=0.003, density=1000.0))
    model.fix("rim")
    node = int(mesh.groups["pole"][0])
    basis = rt.modal_analysis(model, "all")  # every massed mode: the modal solution is then exact
    return model, node, np.array([0.0, 0.0, -0.05]), basis


def test_step_response_direct_converges_to_sldm_at_first_order(case):
    model, node, f, basis = case
    t = np.linspace(0, 0.1, 101)[1:]
    d = rt.Damping(alpha=8.0)
    errs = []
    for dt in (1e-3, 5e-4):
        res = plots.step_responses(model, node, f, t, d, [10], basis, dt_direct=dt)
        errs.append(np.abs(res["direct"] - res["sldm"]).max() / np.abs(res["sldm"]).max())
    # trapezoidal (Newmark) steps across the load's jump: O(dt), so halving dt halves the error
    assert 1.7 < errs[0] / errs[1] < 2.3, errs


def test_error_against_modes_falls_and_the_correction_helps(case, tmp_path):
    model, node, f, basis = case
    t = np.linspace(0, 0.1, 101)[1:]
    d = rt.Damping(alpha=8.0)
    res = plots.step_responses(model, node, f, t, d, [10, 40], basis, dt_direct=1e-3)
    rs = [5, 10, 20, 40, 80, 160, basis.n_modes]
    err = plots.error_vs_modes(res, rs)
    assert np.all(np.diff(err["corrected_rms"]) < 0) and np.all(err["corrected_rms"][:-1] < err["plain_rms"][:-1])
    # all modes: modal superposition is exact, and so is SLDM (tol 1e-8): two algorithms agree
    assert err["plain"][-1] < 1e-6 and err["corrected"][-1] < 1e-6, err
    for name, path in (("step", plots.step_response_png(res, tmp_path / "s.png", 1e-3, [10, 40])),
                       ("error", plots.error_png(err, tmp_path / "e.png")),
                       ("spectrum", plots.spectrum_png(basis, tmp_path / "f.png"))):
        assert path.stat().st_size > 5000, name
