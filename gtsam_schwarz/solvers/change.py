"""How far a matrix has moved from the one a preconditioner was built for: a cheap staleness test."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from ..util import as_csr
from ..util.gathered import entries


class EntryChange:
    """The diagonally scaled RMS change of A's stored entries since a reference R (same pattern):
    δ = sqrt(mean((A_ij − R_ij)² / (R_ii R_jj))) over a fixed random sample of the entries.

    A preconditioner built for R stays good for A while δ is small (a Loewner-order perturbation
    (1 ± ε)R bounds κ(M⁻¹A) by κ(M⁻¹R)(1 + ε)/(1 − ε)). The sample keeps it O(``SAMPLES``) per
    call and in memory (no copy of R: 360 MB for H at 1M 2D poses); a different pattern gives inf.

    ``R`` may be a block of rows (``first_row`` on) with ``diagonal`` the whole matrix's: each process
    of a distributed matrix adds up :meth:`sums` of its own rows.
    """

    SAMPLES = 1 << 17  # entries compared (the RMS of 131 072 terms: a few per cent of noise)

    def __init__(self, R: sp.spmatrix, seed: int = 0, diagonal: np.ndarray | None = None, first_row: int = 0):
        R = as_csr(R)   # not re-wrapped: no new O(nnz) check of sorted indices
        nnz = R.nnz
        self.shape, self.nnz = R.shape, nnz
        if nnz <= self.SAMPLES:
            idx = np.arange(nnz)
        else:
            idx = np.sort(np.random.default_rng(seed).integers(0, nnz, self.SAMPLES))
        self.idx = idx
        self.cols = R.indices[idx].copy()
        rows = np.searchsorted(R.indptr, idx, side="right") - 1 + first_row
        d = np.abs(R.diagonal() if diagonal is None else np.asarray(diagonal, dtype=float))
        d = np.where(d > 0, d, 1.0)
        self.scale = 1.0 / np.sqrt(d[rows] * d[self.cols])
        self.values = entries(R, idx).copy()

    def sums(self, A: sp.spmatrix) -> tuple[float, int]:
        """(Σ of the squared scaled changes, number of entries compared); inf when A's pattern is not
        R's (a different size, count or sampled columns)."""
        A = as_csr(A)
        if A.shape != self.shape or A.nnz != self.nnz or not np.array_equal(A.indices[self.idx], self.cols):
            return float("inf"), 1
        diff = (entries(A, self.idx) - self.values) * self.scale
        return float(diff @ diff), len(self.idx)

    def __call__(self, A: sp.spmatrix) -> float:
        """δ for A (inf for another pattern)."""
        total, count = self.sums(A)
        return float(np.sqrt(total / count)) if count else 0.0
