"""Sparse-matrix helpers below every layer: the vertex-level pattern of a block matrix."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp


def as_csr(A: sp.spmatrix) -> sp.csr_matrix:
    """A in CSR form, the same object when it is one: ``sp.csr_matrix(A)`` of a CSR matrix is a new
    object that has forgotten that its indices are sorted, which scipy then checks again, O(nnz)
    (H at 1M 2D poses: 20-30 ms a time, 0.2 s per first build)."""
    return A if sp.isspmatrix_csr(A) else sp.csr_matrix(A)


def vertex_pattern(A: sp.spmatrix, offsets: np.ndarray) -> sp.csr_matrix:
    """The vertex-level pattern of a block matrix (1 where block (u, v) is stored).

    Reads only the first row of every vertex and, in it, the first column of every block: A's
    pattern holds whole blocks (the fixed pattern of H does), so nothing else is needed. With one
    block size d everywhere that is every d-th entry of those rows, and the CSR arrays are written
    directly (no triplet conversion)."""
    offsets = np.asarray(offsets, dtype=np.int64)
    nv = len(offsets) - 1
    A = as_csr(A)
    dims = np.diff(offsets)
    first = offsets[:-1]
    starts = A.indptr[first].astype(np.int64)
    lengths = A.indptr[first + 1] - starts
    if nv and A.has_sorted_indices and np.all(dims == dims[0]):
        step = int(dims[0])
        count = lengths // step
        indptr = np.zeros(nv + 1, dtype=np.int64)
        np.cumsum(count, out=indptr[1:])
        pos = np.repeat(starts - step * indptr[:-1], count) + step * np.arange(indptr[-1])
        cols = A.indices[pos] // step
        if np.array_equal(cols * step, A.indices[pos]) and indptr[-1] * step == lengths.sum():  # whole blocks
            itype = np.int32 if max(nv, len(cols)) < 2**31 else np.int64
            B = sp.csr_matrix((np.ones(len(cols)), cols.astype(itype), indptr.astype(itype)), shape=(nv, nv))
            B.has_sorted_indices = True
            return B
    owner = np.repeat(np.arange(nv), dims)
    pos = np.repeat(starts - np.cumsum(lengths) + lengths, lengths) + np.arange(int(lengths.sum()))
    cols = A.indices[pos]
    rows = np.repeat(np.arange(nv), lengths)
    keep = cols == first[owner[cols]]
    B = sp.csr_matrix((np.ones(int(keep.sum())), (rows[keep], owner[cols[keep]])), shape=(nv, nv))
    B.data[:] = 1.0
    return B


def edge_pattern(n: int, i: np.ndarray, j: np.ndarray) -> sp.csr_matrix:
    """The symmetric pattern of a graph on n vertices: its diagonal and both directions of every
    edge (i_k, j_k), repeated edges once, as a boolean CSR with sorted 32-bit indices. Booleans and
    32-bit coordinates keep the triplet conversion's scattered writes small: on this project's
    machines a float64 pattern with 64-bit coordinates took 5x as long (1M vertices, 2M edges: 0.32-0.57
    against 0.06-0.10 s in fresh processes), its writes missing the TLB across ~100 MB."""
    itype = np.int32 if n < 2**31 else np.int64
    i, j = np.asarray(i).astype(itype, copy=False), np.asarray(j).astype(itype, copy=False)
    nodes = np.arange(n, dtype=itype)
    B = sp.csr_matrix((np.ones(2 * len(i) + n, dtype=bool), (np.r_[i, j, nodes], np.r_[j, i, nodes])), shape=(n, n))
    B.sum_duplicates()
    return B


def row_entries(A: sp.csr_matrix, rows: np.ndarray, itype=np.int64) -> tuple[np.ndarray, np.ndarray]:
    """Positions in A.data of the entries of ``rows`` (row after row) and the indptr of those rows."""
    start = A.indptr[rows]
    count = (A.indptr[rows + 1] - start).astype(np.int64)
    indptr = np.zeros(len(rows) + 1, dtype=np.int64)
    np.cumsum(count, out=indptr[1:])
    at = (np.repeat(start - indptr[:-1], count) + np.arange(indptr[-1])).astype(itype, copy=False)
    return at, indptr


def row_block(A: sp.csr_matrix, r0: int, r1: int) -> sp.csr_matrix:
    """Rows r0:r1 of a CSR matrix as a view of its data and indices (scipy's slice copies them:
    Φ's interface rows at 91 125 3D poses, 1.5 s per build in all)."""
    lo, hi = int(A.indptr[r0]), int(A.indptr[r1])
    B = sp.csr_matrix((r1 - r0, A.shape[1]), dtype=A.dtype)
    # the arrays set directly: scipy's constructor copies sliced data
    B.data, B.indices, B.indptr = A.data[lo:hi], A.indices[lo:hi], (A.indptr[r0:r1 + 1] - lo).astype(A.indptr.dtype)
    B.has_sorted_indices = A.has_sorted_indices
    return B
