"""Sparse factorizations: every available backend solves the same system to round-off,
orderings are permutations that cut fill, singular matrices are refused."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

import rtfem as rt
from rtfem import linalg


@pytest.fixture(scope="module")
def stiffness():
    model = rt.ShellModel(rt.meshes.liver(3), rt.Material()).fix("attachment")
    K, dofs = model.constrained_stiffness()
    return model, K.tocsc(), dofs


@pytest.mark.parametrize("backend", linalg.available_backends())
@pytest.mark.parametrize("ordered", [False, True])
def test_every_backend_solves_the_stiffness_to_round_off(stiffness, backend, ordered):
    model, K, dofs = stiffness
    order = model.dof_order(dofs) if ordered and backend == "superlu" else None
    fac = linalg.factorize(K, backend=backend, order=order)
    assert fac.backend == backend
    rng = np.random.default_rng(3)
    x_true = rng.standard_normal((K.shape[0], 3))
    b = K @ x_true
    x = fac.solve(b)
    # backward error: the residual relative to ||K|| ||x||, the measure a stable solver meets
    res = np.linalg.norm(K @ x - b) / (sp.linalg.norm(K, 1) * np.linalg.norm(x))
    assert res < 1e-13
    # one right-hand side alone: the same backward error (a supernodal solver blocks one and many
    # right-hand sides differently, so the forward results differ by up to cond(K) eps)
    x1 = fac.solve(b[:, 0])
    assert x1.shape == (K.shape[0],)
    assert np.linalg.norm(K @ x1 - b[:, 0]) / (sp.linalg.norm(K, 1) * np.linalg.norm(x1)) < 1e-13


def test_backends_agree_with_each_other(stiffness):
    model, K, dofs = stiffness
    b = np.random.default_rng(4).standard_normal(K.shape[0])
    answers = [linalg.factorize(K, backend=k).solve(b) for k in linalg.available_backends()]
    answers.append(linalg.factorize(K, order=model.dof_order(dofs), backend="superlu").solve(b))
    for x in answers[1:]:
        np.testing.assert_allclose(x, answers[0], rtol=1e-9, atol=1e-9 * np.abs(answers[0]).max())


def test_nested_dissection_is_a_permutation_and_cuts_fill(stiffness):
    model, K, dofs = stiffness
    mesh = model.mesh
    order = linalg.nested_dissection(mesh.adjacency(), np.asarray(mesh.vertices), leaf=16)
    assert np.array_equal(np.sort(order), np.arange(mesh.n_vertices))
    p = linalg.expand_node_order(order, 6, dofs)
    assert np.array_equal(np.sort(p), np.arange(dofs.size))
    import scipy.sparse.linalg as spla

    A = K[p][:, p].tocsc()
    nd = spla.splu(A, permc_spec="NATURAL", diag_pivot_thresh=0.0, options={"SymmetricMode": True})
    natural = spla.splu(K, permc_spec="NATURAL", diag_pivot_thresh=0.0, options={"SymmetricMode": True})
    assert nd.L.nnz < 0.5 * natural.L.nnz  # the mesh's own numbering fills far more


def test_expand_node_order_keeps_node_blocks_together():
    order = np.array([2, 0, 1])
    kept = np.array([0, 1, 3, 4, 5, 7])  # dofs of 3 nodes with 3 dofs each, some dropped
    p = linalg.expand_node_order(order, 3, kept)
    # node 2 (dofs 6, 7, 8 -> kept 7 at position 5) first, then node 0 (0, 1), then node 1 (3, 4, 5)
    assert p.tolist() == [5, 0, 1, 2, 3, 4]


@pytest.mark.parametrize("backend", linalg.available_backends())
def test_a_singular_matrix_is_refused(backend):
    A = sp.diags([1.0, 2.0, 0.0, 3.0]).tocsc()
    with pytest.raises(rt.SolverError, match="singular"):
        linalg.factorize(A, backend=backend, what="the test matrix")
    lap = sp.diags([-np.ones(9), 2 * np.ones(10), -np.ones(9)], [-1, 0, 1]).tolil()
    lap[0, 0] = lap[-1, -1] = 1.0  # free-free: constants are in the null space
    with pytest.raises(rt.SolverError, match="singular|positive"):
        linalg.factorize(lap.tocsc(), backend=backend)


def test_wrong_shapes_and_backends_are_refused():
    with pytest.raises(rt.SolverError, match="not square"):
        linalg.factorize(sp.random(3, 4, density=0.5, format="csc"))
    with pytest.raises(rt.SolverError, match="unknown backend"):
        linalg.factorize(sp.eye(3, format="csc"), backend="magic")
    fac = linalg.factorize(sp.eye(3, format="csc"))
    with pytest.raises(rt.SolverError, match="rows"):
        fac.solve(np.ones(4))


def test_the_upper_triangle_is_taken_from_any_format():
    """PARDISO reads the upper triangle: from CSR (sorted or not) and CSC alike, empty rows kept."""
    from rtfem.fe.linalg import _upper_triangle

    A = sp.random(40, 40, density=0.15, random_state=6, format="csr")
    A = (A + A.T).tolil()  # symmetric, with its last row and column empty
    A[39, :] = 0
    A[:, 39] = 0
    A = A.tocsr()
    ref = sp.triu(A, format="csr")
    ref.sort_indices()
    unsorted = A.copy()
    for i in range(40):  # reverse each row's column order
        a, b = unsorted.indptr[i], unsorted.indptr[i + 1]
        unsorted.indices[a:b] = unsorted.indices[a:b][::-1].copy()
        unsorted.data[a:b] = unsorted.data[a:b][::-1].copy()
    unsorted.has_sorted_indices = False
    for M in (A, A.tocsc(), unsorted, A.tocoo()):
        indptr, indices, data = _upper_triangle(M)
        assert np.array_equal(indptr, ref.indptr) and np.array_equal(indices, ref.indices)
        assert np.array_equal(data, ref.data)


@pytest.mark.skipif("pardiso" not in linalg.available_backends(), reason="PARDISO is not installed")
def test_pardiso_reports_its_factor_and_solves_alike_on_one_thread_or_more(stiffness):
    from rtfem.fe import linalg as fe_linalg

    model, K, dofs = stiffness
    b = np.random.default_rng(8).standard_normal((K.shape[0], 8))
    x = {}
    for threads in (1, 0):  # one MKL thread for the solve (a small factor's default), MKL's own count
        f = fe_linalg._Pardiso(K, "K")
        assert f.factor_nnz >= sp.triu(K).nnz  # the factor holds the matrix's pattern
        assert f._solve_threads == (1 if f.factor_nnz < fe_linalg._ONE_THREAD_SOLVE else 0)
        f._solve_threads = threads
        x[threads] = f.solve(b)
    res = np.linalg.norm(K @ x[1] - b) / (sp.linalg.norm(K, 1) * np.linalg.norm(x[1]))
    assert res < 1e-13
    np.testing.assert_allclose(x[1], x[0], rtol=0, atol=1e-9 * np.abs(x[0]).max())


@pytest.mark.skipif("pardiso" not in linalg.available_backends(), reason="PARDISO is not installed")
def test_pardiso_solves_leave_no_garbage_for_the_collector(stiffness):
    """A solve passes its arrays by address: arr.ctypes.data_as() went through ctypes.cast, whose
    reference cycles (two objects a call) the garbage collector had to find, in the physics thread of a
    haptic loop."""
    import gc

    from rtfem.fe import linalg as fe_linalg

    model, K, dofs = stiffness
    f = fe_linalg._Pardiso(K, "K")
    b = np.ones(K.shape[0])
    f.solve(b)
    enabled = gc.isenabled()
    gc.disable()
    try:
        gc.collect()
        for _ in range(200):
            f.solve(b)
        assert gc.collect() == 0
    finally:
        if enabled:
            gc.enable()


def test_the_basis_products_match_numpy_on_slices_and_other_layouts():
    """gram (A^T B) and subtract_product (C -= A B), MKL's dgemm where PARDISO's MKL is loaded: the
    Lanczos basis is a column slice of a column-major array; other layouts take numpy's product."""
    rng = np.random.default_rng(9)
    for n in (300, 20_000):  # one MKL thread, then MKL's own count
        Q = np.asfortranarray(rng.standard_normal((n, 120)))
        P, Z = Q[:, 10:90], np.asfortranarray(rng.standard_normal((n, 8)))
        H = linalg.gram(P, Z)
        np.testing.assert_allclose(H, P.T @ Z, rtol=1e-12, atol=1e-12 * np.abs(P.T @ Z).max())
        C = Z.copy(order="F")
        linalg.subtract_product(C, P, H)
        np.testing.assert_allclose(C, Z - P @ H, rtol=0, atol=1e-12 * np.abs(Z).max())
        Cc = np.ascontiguousarray(Z)  # row-major: numpy's product
        linalg.subtract_product(Cc, P, H.T.copy().T)
        np.testing.assert_allclose(Cc, C, rtol=0, atol=1e-12 * np.abs(Z).max())
        np.testing.assert_allclose(linalg.gram(np.ascontiguousarray(P), Z), H, rtol=1e-12, atol=1e-12 * np.abs(H).max())
