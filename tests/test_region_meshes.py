"""Labelled tet meshes and models of several regions (issue 58): labels through repair, the mesh's
derived forms, files and cuts; the region materials' checks and refusals; the full-order step's
compiled kernels against the nonlinear system's batched evaluation on a two-region model."""

from __future__ import annotations

import numpy as np
import pytest

import rtfem as rt


def _labelled(order: int = 1):
    box = rt.meshes.box(0.03, 0.02, 0.02, nx=3, ny=2, nz=2)
    c = np.asarray(box.vertices)[np.asarray(box.corner_tets)].mean(axis=1)
    mesh = rt.TetMesh(box.vertices, box.tets, labels=np.where(c[:, 0] > 0.02, 7, 3),
                      region_names={"liver": 3, "tumor": 7}, groups=box.groups)
    return mesh.quadratic() if order == 2 else mesh


def test_labels_follow_repair_and_the_derived_meshes():
    box = rt.meshes.box(1.0, 1.0, 1.0, nx=2, ny=2, nz=2)
    T = np.asarray(box.tets)
    labels = np.arange(T.shape[0]) % 3
    # a duplicate tet (dropped by repair) and a flat one (removed): the kept tets keep their labels
    flat = np.array([[0, 1, 2, 2]])
    mesh = rt.TetMesh(box.vertices, np.vstack([T, T[:1], flat]), labels=np.r_[labels, 9, 8])
    assert mesh.report.removed_duplicate_tets == 1 and mesh.report.removed_degenerate == 1
    assert np.array_equal(mesh.labels, labels)
    lab = _labelled()
    for other in (lab.quadratic(), lab.quadratic().linear(), lab.scaled(1e3)):
        assert np.array_equal(other.labels, lab.labels) and other.region_names == {"liver": 3, "tumor": 7}
    assert lab.fingerprint() != rt.TetMesh(lab.vertices, lab.tets).fingerprint()
    assert rt.TetMesh(box.vertices, T).fingerprint() == box.fingerprint()  # one region: the fingerprint it had


@pytest.mark.parametrize("bad, match", [(np.zeros(3), "one integer per tet"), (np.full(48, 0.5), "integers"),
                                        ("abc", "one integer per tet")])
def test_labels_that_are_not_one_integer_per_tet_are_refused(bad, match):
    box = rt.meshes.box(1.0, 1.0, 1.0, nx=2, ny=2, nz=2)
    with pytest.raises(rt.MeshError, match=match):
        rt.TetMesh(box.vertices, box.tets, labels=bad)
    with pytest.raises(rt.MeshError, match="name .* and an integer label"):
        rt.TetMesh(box.vertices, box.tets, region_names={"a": "b"})


@pytest.mark.parametrize("suffix, names", [(".vtu", True), (".vtk", False), (".msh", True), (".mesh", False)])
@pytest.mark.parametrize("order", [1, 2])
def test_regions_survive_a_file(tmp_path, suffix, names, order):
    """Gmsh physical groups (with their names), MEDIT references, a VTU (names as field data) or VTK
    'region' cell field."""
    mesh = _labelled(order)
    path = tmp_path / f"organ{suffix}"
    if suffix == ".mesh" and order == 2:
        with pytest.raises(rt.MeshError, match="no 10-node tets"):
            rt.save_mesh(mesh, path)
        return
    rt.save_mesh(mesh, path)
    back = rt.load_mesh(path)
    assert np.array_equal(back.labels, mesh.labels) and np.array_equal(back.tets, mesh.tets)
    assert back.region_names == (mesh.region_names if names else {})


