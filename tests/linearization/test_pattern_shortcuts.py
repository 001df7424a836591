"""Shortcuts on H's fixed block pattern give what the general code gives: the vertex pattern read
with a stride, the cost surrogate written from it directly, the gauge test's column sums."""

import numpy as np
import scipy.sparse as sp

import gtsam_schwarz as gs
from gtsam_schwarz.linearization.native import NativeLinearizer
from gtsam_schwarz.nonlinear.gauge import free_components
from gtsam_schwarz.solvers import cost


def _general_vertex_pattern(A, offsets):
    """Reference: every stored entry mapped to its (vertex, vertex) pair."""
    offsets = np.asarray(offsets)
    owner = np.repeat(np.arange(len(offsets) - 1), np.diff(offsets))
    C = sp.coo_matrix(A)
    B = sp.csr_matrix((np.ones(C.nnz), (owner[C.row], owner[C.col])), shape=(len(offsets) - 1,) * 2)
    B.data[:] = 1.0
    B.sort_indices()
    return B


def _general_surrogate(B):
    nv = B.shape[0]
    B = B + B.T
    B.data[:] = -1.0
    deg = -np.asarray(B.sum(axis=1)).ravel()
    return (B + sp.diags(deg + 1.0 + 1e-3 * np.arange(nv) / max(nv, 1))).tocsc()


def _system(loops=4, points=8):
    p = gs.square_loops(loops=loops, points_per_side=points, sigma=0.01, seed=0)
    lin = NativeLinearizer.from_arrays(**p.arrays)
    state = lin.state(p.initial)
    return lin, state, lin.linearize(state)


def _same(A, B):
    A, B = sp.csr_matrix(A), sp.csr_matrix(B)
    A.sort_indices()
    B.sort_indices()
    return (np.array_equal(A.indptr, B.indptr) and np.array_equal(A.indices, B.indices)
            and np.array_equal(A.data, B.data))


def test_vertex_pattern_strided_equals_general():
    lin, _, system = _system()
    B = cost.vertex_pattern(system.H, lin.offsets)
    assert _same(B, _general_vertex_pattern(system.H, lin.offsets))


def test_vertex_pattern_mixed_block_sizes_and_unsorted():
    rng = np.random.default_rng(1)
    dims = np.array([3, 2, 3, 1, 3, 2])
    offsets = np.concatenate([[0], np.cumsum(dims)])
    nv = len(dims)
    V = sp.random(nv, nv, density=0.4, random_state=2)
    V = ((V + V.T + sp.eye(nv)) != 0).astype(float)
    A = sp.csr_matrix(sp.kron(V, np.ones((3, 3))))   # blocks cut to the real sizes below
    keep = np.concatenate([np.arange(o, o + d) for o, d in zip(np.arange(nv) * 3, dims)])
    A = sp.csr_matrix(A[keep][:, keep])
    A.data = rng.normal(size=A.nnz)
    ref = _general_vertex_pattern(A, offsets)
    assert _same(cost.vertex_pattern(A, offsets), ref)
    U = A.copy()
    U.indices = U.indices.copy()
    for r in range(U.shape[0]):   # reverse each row: unsorted indices
        lo, hi = U.indptr[r], U.indptr[r + 1]
        U.indices[lo:hi] = U.indices[lo:hi][::-1].copy()
        U.data[lo:hi] = U.data[lo:hi][::-1].copy()
    U.has_sorted_indices = False
    assert _same(cost.vertex_pattern(U, offsets), ref)
    # uniform blocks but unsorted: the general path
    W = sp.csr_matrix(sp.kron(V, np.ones((3, 3))))
    W.indices = np.ascontiguousarray(W.indices)
    for r in range(W.shape[0]):
        lo, hi = W.indptr[r], W.indptr[r + 1]
        W.indices[lo:hi] = W.indices[lo:hi][::-1].copy()
    W.has_sorted_indices = False
    assert _same(cost.vertex_pattern(W, np.arange(nv + 1) * 3), _general_vertex_pattern(W, np.arange(nv + 1) * 3))


def test_surrogate_direct_equals_sum():
    lin, _, system = _system()
    B = cost.vertex_pattern(system.H, lin.offsets)
    assert _same(cost._surrogate(B), _general_surrogate(B))
    # unsymmetric pattern and a missing diagonal entry: the general sum
    C = sp.csr_matrix(np.array([[1, 1, 0], [0, 0, 1], [0, 0, 1.0]]))
    assert _same(cost._surrogate(C), _general_surrogate(C))


