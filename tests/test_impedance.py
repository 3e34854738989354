import numpy as np
import pytest

import rtfem as rt
from conftest import liver_model

TIMES = np.round(np.arange(1, 31) * 0.01, 10)  # 10 ms .. 300 ms


@pytest.fixture(scope="module")
def setup():
    model = liver_model(3)
    mesh = model.mesh
    damping = rt.Damping(alpha=8.0)
    a = mesh.groups["probe"][0]
    b = mesh.nearest_vertex([-0.06, 0.04, -0.01])
    imap = rt.ImpedanceMap.build(model, damping, nodes=[a, b], times=TIMES, n_modes=40)
    return model, damping, imap, a, b


def test_infinite_radius_equals_modal_simulation(setup):
    model, damping, imap, a, b = setup
    basis = rt.modal_analysis(model, 40)
    sim = rt.ModalSimulator(basis, 1e-3, damping, static_correction=True)
    fa, fb = np.array([0.0, -0.1, 0.05]), np.array([0.02, 0.0, -0.08])
    loads = [rt.Load(a, tuple(fa), 0.0), rt.Load(b, tuple(fb), 0.05), rt.Load(a, tuple(-fa), 0.12)]
    for k in range(200):
        t = k * 1e-3
        f = {}
        if t < 0.12 - 1e-9:
            f[a] = fa
        if t >= 0.05 - 1e-9:
            f[b] = fb
        sim.step(f)
        if (k + 1) % 50 == 0:  # sample times where every delay is on the map's grid
            u = imap.displacements(loads, sim.time)
            ref = sim.displacements()
            assert np.abs(u - ref).max() < 1e-9 * np.abs(ref).max(), sim.time


def test_static_limit_and_point_compliance(setup):
    model, _, imap, a, b = setup
    G = imap.point_compliance(a)
    assert np.abs(G - G.T).max() < 1e-9 * np.abs(G).max()  # reciprocity at a point
    assert np.all(np.linalg.eigvalsh(G) > 0)
    f = np.array([0.0, -0.1, 0.05])
    ref = model.solve_static({a: f})[a]
    assert np.abs(G @ f - ref).max() < 1e-10 * np.abs(ref).max()
    u = imap.displacements([(a, f, 0.0)], 10.0)  # long after the last sample: static
    assert np.allclose(u, model.solve_static({a: f}), rtol=0, atol=1e-10 * np.abs(u).max())
    # Maxwell-Betti: the response at b to a load at a equals the transpose of the reverse
    Gab = np.stack([imap.displacements([(a, e, 0.0)], 10.0)[b] for e in np.eye(3)], axis=1)
    Gba = np.stack([imap.displacements([(b, e, 0.0)], 10.0)[a] for e in np.eye(3)], axis=1)
    assert np.allclose(Gab, Gba.T, rtol=1e-9, atol=1e-14)
    assert np.allclose(imap.point_compliance(a, 0.0), 0.0)
    assert np.allclose(imap.point_compliance(a, TIMES[4]), imap.point[0, 4])


def test_sldm_map_matches_sldm_and_static(setup):
    model, damping, _, a, _ = setup
    imap = rt.ImpedanceMap.build(model, damping, nodes=[a], times=TIMES[:10], method="sldm", tol=1e-8)
    f = np.array([0.0, -0.1, 0.05])
    U = rt.SLDM(model, damping).step_response({a: f}, TIMES[:10], tol=1e-8)
    for k in (0, 4, 9):
        assert np.abs(imap.displacements([(a, f, 0.0)], TIMES[k]) - U[k]).max() < 1e-6 * np.abs(U[k]).max()
    ref = model.solve_static({a: f})[a]
    assert np.abs(imap.point_compliance(a) @ f - ref).max() < 1e-10 * np.abs(ref).max()


def test_truncation_error_falls_with_radius_and_threshold(setup):
    model, damping, full, a, _ = setup
    f = (0.0, -0.1, 0.05)
    ref = full.displacements([(a, f, 0.0)], 0.1)
    errs = []
    for R in (0.03, 0.06, 0.12, 0.3):
        m = rt.ImpedanceMap.build(model, damping, nodes=[a], times=TIMES, n_modes=40, radius=R)
        errs.append(np.linalg.norm(m.displacements([(a, f, 0.0)], 0.1) - ref) / np.linalg.norm(ref))
    assert all(e2 < e1 for e1, e2 in zip(errs, errs[1:])) and errs[-1] < 1e-12
    g = rt.ImpedanceMap.build(model, damping, nodes=[a], times=TIMES, n_modes=40, radius=0.06, metric="geodesic")
    assert g.offsets[1] <= rt.ImpedanceMap.build(model, damping, nodes=[a], times=TIMES, n_modes=40, radius=0.06).offsets[1]
    t1 = rt.ImpedanceMap.build(model, damping, nodes=[a], times=TIMES, n_modes=40, threshold=0.01)
    err = np.linalg.norm(t1.displacements([(a, f, 0.0)], 0.1) - ref) / np.linalg.norm(ref)
    assert err < 0.01 < errs[1]  # magnitude truncation beats a radius keeping similar numbers of nodes


def test_save_load_and_interrupt(tmp_path, setup):
    model, damping, imap, a, _ = setup
    path = imap.save(tmp_path / "map")
    again = rt.ImpedanceMap.load(path, model=model)
    assert np.array_equal(again.responses, imap.responses) and again.info["method"] == "modal"
    other = rt.ShellModel(rt.meshes.liver(2), rt.Material())
    with pytest.raises(rt.ModelError, match="different mesh"):
        rt.ImpedanceMap.load(path, model=other)
    calls = []

    def stop_after_two(done, total, seconds):
        calls.append(done)
        if done == 2:
            raise KeyboardInterrupt

    part = rt.ImpedanceMap.build(model, damping, nodes=np.arange(10, 20), times=TIMES[:3], n_modes=10,
                                 progress=stop_after_two)
    assert part.loaded.size == 2 and part.info["complete"] is False
    assert part.bytes_per_node > 0


