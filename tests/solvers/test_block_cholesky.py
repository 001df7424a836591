"""The block Cholesky factor of matrices made of dense vertex blocks (solvers/block_cholesky.py)."""

import numpy as np
import pytest
import scipy.sparse as sp

from gtsam_schwarz.dd import GraphStructure, decompose
from gtsam_schwarz.linearization.native import NativeLinearizer
from gtsam_schwarz.problems import lawnmower, survey3d
from gtsam_schwarz.solvers import block_cholesky, cholmod_native
from gtsam_schwarz.solvers.base import SingularLocalMatrixError
from gtsam_schwarz.solvers.block_cholesky import BlockCholesky, applies
from gtsam_schwarz.solvers.block_diagonal import BlockDiagonalSolver, block_diagonal
from gtsam_schwarz.util.threads import local_threads

pytestmark = pytest.mark.skipif(not block_cholesky.AVAILABLE, reason="numba is not installed")


def block_matrix(nv: int, d: int, seed: int = 0, density: float = 0.03) -> sp.csr_matrix:
    """A random SPD matrix of dense d×d blocks on a random symmetric vertex pattern (sorted CSR)."""
    rng = np.random.default_rng(seed)
    P = sp.random(nv, nv, density=density, random_state=seed, format="csr")
    P = (((P + P.T) != 0) + sp.eye(nv, format="csr")).astype(float)
    A = sp.kron(P, np.ones((d, d)), format="csr")
    A.data = rng.standard_normal(A.nnz)
    A = (A + A.T) * 0.5
    A = sp.csr_matrix(A + sp.diags(np.asarray(abs(A).sum(axis=1)).ravel() + 0.1))
    A.sort_indices()
    return A


def dense_factor(F: BlockCholesky) -> np.ndarray:
    """L as a dense matrix, from the factor's stored blocks."""
    d, L = F.d, np.zeros((F.n, F.n))
    for J in range(F.nv):
        L[d * J:d * J + d, d * J:d * J + d] = F._Ld[J]
        for q in range(F.Lp[J], F.Lp[J + 1]):
            I = F.Li[q]
            L[d * I:d * I + d, d * J:d * J + d] = F._Lx[q]
    return L