def test_cholesky_cost_of_native_system_unchanged():
    lin, _, system = _system()
    B = _general_vertex_pattern(system.H, lin.offsets)
    S = _general_surrogate(B)
    counts = cost._factor_column_counts(S)
    c = cost.cholesky_cost(system.H, lin.offsets)
    assert c.nnz_L == 9.0 * counts.sum() - len(counts) * 3.0
    assert c.flops == 27.0 * float(np.sum(counts.astype(float) ** 2))


def test_free_components_with_known_diagonal():
    """No prior: one free component; two copies of the graph side by side: two."""
    p = gs.square_loops(loops=4, points_per_side=8, sigma=0.01, seed=0)
    a = p.arrays
    n = len(a["keys"])
    for copies in (1, 2):
        keys = np.concatenate([a["keys"] + c * 10 * n for c in range(copies)])
        edges = np.concatenate([a["edges"] + c * 10 * n for c in range(copies)])
        lin = NativeLinearizer.from_arrays(
            a["kind"], keys, np.concatenate([a["poses"]] * copies), edges,
            np.concatenate([a["measurements"]] * copies), information=np.concatenate([a["information"]] * copies))
        state = lin.initial_state()
        system = lin.linearize(state)
        geo = lin.geometry(state)
        ref = free_components(system.H, lin.offsets, geo)
        got = free_components(system.H, lin.offsets, geo, system.diagonal)
        assert np.array_equal(ref, got) and len(got) == copies
        assert np.array_equal(got, np.arange(copies) * n)


def test_diagonal_positions_read_the_diagonal():
    """LM's damping reads H's diagonal at the linearizer's positions: the same numbers as H.diagonal()."""
    from gtsam_schwarz.linearization.gtsam_export import GtsamLinearizer

    p = gs.square_loops(loops=4, points_per_side=8, sigma=0.01, seed=0)
    for lin in (NativeLinearizer(p.graph, p.initial), GtsamLinearizer(p.graph, p.initial)):
        system = lin.linearize(lin.state(p.initial))
        assert system.diagonal is not None
        assert np.array_equal(system.H.data[system.diagonal], system.H.diagonal())


def test_block_keys_dropped_after_the_plan_are_made_again_when_asked():
    """The pattern's block search keys go once the gather plan is made (8 bytes per block less beside
    every later phase); a later lookup makes them again and finds the same blocks. The block arrays
    are 32-bit where the vertices allow."""
    p = gs.square_loops(loops=4, points_per_side=8, sigma=0.01, seed=0)
    lin = NativeLinearizer(p.graph, p.initial)
    pat = lin.pattern
    assert pat._block_keys is None
    assert pat.block_rows.dtype == np.int32 and pat.block_cols.dtype == np.int32
    H = lin.linearize(lin.state(p.initial)).H.tocoo()
    off = H.row // 3 != H.col // 3
    rows, cols = H.row[off] // 3, H.col[off] // 3
    k = pat.block_index(rows, cols)
    assert np.array_equal(pat.block_rows[k], rows) and np.array_equal(pat.block_cols[k], cols)
    assert np.array_equal(pat.block_keys, np.sort(pat.block_keys))
    try:
        pat.block_index(np.array([0]), np.array([len(lin.keys) - 1]))   # not coupled in this graph
        coupled = True
    except KeyError:
        coupled = False
    assert coupled == bool(np.any((rows == 0) & (cols == len(lin.keys) - 1)))


def test_construction_faults_in_fresh_heap_ahead_only_for_large_graphs(monkeypatch):
    """The construction asks for CONSTRUCTION_BYTES_PER_ENTRY per (estimated) entry of H on a helper
    thread where that is at least CONSTRUCTION_POPULATE_FROM; small graphs ask for nothing."""
    import gtsam_schwarz.linearization.native as native

    asked = []
    monkeypatch.setattr(native, "populate_ahead", lambda nbytes: asked.append(nbytes))

    def chain(n):
        keys = np.arange(n)
        poses = np.column_stack([keys.astype(float), np.zeros(n), np.zeros(n)])
        edges = np.column_stack([keys[:-1], keys[1:]])
        z = np.tile([1.0, 0.0, 0.0], (n - 1, 1))
        return native.NativeLinearizer.from_arrays("pose2", keys, poses, edges, z, information=np.eye(3))

    lin = chain(1000)
    assert asked == []
    n = 140_000
    lin = chain(n)
    expected = native.CONSTRUCTION_BYTES_PER_ENTRY * 9 * (n + 2 * (n - 1))
    assert asked == [expected] and expected >= native.CONSTRUCTION_POPULATE_FROM
    assert lin.pattern.nnz == 9 * (n + 2 * (n - 1))   # the estimate is exact for a graph without repeated pairs