def test_parallel_build_and_fixed_nodes(setup):
    model, damping, _, a, b = setup
    fixed = int(model.mesh.groups["attachment"][0])
    nodes = [a, b, fixed, 7, 11]
    one = rt.ImpedanceMap.build(model, damping, nodes=nodes, times=TIMES[:4], n_modes=20, radius=0.05)
    two = rt.ImpedanceMap.build(model, damping, nodes=nodes, times=TIMES[:4], n_modes=20, radius=0.05, workers=2)
    assert fixed not in one.loaded and one.info["skipped_fixed_nodes"] == 1
    assert np.array_equal(one.loaded, two.loaded) and np.array_equal(one.neighbours, two.neighbours)
    assert np.abs(one.responses - two.responses).max() < 1e-12 * np.abs(one.responses).max()


def test_bad_input(setup):
    model, damping, imap, a, _ = setup
    with pytest.raises(rt.ModelError, match="not a loaded node"):
        imap.displacements([(5, (1, 0, 0), 0.0)], 0.1)
    with pytest.raises(rt.ModelError, match="finite"):
        imap.displacements([(a, (np.nan, 0, 0), 0.0)], 0.1)
    with pytest.raises(rt.ModelError, match="GiB"):
        rt.ImpedanceMap.build(model, damping, times=TIMES, memory_limit=1e6)
    with pytest.raises(rt.ModelError, match="times"):
        rt.ImpedanceMap.build(model, damping, nodes=[a], times=[0.1, 0.05])
    with pytest.raises(rt.ModelError, match="method"):
        rt.ImpedanceMap.build(model, damping, nodes=[a], method="fem")


def test_the_size_estimate_is_what_the_build_holds_and_the_cli_asks_before_a_large_map(tmp_path, capsys):
    """ImpedanceMap.estimate_bytes, before any work, against the map built with the same settings
    (exact for up to 20 loaded nodes, which it samples all); `rtfem impedance` prints it first and
    refuses a map past 1 GiB without --allow-large (the README's old example wrote 567 MiB
    unannounced; every free node with no radius would be ~3.6 GB)."""
    from rtfem.cli.main import main

    model = rt.ShellModel(rt.meshes.liver(2), rt.Material()).fix("attachment")
    nodes = model.mesh.used_vertices()[::40][:12]
    est = rt.ImpedanceMap.estimate_bytes(model, nodes=nodes, radius=0.03, times=[0.01, 0.1])
    imap = rt.ImpedanceMap.build(model, rt.Damping(alpha=8.0), nodes=nodes, radius=0.03, times=[0.01, 0.1],
                                 n_modes=10)
    assert est["loaded"] == imap.loaded.size and est["samples"] == 3
    assert est["bytes"] == imap.responses.nbytes
    out = tmp_path / "big.map.npz"
    assert main(["impedance", "-o", str(out)]) == 2
    said = capsys.readouterr()
    assert "estimate" in said.out and "--allow-large" in said.err and not out.exists()


def test_a_loaded_nodes_result_holds_only_what_the_map_keeps():
    """Each loaded node's result owns its arrays: its point response was a view of the node's whole
    (n, samples, 3, 3) column block, which kept every block alive until the map was assembled (the
    default liver's 194 MB map peaked at 4.26 GB; 0.85 GB since)."""
    from rtfem.drivers.impedance_columns import _column_task, _ModalColumns, _NeighbourFinder

    model = rt.ShellModel(rt.meshes.hemisphere(), rt.Material())
    X = np.asarray(model.mesh.vertices)
    model.fix(np.flatnonzero(X[:, 2] < 1e-4))
    engine = _ModalColumns(model, rt.Damping(), np.array([0.01]), 10)
    j, keep, cols, point = _column_task(engine, _NeighbourFinder(model.mesh, 0.01, "euclidean"), None, None)(100)
    for a in (cols, point):
        assert a.base is None or a.base.nbytes == a.nbytes  # no view into the node's whole block
    assert keep.size < model.n_nodes / 4 and point.shape == (2, 3, 3)


def test_an_on_demand_driver_steps_before_any_load_and_then_answers_as_one_loaded_at_once(setup):
    """A dynamic on-demand driver (the viewer's impedance method) has no map before the first load: stepped
    idle it stays at rest (it raised ValueError: no map to take the history's resolution from), and a load
    applied after the idle steps gets the response a fresh driver gives the same load (time invariance)."""
    model = setup[0]
    node = int(model.mesh.used_vertices()[0])
    modes = rt.modal_analysis(model, 8)
    idle, fresh = (rt.ImpedanceDriver.on_demand(model, rt.Damping(alpha=5.0), 1e-3, dynamic=True, modes=modes,
                                                times=(0.005, 0.01)) for _ in range(2))
    for _ in range(5):
        idle.step()
    assert np.abs(idle.displacements()).max() == 0.0 and idle.steps == 5
    load = {node: np.array([0.0, 0.0, -0.5])}
    for d in (idle, fresh):
        d.prepare([node])  # (the viewer's grab does this)
        for _ in range(8):
            d.step(load)
    np.testing.assert_allclose(idle.displacements(), fresh.displacements(), rtol=0, atol=1e-15)
    assert np.abs(fresh.displacements()).max() > 0
