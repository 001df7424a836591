"""Dense Cholesky for small, fairly full matrices (e.g. the coarse matrix A_0)."""

from __future__ import annotations

import numpy as np
import scipy.linalg as la
import scipy.sparse as sp

from .base import SingularLocalMatrixError, register_solver


@register_solver("dense")
class DenseCholesky:
    """LAPACK Cholesky of K (dense); ``refactor`` recomputes it."""

    def __init__(self, K: sp.spmatrix, what: str = "local matrix"):
        self.what = what
        self.refactor(K)

    def refactor(self, K) -> "DenseCholesky":
        dense = K.toarray() if sp.issparse(K) else np.asarray(K, dtype=float)
        try:
            self._c = la.cho_factor(dense, lower=True, check_finite=True)
        except (la.LinAlgError, ValueError) as exc:
            raise SingularLocalMatrixError(f"{self.what} is not positive definite: {exc}") from None
        return self

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        return la.cho_solve(self._c, rhs, check_finite=False)

    __call__ = solve
