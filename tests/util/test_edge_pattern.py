"""The graph pattern behind the chordal start's solver choice: the float triplet build it replaces,
repeated edges once, and the same analysis."""

import numpy as np
import scipy.sparse as sp

from gtsam_schwarz.linearization.native import NativeLinearizer
from gtsam_schwarz.problems import lawnmower
from gtsam_schwarz.solvers import cost, pattern_cholesky_cost
from gtsam_schwarz.util.sparse import edge_pattern


def _reference(n, i, j):
    nodes = np.arange(n)
    B = sp.csr_matrix((np.ones(2 * len(i) + n), (np.r_[i, j, nodes], np.r_[j, i, nodes])), shape=(n, n))
    B.sum_duplicates()
    return B


def test_edge_pattern_is_the_symmetric_pattern_with_the_diagonal_and_repeated_edges_once():
    rng = np.random.default_rng(3)
    n = 200
    i, j = rng.integers(0, n, 900), rng.integers(0, n, 900)
    keep = i != j
    i, j = np.r_[i[keep], i[keep][:50]], np.r_[j[keep], j[keep][:50]]   # 50 edges twice
    B, R = edge_pattern(n, i, j), _reference(n, i, j)
    assert B.dtype == bool and B.indices.dtype == np.int32 and B.has_sorted_indices
    assert np.array_equal(B.indptr, R.indptr) and np.array_equal(B.indices, R.indices)
    assert B.data.all()   # no entry summed away
    assert (B != B.T).nnz == 0 and np.all(B.diagonal())


def test_the_chordal_start_s_choice_analyses_the_same_pattern():
    lin = NativeLinearizer.from_arrays(**lawnmower(60, 60).arrays)
    n, d, i, j = lin.pose_edges()
    b = lin.pose_graph()["between"]
    assert d == 2 and n == lin.pose_graph()["n"]
    assert np.array_equal(i, b["i"]) and np.array_equal(j, b["j"])
    cost._LAST_COUNTS.clear()
    got = pattern_cholesky_cost(edge_pattern(n, i, j), np.ones(n))
    cost._LAST_COUNTS.clear()
    want = pattern_cholesky_cost(_reference(n, i, j), np.ones(n))
    assert got == want
