"""Preconditioned CG against scipy's direct solve and exact eigenvalues."""

import numpy as np
import pytest
import scipy.linalg as la
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from gtsam_schwarz import Jacobi, pcg
from gtsam_schwarz.krylov import pcg_columns


def spd(n=60, seed=0, cond=1e4):
    rng = np.random.default_rng(seed)
    Q, _ = np.linalg.qr(rng.normal(size=(n, n)))
    ev = np.logspace(0, np.log10(cond), n)
    return sp.csr_matrix(Q @ np.diag(ev) @ Q.T), ev


def test_cg_matches_direct_solve_and_records_history():
    A, _ = spd()
    b = np.random.default_rng(1).normal(size=A.shape[0])
    x, info = pcg(A, b, tol=1e-10)
    assert info.converged
    assert np.allclose(x, spla.spsolve(A.tocsc(), b), rtol=1e-7, atol=1e-9)
    assert len(info.residuals) == info.iterations + 1
    assert info.residuals[0] == pytest.approx(1.0)
    assert info.residuals[-1] <= 1e-10
    assert np.linalg.norm(b - A @ x) / np.linalg.norm(b) <= 1e-9


def test_lanczos_estimates_converge_to_extreme_eigenvalues():
    A, ev = spd(n=40, cond=1e3)
    b = np.ones(40)
    _, info = pcg(A, b, tol=1e-12)
    assert info.lambda_min == pytest.approx(ev.min(), rel=1e-6)
    assert info.lambda_max == pytest.approx(ev.max(), rel=1e-6)
    # preconditioned: estimates of M⁻¹A's spectrum
    M = Jacobi(A.shape[0]).update(A)
    _, info = pcg(A, b, M, tol=1e-12)
    d = A.diagonal()
    pev = la.eigvalsh(A.toarray(), np.diag(d))  # eigenvalues of D⁻¹A
    assert info.lambda_min == pytest.approx(pev.min(), rel=1e-5)
    assert info.lambda_max == pytest.approx(pev.max(), rel=1e-5)


def test_iteration_cap_reports_not_converged():
    A, _ = spd(cond=1e8)
    x, info = pcg(A, np.ones(A.shape[0]), maxiter=3)
    assert info.iterations == 3 and not info.converged
    assert "limit" in info.reason
    assert np.all(np.isfinite(x))


def test_zero_rhs_and_indefinite_preconditioner():
    A, _ = spd()
    x, info = pcg(A, np.zeros(A.shape[0]))
    assert info.converged and info.iterations == 0 and not x.any()
    _, info = pcg(A, np.ones(A.shape[0]), M=lambda r: -r)
    assert not info.converged and "positive definite" in info.reason


def test_pcg_bounds_give_up_only_when_behind():
    rng = np.random.default_rng(3)
    Q = rng.standard_normal((60, 60))
    A = Q @ Q.T + 0.1 * np.eye(60)
    b = rng.standard_normal(60)
    _, free = pcg(A, b, tol=1e-10, maxiter=600)
    assert free.converged and free.iterations > 8
    _, behind = pcg(A, b, tol=1e-10, maxiter=600, bounds=[np.inf] * 4 + [0.0])  # any residual is above 0
    assert not behind.converged and behind.iterations == 4 and "behind" in behind.reason
    _, ahead = pcg(A, b, tol=1e-10, maxiter=600, bounds=[1e9] * 50)  # never above: the same solve
    assert ahead.converged and ahead.iterations == free.iterations


def _laplacian_2d(m=30, shift=1e-3):
    """A 2D grid Laplacian plus a small shift (slow CG, small λmin): a hard case for the bound."""
    T = sp.diags([-np.ones(m - 1), 2 * np.ones(m), -np.ones(m - 1)], [-1, 0, 1])
    I = sp.identity(m)
    return (sp.kron(T, I) + sp.kron(I, T) + shift * sp.identity(m * m)).tocsr()


