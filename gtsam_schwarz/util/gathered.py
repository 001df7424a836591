"""A CSR matrix whose values are never stored: entry k is ``source[index[k]]``.

A linearizer that sums H into a compact source array (per pose, per factor) can hand out H without
its 8·nnz bytes of values (1M 2D poses: 343 MiB beside a Schwarz preconditioner). Products come from
the source by a kernel the linearizer supplies; readers of single entries (gathers of submatrices,
H's diagonal, samples) go through :func:`entries` or compose their positions once (:meth:`compose`).
``data`` holds one NaN for every entry (a broadcast, no memory): a reader that forgets the source
gets NaNs, never numbers that look right.
"""

from __future__ import annotations

from typing import Callable

import numpy as np
import scipy.sparse as sp

_CHUNK = 1 << 22   # positions converted to intp a chunk at a time (int32 index arrays)


class GatheredCSR(sp.csr_matrix):
    """H in a fixed CSR pattern with values ``source[index]`` (see the module's docstring).

    Made by :meth:`of`. ``product(x)`` returns H·x from the source. Anything scipy derives from it
    (slices, sums, copies) carries NaN values and no source: it fails loudly, not silently."""

    source: np.ndarray | None = None
    index: np.ndarray | None = None
    product: Callable | None = None
    diagonal_at: np.ndarray | None = None   # the position of every row's diagonal entry (square, all stored)

    @classmethod
    def of(cls, indptr: np.ndarray, indices: np.ndarray, shape: tuple, source: np.ndarray, index: np.ndarray,
           product: Callable[[np.ndarray], np.ndarray], diagonal_at: np.ndarray | None = None) -> "GatheredCSR":
        """``diagonal_at``: where the caller knows them, the positions of the diagonal entries, one per
        row in order (else :meth:`diagonal` finds them)."""
        nan = np.broadcast_to(np.float64(np.nan), (len(indices),))
        A = cls((nan, indices, indptr), shape=shape, copy=False)
        A.has_sorted_indices = True
        A.has_canonical_format = True
        A.source, A.index, A.product, A.diagonal_at = source, index, product, diagonal_at
        return A

    def compose(self, positions: np.ndarray) -> np.ndarray:
        """Positions in ``source`` of the entries at ``positions`` of H's values. ``index``: an array (one
        position per entry) or an object whose ``compose(positions)`` finds them (a block map)."""
        positions = np.asarray(positions)
        if not isinstance(self.index, np.ndarray):
            return self.index.compose(positions)
        out = np.empty(len(positions), dtype=self.index.dtype)
        for lo in range(0, len(positions), _CHUNK):
            np.take(self.index, positions[lo:lo + _CHUNK], out=out[lo:lo + _CHUNK])
        return out

    def take(self, positions: np.ndarray) -> np.ndarray:
        """H's values at ``positions`` (of a CSR ``data`` with this pattern)."""
        return self.take_source(self.compose(positions))

    def take_source(self, composed: np.ndarray) -> np.ndarray:
        """The source's numbers at ``composed`` positions (:meth:`compose`), a chunk at a time."""
        out = np.empty(len(composed))
        for lo in range(0, len(composed), _CHUNK):
            np.take(self.source, composed[lo:lo + _CHUNK], out=out[lo:lo + _CHUNK])
        return out

    def materialize(self) -> sp.csr_matrix:
        """The ordinary CSR matrix (its values gathered: 8·nnz bytes), for solvers that factorize H."""
        if self.source is None:
            raise TypeError("a matrix derived from a GatheredCSR has no source: materialize() the GatheredCSR first")
        data = np.empty(self.nnz)
        for lo in range(0, self.nnz, _CHUNK):
            hi = min(lo + _CHUNK, self.nnz)
            at = self.index[lo:hi] if isinstance(self.index, np.ndarray) else self.index.entries(lo, hi)
            np.take(self.source, at, out=data[lo:hi])
        H = sp.csr_matrix((data, self.indices, self.indptr), shape=self.shape, copy=False)
        H.has_sorted_indices = True
        H.has_canonical_format = True
        return H

    def diagonal(self, k: int = 0) -> np.ndarray:
        if k != 0:
            return self.materialize().diagonal(k)
        if self.diagonal_at is not None:
            return self.take(self.diagonal_at)
        d = np.zeros(min(self.shape))
        for r0 in range(0, self.shape[0], _CHUNK // 8):   # (a row index per entry: a chunk of rows at a time)
            r1 = min(r0 + _CHUNK // 8, self.shape[0])
            lo, hi = self.indptr[r0], self.indptr[r1]
            rows = np.repeat(np.arange(r0, r1), np.diff(self.indptr[r0:r1 + 1]))
            at = lo + np.flatnonzero(rows == self.indices[lo:hi])
            d[self.indices[at]] = self.take(at)
        return d

    # what scipy would compute from ``data`` (NaNs) is computed from the stored matrix instead: correct,
    # at the memory of H's values for the moment (no hot path calls these)
    def __getitem__(self, key):
        return self.materialize()[key]

    def tocoo(self, copy=False):
        return self.materialize().tocoo()

    def asformat(self, format, copy=False):   # (scipy's conversions, sp.csr_matrix(A) among them)
        return self.materialize().asformat(format)

    def tocsc(self, copy=False):
        return self.materialize().tocsc()

    def toarray(self, order=None, out=None):
        return self.materialize().toarray(order, out)

    def transpose(self, axes=None, copy=False):
        return self.materialize().transpose(axes, copy)

    def _matmul_sparse(self, other):
        return self.materialize()._matmul_sparse(other)

    def _rmatmul_dispatch(self, other):
        return self.materialize()._rmatmul_dispatch(other)

    def multiply(self, other):
        return self.materialize().multiply(other)

    def _binopt(self, other, op):   # sums, differences, elementwise products
        return self.materialize()._binopt(other, op)

    def _mul_scalar(self, other):
        return self.materialize()._mul_scalar(other)

    def _with_data(self, data, copy=True):   # other functions of the values: not from NaNs
        raise TypeError("a GatheredCSR's values live in its source: materialize() it first")

    def _matmul_vector(self, x):
        return self.product(np.ascontiguousarray(x, dtype=np.float64))

    def _matmul_multivector(self, X):
        return np.column_stack([self.product(np.ascontiguousarray(X[:, k], dtype=np.float64))
                                for k in range(X.shape[1])]) if X.shape[1] else np.zeros((self.shape[0], 0))


def is_gathered(A) -> bool:
    return isinstance(A, GatheredCSR) and A.source is not None


def stored(A: sp.spmatrix) -> sp.csr_matrix:
    """A as a CSR matrix with its values stored (a gathered one materialized), for factorizations."""
    return A.materialize() if is_gathered(A) else sp.csr_matrix(A)


def entries(A: sp.csr_matrix, positions: np.ndarray) -> np.ndarray:
    """A's values at ``positions`` of its CSR data, whether stored or gathered from a source."""
    return A.take(positions) if is_gathered(A) else A.data[positions]
