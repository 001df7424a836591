"""Preconditioned CG against scipy's direct solve and exact eigenvalues."""

import numpy as np
import pytest
import scipy.linalg as la
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from gtsam_schwarz import Jacobi, pcg


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
