"""All subdomain solves at once: one factorization of diag(A_1, …, A_N), A_i = R_i A R_iᵀ.

Subdomain i is an index set I_i (paper Sec. 3.1); R_i extracts its dofs. Stacking the R_i gives
one gather ``x[indices]``; the block-diagonal matrix of all local matrices is factorized once and
every application of Σ R_iᵀ A_i⁻¹ R_i is one gather, one solve and one scatter-add — no Python
loop over subdomains. Blocks never couple, so each could equally be factorized on its own process.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np
import scipy.linalg as la
import scipy.sparse as sp
import scipy.sparse.linalg as spla


class SingularLocalMatrixError(RuntimeError):
    """A local (subdomain, interior or coarse) matrix could not be factorized."""


@dataclass(frozen=True)
class IndexSets:
    """N possibly overlapping dof sets, concatenated: set i is ``indices[ptr[i]:ptr[i+1]]``."""

    indices: np.ndarray
    ptr: np.ndarray
    n: int  # global dimension

    @property
    def count(self) -> int:
        return len(self.ptr) - 1

    @property
    def sizes(self) -> np.ndarray:
        return np.diff(self.ptr)

    def block_of_entry(self) -> np.ndarray:
        return np.repeat(np.arange(self.count), self.sizes)

    def restriction(self) -> sp.csr_matrix:
        """Stacked restriction R = [R_1; …; R_N] (len(indices) × n)."""
        m = len(self.indices)
        return sp.csr_matrix((np.ones(m), (np.arange(m), self.indices)), shape=(m, self.n))

    def get(self, i: int) -> np.ndarray:
        return self.indices[self.ptr[i]:self.ptr[i + 1]]

    @classmethod
    def from_lists(cls, sets, n: int) -> "IndexSets":
        sets = [np.asarray(s, dtype=np.int64) for s in sets]
        ptr = np.zeros(len(sets) + 1, dtype=np.int64)
        np.cumsum([len(s) for s in sets], out=ptr[1:])
        idx = np.concatenate(sets) if sets else np.zeros(0, dtype=np.int64)
        return cls(indices=idx, ptr=ptr, n=n)


def block_diagonal(A: sp.spmatrix, sets: IndexSets) -> sp.csr_matrix:
    """diag(R_1 A R_1ᵀ, …, R_N A R_Nᵀ) as one sparse matrix (couplings between blocks dropped)."""
    R = sets.restriction()
    C = (R @ sp.csr_matrix(A) @ R.T).tocoo()
    blk = sets.block_of_entry()
    keep = blk[C.row] == blk[C.col]
    m = len(sets.indices)
    return sp.csr_matrix((C.data[keep], (C.row[keep], C.col[keep])), shape=(m, m))


DENSE_FACTOR_MAX = 4000  # a matrix this small and at least 10 % full is factorized densely

try:  # CHOLMOD (SuiteSparse) through scikit-sparse: supernodal, reusable symbolic analysis
    from sksparse.cholmod import CholmodError as _CholmodError
    from sksparse.cholmod import analyze as _cholmod_analyze
    _HAVE_CHOLMOD = True
except ImportError:  # SuperLU (scipy) with a symmetric ordering
    _HAVE_CHOLMOD = False
# GTSAM_SCHWARZ_SPARSE=superlu forces the fallback (to measure one against the other)
SPARSE_BACKEND = ("cholmod" if _HAVE_CHOLMOD and os.environ.get("GTSAM_SCHWARZ_SPARSE", "") != "superlu"
                  else "superlu")


def _check_finite(K: sp.spmatrix, what: str) -> None:
    if not np.all(np.isfinite(K.data)):
        raise SingularLocalMatrixError(f"{what} has non-finite entries")


class SparseCholesky:
    """Sparse factorization of an SPD matrix whose sparsity pattern stays fixed.

    With CHOLMOD the fill-reducing ordering and symbolic analysis are done once and
    :meth:`refactor` only recomputes numbers; with SuperLU (the fallback when scikit-sparse is
    not installed) every refactor is a fresh ``splu``.
    """

    def __init__(self, K: sp.spmatrix, what: str = "local matrix", backend: str | None = None):
        self.what = what
        self.backend = backend or SPARSE_BACKEND
        K = K.T if sp.isspmatrix_csr(K) else sp.csc_matrix(K)
        self.n = K.shape[0]
        self._factor = None
        if self.backend == "cholmod" and self.n:
            self._analysis = _cholmod_analyze(K)
        self.refactor(K)

    def refactor(self, K: sp.spmatrix) -> "SparseCholesky":
        """New numbers, same pattern (CHOLMOD keeps its ordering and supernodes)."""
        if self.n == 0:
            return self
        # K is symmetric: the transpose of its CSR form is its CSC form, without a conversion
        K = K.T if sp.isspmatrix_csr(K) else sp.csc_matrix(K)
        _check_finite(K, self.what)
        if self.backend == "cholmod":
            try:
                if self._factor is None:
                    self._factor = self._analysis.cholesky(K)
                else:
                    self._factor.cholesky_inplace(K)
            except _CholmodError as exc:
                self._factor = None
                raise SingularLocalMatrixError(f"{self.what} is not positive definite: {exc}") from None
            return self
        try:
            self._factor = spla.splu(K, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                                     options={"SymmetricMode": True})
        except RuntimeError as exc:  # SuperLU: "Factor is exactly singular"
            raise SingularLocalMatrixError(f"{self.what} is singular: {exc}") from None
        return self

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        if self.n == 0:
            return np.zeros_like(rhs)
        if self.backend == "cholmod":
            return self._factor(rhs)
        return self._factor.solve(rhs)

    __call__ = solve


def factorize(K: sp.spmatrix, what: str = "local matrix"):
    """Factorize a symmetric positive definite matrix; returns a callable solve(rhs).

    Small, fairly dense matrices (e.g. a coarse matrix A_0) get a dense Cholesky, everything else
    a sparse Cholesky (:class:`SparseCholesky`). A singular matrix raises a clear error.
    """
    n = K.shape[0]
    if n == 0:
        return lambda rhs: np.zeros_like(rhs)
    if n <= DENSE_FACTOR_MAX and K.nnz >= 0.1 * n * n:
        try:
            c = la.cho_factor(K.toarray(), lower=True, check_finite=True)
        except (la.LinAlgError, ValueError) as exc:
            raise SingularLocalMatrixError(f"{what} is not positive definite: {exc}") from None
        return lambda rhs: la.cho_solve(c, rhs, check_finite=False)
    return SparseCholesky(K, what)


class SparsityPattern:
    """A CSR pattern (indptr, indices) to recognise matrices whose symbolic work can be reused."""

    def __init__(self, A: sp.csr_matrix):
        self.shape = A.shape
        self.indptr = A.indptr.copy()
        self.indices = A.indices.copy()

    def matches(self, A: sp.spmatrix) -> bool:
        return (isinstance(A, sp.csr_matrix) and A.shape == self.shape and A.has_sorted_indices
                and np.array_equal(A.indptr, self.indptr) and np.array_equal(A.indices, self.indices))


class Gather:
    """B = extract(A) for an extraction that copies entries (submatrix, block diagonal, …).

    The pattern of B and the position in ``A.data`` of each of its entries are found once per
    sparsity pattern of A; afterwards new numbers cost one gather ``A.data[src]``.
    """

    def __init__(self, extract):
        self.extract = extract
        self.pattern = None

    def __call__(self, A: sp.spmatrix) -> sp.csr_matrix:
        A = sp.csr_matrix(A)
        if not A.has_sorted_indices:
            A = A.sorted_indices()
        if self.pattern is None or not self.pattern.matches(A):
            pos = sp.csr_matrix((np.arange(1, A.nnz + 1, dtype=float), A.indices, A.indptr), shape=A.shape)
            B = sp.csr_matrix(self.extract(pos))
            B.sort_indices()
            self.src = B.data.astype(np.int64) - 1
            self.B, self.pattern = B, SparsityPattern(A)
        B = self.B.copy()
        B.data = A.data[self.src]
        return B


class BlockDiagonalSolver:
    """Applies Σ_i R_iᵀ A_i⁻¹ R_i for the index sets ``sets`` (one-level additive Schwarz).

    Blocks that are all the same small size (block-Jacobi: one pose each) are inverted as a dense
    batch; anything else is one sparse Cholesky of the block-diagonal matrix. :meth:`update`
    takes a matrix with the same pattern and only refactors numerically.
    """

    DENSE_MAX = 12

    def __init__(self, A: sp.spmatrix, sets: IndexSets):
        self.sets = sets
        self.n = sets.n
        sizes = sets.sizes
        self._dense = None
        self._blocks = Gather(lambda M: block_diagonal(M, sets))
        self._factor = None
        self._dense_blocks = bool(sets.count and sizes.min() == sizes.max() and sizes[0] <= self.DENSE_MAX)
        self.update(A)

    def update(self, A: sp.spmatrix) -> "BlockDiagonalSolver":
        """Refactor for new numbers in A (symbolic work is reused while A's pattern is unchanged)."""
        A = sp.csr_matrix(A)
        if self._dense_blocks:
            s = int(self.sets.sizes[0])
            idx = self.sets.indices.reshape(-1, s)
            blocks = np.asarray(A[idx[:, :, None].repeat(s, 2).ravel(),
                                  idx[:, None, :].repeat(s, 1).ravel()]).reshape(-1, s, s)
            try:
                self._dense = np.linalg.inv(blocks)
            except np.linalg.LinAlgError:
                raise SingularLocalMatrixError("a diagonal block is singular") from None
            if not np.all(np.isfinite(self._dense)):
                raise SingularLocalMatrixError("a diagonal block is singular")
            return self
        pattern = self._blocks.pattern
        B = self._blocks(A)
        if self._factor is None or self._blocks.pattern is not pattern:
            self._factor = SparseCholesky(B, "a subdomain matrix")
        else:
            self._factor.refactor(B)
        return self

    def matvec(self, x: np.ndarray) -> np.ndarray:
        xl = x[self.sets.indices]
        if self._dense is not None:
            s = self._dense.shape[1]
            yl = np.einsum("bij,bj->bi", self._dense, xl.reshape(-1, s)).ravel()
        else:
            yl = self._factor.solve(xl)
        return np.bincount(self.sets.indices, weights=yl, minlength=self.n)
