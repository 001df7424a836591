"""Sparse matrix products on the local threads: a CSR matrix cut into row blocks of about equal
entries, each multiplied by scipy (whose product releases the GIL) on its own thread.

CG's product with H is the one step of an iteration that ran on one core while the other waited
(the preconditioner's local solves and coarse correction already use both): H of a 1M-pose 2D
lawnmower (45M entries) 36-43 ms per product on one thread."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from ..util.gathered import GatheredCSR
from ..util.sparse import row_block
from ..util.threads import WORKERS, local_threads, on_local_thread

THREADED_FROM = 2_000_000  # entries; below, one thread (the hand-off costs ~0.1 ms a product)


class RowBlockMatrix:
    """A CSR matrix applied block of rows by block of rows, the blocks side by side on the local
    threads (views of A's arrays: nothing copied but each block's row pointers)."""

    def __init__(self, A: sp.csr_matrix, parts: int = WORKERS):
        self.A = A
        self.shape, self.dtype, self.nnz = A.shape, A.dtype, A.nnz
        n = A.shape[0]
        cuts = np.searchsorted(A.indptr, np.arange(1, parts) * (A.nnz / parts)).tolist()
        bounds = sorted({0, n, *[min(max(int(c), 0), n) for c in cuts]})
        self.blocks = [(r0, r1, row_block(A, r0, r1)) for r0, r1 in zip(bounds[:-1], bounds[1:])]

    def __matmul__(self, X):
        X = np.asarray(X)
        out = np.empty((self.shape[0],) + X.shape[1:], dtype=np.result_type(self.dtype, X.dtype))

        def product(r0, r1, B):
            out[r0:r1] = B @ X

        pool = local_threads()
        first, *rest = self.blocks
        pending = [pool.submit(product, *block) for block in rest]
        try:
            product(*first)
        finally:
            for f in pending:
                f.result()
        return out

    def matvec(self, x):
        return self @ x


def threaded(A):
    """A as a :class:`RowBlockMatrix` where that pays (a CSR matrix of at least ``THREADED_FROM``
    entries, used outside the local threads: a job there waiting on its own pool could wait
    forever), else A itself."""
    if (isinstance(A, (RowBlockMatrix, GatheredCSR)) or not sp.isspmatrix_csr(A) or A.nnz < THREADED_FROM
            or on_local_thread()):   # (a gathered matrix's product splits its work itself)
        return A
    return RowBlockMatrix(A)
