"""CHOLMOD's simplicial factor through ctypes: the numbers of a direct solve, released and refilled,
singular pivots refused, and the same results on two threads as on one."""

import threading

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from gtsam_schwarz.solvers import SingularLocalMatrixError, cholmod_native, cholmod_symbolic


def _spd(n: int, seed: int) -> sp.csc_matrix:
    rng = np.random.default_rng(seed)
    R = sp.random(n, n, density=4.0 / n, random_state=seed)
    return sp.csc_matrix(R @ R.T + sp.identity(n) * (1.0 + rng.random()))


def test_available_wherever_the_symbolic_interface_is():
    assert cholmod_native.available() == cholmod_symbolic.available()


needs = pytest.mark.skipif(not cholmod_symbolic.available(), reason="CHOLMOD's library is not installed")


@needs
@pytest.mark.parametrize("natural", [True, False])
def test_solves_like_a_direct_solve_and_refills_after_release(natural):
    K = _spd(400, 1)
    b = np.random.default_rng(2).standard_normal((400, 3))
    F = cholmod_native.SimplicialCholesky(K, "K", natural=natural)
    ref = spla.spsolve(K, b)
    assert np.allclose(F.solve(b), ref, rtol=1e-10, atol=1e-12)
    assert np.allclose(F(b[:, 0]), ref[:, 0], rtol=1e-10, atol=1e-12) and F(b[:, 0]).shape == (400,)
    assert F.column_counts().sum() >= (K.nnz + 400) // 2   # L holds K's lower triangle at least
    x = F.solve(b)
    F.release_numeric()
    assert not F.has_numeric
    K2 = sp.csc_matrix(K * 2.0)
    F.refactor(K2)
    assert F.has_numeric and np.allclose(F.solve(b), x / 2.0, rtol=1e-10, atol=1e-12)


@needs
def test_supernodal_preferred_where_cholmod_would_choose_it():
    """Simplicial where the factor stays sparse (a chain), supernodal where it fills in (dense)."""
    chain = sp.csc_matrix(sp.diags([-np.ones(999), 2.5 * np.ones(1000), -np.ones(999)], [-1, 0, 1]))
    assert not cholmod_native.SimplicialCholesky(chain, factor=False).supernodal_preferred()
    dense = sp.csc_matrix(np.eye(200) * 200 + np.ones((200, 200)))
    assert cholmod_native.SimplicialCholesky(dense, factor=False).supernodal_preferred()


@needs
def test_a_zero_pivot_is_refused():
    K = sp.csc_matrix(sp.diags([1.0, 0.0, 2.0]))
    with pytest.raises(SingularLocalMatrixError):
        cholmod_native.SimplicialCholesky(K, "K")
    F = cholmod_native.SimplicialCholesky(sp.csc_matrix(sp.diags([1.0, 3.0, 2.0])), "K")
    with pytest.raises(SingularLocalMatrixError):
        F.refactor(sp.csc_matrix(sp.diags([1.0, np.nan, 2.0])))


@needs
def test_two_threads_give_the_numbers_of_one():
    mats = [_spd(3000, s) for s in (3, 4)]
    b = np.random.default_rng(5).standard_normal(3000)
    serial = [cholmod_native.SimplicialCholesky(K, natural=False).solve(b) for K in mats]
    out = [None, None]

    def work(k):
        F = cholmod_native.SimplicialCholesky(mats[k], natural=False)
        for _ in range(5):
            F.refactor(mats[k])
            out[k] = F.solve(b)

    threads = [threading.Thread(target=work, args=(k,)) for k in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert all(np.array_equal(o, s) for o, s in zip(out, serial))
