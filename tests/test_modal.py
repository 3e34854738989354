import numpy as np
import pytest

import rtfem as rt
from conftest import liver_model


@pytest.fixture(scope="module")
def liver3():
    model = liver_model(3)
    return model, rt.modal_analysis(model, 12)


def test_save_load_round_trip(tmp_path, liver3):
    model, basis = liver3
    path = basis.save(tmp_path / "liver.modes")
    assert path.suffix == ".npz"
    again = rt.ModalBasis.load(path, model=model)
    assert np.array_equal(again.omega, basis.omega) and np.array_equal(again.shapes, basis.shapes)
    assert again.model is model
    assert again.info["method"] == basis.info["method"]
    assert rt.ModalBasis.load(path).model is None


def test_load_refuses_another_mesh(tmp_path, liver3):
    _, basis = liver3
    path = basis.save(tmp_path / "liver.npz")
    other = rt.ShellModel(rt.meshes.liver(2), rt.Material())
    with pytest.raises(rt.ModelError, match="different mesh"):
        rt.ModalBasis.load(path, model=other)
    moved = rt.TriMesh(np.asarray(basis.model.mesh.vertices) * 1.001, basis.model.mesh.triangles)
    with pytest.raises(rt.ModelError, match="different mesh"):
        rt.ModalBasis.load(path, mesh=moved)


def test_load_checks_format_and_version(tmp_path, liver3):
    _, basis = liver3
    bad = tmp_path / "bad.npz"
    np.savez(bad, omega=basis.omega)
    with pytest.raises(rt.ModelError, match="not an rtfem modal basis"):
        rt.ModalBasis.load(bad)
    newer = tmp_path / "newer.npz"
    np.savez(newer, format=np.array("rtfem.ModalBasis"), version=np.array(99), omega=basis.omega,
             shapes=basis.shapes, fingerprint=np.array("x"), info_keys=np.array([], str), info_values=np.array([], str))
    with pytest.raises(rt.ModelError, match="version 99"):
        rt.ModalBasis.load(newer)
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"not a zip")
    with pytest.raises(rt.ModelError, match="could not read"):
        rt.ModalBasis.load(junk)
    with pytest.raises(rt.ModelError, match="does not exist"):
        rt.ModalBasis.load(tmp_path / "none.npz")


def test_truncated_and_progress(liver3):
    model, basis = liver3
    assert basis.truncated(5).n_modes == 5
    assert np.array_equal(basis.truncated(5).omega, basis.omega[:5])
    with pytest.raises(rt.ModelError):
        basis.truncated(0)
    calls = []
    rt.modal_analysis(model, 4, progress=lambda done, total, message: calls.append((done, total, message)))
    assert any("Lanczos" in m for _, _, m in calls) and "modes in" in calls[-1][2]
    assert all(0 <= d <= t for d, t, _ in calls) and calls[-1][0] == calls[-1][1]  # ends at 100 %
    solves = [d for d, _, m in calls if m.startswith("Lanczos:")]
    assert solves == list(range(1, len(solves) + 1))  # one call per solve, counted


def test_bad_requests(liver3):
    model, _ = liver3
    with pytest.raises(rt.ModelError, match="n_modes"):
        rt.modal_analysis(model, 0)
    big = rt.ShellModel(rt.meshes.liver(4), rt.Material()).fix("attachment")
    with pytest.raises(rt.ModelError, match="dense eigensolver"):
        rt.modal_analysis(big, "all")
    with pytest.raises(rt.ModelError, match="below the number"):
        rt.modal_analysis(rt.ShellModel(rt.meshes.plate(1, 1, 1), rt.Material()).fix([0]), 100)


def test_damping_mapping():
    w = np.array([1.0, 10.0, 100.0])
    assert np.allclose(rt.Damping(alpha=4.0).modal_alpha(w), 4.0)
    assert np.allclose(rt.Damping(alpha=1.0, beta=0.01).modal_alpha(w), 1.0 + 0.01 * w**2)
    assert np.allclose(rt.Damping(zeta=0.05).modal_alpha(w), 0.1 * w)
    assert np.allclose(rt.Damping(zeta=(0.1, 0.2, 0.3)).modal_alpha(w), 2 * np.array([0.1, 0.2, 0.3]) * w)
    with pytest.raises(rt.ModelError, match="3 modes"):
        rt.Damping(zeta=(0.1, 0.2)).modal_alpha(w)
    for bad in (dict(alpha=-1.0), dict(beta=np.nan), dict(zeta=-0.1), dict(alpha="x")):
        with pytest.raises(rt.ModelError):
            rt.Damping(**bad)
    with pytest.raises(rt.ModelError, match="no full-system"):
        rt.Damping(zeta=0.05).matrix(1.0, 1.0)
