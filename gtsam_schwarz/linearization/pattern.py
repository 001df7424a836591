"""The fixed block pattern of a graph's Hessian, so that symbolic work downstream is done once."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp


def _expand_uniform(blocks: sp.csr_matrix, d: int) -> tuple[np.ndarray, np.ndarray]:
    """CSR (indptr, indices) of the dof pattern of a vertex pattern whose vertices all have d dofs."""
    nv = blocks.shape[0]
    cnt = np.diff(blocks.indptr)
    expanded = (blocks.indices[:, None].astype(np.int64) * d + np.arange(d)).ravel()  # per vertex row
    row_len = np.repeat(cnt * d, d)  # each of the d dof rows of vertex v repeats its expanded segment
    starts = np.repeat(blocks.indptr[:-1].astype(np.int64) * d, d)
    indptr = np.zeros(nv * d + 1, dtype=np.int64)
    np.cumsum(row_len, out=indptr[1:])
    gather = np.repeat(starts - indptr[:-1], row_len) + np.arange(indptr[-1])
    index_type = np.int32 if nv * d < 2**31 and indptr[-1] < 2**31 else np.int64
    return indptr.astype(index_type), expanded[gather].astype(index_type)


class HessianPattern:
    """The full block sparsity of H: every entry of every block (u, v) of coupled variables.

    ``sparseJacobian_`` drops entries below 1e-12 and scipy's products drop exact zeros, so the
    pattern of JᵀJ can change between linearization points (e.g. at the zero-residual dead-reckoning
    start). Placing H into this fixed pattern lets everything symbolic downstream (subdomain
    gathers, orderings, harmonic-extension plans) be computed once per graph.
    """

    def __init__(self, H: sp.csr_matrix, offsets: np.ndarray):
        offsets = np.asarray(offsets, dtype=np.int64)
        nv, n = len(offsets) - 1, int(offsets[-1])
        owner = np.repeat(np.arange(nv), np.diff(offsets))
        C = sp.coo_matrix(H)
        blocks = sp.csr_matrix((np.ones(C.nnz + nv), (np.concatenate([owner[C.row], np.arange(nv)]),
                                                      np.concatenate([owner[C.col], np.arange(nv)]))),
                               shape=(nv, nv))
        blocks.sum_duplicates()
        blocks.sort_indices()
        dims = np.diff(offsets)
        if nv and np.all(dims == dims[0]):  # every variable d dofs: expand the block pattern directly
            self.indptr, self.indices = _expand_uniform(blocks, int(dims[0]))
        else:
            E = sp.csr_matrix((np.ones(n), (np.arange(n), owner)), shape=(n, nv))
            F = (E @ blocks @ E.T).tocsr()
            F.sort_indices()
            self.indptr, self.indices = F.indptr, F.indices
        self.shape = (n, n)
        rows = np.repeat(np.arange(n, dtype=np.int64), np.diff(self.indptr))
        self.diagonal = np.flatnonzero(rows == self.indices)

        self._last = None  # (indptr, indices, positions) of the last pattern placed into this one

    def fit(self, H: sp.csr_matrix) -> sp.csr_matrix | None:
        """H with the fixed pattern (explicit zeros where needed); None if H has entries outside it.

        The positions of H's entries are found by a search once per pattern of H (JᵀJ keeps one
        pattern after the first step), afterwards by comparing two arrays."""
        H = sp.csr_matrix(H)
        H.sort_indices()
        last = self._last
        if last is None or not (np.array_equal(H.indptr, last[0]) and np.array_equal(H.indices, last[1])):
            # position of each entry of H in the fixed pattern: the elementwise product of H's
            # pattern with a matrix holding 1-based positions (scipy keeps canonical order)
            pos = sp.csr_matrix((np.arange(1, len(self.indices) + 1, dtype=float), self.indices, self.indptr),
                                shape=self.shape)
            ones = sp.csr_matrix((np.ones(H.nnz), H.indices, H.indptr), shape=self.shape)
            hit = sp.csr_matrix(ones.multiply(pos))
            hit.sort_indices()
            if hit.nnz != H.nnz or not np.array_equal(hit.indices, H.indices):
                return None
            self._last = last = (H.indptr.copy(), H.indices.copy(), hit.data.astype(np.int64) - 1)
        data = np.zeros(len(self.indices))
        data[last[2]] = H.data
        return sp.csr_matrix((data, self.indices, self.indptr), shape=self.shape)
