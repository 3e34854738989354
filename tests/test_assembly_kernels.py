"""The compiled assembly (rtfem.fe.assembly_kernels, issue 43) against the numpy path it replaces and
against closed forms: a linear field's strain energy (the patch test), rigid-body modes, symmetry."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest
import scipy.sparse as sp

import rtfem as rt
from rtfem.fe import assembly, assembly_kernels, solid

pytestmark = pytest.mark.skipif(not assembly_kernels.available(), reason="numba is not installed: no compiled assembly")


@pytest.fixture(scope="module")
def block():
    """A tet4 box meshed for this test (not the liver the kernels were timed on), its nodes moved off
    the grid so that no two tets are alike."""
    mesh = rt.meshes.box(0.03, 0.02, 0.015, 6, 5, 4)
    X = np.asarray(mesh.vertices)
    X = X + np.random.default_rng(1).uniform(-1e-3, 1e-3, X.shape)
    return rt.TetMesh(X, np.asarray(mesh.tets))


def _model(mesh, monkeypatch, how: str, **kw):
    monkeypatch.setenv("RTFEM_ASSEMBLY", how)
    model = rt.SolidModel(mesh, rt.Material(E=3e4, nu=0.45, density=1050.0), **kw)
    model.K
    return model


def test_node_pattern_is_the_pairs_sharing_an_element():
    rng = np.random.default_rng(0)
    cells = np.array([rng.choice(30, 4, replace=False) for _ in range(40)])
    indptr, indices = assembly_kernels.node_pattern(cells, 30)
    r = np.repeat(cells, 4, axis=1).ravel()
    c = np.tile(cells, (1, 4)).ravel()
    ref = sp.coo_matrix((np.ones(r.size), (r, c)), shape=(30, 30)).tocsr()
    ref.sum_duplicates()
    ref.sort_indices()
    assert np.array_equal(indptr, ref.indptr) and np.array_equal(indices, ref.indices)


@pytest.mark.parametrize("element", ["tet4", "tet10", "tet4-anp"])
def test_compiled_and_numpy_assembly_agree(block, monkeypatch, element):
    a = _model(block, monkeypatch, "numpy", element=element)
    b = _model(block, monkeypatch, "compiled", element=element)
    assert abs(b.K - b.K.T).max() == 0.0  # exactly symmetric
    assert abs(a.K - b.K).max() <= 1e-14 * abs(a.K).max()
    assert np.abs(a.mass_diagonal - b.mass_diagonal).max() <= 1e-14 * a.mass_diagonal.max()
    assert b.K.has_sorted_indices and np.all(np.diff(b.K.indptr) > 0)


@pytest.mark.parametrize("surface", ["liver", "cylinder"])
def test_the_compiled_shell_is_the_numpy_shell(monkeypatch, surface):
    """The compiled OPT + DKT triangle (fe/shell_kernels.py) against the batched numpy one, on the
    liver and on a cylinder whose nodes are moved off their rings (every triangle different)."""
    mesh = rt.meshes.liver(3) if surface == "liver" else rt.meshes.cylinder()
    if surface == "cylinder":
        X = np.asarray(mesh.vertices)
        mesh = rt.TriMesh(X + np.random.default_rng(2).uniform(-0.02, 0.02, X.shape) * np.ptp(X, axis=0).max() / 10,
                          np.asarray(mesh.triangles))
    T, X = np.asarray(mesh.triangles), np.asarray(mesh.vertices)
    monkeypatch.setenv("RTFEM_ASSEMBLY", "compiled")
    assert assembly.assemble_shell(X, T, rt.Material(), mesh.n_vertices) is not None  # the compiled path runs
    monkeypatch.setenv("RTFEM_ASSEMBLY", "numpy")
    a = rt.ShellModel(mesh, rt.Material(E=5e4, nu=0.3, thickness=2e-3), rotary_inertia=True)
    Ka = a.K
    monkeypatch.setenv("RTFEM_ASSEMBLY", "compiled")
    b = rt.ShellModel(mesh, rt.Material(E=5e4, nu=0.3, thickness=2e-3), rotary_inertia=True)
    assert abs(b.K - b.K.T).max() == 0.0
    assert abs(Ka - b.K).max() <= 1e-14 * abs(Ka).max()
    assert np.abs(a.mass_diagonal - b.mass_diagonal).max() <= 1e-14 * a.mass_diagonal.max()


@pytest.mark.parametrize("element", ["tet4", "tet10"])
def test_patch_test_and_rigid_modes(block, monkeypatch, element):
    """A linear field u = A x: its strain energy is V (lam tr(e)^2 / 2 + mu e:e) exactly on any mesh
    of straight-edged tets (e the symmetric part of A), and a rigid motion (A skew) has none."""
    model = _model(block, monkeypatch, "", element=element)
    X = np.asarray(model.mesh.vertices)
    mat = model.material
    lam = mat.E * mat.nu / ((1 + mat.nu) * (1 - 2 * mat.nu))
    mu = mat.E / (2 * (1 + mat.nu))
    P = X[np.asarray(model.tetmesh.tets)[:, :4]]
    volume = np.abs(np.einsum("ij,ij->i", np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]), P[:, 3] - P[:, 0])).sum() / 6
    A = np.array([[1.0, 0.3, -0.2], [0.1, -0.5, 0.4], [0.25, 0.0, 0.7]]) * 1e-2
    e = 0.5 * (A + A.T)
    u = (X @ A.T).ravel()
    exact = volume * (0.5 * lam * np.trace(e) ** 2 + mu * np.sum(e * e))
    assert 0.5 * u @ (model.K @ u) == pytest.approx(exact, rel=1e-12)
    W = 0.5 * (A - A.T)
    for rigid in ((X @ W.T).ravel(), np.tile([1.0, -2.0, 0.5], X.shape[0])):
        assert np.abs(model.K @ rigid).max() <= 1e-12 * abs(model.K).max() * np.abs(rigid).max()
    assert model.mass_diagonal.sum() == pytest.approx(3 * mat.density * volume, rel=1e-12)


def test_an_inverted_tet_is_refused():
    X = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]])
    cells = np.array([[0, 1, 2, 3], [1, 2, 3, 4], [0, 2, 1, 3]])  # the last one inverted
    with pytest.raises(rt.MeshError, match="element 2 has a non-positive Jacobian"):
        assembly.assemble_solid(X, cells, *solid.stiffness_rule("tet4"), 1.0, 1.0, 5)


def test_a_flat_triangle_is_refused():
    X = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [2, 0, 0]])
    cells = np.array([[0, 1, 2], [0, 1, 3]])  # the second one has its corners on a line
    with pytest.raises(rt.MeshError, match="triangle 1 has zero area"):
        assembly.assemble_shell(X, cells, rt.Material(), 4)


def test_bad_input_is_refused_before_the_kernels_see_it(block, monkeypatch):
    """The kernels index without bounds checks: out-of-range cells, wrong shapes and NaN coordinates
    are refused at the door, and a model whose assembly was refused keeps nothing half-built."""
    X = np.asarray(block.vertices)
    T = np.asarray(block.tets)
    n = X.shape[0]
    rule = solid.stiffness_rule("tet4")
    bad_cells = T.copy()
    bad_cells[3, 1] = n
    with pytest.raises(rt.MeshError, match="outside 0"):
        assembly.assemble_solid(X, bad_cells, *rule, 1.0, 1.0, n)
    with pytest.raises(rt.MeshError, match="finite"):
        assembly.assemble_solid(np.where(np.arange(n)[:, None] == 5, np.nan, X), T, *rule, 1.0, 1.0, n)
    with pytest.raises(rt.MeshError, match="cells must be"):
        assembly.assemble_shell(X, T, rt.Material(), n)  # tets where triangles belong
    with pytest.raises(rt.ModelError, match="element matrices must be"):
        assembly.assemble_blocks(T, np.zeros((T.shape[0], 12, 11)), n, 3)
    with pytest.raises(rt.MeshError, match="outside 0"):
        assembly.assemble_blocks(-T, np.zeros((T.shape[0], 12, 12)), n, 3)
    model = rt.SolidModel(block, rt.Material())
    monkeypatch.setenv("RTFEM_ASSEMBLY", "fast")
    with pytest.raises(rt.ModelError, match="RTFEM_ASSEMBLY='fast' names no assembly"):
        model.K
    assert model._K is None and model._M is None  # nothing half-built
    monkeypatch.setenv("RTFEM_ASSEMBLY", "compiled")
    assert abs(model.K - model.K.T).max() == 0.0  # and it assembles once the setting is right


def test_a_cold_process_assembles_a_small_organ_without_starting_numba():
    """Issue 54: numba's start (0.35-0.4 s of CPU) costs a fresh `rtfem modes` of a small organ more than the
    compiled kernels save; where numba is loaded already, or the mesh is large, the compiled path runs."""
    code = ("import sys, rtfem as rt; m = rt.ShellModel(rt.meshes.liver(3), rt.Material()); m.K; "
            "print('numba' in sys.modules)")
    env = {k: v for k, v in os.environ.items() if k != "RTFEM_ASSEMBLY"}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True, timeout=120)
    assert out.stdout.strip() == "False"


def test_the_compiled_assembly_runs_where_it_saves_more_than_numbas_start(monkeypatch):
    monkeypatch.delenv("RTFEM_ASSEMBLY", raising=False)
    assert assembly.compiled_assembly(np.zeros((10, 4), int))  # numba is loaded in this process: always
    monkeypatch.delitem(sys.modules, "numba")  # as in a process that has not loaded it
    assert not assembly.compiled_assembly(np.zeros((20_000, 4), int))  # 0.09 s saved < its start
    assert assembly.compiled_assembly(np.zeros((100_000, 4), int))
    assert assembly.compiled_assembly(np.zeros((5_000, 10), int))  # tet10: 0.7 s saved
    monkeypatch.setenv("RTFEM_ASSEMBLY", "compiled")
    assert assembly.compiled_assembly(np.zeros((10, 3), int))


def test_the_basis_products_refuse_mismatched_shapes():
    A = np.asfortranarray(np.ones((50, 4)))
    with pytest.raises(rt.SolverError, match="same rows"):
        rt.linalg.gram(A, np.ones((49, 2), order="F"))
    C = np.ones((50, 2), order="F")
    with pytest.raises(rt.SolverError, match="subtract_product needs"):
        rt.linalg.subtract_product(C, A, np.ones((3, 2)))
    assert np.all(C == 1.0)  # untouched
