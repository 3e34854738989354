"""The drawn field on a GPU through CuPy (issue 12): ModalSimulator.displacements(device="gpu").

CI has no GPU, so the path's own code is run with a stand-in for CuPy that computes with numpy
(same calls: asarray uploads, a product, asnumpy brings it back) and is checked against the CPU
field; the real CuPy check runs where CuPy finds a CUDA device and is skipped elsewhere. It has
passed on an H100 with CuPy 14.2 for CUDA 13 (benchmarks/results/haptic_loop_gpu_h100.txt)."""

from __future__ import annotations

import types

import numpy as np
import pytest

import rtfem as rt
from rtfem.drivers import gpu


@pytest.fixture()
def stand_in(monkeypatch):
    """CuPy's calls on numpy, counting the uploads of the shape matrix."""
    uploads = []

    def asarray(a, dtype=None):
        a = np.array(a, dtype=dtype)
        if a.ndim == 2:
            uploads.append(a.dtype)
        return a

    fake = types.SimpleNamespace(asarray=asarray, asnumpy=lambda a: np.array(a))
    monkeypatch.setitem(gpu._FOUND, "xp", fake)
    monkeypatch.setitem(gpu._FOUND, "why", "numpy stand-in")
    return uploads


def loaded_sim(basis, **kw):
    sim = rt.ModalSimulator(basis, 1e-3, rt.Damping(alpha=8.0), **kw)
    for _ in range(5):
        sim.step({7: (0.0, 0.0, -0.2), 40: (0.05, 0.0, 0.0)})
    return sim


@pytest.mark.parametrize("static_correction", [False, True])
def test_the_gpu_path_gives_the_cpu_field(liver3_modes, stand_in, static_correction):
    model, basis = liver3_modes
    sim = loaded_sim(basis, static_correction=static_correction)
    for dtype, tol in ((np.float64, 1e-14), (np.float32, 1e-6)):
        cpu = sim.displacements(dtype=dtype)
        for _ in range(2):
            u = sim.displacements(dtype=dtype, device="gpu")
            assert u.dtype == dtype and u.shape == (model.n_nodes, 3)
            assert np.abs(u - cpu).max() <= tol * np.abs(cpu).max()
        out = np.empty((model.n_nodes, 3), dtype=dtype)
        assert sim.displacements(out, dtype=dtype, device="gpu") is out and np.array_equal(out, u)
    assert stand_in == [np.float64, np.float32]  # the shapes uploaded once per dtype, not per frame
    assert np.abs(cpu).max() > 0


def test_the_gpu_field_refuses_clearly(liver3_modes, monkeypatch):
    model, basis = liver3_modes
    sim = loaded_sim(basis)
    monkeypatch.setitem(gpu._FOUND, "xp", None)
    monkeypatch.setitem(gpu._FOUND, "why", "CuPy is not installed")
    with pytest.raises(rt.ModelError, match="needs CuPy and a CUDA GPU: CuPy is not installed"):
        sim.displacements(device="gpu")
    with pytest.raises(rt.ModelError, match="choose one of 'cpu', 'gpu'"):
        sim.displacements(device="tpu")
    with pytest.raises(rt.ModelError, match="float64 or float32"):
        sim.displacements(dtype=np.int32, device="gpu")
    warped = rt.ModalSimulator(basis, 1e-3, warping=True)
    with pytest.raises(rt.ModelError, match="on the CPU"):
        warped.displacements(device="gpu")
    assert sim.steps == 5  # nothing stepped or lost


@pytest.mark.skipif(gpu.module() is None, reason=f"no GPU field here: {gpu.status()}")
def test_the_cupy_field_on_a_real_gpu(liver3_modes):
    model, basis = liver3_modes
    sim = loaded_sim(basis, static_correction=True)
    for dtype, tol in ((np.float64, 1e-12), (np.float32, 1e-6)):
        cpu = sim.displacements(dtype=dtype)
        u = sim.displacements(dtype=dtype, device="gpu")
        assert u.dtype == dtype and np.abs(u - cpu).max() <= tol * np.abs(cpu).max()


def test_the_viewer_draws_from_the_cpu_when_the_gpu_fails(liver3_modes, monkeypatch):
    """A GPU product that fails mid-session (out of device memory, a lost device) is said in the
    panel and the frames go on from the CPU field."""
    import threading

    from rtfem.viewer.session import Session

    model, basis = liver3_modes
    sim = loaded_sim(basis)

    def broken(a, dtype=None):
        raise MemoryError("out of device memory")

    monkeypatch.setitem(gpu._FOUND, "xp", types.SimpleNamespace(asarray=broken, asnumpy=np.asarray))
    session = types.SimpleNamespace(_lock=threading.RLock(), driver=sim, field_device="gpu", error=None)
    u = Session.displacements(session)
    assert np.array_equal(u, sim.displacements(dtype=np.float32))
    assert session.field_device == "cpu" and "out of device memory" in session.error
