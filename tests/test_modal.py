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
    for solver, prefix, step in (("arpack", "Lanczos:", 1), ("block", "block Lanczos:", 8)):
        calls = []
        rt.modal_analysis(model, 4, solver=solver, progress=lambda done, total, message: calls.append((done, total, message)))
        assert any("Lanczos" in m for _, _, m in calls) and "modes in" in calls[-1][2]
        assert all(0 <= d <= t for d, t, _ in calls) and calls[-1][0] == calls[-1][1]  # ends at 100 %
        counts = [d for d, _, m in calls if m.startswith(prefix)]
        assert len(counts) > 1 and counts == list(range(step, step * len(counts) + 1, step))  # one call per solve


def test_block_and_arpack_give_the_same_modes():
    """The block shift-invert Lanczos against ARPACK on the same factorization (issue 12:
    modes equal to 1e-8), restrained and free (shifted below the rigid-body modes)."""
    restrained = liver_model(3)
    free = rt.ShellModel(rt.meshes.liver(3), rt.Material())
    for model, r in ((restrained, 40), (free, 16)):
        a = rt.modal_analysis(model, r, solver="block")
        b = rt.modal_analysis(model, r, solver="arpack")
        assert a.info["method"].startswith("block") and b.info["method"].startswith("shift-invert")
        assert a.info["block_solves"] > 1 and a.info["krylov_dim"] >= r
        assert np.abs(a.eigenvalues - b.eigenvalues).max() <= 1e-10 * b.eigenvalues.max()
        elastic = slice(6, None) if model is free else slice(None)  # rigid modes: any basis of the null space
        assert np.abs(a.shapes[..., elastic] - b.shapes[..., elastic]).max() <= 1e-8 * np.abs(b.shapes).max()
    assert np.abs(a.eigenvalues[:6]).max() < 1e-6 * a.eigenvalues[6]  # the free model's rigid-body modes


def test_block_modes_recover_massless_translations(monkeypatch):
    """The block method recovers a mode's massed rows from the Lanczos relation and its
    massless translations from the kept rows of the block solves (no solve after the
    iteration): with the mass of a few free nodes' translations set to zero, it equals ARPACK's
    generalized shift-invert mode on the same matrices, at those nodes too."""
    model = liver_model(3)
    M, dofs = model.constrained_mass()
    node_of = np.asarray(dofs) // model.dofs_per_node
    free_nodes = np.flatnonzero(~model.fixed.any(axis=1))[[5, 40, 90]]
    cut = np.isin(node_of, free_nodes) & (np.asarray(dofs) % model.dofs_per_node < 3)
    M2 = M.tolil(copy=True)
    M2.setdiag(np.where(cut, 0.0, M.diagonal()))
    M2 = M2.tocsr()
    monkeypatch.setattr(model, "constrained_mass", lambda: (M2, dofs))
    a = rt.modal_analysis(model, 30, solver="block")
    b = rt.modal_analysis(model, 30, solver="arpack")
    assert a.info["solves"] == 8 * a.info["block_solves"]  # no recovery solve
    assert np.abs(a.eigenvalues - b.eigenvalues).max() <= 1e-10 * b.eigenvalues.max()
    at = a.shapes[free_nodes]
    assert np.abs(at).max() > 0.01 * np.abs(a.shapes).max()  # the massless nodes do move
    assert np.abs(at - b.shapes[free_nodes]).max() <= 1e-8 * np.abs(b.shapes).max()
    assert np.abs(a.shapes - b.shapes).max() <= 1e-8 * np.abs(b.shapes).max()


def test_block_solver_choice(liver3, monkeypatch):
    model, basis = liver3
    with pytest.raises(rt.ModelError, match="positive definite"):
        rt.modal_analysis(model, 4, solver="block", sigma=10.0)
    with pytest.raises(rt.ModelError, match="solver"):
        rt.modal_analysis(model, 4, solver="lobpcg")
    import rtfem.reduction.modal

    def stops_short(*args, **kwargs):
        raise rtfem.reduction.modal.BlockLanczosFailed("the Krylov block lost rank")

    monkeypatch.setattr(rtfem.reduction.modal, "block_eigs", stops_short)
    auto = rt.modal_analysis(model, 12)  # the block method stops short: ARPACK, and says why
    assert auto.info["method"].startswith("shift-invert") and "lost rank" in auto.info["fallback"]
    assert np.abs(auto.eigenvalues - basis.eigenvalues).max() <= 1e-10 * basis.eigenvalues.max()
    with pytest.raises(rt.SolverError, match="solver='arpack'"):
        rt.modal_analysis(model, 12, solver="block")
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