@pytest.mark.parametrize("precondition", [False, True])
def test_model_decrease_and_decrement_bound(precondition):
    """CG's model decrease φ(0) − φ(x), φ(x) = ½xᵀAx − bᵀx, is tracked exactly (also from a warm start), and the
    decrement bound never stops CG when the exact step's decrease ½bᵀA⁻¹b exceeds the tolerance;
    it stops early when the tolerance is above it."""
    A = _laplacian_2d()
    b = np.random.default_rng(3).normal(size=A.shape[0])
    M = Jacobi(A.shape[0]).update(A) if precondition else None
    phi = lambda x: 0.5 * x @ (A @ x) - b @ x
    decrement = 0.5 * b @ spla.spsolve(A.tocsc(), b)
    x, full = pcg(A, b, M, tol=1e-10)
    assert full.converged and full.model_decrease == pytest.approx(-phi(x), rel=1e-10)
    assert full.model_decrease == pytest.approx(decrement, rel=1e-8)
    x0 = 0.3 * x + 0.01
    xw, warm = pcg(A, b, M, tol=1e-10, x0=x0, maxiter=3)
    assert warm.model_decrease == pytest.approx(-phi(xw), rel=1e-10)
    # a tolerance below the exact decrease: never stopped by the bound (it bounds from above)
    _, below = pcg(A, b, M, tol=1e-10, decrement_tol=0.99 * decrement)
    assert below.converged and not below.decrement_stop
    assert below.decrement_bound >= below.model_decrease
    # a tolerance above it: stopped early, with the decrease reached ≤ the exact one ≤ the bound
    xs, above = pcg(A, b, M, tol=1e-10, decrement_tol=20 * decrement)
    assert above.decrement_stop and not above.converged and above.iterations < full.iterations
    assert above.model_decrease == pytest.approx(-phi(xs), rel=1e-10)
    assert above.model_decrease <= decrement * (1 + 1e-12) <= above.decrement_bound


@pytest.mark.parametrize("precondition", [False, True])
def test_left_bound_bounds_what_cg_left_of_the_model_decrease(precondition):
    """``bound_left``: on convergence to a loose tolerance, ``left_bound`` is at least what the exact
    solution would still lower the model beyond x, φ(x) − φ(x*) = ½(x* − x)ᵀA(x* − x); unknown (nan)
    after fewer iterations than the Ritz values need, and not computed unless asked for."""
    A = _laplacian_2d()
    b = np.random.default_rng(5).normal(size=A.shape[0])
    M = Jacobi(A.shape[0]).update(A) if precondition else None
    x_star = spla.spsolve(A.tocsc(), b)
    for tol in (1e-1, 1e-2, 1e-4):
        x, info = pcg(A, b, M, tol=tol, bound_left=True)
        left = 0.5 * (x_star - x) @ (A @ (x_star - x))
        assert info.converged and info.iterations >= 5
        assert left <= info.left_bound < 1e4 * max(left, 1e-300)
    _, plain = pcg(A, b, M, tol=1e-2)
    assert np.isnan(plain.left_bound)
    _, early = pcg(A, b, M, tol=0.9, bound_left=True)
    assert early.converged and early.iterations < 5 and np.isnan(early.left_bound)


def test_pcg_columns_runs_each_column_as_pcg_does():
    """Side-by-side CG: every column takes the iterations, residuals and solution of its own pcg run
    (columns stop separately; a zero column is converged at once)."""
    rng = np.random.default_rng(3)
    n = 300
    A = sp.diags([-1.0, 2.05, -1.0], [-1, 0, 1], shape=(n, n)).tocsr()
    A = A + sp.diags(rng.uniform(0.0, 0.5, n))
    d = A.diagonal()
    M = lambda r: r / d[:, None] if r.ndim == 2 else r / d  # noqa: E731 (Jacobi on one or several columns)
    B = rng.normal(size=(n, 3))
    B[:, 1] *= 1e-3  # another scale: the same relative tolerance, other iterates
    B[:, 2] = 0.0
    X, infos = pcg_columns(A, B, M=M, tol=1e-9)
    for k in range(2):
        x, info = pcg(A, B[:, k], M=M, tol=1e-9)
        assert infos[k].converged and infos[k].iterations == info.iterations
        np.testing.assert_allclose(infos[k].residuals, info.residuals, rtol=1e-8, atol=1e-14)
        np.testing.assert_allclose(X[:, k], x, rtol=1e-10, atol=1e-12)
        assert np.linalg.norm(B[:, k] - A @ X[:, k]) <= 1e-9 * np.linalg.norm(B[:, k])
    assert infos[2].converged and infos[2].iterations == 0 and not X[:, 2].any()
    capped, capped_infos = pcg_columns(A, B[:, :1], M=M, tol=1e-14, maxiter=5)
    assert not capped_infos[0].converged and capped_infos[0].iterations == 5


