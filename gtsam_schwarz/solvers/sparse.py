"""Sparse Cholesky with a fixed pattern: CHOLMOD (symbolic analysis once) or SuperLU (fallback)."""

from __future__ import annotations

import os
import time

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from .base import SingularLocalMatrixError, check_finite, register_solver
from .openmp import limit_threads

limit_threads()  # before CHOLMOD (and its OpenMP runtime) loads: one thread, not CHOLMOD's four
try:  # CHOLMOD (SuiteSparse) through scikit-sparse: supernodal, reusable symbolic analysis
    from sksparse.cholmod import CholmodError as _CholmodError
    from sksparse.cholmod import analyze as _cholmod_analyze
    HAVE_CHOLMOD = True
except ImportError:  # SuperLU (scipy) with a symmetric ordering
    HAVE_CHOLMOD = False
# GTSAM_SCHWARZ_SPARSE=superlu forces the fallback (to measure one against the other)
SPARSE_BACKEND = ("cholmod" if HAVE_CHOLMOD and os.environ.get("GTSAM_SCHWARZ_SPARSE", "") != "superlu"
                  else "superlu")


def _csc(K: sp.spmatrix) -> sp.csc_matrix:
    # K is symmetric: the transpose of its CSR form is its CSC form, without a conversion (and
    # with the same sorted-indices flag, so CHOLMOD's wrapper does not check it again)
    if sp.isspmatrix_csr(K):
        sorted_ = K.has_sorted_indices
        K = K.T
        K.has_sorted_indices = sorted_
        return K
    return sp.csc_matrix(K)


class SparseCholesky:
    """Sparse factorization of an SPD matrix whose sparsity pattern stays fixed.

    With CHOLMOD the fill-reducing ordering and symbolic analysis are done once (:meth:`analyze`,
    from the pattern) and :meth:`refactor` only recomputes numbers; with SuperLU (the fallback when
    scikit-sparse is not installed) every refactor is a fresh ``splu``.
    """

    analyze_seconds = factor_seconds = 0.0

    def __init__(self, K: sp.spmatrix, what: str = "local matrix", backend: str | None = None, mode: str = "auto",
                 ordering: str | None = None):
        self.what = what
        self.backend = backend or SPARSE_BACKEND
        self.mode = mode  # CHOLMOD's: auto (supernodal where dense enough), simplicial or supernodal
        self.ordering = ordering  # CHOLMOD's ordering method ("natural": K's own order); None: its default
        self.analyze(K)
        self.refactor(K)

    def analyze(self, K: sp.spmatrix) -> "SparseCholesky":
        """Symbolic work from K's pattern: ordering and supernodes (CHOLMOD); nothing for SuperLU."""
        t0 = time.perf_counter()
        K = _csc(K)
        self.n = K.shape[0]
        self._factor = None
        if self.backend == "cholmod" and self.n:
            self._analysis = _cholmod_analyze(K, mode=getattr(self, "mode", "auto"),
                                              ordering_method=getattr(self, "ordering", None) or "default")
        self.analyze_seconds = time.perf_counter() - t0
        return self

    def refactor(self, K: sp.spmatrix) -> "SparseCholesky":
        """New numbers, same pattern (CHOLMOD keeps its ordering and supernodes)."""
        if self.n == 0:
            return self
        t0 = time.perf_counter()
        try:
            return self._refactor(K)
        finally:
            self.factor_seconds = time.perf_counter() - t0  # the numeric factorization (callers budget by it)

    def _refactor(self, K: sp.spmatrix) -> "SparseCholesky":
        K = _csc(K)
        check_finite(K, self.what)
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

    @property
    def has_numeric(self) -> bool:
        """Whether the factor holds numbers (not after :meth:`release_numeric`)."""
        return self._factor is not None

    def release_numeric(self) -> None:
        """Drop the numeric factor (its memory) and keep the symbolic analysis: the next
        :meth:`refactor` allocates a factor again without a new ordering (lawnmower 600x600: the
        analyses of the subdomain and interior blocks cost 0.7 s per rebuild)."""
        self._factor = None

    def column_counts(self) -> np.ndarray:
        """Entries per column of the factor L (CHOLMOD; D on L's diagonal)."""
        return np.diff(sp.csc_matrix(self._factor.LD()).indptr)

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        if self.n == 0:
            return np.zeros_like(rhs)
        if self.backend == "cholmod":
            return self._factor(rhs)
        return self._factor.solve(rhs)

    __call__ = solve


@register_solver("cholmod")
class CholmodCholesky(SparseCholesky):
    """CHOLMOD supernodal Cholesky (scikit-sparse)."""

    def __init__(self, K, what: str = "local matrix"):
        if not HAVE_CHOLMOD:
            raise ValueError("CHOLMOD is not installed (pip install -e '.[cholmod]')")
        super().__init__(K, what, "cholmod")


@register_solver("superlu")
class SuperLUCholesky(SparseCholesky):
    """scipy's SuperLU in symmetric mode (no symbolic reuse)."""

    def __init__(self, K, what: str = "local matrix"):
        super().__init__(K, what, "superlu")
