import warnings

import numpy as np
import pytest

import rtfem as rt
from conftest import liver_model as make_liver_model


@pytest.fixture
def liver_model():
    return make_liver_model(3)


def test_assembly_symmetric_and_mass_totals(liver_model):
    K = liver_model.K
    assert K.shape == (liver_model.n_dofs,) * 2
    assert abs(K - K.T).max() == 0.0
    m = liver_model.mass_diagonal.reshape(-1, 6)
    mat = liver_model.material
    total = mat.density * mat.thickness * liver_model.mesh.areas().sum()
    for k in range(3):
        assert m[:, k].sum() == pytest.approx(total, rel=1e-12)
    assert np.all(m[:, 3:] == 0)  # massless rotations by default


def test_rotary_inertia_option():
    mesh = rt.meshes.plate(1, 1, 2)
    mat = rt.Material(thickness=0.01)
    m = rt.ShellModel(mesh, mat, rotary_inertia=True).mass_diagonal.reshape(-1, 6)
    assert m[:, 3:].sum() == pytest.approx(m[:, :3].sum() * mat.thickness**2 / 12)


def test_penalty_and_elimination_agree(liver_model):
    mesh = liver_model.mesh
    pen = rt.ShellModel(mesh, liver_model.material, constraints="penalty", penalty=1e8)
    pen.fix("attachment")
    node = mesh.nearest_vertex([0.08, 0.0, 0.0])
    f = {node: (0.0, 0.0, -0.5)}
    u_e = liver_model.solve_static(f)
    u_p = pen.solve_static(f)
    scale = np.abs(u_e).max()
    # the penalty leaves the fixed dofs at ~1/penalty of the response and perturbs the rest as much
    assert np.abs(u_p - u_e).max() < 1e-6 * scale
    assert np.abs(u_p[mesh.groups["attachment"]]).max() < 1e-6 * scale
    assert np.all(u_e[mesh.groups["attachment"]] == 0)