def test_pcg_columns_solves_hermitian_systems_as_their_real_equivalent():
    """A complex Hermitian A x = b (2D rotations as unit complex numbers) runs as CG on the real
    symmetric [[Re A, −Im A], [Im A, Re A]] does: the same iterates, so the same iteration count."""
    rng = np.random.default_rng(5)
    n = 200
    phase = np.exp(1j * rng.uniform(-np.pi, np.pi, n - 1))
    w = rng.uniform(1.0, 3.0, n - 1)
    off = sp.diags([-w * phase], [1], shape=(n, n))
    A = (off + off.conj().T + sp.diags(np.r_[w, 0] + np.r_[0, w] + 0.1)).tocsr()
    b = rng.normal(size=(n, 1)) + 1j * rng.normal(size=(n, 1))
    X, infos = pcg_columns(A, b, tol=1e-10)
    assert X.dtype == complex and infos[0].converged
    assert np.linalg.norm(b[:, 0] - A @ X[:, 0]) <= 1e-10 * np.linalg.norm(b)
    Ar = sp.bmat([[A.real, -A.imag], [A.imag, A.real]]).tocsr()
    xr, info = pcg(Ar, np.r_[b.real[:, 0], b.imag[:, 0]], tol=1e-10)
    assert info.iterations == infos[0].iterations
    np.testing.assert_allclose(X[:, 0], xr[:n] + 1j * xr[n:], rtol=1e-8, atol=1e-10)


def test_row_block_products_equal_scipys_and_stay_on_one_thread_where_they_must(monkeypatch):
    """The threaded product of a CSR matrix (row blocks of about equal entries on the local threads)
    equals scipy's for vectors, blocks of columns and complex numbers; small matrices, other formats
    and calls from a local thread keep the matrix itself; CG gives the same iterate either way."""
    import scipy.sparse as sp

    from gtsam_schwarz.krylov import spmv
    from gtsam_schwarz.util.threads import local_threads

    rng = np.random.default_rng(3)
    n = 3000
    A = sp.random(n, n, density=2e-3, random_state=4, format="csr") + sp.eye(n, format="csr") * n
    A = (A + A.T).tocsr()
    A.sort_indices()
    T = spmv.RowBlockMatrix(A)
    assert len(T.blocks) == 2 and T.blocks[0][0] == 0 and T.blocks[-1][1] == n
    x, X = rng.random(n), rng.random((n, 3))
    assert np.allclose(T @ x, A @ x, rtol=0, atol=1e-10) and np.allclose(T @ X, A @ X, rtol=0, atol=1e-10)
    Z = rng.random((n, 1)) + 1j * rng.random((n, 1))
    assert np.allclose(T @ Z, A @ Z) and (T @ Z).dtype == complex
    assert spmv.threaded(A) is A   # below THREADED_FROM entries
    monkeypatch.setattr(spmv, "THREADED_FROM", 10)
    assert isinstance(spmv.threaded(A), spmv.RowBlockMatrix) and spmv.threaded(A.tocsc()) is not None
    assert not isinstance(spmv.threaded(A.tocsc()), spmv.RowBlockMatrix)
    assert local_threads().submit(lambda: spmv.threaded(A)).result() is A   # no waiting on its own pool
    b = rng.random(n)
    x_threaded, info_t = pcg(A, b, tol=1e-10)
    monkeypatch.setattr(spmv, "THREADED_FROM", 10**12)
    x_plain, info_p = pcg(A, b, tol=1e-10)
    assert info_t.iterations == info_p.iterations and np.allclose(x_threaded, x_plain, rtol=0, atol=1e-12)
