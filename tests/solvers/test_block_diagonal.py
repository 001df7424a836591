"""diag(R_i A R_iᵀ) by vertex blocks equals the dof-level product R A Rᵀ with couplings dropped."""

import numpy as np
import pytest
import scipy.sparse as sp

from gtsam_schwarz.dd import GraphStructure, decompose
from gtsam_schwarz.dd.index_sets import IndexSets
from gtsam_schwarz.linearization.native import NativeLinearizer
from gtsam_schwarz.problems import lawnmower, survey3d
from gtsam_schwarz.solvers.block_diagonal import block_diagonal


def _positions(H):
    H = sp.csr_matrix(H)
    H.sort_indices()
    return sp.csr_matrix((np.arange(1, H.nnz + 1, dtype=float), H.indices, H.indptr), shape=H.shape)


@pytest.mark.parametrize("problem, overlap", [(lambda: lawnmower(12, 12, sigma=0.01, seed=0), 0),
                                              (lambda: lawnmower(12, 12, sigma=0.01, seed=0), 1),
                                              (lambda: survey3d(3, 6, 6, sigma=0.01, seed=0), 0),
                                              (lambda: survey3d(3, 6, 6, sigma=0.01, seed=0), 2)])
def test_vertex_block_extraction_equals_the_dof_product(problem, overlap):
    prob = problem()
    lin = NativeLinearizer.from_arrays(**prob.arrays)
    H = _positions(lin.linearize(lin.initial_state()).H)  # entries = their own positions: nothing cancels
    dec = decompose(GraphStructure.from_matrix(H, lin.offsets), 6, "metis", overlap)
    sets = dec.index_sets(True)
    assert sets.vertices is not None
    by_vertices = block_diagonal(H, sets)
    by_dofs = block_diagonal(H, IndexSets(indices=sets.indices, ptr=sets.ptr, n=sets.n))
    by_dofs.sort_indices()
    assert by_vertices.has_sorted_indices
    for a in ("indptr", "indices", "data"):
        assert np.array_equal(getattr(by_vertices, a), getattr(by_dofs, a))


def test_a_matrix_without_whole_blocks_takes_the_dof_product():
    prob = lawnmower(6, 6, sigma=0.01, seed=0)
    lin = NativeLinearizer.from_arrays(**prob.arrays)
    H = _positions(lin.linearize(lin.initial_state()).H).tolil()
    H[0, 1] = 0.0  # one entry of a block missing from the pattern
    H = _positions(sp.csr_matrix(H))
    H.eliminate_zeros()
    dec = decompose(GraphStructure.from_matrix(H, lin.offsets), 4, "metis", 1)
    sets = dec.index_sets(True)
    B = block_diagonal(H, sets)
    ref = block_diagonal(H, IndexSets(indices=sets.indices, ptr=sets.ptr, n=sets.n))
    assert B.nnz == ref.nnz and abs(B - ref).max() == 0