@pytest.mark.parametrize("suffix, label", [(".vtu", 0), (".msh", 0), (".inp", 1)])
def test_a_single_named_region_keeps_its_name_in_a_file(tmp_path, suffix, label):
    """A mesh of one region, label 0, named: its name was lost in a file (only labels not all 0 were
    written). An Abaqus deck numbers its sets from 1."""
    box = rt.meshes.box(0.02, 0.02, 0.02, nx=2, ny=2, nz=2)
    mesh = rt.TetMesh(box.vertices, box.tets, labels=np.zeros(len(box.tets), dtype=int), region_names={"liver": 0})
    rt.save_mesh(mesh, tmp_path / f"organ{suffix}")
    back = rt.load_mesh(tmp_path / f"organ{suffix}")
    assert back.region_names == {"liver": label} and (np.asarray(back.labels) == label).all()


def test_abaqus_element_sets_are_regions_by_name(tmp_path):
    """An Abaqus deck has element sets, not numbers: each set is a region numbered from 1 in the file's
    order, named as the set."""
    mesh = _labelled()
    rt.save_mesh(mesh, tmp_path / "organ.inp")
    back = rt.load_mesh(tmp_path / "organ.inp")
    assert back.region_names == {"liver": 1, "tumor": 2}
    assert np.array_equal(back.labels, np.where(mesh.labels == 7, 2, 1))


def test_a_model_of_regions_says_what_it_lacks():
    mesh = _labelled()
    soft, stiff = rt.Material(E=3e4, nu=0.45), rt.Material(E=3e5, nu=0.45)
    with pytest.raises(rt.ModelError, match=r"regions \[7\] have no material"):
        rt.SolidModel(mesh, {3: soft})
    with pytest.raises(rt.ModelError, match="'kidney' names no region.*'liver' = 3"):
        rt.SolidModel(mesh, {"liver": soft, "kidney": stiff})
    with pytest.raises(rt.ModelError, match="no tet of this mesh has label 5"):
        rt.SolidModel(mesh, {3: soft, 7: stiff, 5: stiff})
    with pytest.raises(rt.ModelError, match="given two materials"):
        rt.SolidModel(mesh, {3: soft, "liver": soft, 7: stiff})
    with pytest.raises(rt.ModelError, match="must be an rt.Material"):
        rt.SolidModel(mesh, {3: soft, 7: 3e5})
    with pytest.raises(rt.ModelError, match="tet4-anp"):
        rt.SolidModel(mesh, {3: soft, 7: stiff}, element="tet4-anp")
    model = rt.SolidModel(mesh, {"liver": soft, "tumor": stiff})
    assert model.materials == {3: soft, 7: stiff}
    assert rt.SolidModel(mesh, {"3": soft, "tumor": stiff}).materials == {3: soft, 7: stiff}  # a file's "3": the label
    named = rt.TetMesh(mesh.vertices, mesh.tets, labels=mesh.labels, region_names={"7": 3, "tumor": 7})
    with pytest.raises(rt.ModelError, match="'7' is the name of region 3 and the label of another region"):
        rt.SolidModel(named, {"7": soft, "tumor": stiff})
    with pytest.raises(rt.ModelError, match="2 regions"):
        model.material
    one = rt.SolidModel(mesh, {3: soft, 7: soft})  # every region the same: still two regions, the same K
    plain = rt.SolidModel(rt.TetMesh(mesh.vertices, mesh.tets), soft)
    assert abs(one.K - plain.K).max() < 1e-12 * abs(plain.K).max()
    single = rt.SolidModel(rt.TetMesh(mesh.vertices, mesh.tets, labels=np.full(mesh.n_tets, 4)), {4: soft})
    assert single.materials is None and single.material == soft  # one region: a model of one material


