"""The trivial preconditioners: identity (plain CG) and point Jacobi."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from ..solvers import SingularLocalMatrixError
from .base import SchwarzOperator


class Identity(SchwarzOperator):
    """M⁻¹ = I: unpreconditioned CG."""

    def __init__(self, n: int):
        self.n = int(n)

    def update(self, A, geometry=None):
        return self

    def apply(self, x):
        return np.array(x, dtype=float, copy=True)


class Jacobi(SchwarzOperator):
    """Point Jacobi: diag(A)⁻¹."""

    def __init__(self, n: int):
        self.n = int(n)

    def update(self, A, geometry=None):
        d = np.asarray(sp.csr_matrix(A).diagonal(), dtype=float)
        if np.any(d <= 0) or not np.all(np.isfinite(d)):
            raise SingularLocalMatrixError("Jacobi: the matrix has a non-positive diagonal entry")
        self.inv_diag = 1.0 / d
        return self

    def apply(self, x):
        return self.inv_diag * x
