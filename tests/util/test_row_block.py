"""Row blocks of a CSR matrix as views."""

import numpy as np
import scipy.sparse as sp

from gtsam_schwarz.util.sparse import row_block


def test_row_block_equals_scipy_slice_and_shares_storage():
    A = sp.random(300, 200, density=0.05, random_state=3, format="csr")
    A.sort_indices()
    for r0, r1 in [(0, 300), (17, 121), (299, 300), (50, 50)]:
        B, ref = row_block(A, r0, r1), A[r0:r1]
        assert B.shape == ref.shape and (B != ref).nnz == 0
        assert np.array_equal(B.indptr, ref.indptr) and np.array_equal(B.indices, ref.indices)
        if B.nnz:
            assert np.shares_memory(B.data, A.data)