def test_the_full_order_kernels_of_regions_equal_the_batched_system():
    """The lagged full-order step's compiled kernels (each region's own: the corotated material and a
    neo-Hookean law) against the nonlinear system's batched evaluation, at a random displacement:
    the same internal forces and tangent (1e-10), so DirectSimulator steps the two-region model as
    rt.nonlinear.solve_static sees it."""
    from rtfem.drivers.lagged_newmark import _Kernels
    from rtfem.fe.nonlinear import Configuration

    mesh = _labelled(2)
    model = rt.SolidModel(mesh, {3: rt.Material(E=3e4, nu=0.45), 7: rt.NeoHookean(mu=5e4, kappa=5e5)}, element="tet10")
    model.fix("x0")
    system = model.nonlinear()
    kernels = _Kernels(system)
    if not kernels.ok:
        pytest.skip("numba is not installed: the compiled kernels do not run")
    u = np.random.default_rng(5).normal(scale=2e-4, size=(model.n_nodes, 3)) * ~model.fixed
    conf = Configuration.rest(model.n_nodes, False)
    conf.u = u
    f, K = system.evaluate(conf)[:2]
    f_k = kernels.forces(u)
    assert np.abs(f_k - f).max() < 1e-10 * np.abs(f).max()
    K_k = kernels.tangent(u)
    assert abs(K_k - K).max() < 1e-10 * abs(K).max()


def test_a_cut_keeps_the_regions():
    """rt.cut of a two-region model: the cut model's tets keep their regions (split ones their
    parent's), and its materials are the model's."""
    mesh = _labelled()
    soft, stiff = rt.Material(E=3e4, nu=0.45), rt.Material(E=3e5, nu=0.45)
    model = rt.SolidModel(mesh, {3: soft, 7: stiff})
    model.fix("x0")
    x = 0.0155  # between the node planes at 10 and 20 mm: elements are split
    V = np.array([[x, -0.01, -0.01], [x, 0.03, -0.01], [x, 0.03, 0.012], [x, -0.01, 0.012]])
    cut = rt.cut(model, V, np.array([[0, 1, 2], [0, 2, 3]]), snap="split")
    assert cut.materials == {3: soft, 7: stiff}
    c_old = np.asarray(mesh.vertices)[mesh.corner_tets].mean(axis=1)
    c_new = np.asarray(cut.tetmesh.vertices)[cut.tetmesh.corner_tets].mean(axis=1)
    assert np.array_equal(cut.tetmesh.labels, np.where(c_new[:, 0] > 0.02, 7, 3))
    assert np.isclose(cut.tetmesh.volumes()[cut.tetmesh.labels == 7].sum(), mesh.volumes()[mesh.labels == 7].sum())
    assert c_old.shape[0] < c_new.shape[0]


@pytest.mark.parametrize("stiff", [rt.Material(E=3e5, nu=0.45), rt.NeoHookean(mu=1e5, kappa=1e6)],
                         ids=["corotated", "neo-hookean"])
