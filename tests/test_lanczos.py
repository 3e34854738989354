import numpy as np
import pytest

import rtfem as rt
from rtfem.reduction.lanczos import Lanczos


def spd(n, seed=0):
    rng = np.random.default_rng(seed)
    X = rng.normal(size=(n, n))
    return X @ X.T / n + np.diag(np.linspace(0.0, 50.0, n))


@pytest.mark.parametrize("reorth", ["cgs2", "householder"])
def test_orthogonality_and_projection(reorth):
    A = spd(300)
    b = np.random.default_rng(1).normal(size=300)
    L = Lanczos(lambda x: A @ x, b, reorth)
    L.extend(120)
    a, be = L.tridiagonal()
    T = np.diag(a) + np.diag(be, 1) + np.diag(be, -1)
    Q = L.Q
    assert L.m == 120 and Q.shape == (300, 120)
    assert L.orthogonality_loss() < 1e-14
    assert np.abs(Q.T @ A @ Q - T).max() < 1e-12 * np.abs(A).max()
    assert np.allclose(Q[:, 0], b / np.linalg.norm(b), rtol=0, atol=1e-15)
    assert np.all(be > 0)
    # Lanczos relation A Q_m = Q_m T_m + beta_m q_{m+1} e_m^T
    R = A @ Q - Q @ T
    R[:, -1] -= L.last_beta * L.next_vector()
    assert np.abs(R).max() < 1e-11 * np.abs(A).max()


def test_both_reorthogonalizations_give_the_same_tridiagonal():
    A = spd(200, seed=3)
    b = np.ones(200)
    T = []
    for reorth in ("cgs2", "householder"):
        L = Lanczos(lambda x: A @ x, b, reorth)
        L.extend(60)
        T.append(np.concatenate(L.tridiagonal()))
    assert np.allclose(T[0], T[1], rtol=1e-9)


@pytest.mark.parametrize("reorth", ["cgs2", "householder"])
def test_breakdown_on_an_invariant_subspace(reorth):
    A = np.diag(np.repeat([1.0, 2.0, 3.0, 4.0, 5.0], 40))
    L = Lanczos(lambda x: A @ x, np.random.default_rng(0).normal(size=200), reorth)
    L.extend(50)
    assert L.breakdown and L.m == 5
    assert np.allclose(np.sort(np.linalg.eigvalsh(np.diag(L.tridiagonal()[0]) + np.diag(L.tridiagonal()[1], 1)
                                                   + np.diag(L.tridiagonal()[1], -1))), [1, 2, 3, 4, 5])
    assert L.extend(5) == 0  # nothing more to do, no crash


def test_bad_start_vectors():
    with pytest.raises(rt.SolverError, match="zero"):
        Lanczos(lambda x: x, np.zeros(5))
    with pytest.raises(rt.SolverError, match="NaN"):
        Lanczos(lambda x: x, np.array([1.0, np.nan]))
    with pytest.raises(rt.SolverError, match="reorth"):
        Lanczos(lambda x: x, np.ones(3), "mgs")


# ---------------------------------------------------------------- block eigensolver
from rtfem.reduction.lanczos import BlockLanczosFailed, block_eigs  # noqa: E402


def test_block_eigs_on_a_known_spectrum():
    # C = U diag(d) U^T with a random orthogonal U: the 15 largest eigenpairs are known exactly
    n, k = 600, 15
    rng = np.random.default_rng(3)
    U = np.linalg.qr(rng.normal(size=(n, n)))[0]
    d = 1.0 / np.linspace(1.0, 400.0, n) ** 2  # clustered towards zero like 1/w^2
    C = (U * d) @ U.T
    calls = []
    theta, Y, info = block_eigs(lambda B: C @ B, n, k, block=4, report=lambda dim, est: calls.append(dim))
    assert np.abs(theta - d[:k]).max() < 1e-14 * d[0]
    assert np.abs(Y.T @ Y - np.eye(k)).max() < 1e-12
    for i in range(k):  # the Ritz vectors are the eigenvectors up to sign
        assert abs(abs(Y[:, i] @ U[:, i]) - 1.0) < 1e-9
    assert info["max_residual"] <= 1e-10 and info["krylov_dim"] == calls[-1] and info["block_solves"] == len(calls)
    assert info["skipped"] > 0  # blocks whose whole-basis pass subtracted nothing, and Y is orthonormal all the same
    assert calls == list(range(4, 4 * len(calls) + 1, 4))
    # C Y read off the Lanczos relation (no further application of C), residual term included. The
    # relation holds to round-off: 6.7e-14 of |C| here, 1.4e-13 with MKL_CBWR=COMPATIBLE (products of 600
    # terms); 1e-12 leaves room for any BLAS, and is 45 times below the residual term checked next
    round_off = 1e-12 * d[0]
    assert np.abs(info["image"] - C @ Y).max() <= round_off
    assert info["coefficients"].shape == (info["krylov_dim"], k)
    theta, Y, info = block_eigs(lambda B: C @ B, n, k, block=4, tol=1e-5)  # stopped with a visible residual
    assert info["max_residual"] > 1e-9
    assert np.abs(info["image"] - C @ Y).max() <= round_off
    assert np.abs(Y * theta - C @ Y).max() > 40 * round_off  # without the residual term: 4.6e-11


def test_block_eigs_stops_short_instead_of_giving_wrong_pairs():
    n = 40
    C = np.diag(np.arange(1.0, n + 1))
    with pytest.raises(BlockLanczosFailed, match="more than"):
        block_eigs(lambda B: C @ B, n, 38, block=8)
    # an invariant start block (C has rank 5): the block loses rank
    low = np.zeros((n, n))
    low[:5, :5] = np.diag([5.0, 4, 3, 2, 1])
    with pytest.raises(BlockLanczosFailed):
        block_eigs(lambda B: low @ B, n, 6, block=4, max_dim=40)
    with pytest.raises(rt.SolverError, match="NaN"):
        block_eigs(lambda B: B * np.nan, n, 4, block=4)