@pytest.mark.parametrize("d", [3, 6])
def test_double_precision_solves_equal_a_dense_solve(d):
    A = block_matrix(120, d, seed=d)
    F = BlockCholesky(A, d, dtype=np.float64)
    rng = np.random.default_rng(1)
    b, B = rng.standard_normal(A.shape[0]), rng.standard_normal((A.shape[0], 5))
    dense = A.toarray()
    np.testing.assert_allclose(F.solve(b), np.linalg.solve(dense, b), rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(F.solve(B), np.linalg.solve(dense, B), rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(F.solve(np.asfortranarray(B), local_threads()), F.solve(B), rtol=0, atol=0)
    L = dense_factor(F)
    assert np.allclose(np.triu(L, 1), 0)
    np.testing.assert_allclose(L @ L.T, dense, rtol=1e-12, atol=1e-10)


def test_the_pattern_is_choleskys_own():
    """L's blocks hold exactly the entries of CHOLMOD's simplicial factor in the same (natural) order."""
    A = block_matrix(150, 3, seed=4)
    F = BlockCholesky(A, 3, dtype=np.float64)
    if cholmod_native.available():
        S = cholmod_native.SimplicialCholesky(A, natural=True)
        assert F.nnz == int(S.column_counts().sum())
    L = dense_factor(F)
    reference = np.linalg.cholesky(A.toarray())
    np.testing.assert_allclose(L, reference, rtol=1e-9, atol=1e-10)   # the unique Cholesky factor


@pytest.mark.parametrize("d", [3, 6])
def test_single_precision_applies_the_inverse_of_its_own_spd_product(d):
    """In single precision the solve is the exact inverse of L̃ L̃ᵀ (L̃: the stored blocks), an SPD matrix
    within single-precision rounding of A."""
    A = block_matrix(100, d, seed=10 + d)
    F = BlockCholesky(A, d)
    assert F._Lx.dtype == np.float32 and F.nbytes < BlockCholesky(A, d, dtype=np.float64).nbytes * 0.55
    L = dense_factor(F).astype(np.float64)
    M = L @ L.T
    b = np.random.default_rng(2).standard_normal(A.shape[0])
    np.testing.assert_allclose(M @ F.solve(b), b, rtol=1e-9, atol=1e-9)
    assert np.linalg.eigvalsh(M).min() > 0
    assert np.abs(M - A.toarray()).max() <= 1e-5 * np.abs(A.data).max()


def test_refactor_with_new_numbers_equals_a_fresh_factor():
    A = block_matrix(80, 3, seed=5)
    F = BlockCholesky(A, 3, dtype=np.float64)
    A2 = A.copy()
    A2.data = A.data * (1.0 + 0.1 * np.random.default_rng(3).random(A.nnz))
    A2 = sp.csr_matrix((A2 + A2.T) * 0.5)
    A2.sort_indices()
    assert np.array_equal(A2.indices, A.indices)
    b = np.ones(A.shape[0])
    F.refactor(A2)
    np.testing.assert_allclose(F.solve(b), BlockCholesky(A2, 3, dtype=np.float64).solve(b), rtol=0, atol=0)
    F.release_numeric()
    assert not F.has_numeric
    with pytest.raises(RuntimeError, match="released"):
        F.solve(b)
    F.refactor(A)
    np.testing.assert_allclose(F.solve(b), np.linalg.solve(A.toarray(), b), rtol=1e-10)
    other = block_matrix(80, 3, seed=9)   # another pattern: refused, not factorized on the analysed one
    assert other.nnz != A.nnz
    with pytest.raises(ValueError, match="the analysis had"):
        F.refactor(other)


def test_a_matrix_that_is_not_positive_definite_or_not_finite_is_refused():
    A = block_matrix(40, 3, seed=6)
    bad = A.copy()
    bad.data *= -1.0   # negative definite, the same pattern
    with pytest.raises(SingularLocalMatrixError, match="not positive definite"):
        BlockCholesky(bad, 3)
    nan = A.copy()
    nan.data[7] = np.nan
    with pytest.raises(SingularLocalMatrixError, match="non-finite"):
        BlockCholesky(nan, 3)


def test_only_whole_sorted_blocks_apply():
    A = block_matrix(30, 3, seed=7)
    assert applies(A, 3) and not applies(A, 2) and not applies(A.tocsc(), 3)
    assert not applies(sp.csr_matrix(A[:-1, :-1]), 3)   # a partial last block
    holes = A.tolil()
    holes[0, 1] = 0.0   # inside the first diagonal block
    holes[1, 0] = 0.0
    holes = sp.csr_matrix(holes)
    holes.eliminate_zeros()
    holes.sort_indices()
    assert not applies(holes, 3)   # one block missing an entry
    unsorted = A.copy()
    unsorted.has_sorted_indices = False
    assert not applies(unsorted, 3)
    with pytest.raises(ValueError, match="whole sorted"):
        BlockCholesky(holes, 3)


@pytest.mark.parametrize("problem", ["lawnmower", "survey"])
def test_one_level_blocks_are_factorized_by_blocks(problem, monkeypatch):
    """The one-level solver of a pose graph's ordered subdomain blocks takes block factors: in double
    precision it applies Σ R_iᵀ A_i⁻¹ R_i exactly; in single precision within rounding, in less memory."""
    prob = lawnmower(10, 10, sigma=0.01, seed=1) if problem == "lawnmower" else survey3d(4, 4, 3, seed=1)
    lin = NativeLinearizer.from_arrays(**prob.arrays)
    H = sp.csr_matrix(lin.linearize(lin.initial_state()).H)
    H.sort_indices()
    dec = decompose(GraphStructure.from_matrix(H, lin.offsets), 6, "metis", 1)
    x = np.random.default_rng(4).normal(size=H.shape[0])
    results = {}
    monkeypatch.setattr(BlockDiagonalSolver, "BLOCK_FROM", H.nnz)
    for dtype in (np.float64, np.float32):
        monkeypatch.setattr(BlockDiagonalSolver, "factor_dtype", np.dtype(dtype))
        solver = BlockDiagonalSolver(dec.index_sets(True))
        solver.order_vertices(H)
        solver.update(H)
        assert all(isinstance(c[3], BlockCholesky) and c[3].dtype == dtype for c in solver._chunks)
        results[dtype] = (solver.matvec(x), sum(c[3].nbytes for c in solver._chunks))
    sets = solver.sets
    B = block_diagonal(H, sets).toarray()
    exact = np.bincount(sets.indices, np.linalg.solve(B, x[sets.indices]), minlength=H.shape[0])
    np.testing.assert_allclose(results[np.float64][0], exact, rtol=1e-9, atol=1e-9 * np.abs(exact).max())
    np.testing.assert_allclose(results[np.float32][0], exact, rtol=0, atol=1e-3 * np.abs(exact).max())
    assert results[np.float32][1] < 0.55 * results[np.float64][1]


@pytest.mark.parametrize("setting", ["none", "below"])
def test_without_block_factors_the_one_level_solver_keeps_cholmod(monkeypatch, setting):
    """With the setting none, or for a matrix below BLOCK_FROM entries, the chunks keep CHOLMOD's factors."""
    prob = lawnmower(8, 8, sigma=0.01, seed=2)
    lin = NativeLinearizer.from_arrays(**prob.arrays)
    H = sp.csr_matrix(lin.linearize(lin.initial_state()).H)
    H.sort_indices()
    dec = decompose(GraphStructure.from_matrix(H, lin.offsets), 4, "metis", 1)
    if setting == "none":
        monkeypatch.setattr(BlockDiagonalSolver, "BLOCK_FROM", 0)
        monkeypatch.setattr(BlockDiagonalSolver, "factor_dtype", None)
    else:
        monkeypatch.setattr(BlockDiagonalSolver, "BLOCK_FROM", H.nnz + 1)
    solver = BlockDiagonalSolver(dec.index_sets(True))
    solver.order_vertices(H)
    solver.update(H)
    assert solver.ordered and not any(isinstance(c[3], BlockCholesky) for c in solver._chunks)


def test_the_precision_setting_is_read_from_the_environment(monkeypatch):
    monkeypatch.setenv("GTSAM_SCHWARZ_BLOCK_FACTOR", "float64")
    assert block_cholesky._precision() == np.float64
    monkeypatch.setenv("GTSAM_SCHWARZ_BLOCK_FACTOR", "none")
    assert block_cholesky._precision() is None
    monkeypatch.setenv("GTSAM_SCHWARZ_BLOCK_FACTOR", "half")
    with pytest.raises(ValueError, match="GTSAM_SCHWARZ_BLOCK_FACTOR"):
        block_cholesky._precision()
    assert block_cholesky.vertex_block(np.array([0, 3, 6, 9])) == 3
    assert block_cholesky.vertex_block(np.array([0, 3, 9])) is None


def test_the_extension_factors_interiors_by_blocks_in_the_basis_precision(monkeypatch):
    """With Φ in single precision (forced from 0 entries) and H of whole blocks, the interior factors
    A_II are block factors in single precision: Φ stays within single-precision rounding of the one
    CHOLMOD's factors give, A_0 is Φᵀ H Φ of that Φ, and CG takes the same iterations within one."""
    from gtsam_schwarz import make_preconditioner, pcg
    from gtsam_schwarz.coarse import HarmonicExtension

    prob = lawnmower(30, 30, sigma=0.01, seed=3)
    lin = NativeLinearizer.from_arrays(**prob.arrays)
    state = lin.initial_state()
    H = sp.csr_matrix(lin.linearize(state).H)
    H.sort_indices()
    dec = decompose(GraphStructure.from_matrix(H, lin.offsets), 12, "metis", 1)
    b = np.random.default_rng(5).standard_normal(H.shape[0])
    monkeypatch.setattr(HarmonicExtension, "SINGLE_FROM", 0)
    runs = {}
    for precision in (None, np.dtype(np.float32)):
        monkeypatch.setattr(block_cholesky, "PRECISION", precision)
        M = make_preconditioner("rgdsw-linear", H, dec, lin.translation_mask(), geometry=lin.geometry(state))
        assert M.extension.ordered
        assert all(isinstance(g.factor, BlockCholesky) == (precision is not None) for g in M.extension.groups)
        Phi = M.coarse_space.Phi.astype(np.float64)
        expected = (Phi.T @ H @ Phi).toarray()
        gap = np.abs(M.coarse_space.A0.toarray() - 0.5 * (expected + expected.T)).max() / np.abs(expected).max()
        assert gap < 1e-6
        runs[precision] = (Phi, pcg(H, b, M, tol=1e-8, maxiter=500)[1])
    (Phi64, cg64), (Phi32, cg32) = runs[None], runs[np.dtype(np.float32)]
    assert abs(Phi32 - Phi64).max() <= 1e-5 * abs(Phi64).max()
    assert cg32.converged and abs(cg32.iterations - cg64.iterations) <= 1