def test_the_reduced_model_of_regions_and_its_cubature_per_region(stiff):
    """The reduced nonlinear model of a two-region solid (E 30 kPa, and 300 kPa or a neo-Hookean of
    about that): its element forces (Lame constants per element, or each region's law) equal the
    projected full-order forces (the nonlinear system's per-region kernels; 1e-10) at a pose moving
    the solid by a tenth of its size, and its element tangents the projected full-order tangent; its
    cubature is fitted per region by default (elements from both regions, each region's training
    forces to the tolerance) and reproduces held-out poses' forces within 3 tol, as one fit does."""
    from rtfem.reduction.reduced import ReducedNonlinearModel

    mesh = _labelled()
    model = rt.SolidModel(mesh, {3: rt.Material(E=3e4, nu=0.45), 7: stiff}).fix("x0")
    red = ReducedNonlinearModel(model, rt.modal_analysis(model, 12), 4)
    rng = np.random.default_rng(3)
    poses = []
    for _ in range(4):
        q = rng.normal(size=red.size)
        poses.append(q * 0.1 * red.system.size / np.abs(red.displacements(q)).max())
    exact = [red.reduced_forces(q, tangent=False)[0] for q in poses]
    data = red._element_data()
    for q, g in zip(poses, exact):
        mine = red._element_forces(q, data, np.ones(mesh.n_tets), False)[0]
        assert np.abs(mine - g).max() < 1e-10 * np.abs(g).max()
    q = poses[0]
    K = red.reduced_forces(q, tangent=True)[1]
    rest = red._element_tangents(np.zeros(data[0].shape[:2]), data)
    mine = red.tangent_change(q, data, np.ones(mesh.n_tets), rest) + red.tangent_change(
        np.zeros_like(q), data, np.ones(mesh.n_tets), np.zeros_like(rest))
    assert np.abs(mine - K).max() < 1e-8 * np.abs(K).max()
    for regions in (None, False):
        info = red.train_cubature(16, tol=0.05, regions=regions)
        assert info["regions"] == (2 if regions is None else 0) and info["training_error"] <= 0.05
        chosen = np.asarray(mesh.labels)[info["elements"]]
        if regions is None:
            assert set(chosen.tolist()) == {3, 7}
        err = np.mean([np.linalg.norm(red.cubature_forces(q) - g) / np.linalg.norm(g) for q, g in zip(poses, exact)])
        assert err < 3 * 0.05 and 0 < info["held_out_error"] < 3 * 0.05, (regions, err, info["held_out_error"])
    # fitted to every training pose exactly (256 rows, 48 elements: the weights all 1), exact on poses it never saw
    info = red.train_cubature(16, tol=1e-12, regions=False)
    assert info["training_error"] < 1e-10 and info["held_out_error"] < 1e-10 and info["held_out_poses"] == 4
    plain = rt.SolidModel(rt.TetMesh(mesh.vertices, mesh.tets, groups=mesh.groups), rt.Material()).fix("x0")
    with pytest.raises(rt.ModelError, match="the modal basis was computed for this mesh with other"):
        ReducedNonlinearModel(plain, rt.modal_analysis(model, 4), 0)  # the regions are in the model's key
    with pytest.raises(rt.ModelError, match="several regions"):
        ReducedNonlinearModel(plain, rt.modal_analysis(plain, 4), 0).train_cubature(4, regions=True)


def test_fits_per_region_together_meet_the_tolerance_where_the_regions_forces_cancel():
    """cubature.region_tol on two regions whose training forces nearly cancel (each many times their sum,
    as where one region presses on the other): each fitted to tol of its own forces alone, the sum misses
    the whole's by several tol of it; with region_tol each meets tol of its own and the two together tol of
    the whole, as one fit over all elements must."""
    from rtfem.reduction import cubature

    rng = np.random.default_rng(0)
    A0 = rng.random((300, 80))
    A1 = -A0[:, rng.permutation(80)] * (1.0 + 0.1 * rng.standard_normal((300, 80)))
    A = np.hstack([A0, A1])
    b = A.sum(axis=1)
    groups = [np.arange(80), np.arange(80, 160)]
    assert min(np.linalg.norm(A[:, g].sum(axis=1)) for g in groups) > 10 * np.linalg.norm(b)
    tol = 0.05
    for own in (True, False):
        total = np.zeros_like(b)
        for g in groups:
            bg = A[:, g].sum(axis=1)
            t = tol if own else cubature.region_tol(tol, bg, b, len(groups))
            chosen, w, err = cubature.train(A[:, g], bg, t)
            miss = bg - A[:, g[chosen]] @ w
            assert np.linalg.norm(miss) <= tol * np.linalg.norm(bg)
            total += miss
        if own:
            assert np.linalg.norm(total) > 3 * tol * np.linalg.norm(b)
        else:
            assert np.linalg.norm(total) <= tol * np.linalg.norm(b)
    assert cubature.region_tol(tol, b, 10 * b, 2) == tol  # a region whose forces are small is held to its own


