"""SolidModel through the Model protocol: masses, fixes, and every consumer unchanged
(modal, SLDM, the full-order simulators, static correction, impedance map, probe, haptic loop,
viewer session, exports); meshing surfaces into tets."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg as sla

import rtfem as rt
from rtfem.fe.protocol import MODEL_MEMBERS, check_model
from rtfem.reduction.oscillator import step_response
from conftest import organ

MAT = rt.Material(E=2e4, nu=0.45, density=1000.0)


@pytest.fixture(scope="module")
def beam():
    """A small clamped solid bar (tet4, lumped): small enough for dense references."""
    model = rt.SolidModel(rt.meshes.box(0.12, 0.03, 0.03, 6, 2, 2), MAT).fix("x0")
    return model, int(np.flatnonzero(np.all(np.isclose(model.mesh.vertices, [0.12, 0.03, 0.03]), axis=1))[0])


def test_protocol_and_repr(beam):
    model, _ = beam
    assert check_model(model) is model and all(hasattr(model, m) for m in MODEL_MEMBERS)
    assert isinstance(model, rt.Model)
    assert model.dofs_per_node == 3 and model.n_dofs == 3 * model.n_nodes
    assert model.metadata == {"model": "solid", "element": "tet4", "mass": "lumped", "constraints": "elimination"}
    assert "tet4 tets" in repr(model)
    before = model.fixed.copy()
    with pytest.raises(rt.ModelError, match="no rotations"):
        model.fix([0], "rx")
    assert np.array_equal(model.fixed, before)  # a refused fix changes nothing
    with pytest.raises(rt.ModelError, match="no whole surface triangle"):
        model.pressure_forces(100.0, nodes=[0])
    with pytest.raises(rt.ModelError, match="traction"):
        model.traction_forces((0.0, np.nan, 0.0), "x1")
    with pytest.raises(rt.ModelError, match="TriMesh or TetMesh"):
        rt.io.write_vtu("never.vtu", model)
    with pytest.raises(rt.ModelError, match="TetMesh"):
        rt.SolidModel(rt.meshes.icosphere(0.1, 1), MAT)
    with pytest.raises(rt.ModelError, match="element='tet10'"):
        rt.SolidModel(rt.meshes.box(0.1, 0.1, 0.1, 1, 1, 1).quadratic(), MAT)
    with pytest.raises(rt.ModelError, match="element"):
        rt.SolidModel(rt.meshes.box(), MAT, element="hex8")


@pytest.mark.parametrize("element", ["tet4", "tet10"])
@pytest.mark.parametrize("mass", ["lumped", "consistent"])
def test_mass_totals_and_definiteness(element, mass):
    mesh = rt.meshes.box(0.2, 0.1, 0.05, 2, 2, 1)
    model = rt.SolidModel(mesh, MAT, element=element, mass=mass)
    M = model.M
    total = MAT.density * mesh.volume()
    # each translation carries the body's mass: 1^T M 1 per direction
    e = np.zeros(model.n_dofs)
    e[0::3] = 1.0
    assert e @ (M @ e) == pytest.approx(total, rel=1e-12)
    assert model.mass_diagonal.sum() == pytest.approx(3 * total, rel=1e-12)
    assert np.all(model.mass_diagonal > 0)  # HRZ: no negative corner masses for tet10
    assert np.linalg.eigvalsh(M.toarray()).min() > 0
    assert abs(M - M.T).max() < 1e-15 * abs(M).max()


def test_quadrature_rules_integrate_monomials_to_their_degree():
    """Stroud's rule with n points per direction integrates every monomial x^a y^b z^c of degree
    <= 2n - 1 over the reference tet exactly (a! b! c! / (a + b + c + 3)!) and not every one of
    degree 2n; the tet10 stiffness takes n = 2 (8 points, a quadratic integrand on a straight-sided
    tet10: exact), its consistent mass n = 3."""
    from math import factorial

    from rtfem.fe import solid

    def worst(rule, degree):
        pts, w = rule
        errs = []
        for a in range(degree + 1):
            for b in range(degree + 1 - a):
                c = degree - a - b
                exact = factorial(a) * factorial(b) * factorial(c) / factorial(degree + 3)
                errs.append(abs(w @ (pts[:, 0] ** a * pts[:, 1] ** b * pts[:, 2] ** c) - exact) / exact)
        return max(errs)

    for n in (1, 2, 3):
        assert solid.tet_rule(n)[0].shape == (n**3, 3)
        assert all(worst(solid.tet_rule(n), d) < 1e-13 for d in range(2 * n))
        assert worst(solid.tet_rule(n), 2 * n) > 1e-6


def test_consistent_mass_modes_equal_the_dense_generalized_problem():
    model = rt.SolidModel(rt.meshes.box(0.12, 0.03, 0.03, 6, 2, 2), MAT, mass="consistent").fix("x0")
    K, dofs = model.constrained_stiffness()
    M, _ = model.constrained_mass()
    lam = sla.eigh(K.toarray(), M.toarray(), eigvals_only=True, subset_by_index=[0, 11])
    basis = rt.modal_analysis(model, 12, solver="auto")
    np.testing.assert_allclose(basis.omega**2, lam, rtol=1e-8)
    assert "consistent" in basis.info.get("fallback", "")
    P = basis.matrix
    np.testing.assert_allclose(P.T @ (model.M @ P), np.eye(12), atol=1e-9)
    with pytest.raises(rt.ModelError, match="lumped"):
        rt.SLDM(model, rt.Damping(alpha=4.0))
    with pytest.raises(rt.ModelError, match="lumped"):
        rt.CentralDifferenceSimulator(model, 1e-5, rt.Damping(alpha=4.0))
    with pytest.raises(rt.ModelError, match="diagonal"):
        rt.modal_analysis(model, 12, solver="block")


def test_sldm_and_direct_newmark_agree_with_the_full_modal_solution(beam):
    model, node = beam
    damping = rt.Damping(alpha=20.0)
    basis = rt.modal_analysis(model, "all")
    forces = {node: (0.0, 0.02, -0.05)}
    times = np.linspace(0.0, 0.1, 11)
    P = basis.matrix
    F = model.force_vector(forces).reshape(-1, 3).ravel()
    coef = step_response(basis.omega[:, None] ** 2, damping.modal_alpha(basis.omega)[:, None], times[None, :])
    ref = (P @ (coef * (P.T @ F)[:, None])).T.reshape(times.size, -1, 3)
    U = rt.SLDM(model, damping).step_response(forces, times, tol=1e-10)
    assert np.abs(U - ref).max() < 1e-7 * np.abs(ref).max()
    # full-order Newmark and the modal Newmark integrator on all modes: the same recursion
    dt = 1e-3
    direct = rt.DirectSimulator(model, dt, damping)
    modal = rt.ModalSimulator(basis, dt, damping, integrator="newmark")
    for _ in range(60):
        direct.step(forces)
        modal.step(forces)
    np.testing.assert_allclose(modal.displacements(), direct.displacements(), rtol=0,
                               atol=1e-9 * np.abs(direct.displacements()).max())


def test_static_correction_and_impedance_map_settle_at_the_static_solution(beam):
    model, node = beam
    f = (0.0, 0.0, -0.05)
    u_static = model.solve_static({node: f})
    sim = rt.ModalSimulator(rt.modal_analysis(model, 10), 1e-3, rt.Damping(alpha=20.0), static_correction=True)
    for _ in range(3000):
        sim.step({node: f})
    np.testing.assert_allclose(sim.displacements(), u_static, atol=1e-9 * np.abs(u_static).max())
    imap = rt.ImpedanceMap.build(model, rt.Damping(alpha=4.0), nodes=[node], n_modes=10)
    np.testing.assert_allclose(imap.point_compliance(node) @ f, u_static[node], rtol=1e-10)
    # the default loaded nodes are the free surface nodes, not the interior ones
    X = np.asarray(model.mesh.vertices)
    interior = np.flatnonzero(((X > 1e-9) & (X < np.array([0.12, 0.03, 0.03]) - 1e-9)).all(axis=1))
    assert interior.size and not np.isin(interior, model.mesh.used_vertices()).any()


def test_surface_compliance_by_condensation_equals_the_solves_and_the_map_built_on_it(beam, monkeypatch):
    """Bro-Nielsen & Cotin's condensed surface compliance (the interior's Schur complement,
    inverted) equals the surface block of K^-1 by multi-column solves and the single unit-load
    responses, and is symmetric; an impedance map whose static limits come from it equals the
    default one (three solves per node) at the surface nodes and keeps no interior node."""
    model, node = beam
    nodes, C = model.surface_compliance()
    nodes_c, C_c = model.surface_compliance(method="condensation")
    used = model.mesh.used_vertices()
    assert np.array_equal(nodes, nodes_c) and np.array_equal(nodes, used[~model.fixed[used, :3].all(axis=1)])
    scale = np.abs(C).max()
    assert np.abs(C - C_c).max() < 1e-12 * scale and np.abs(C_c - C_c.T).max() < 1e-12 * scale
    b = 3 * int(np.searchsorted(nodes, node))
    ref = np.stack([model.unit_load_response(node, k)[nodes] for k in range(3)], axis=2).reshape(-1, 3)
    assert np.abs(C_c[:, b:b + 3] - ref).max() < 1e-12 * scale
    other = int(nodes[nodes.size // 3])
    maps = [rt.ImpedanceMap.build(model, rt.Damping(alpha=4.0), nodes=[node, other], radius=0.05, n_modes=10,
                                  static=static) for static in ("solves", "condensation")]
    a, c = maps
    assert c.info["static"] == "condensation" and np.isin(c.neighbours, used).all()
    assert not np.isin(a.neighbours, used).all()  # the default map keeps interior nodes too
    for k in range(2):
        na, nc = (m.neighbours[m.offsets[k]:m.offsets[k + 1]] for m in maps)
        ra, rc = (m.responses[m.offsets[k]:m.offsets[k + 1]] for m in maps)
        on = np.isin(na, used)
        assert np.array_equal(na[on], nc)
        assert np.abs(ra[on] - rc).max() < 1e-10 * np.abs(ra).max()
    np.testing.assert_allclose(c.point, a.point, rtol=0, atol=1e-10 * np.abs(a.point).max())
    with pytest.raises(rt.ModelError, match="method"):
        model.surface_compliance(method="dense")
    monkeypatch.setattr("rtfem.fe.compliance._DENSE_LIMIT", 30)
    with pytest.raises(rt.ModelError, match="allow_large"):
        model.surface_compliance()


def test_probe_and_loop_touch_the_surface_only(beam):
    model, node = beam
    sim = rt.ModalSimulator(rt.modal_analysis(model, 12), 1e-3, rt.Damping(alpha=20.0), static_correction=True)
    probe = rt.Probe(model.mesh, sim, stiffness=200.0)
    surface = set(model.mesh.used_vertices().tolist())
    X = np.asarray(model.mesh.vertices)
    top = X[node] + np.array([0.0, 0.0, 0.002])
    path = np.array([top - np.array([0.0, 0.0, 0.004 * k / 50]) for k in range(50)])
    forces = probe.replay(path, compiled=False)
    assert probe.contact_node in surface and forces[-1, 2] > 0  # the organ pushes the probe back up
    # the centre of the bar is an interior node: the nearest *touchable* vertex is chosen there
    centre = np.array([0.06, 0.015, 0.015])
    assert model.nearest_free_node(centre) in surface
    assert model.mesh.nearest_vertex(centre) in surface
    stats = rt.HapticLoop(rt.Probe(model.mesh, sim), rt.ScriptedDevice(lambda t: top - [0, 0, 0.004 * t]),
                          rate=1000).run(0.05)
    assert stats.steps > 0


def test_viewer_session_grabs_and_pulls_a_solid():
    from rtfem.viewer.session import Session, Settings

    mesh = rt.meshes.box(0.12, 0.03, 0.03, 6, 2, 2)
    s = Session(mesh, MAT, fixed="x0", settings=Settings(n_modes=12, alpha=60.0, grasp_stiffness=50.0),
                model_options={"element": "tet10"})
    assert s.model.metadata["element"] == "tet10" and s.mesh is s.model.mesh
    tip = np.array([0.12, 0.015, 0.03])
    node = s.grab(tip)
    assert node in set(s.mesh.used_vertices().tolist())
    s.drag(tip + [0.0, 0.0, 0.003])
    for _ in range(400):
        s.step()
    u = s.displacements()
    assert u.shape == (s.model.n_nodes, 3) and u[node, 2] > 0.0005


def test_volume_vtu_carries_the_displacements(tmp_path, beam):
    import meshio

    model, node = beam
    u = model.solve_static({node: (0.0, 0.0, -0.05)})
    path = rt.io.write_vtu(tmp_path / "bar.vtu", model.tetmesh, u)
    m = meshio.read(path)
    assert m.cells[0].type == "tetra" and len(m.cells[0].data) == model.tetmesh.n_tets
    np.testing.assert_allclose(m.point_data["displacement"], u)
    np.testing.assert_allclose(m.points, model.tetmesh.vertices)  # at rest: ParaView's Warp By Vector adds u


needs_mesher = pytest.mark.skipif(not rt.mesh.meshing.mesher_available(), reason="the mesh extra (pytetwild) is not installed")


@needs_mesher
def test_tetrahedralize_a_sphere_and_refusals(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "__tracked_surface.stl").write_text("the user's own file")
    sphere = rt.meshes.icosphere(0.05, 2)
    tets = rt.tetrahedralize(sphere, 0.01)
    # fTetWild writes a debug surface into the working directory: it runs in a scratch one
    assert [p.name for p in tmp_path.iterdir()] == ["__tracked_surface.stl"]
    assert (tmp_path / "__tracked_surface.stl").read_text() == "the user's own file"
    assert tmp_path.samefile(".")
    assert tets.volume() == pytest.approx(sphere.volume(), rel=0.01)
    assert tets.surface.is_closed() and tets.quality().radius_ratio.min() > 0.05
    with pytest.raises(rt.MeshError, match="boundary edges"):
        rt.tetrahedralize(rt.meshes.hemisphere(0.05, 6))
    two = rt.TriMesh(np.vstack([sphere.vertices, sphere.vertices + 1.0]),
                     np.vstack([sphere.triangles, sphere.triangles + sphere.n_vertices]))
    with pytest.raises(rt.MeshError, match="separate pieces"):
        rt.tetrahedralize(two)
    with pytest.raises(rt.MeshError, match="edge_length"):
        rt.tetrahedralize(sphere, 1e-9)


def test_solid_default_liver_keeps_its_groups_and_its_mesh():
    """The default solid liver is the shipped mesh (no mesher needed: the same organ on every
    machine), and it is a mesh of the surface ``liver(3)`` that the code generates: its boundary
    lies within fTetWild's envelope (1e-3 of the diagonal) of the surface's triangles."""
    from importlib import resources

    from scipy.spatial import cKDTree

    from rtfem.interaction.contact_points import closest_points_on_triangles

    a = rt.meshes.liver(solid=True)
    b = rt.meshes.liver(solid=True)
    assert a.fingerprint() == b.fingerprint()
    with np.load(resources.files("rtfem") / "data" / "liver_tets.npz") as shipped:
        assert np.array_equal(a.vertices, shipped["vertices"]) and np.array_equal(a.tets, shipped["tets"])
    s = rt.meshes.liver(3)
    V, T = np.asarray(s.vertices), np.asarray(s.triangles)
    P = np.asarray(a.vertices)[a.surface_nodes()]
    _, near = cKDTree(V[T].mean(axis=1)).query(P, k=12)
    dist = np.full(len(P), np.inf)
    for j in range(near.shape[1]):
        t = T[near[:, j]]
        q, _ = closest_points_on_triangles(P, V[t[:, 0]], V[t[:, 1]], V[t[:, 2]])
        dist = np.minimum(dist, np.linalg.norm(q - P, axis=1))
    assert dist.max() < 1e-3 * s.diagonal(), dist.max() / s.diagonal()  # shipped: 3.2e-4
    surface = set(a.surface_nodes().tolist())
    assert len(a.groups["probe"]) == 1 and int(a.groups["probe"][0]) in surface
    assert a.groups["attachment"].size >= 10 and set(a.groups["attachment"].tolist()) <= surface
    assert a.volume() == pytest.approx(rt.meshes.liver(3).volume(), rel=0.02)


@needs_mesher
def test_small_organ_file_meshes():
    surface = rt.load_mesh(organ("sofa_env_gallbladder_collision.stl"), scale=1e-3)
    tets = rt.tetrahedralize(surface)
    assert tets.volume() == pytest.approx(surface.volume(), rel=0.02)
    model = rt.SolidModel(tets, MAT).fix("bottom:0.2")
    assert rt.modal_analysis(model, 6).frequencies[0] > 0


def test_clamping_a_tet10_model_by_its_corner_nodes_clamps_the_mid_edge_nodes_between_them():
    """Fixing the corner nodes of a face (the indices of the 4-node mesh the tet10 model was made
    from) fixes the mid-edge nodes between two fixed corners: the cantilever deflects as when
    clamped by the region (to round-off; before, the free mid-edge nodes let it deflect 8.6 % more);
    a mid-edge node with one corner fixed stays free, and only the dofs asked are fixed."""
    mesh = rt.meshes.box(1.0, 0.1, 0.1, nx=10, ny=2, nz=2)
    X = np.asarray(mesh.vertices)
    corners = np.flatnonzero(X[:, 0] == 0.0)
    by_corners = rt.SolidModel(mesh, rt.Material(E=1e5, nu=0.3), element="tet10").fix(corners)
    by_region = rt.SolidModel(mesh, rt.Material(E=1e5, nu=0.3), element="tet10").fix("x0")
    assert np.array_equal(by_corners.fixed, by_region.fixed)
    tip = by_region.select_nodes("x1")
    F = np.zeros((by_region.n_nodes, 3))
    F[tip, 2] = 0.01
    np.testing.assert_allclose(by_corners.solve_static(F), by_region.solve_static(F), rtol=1e-12, atol=1e-15)
    one = rt.SolidModel(mesh, rt.Material(E=1e5, nu=0.3), element="tet10").fix(corners[:1])
    assert one.fixed.any(axis=1).sum() == 1  # no edge with both corners fixed
    z = rt.SolidModel(mesh, rt.Material(E=1e5, nu=0.3), element="tet10").fix(corners, dofs="z")
    assert z.fixed[:, 2].sum() == by_region.held_nodes.sum() and not z.fixed[:, :2].any()


def test_a_damaged_shipped_liver_says_reinstall(tmp_path, monkeypatch):
    """The shipped tets, damaged in the installed package: a MeshError that says what to do, not a
    traceback from numpy's reader."""
    import importlib.resources

    from rtfem.mesh.meshes import _embedded_liver  # under liver(solid=True)'s memo of its meshes

    (tmp_path / "data").mkdir()
    (tmp_path / "data" / "liver_tets.npz").write_bytes(b"PK\x03\x04 not a zip any more")
    monkeypatch.setattr(importlib.resources, "files", lambda package: tmp_path)
    with pytest.raises(rt.MeshError, match="liver_tets.npz.*reinstall rtfem"):
        _embedded_liver()