def test_dense_and_sparse_condensation_agree():
    mesh = rt.meshes.liver(2)  # 162 nodes: the dense Schur complement is small
    model = rt.ShellModel(mesh, rt.Material())
    model.fix("attachment")
    Kc = model.condensed_stiffness()  # paper Eq. 5, dense
    op = model.condensed_operator()  # sparse route
    t = model.translational_free_dofs()
    assert Kc.shape == (t.size, t.size)
    assert np.abs(Kc - Kc.T).max() < 1e-9 * np.abs(Kc).max()
    X = np.random.default_rng(0).normal(size=(t.size, 4))
    assert np.abs(op.matmat(X) - Kc @ X).max() < 1e-9 * np.abs(Kc @ X).max()
    # solving the condensed system equals the static solve of the full system
    F = np.zeros(model.n_dofs)
    F[t] = np.random.default_rng(1).normal(size=t.size)
    u_dense = np.linalg.solve(Kc, F[t])
    u_full = model.solve_static(F.reshape(-1, 6)[:, :3]).ravel()
    trans = (t // 6) * 3 + t % 6
    assert np.abs(u_full[trans] - u_dense).max() < 1e-8 * np.abs(u_dense).max()


def test_dense_condensation_refused_when_large():
    model = rt.ShellModel(rt.meshes.liver(4), rt.Material())
    model.fix("attachment")
    with pytest.raises(rt.ModelError, match="condensed_operator"):
        model.condensed_stiffness()


def test_factorization_cached_and_invalidated(liver_model):
    f1 = liver_model.factorization()
    assert liver_model.factorization() is f1
    liver_model.fix([0], "all")
    assert liver_model.factorization() is not f1


def test_moments_and_return_rotations():
    mesh = rt.meshes.plate(1.0, 0.1, 10, 1)
    mat = rt.Material(E=1e6, nu=0.0, thickness=0.01)
    model = rt.ShellModel(mesh, mat)
    model.fix("x0")
    F = np.zeros((mesh.n_vertices, 6))
    tip = mesh.groups["x1"]
    F[tip, 4] = -0.5  # total end moment 1 about -y: bends the strip upward (+z)
    U = model.solve_static(F, return_rotations=True)
    I = 0.1 * mat.thickness**3 / 12
    # pure bending: w(L) = M L^2 / (2 E I), slope M L / (E I)
    assert U[tip, 2].mean() == pytest.approx(1.0 / (2 * mat.E * I), rel=1e-6)
    assert U.shape == (mesh.n_vertices, 6)


def test_nothing_fixed_raises():
    model = rt.ShellModel(rt.meshes.liver(2), rt.Material())
    with pytest.raises(rt.ModelError, match="nothing is fixed"):
        model.solve_static(np.zeros((model.n_nodes, 3)))


def test_insufficient_fixes_name_the_free_motion():
    mesh = rt.meshes.plate(1, 1, 4)
    model = rt.ShellModel(mesh, rt.Material())
    model.fix([0], "xyz")  # one pinned node: the plate can still rotate about it
    with pytest.raises(rt.ModelError, match="rotation"):
        model.solve_static(np.zeros((mesh.n_vertices, 3)))
    model.fix(mesh.groups["x0"], "xyz")  # a line of pins: rotation about that line is free
    with pytest.raises(rt.ModelError, match=r"rotation about the axis \(0, -?1, 0\) through the point \(0, "):
        model.solve_static(np.zeros((mesh.n_vertices, 3)))
    model.fix(mesh.groups["y0"], "xyz")
    model.solve_static(np.zeros((mesh.n_vertices, 3)))


def test_unfixed_separate_piece_is_reported():
    a = rt.meshes.plate(1, 1, 2)
    V = np.vstack([a.vertices, np.asarray(a.vertices) + [3, 0, 0]])
    T = np.vstack([a.triangles, np.asarray(a.triangles) + a.n_vertices])
    model = rt.ShellModel(rt.TriMesh(V, T), rt.Material())
    model.fix(np.arange(a.n_vertices))
    with pytest.raises(rt.ModelError, match="piece 2 of 2"):
        model.solve_static(np.zeros((model.n_nodes, 3)))


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_forces_raise(liver_model, bad):
    F = np.zeros((liver_model.n_nodes, 3))
    F[5, 1] = bad
    with pytest.raises(rt.ModelError, match="node 5"):
        liver_model.solve_static(F)
    with pytest.raises(rt.ModelError, match="non-finite"):
        liver_model.solve_static({7: (0.0, bad, 0.0)})


def test_force_shape_errors(liver_model):
    with pytest.raises(rt.ModelError, match="shape"):
        liver_model.solve_static(np.zeros((3, 3)))
    with pytest.raises(rt.ModelError, match="3 .or 6. components"):
        liver_model.solve_static({0: (1.0, 2.0)})
    with pytest.raises(rt.ModelError, match="out of range"):
        liver_model.solve_static({10**6: (1.0, 0.0, 0.0)})


def test_force_on_fixed_dof_is_reported(liver_model):
    fixed_node = int(liver_model.mesh.groups["attachment"][0])
    free_node = liver_model.mesh.nearest_vertex([0.08, 0.0, 0.0])
    with pytest.warns(rt.RtfemWarning, match=f"node {fixed_node}"):
        u = liver_model.solve_static({fixed_node: (0.0, 0.0, 1.0), free_node: (0.0, 0.0, 1.0)})
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        u2 = liver_model.solve_static({free_node: (0.0, 0.0, 1.0)})
    assert np.allclose(u, u2)  # the support took the load on the fixed node


def test_dof_parsing():
    from rtfem.fe.protocol import parse_dofs

    assert parse_dofs("all").all()
    assert parse_dofs("xyz").tolist() == [True] * 3 + [False] * 3
    assert parse_dofs("z").tolist() == [False, False, True, False, False, False]
    assert parse_dofs("x, rz").tolist() == [True, False, False, False, False, True]
    assert parse_dofs("rotations").tolist() == [False] * 3 + [True] * 3
    assert parse_dofs(["y", 3]).tolist() == [False, True, False, True, False, False]
    with pytest.raises(rt.ModelError, match="not understood"):
        parse_dofs("q")
    with pytest.raises(rt.ModelError, match="no vertex group"):
        rt.ShellModel(rt.meshes.plate(), rt.Material()).fix("nope")


def test_pressure_resultant():
    mesh = rt.meshes.icosphere(0.1, 3)
    F = rt.ShellModel(mesh, rt.Material()).pressure_forces(100.0)
    assert np.abs(F.sum(axis=0)).max() < 1e-12  # closed surface: no net force
    # inward on an outward-oriented sphere
    radial = np.einsum("ij,ij->i", F, np.asarray(mesh.vertices))
    assert np.all(radial < 0)
    # virial identity: sum F_i . x_i = -p sum_faces A n . centroid = -3 p V (divergence theorem)
    assert radial.sum() == pytest.approx(-3 * 100.0 * mesh.volume(), rel=1e-12)


def test_model_argument_errors():
    mesh = rt.meshes.plate()
    with pytest.raises(rt.ModelError, match="membrane"):
        rt.ShellModel(mesh, rt.Material(), membrane="quad")
    with pytest.raises(rt.ModelError, match="constraints"):
        rt.ShellModel(mesh, rt.Material(), constraints="lagrange")
    with pytest.raises(rt.ModelError, match="TriMesh"):
        rt.ShellModel(np.zeros((3, 3)), rt.Material())