def test_the_viewer_colours_the_regions_and_scales_every_region_alike():
    """The viewer's session on a solid of two regions given a material each: the drawn surface in two
    palette colours, each on its region's side (x < 30 mm one, x > 30 mm the other; the vertices of the
    interface ring take either), lightened where the surface moves; the panel's E scales both regions'
    moduli alike (their ratio kept) and the panel names them."""
    pytest.importorskip("viser", reason="the viewer extra is not installed")
    from rtfem.viewer.app import surface_encoder, surface_glb
    from rtfem.viewer.gltf import REGION_PALETTE
    from rtfem.viewer.session import Session, Settings, describe_material

    box = rt.meshes.box(0.06, 0.02, 0.02, nx=6, ny=2, nz=2)
    c = np.asarray(box.vertices)[np.asarray(box.corner_tets)].mean(axis=1)
    mesh = rt.TetMesh(box.vertices, box.tets, labels=np.where(c[:, 0] > 0.03, 2, 1), groups=box.groups)
    s = Session(mesh, {1: rt.Material(E=3e4), 2: rt.Material(E=3e5)}, fixed="x0", settings=Settings(n_modes=10),
                model_options={"element": "tet4"})
    x = s.X[s.drawn, 0]
    rgb = s.region_colours[:, :3]
    assert (rgb[x < 0.029] == REGION_PALETTE[0]).all() and (rgb[x > 0.031] == REGION_PALETTE[1]).all()
    assert len(surface_glb(s, surface_encoder(s), np.zeros((s.drawn.size, 3)), 1e-3)) > 0  # a frame is made
    colours = []
    u = np.zeros((s.drawn.size, 3))
    u[x > 0.05, 2] = 1e-3  # the free end moved by the colour scale
    for field in (np.zeros_like(u), u):
        surface_glb(s, lambda X, rgba: colours.append(rgba), field, 1e-3)
    assert np.array_equal(colours[0], s.region_colours)  # at rest: the regions' own colours
    lighter = colours[1][:, :3].astype(int) - s.region_colours[:, :3]
    assert (lighter[x > 0.05] > 0).all() and (lighter[x < 0.05] == 0).all()
    s.configure(E=6e4)
    assert [m.E for m in s.model.materials.values()] == [6e4, 6e5]
    assert "region 1: Material(E=60000.0" in describe_material(s.model)


def test_the_reduced_model_of_a_neo_hookean_region_settles_at_the_full_orders_equilibrium():
    """A tet4 cantilever 100 x 40 x 40 mm, its root half linear (E 30 kPa, corotated) and its tip
    half neo-Hookean (mu 103 kPa, kappa 1 MPa), clamped at the root and bent by a 3 N tip load to
    74 mm (the linear model: 86 mm). The reduced nonlinear model (20 modes, derivatives of 10,
    cubature per region, the simulator's run-time path) settles within 4 % of the worst node's
    full-order displacement (measured 1.5 %; without cubature 0.9 %), the linear model 21 % off.
    The full order is CalculiX's (test_regions.py, NLGEOM)."""
    from rtfem.reduction.reduced import ReducedNonlinearModel

    box = rt.meshes.box(0.1, 0.04, 0.04, nx=10, ny=4, nz=4)
    c = np.asarray(box.vertices)[np.asarray(box.corner_tets)].mean(axis=1)
    mesh = rt.TetMesh(box.vertices, box.tets, labels=np.where(c[:, 0] > 0.05, 2, 1), groups=box.groups)
    law = rt.NeoHookean(mu=1.03e5, kappa=1e6)
    model = rt.SolidModel(mesh, {1: rt.Material(E=3e4, nu=0.45), 2: law}, element="tet4").fix("x0")
    tip = np.flatnonzero(np.asarray(mesh.vertices)[:, 0] > 0.0999)
    F = {int(n): (0.0, 0.0, -3.0 / tip.size) for n in tip}
    full = np.linalg.norm(rt.nonlinear.solve_static(model, F, steps=4).displacements, axis=1)
    linear = np.linalg.norm(model.solve_static(F), axis=1)
    red = ReducedNonlinearModel(model, rt.modal_analysis(model, 20), 10)
    assert red.train_cubature(16, tol=0.05)["regions"] == 2
    sim = rt.ReducedNonlinearSimulator(red, dt=1e-3, damping=rt.Damping(alpha=60.0))
    for _ in range(1500):
        sim.step(F)
    settled = np.linalg.norm(sim.displacements(), axis=1)
    assert np.abs(sim.displacements()).max() > 0.05  # m: a large bend
    error = np.abs(settled - full).max() / full.max()
    assert error < 0.04, error
    assert np.abs(linear - full).max() / full.max() > 0.15


def two_region_bar():
    """A tet4 bar 60 x 20 x 20 mm, its root half labelled 0 and its tip half 1, a Prony law (a neo-Hookean,
    g 0.5, tau 50 ms), a 50 mN tip load and its tip nodes: (box, labelled mesh, law, loads, tip)."""
    box = rt.meshes.box(0.06, 0.02, 0.02, nx=6, ny=2, nz=2)
    c = np.asarray(box.vertices)[np.asarray(box.corner_tets)].mean(axis=1)
    two = rt.TetMesh(box.vertices, box.tets, labels=(c[:, 0] > 0.03).astype(int), groups=box.groups)
    law = rt.Prony(rt.NeoHookean(mu=1e4, kappa=1e5), g=[0.5], tau=[0.05])
    tip = np.flatnonzero(np.asarray(box.vertices)[:, 0] > 0.0599)
    return box, two, law, {int(n): (0.0, 0.0, -0.05 / tip.size) for n in tip}, tip


def test_a_prony_region_creeps_with_its_own_history_to_its_long_term_equilibrium():
    """Full-order dynamics (rt.DirectSimulator, large deformation) of a tet4 bar 60 x 20 x 20 mm held at
    one end and bent by a 50 mN tip load. Both halves of one Prony law (a neo-Hookean, g 0.5, tau
    50 ms) as two regions step exactly as the one-law model (1e-12); a Prony root half and a stiff
    neo-Hookean tip half: only the Prony region carries a history (its 72 tets' Q and S_iso), and the
    bar creeps from 0.71 of its final deflection (the instantaneous law's static answer) to the
    long-term law's static equilibrium of the two regions (a second path: hyperelastic regions,
    CalculiX-checked in test_regions.py) within 1e-3 (measured 1.5e-4 after 0.8 s, 16 tau)."""
    from rtfem.fe.viscoelastic import history_size

    box, two, law, F, _ = two_region_bar()

    def run(model, steps):
        sim = rt.DirectSimulator(model, 1e-3, rt.Damping(alpha=40.0), large_deformation=True)
        out = []
        for _ in range(steps):
            sim.step(F)
            out.append(np.array(sim.displacements()))
        return np.array(out)

    same = run(rt.SolidModel(two, {0: law, 1: law}, element="tet4").fix("x0"), 200)
    one = run(rt.SolidModel(box, law, element="tet4").fix("x0"), 200)
    assert np.abs(same - one).max() < 1e-12 * np.abs(one).max()
    stiff = rt.NeoHookean(mu=1e5, kappa=1e6)
    mixed = rt.SolidModel(two, {0: law, 1: stiff}, element="tet4").fix("x0")
    assert mixed.nonlinear().kernel.history_size == history_size(law, 1, int(np.sum(two.labels == 0))) > 0
    u = run(mixed, 800)
    final = rt.nonlinear.solve_static(rt.SolidModel(two, {0: law.long_term(), 1: stiff}, element="tet4").fix("x0"),
                                      F).displacements
    start = rt.nonlinear.solve_static(rt.SolidModel(two, {0: law.instantaneous, 1: stiff}, element="tet4").fix("x0"),
                                      F).displacements
    scale = np.abs(final).max()
    assert np.abs(u[-1] - final).max() < 1e-3 * scale
    assert np.abs(start).max() < 0.75 * scale and np.abs(u[100]).max() < 0.95 * scale  # it crept
