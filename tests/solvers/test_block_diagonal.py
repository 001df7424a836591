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


def test_mixed_block_sizes_and_the_positions_gather():
    """Vertices of 3 and 2 dofs (poses and 2D landmarks) take the general expansion, one block size the
    positions as a BSR pattern; both equal the dof-level product, and the gather of a one-size H by
    those positions equals the extraction itself."""
    from gtsam_schwarz.dd.index_sets import vertex_dofs
    from gtsam_schwarz.solvers.block_diagonal import _BlockDiagonalGather, block_diagonal_positions

    rng = np.random.default_rng(4)
    nv = 40
    edges = np.r_[np.column_stack([np.arange(nv - 1), np.arange(1, nv)]), rng.integers(0, nv, (30, 2))]
    edges = edges[edges[:, 0] != edges[:, 1]]
    V = sp.csr_matrix((np.ones(2 * len(edges) + nv), (np.r_[edges[:, 0], edges[:, 1], np.arange(nv)],
                                                       np.r_[edges[:, 1], edges[:, 0], np.arange(nv)])), shape=(nv, nv))
    groups = [np.arange(0, 15), np.arange(10, 28), np.arange(25, 40)]   # overlapping vertex sets
    for dims in (rng.choice([2, 3], nv), np.full(nv, 3)):
        offsets = np.r_[0, np.cumsum(dims)]
        owner = np.repeat(np.arange(nv), dims)
        n = int(offsets[-1])
        mask = V[owner][:, owner]
        H = _positions(sp.csr_matrix((np.ones(mask.nnz), mask.indices, mask.indptr), shape=(n, n)))
        vertices = np.concatenate(groups)
        vertex_ptr = np.r_[0, np.cumsum([len(g) for g in groups])]
        indices = vertex_dofs(vertices, offsets)
        ptr = np.r_[0, np.cumsum([int(dims[g].sum()) for g in groups])]
        sets = IndexSets(indices=indices, ptr=ptr, n=n, vertices=vertices, vertex_ptr=vertex_ptr, offsets=offsets)
        by_vertices = block_diagonal(H, sets)
        by_dofs = block_diagonal(H, IndexSets(indices=indices, ptr=ptr, n=n))
        by_dofs.sort_indices()
        for a in ("indptr", "indices", "data"):
            assert np.array_equal(getattr(by_vertices, a), getattr(by_dofs, a))
        P = block_diagonal_positions(H, sets)
        assert (P is None) == bool(np.any(dims != 3))
    gathered = _BlockDiagonalGather(sets)(H)
    assert np.array_equal(gathered.data, P.data + 1) and np.array_equal(gathered.indices, by_dofs.indices)
    assert np.array_equal(gathered.data, by_dofs.data)


def test_chunks_share_the_vertex_level_while_finding_positions(monkeypatch):
    """A solver of several chunks finds every chunk's block diagonal from one vertex-level pattern of A
    (kept only during its update): each chunk's matrix equals the extraction of its subsets, and
    the solver applies the inverse of the whole block diagonal."""
    import importlib

    from gtsam_schwarz.solvers.block_diagonal import BlockDiagonalSolver

    gather = importlib.import_module("gtsam_schwarz.solvers.gather")

    prob = lawnmower(12, 12, sigma=0.01, seed=0)
    lin = NativeLinearizer.from_arrays(**prob.arrays)
    H = sp.csr_matrix(lin.linearize(lin.initial_state()).H)
    H.sort_indices()
    dec = decompose(GraphStructure.from_matrix(H, lin.offsets), 8, "metis", 1)
    sets = dec.index_sets(True)
    monkeypatch.setattr(BlockDiagonalSolver, "CHUNK_ENTRIES", H.nnz // 4)
    calls = []
    pattern = gather.vertex_pattern
    monkeypatch.setattr(gather, "vertex_pattern", lambda *a: (calls.append(1), pattern(*a))[1])
    solver = BlockDiagonalSolver(sets, H)
    assert len(solver._chunks) >= 3 and len(calls) == 1   # one vertex pattern for every chunk
    assert gather._VERTEX_LEVEL == {"users": 0, "entry": None}   # dropped after the update
    x = np.random.default_rng(1).normal(size=H.shape[0])
    B = block_diagonal(H, sets).toarray()
    xl = x[sets.indices]
    np.testing.assert_allclose(solver.matvec(x), np.bincount(sets.indices, np.linalg.solve(B, xl), minlength=H.shape[0]),
                               rtol=1e-8, atol=1e-10)
    for lo, hi, gather, _ in solver._chunks:
        part = block_diagonal(H, gather.sets)
        assert np.array_equal(gather(H).toarray(), part.toarray()) and part.shape[0] == hi - lo


@pytest.mark.parametrize("parts", [1.0, 2.5, 4.0, 7.0])
def test_chunks_are_equal_shares_a_multiple_of_the_local_threads(monkeypatch, parts):
    """The one-level chunks split A's rows' entries into about equal shares, as many as a multiple of
    the local threads and at least total / CHUNK_ENTRIES (each thread factorizes and solves as much
    as the other); consecutive, covering every subdomain once."""
    from gtsam_schwarz.solvers.block_diagonal import BlockDiagonalSolver
    from gtsam_schwarz.util.threads import WORKERS

    prob = lawnmower(24, 24, sigma=0.01, seed=0)
    lin = NativeLinearizer.from_arrays(**prob.arrays)
    H = sp.csr_matrix(lin.linearize(lin.initial_state()).H)
    H.sort_indices()
    sets = decompose(GraphStructure.from_matrix(H, lin.offsets), 48, "metis", 1).index_sets(True)
    row_nnz = np.diff(H.indptr)
    total = row_nnz[sets.indices].sum()
    monkeypatch.setattr(BlockDiagonalSolver, "CHUNK_ENTRIES", int(total / parts))
    chunks = BlockDiagonalSolver(sets)._plan_chunks(H)
    want = int(np.ceil(total / int(total / parts)))
    assert len(chunks) == (1 if want == 1 else -(-want // WORKERS) * WORKERS)
    assert [c[0] for c in chunks[1:]] == [c[1] for c in chunks[:-1]] and chunks[0][0] == 0
    assert chunks[-1][1] == len(sets.indices)
    shares = np.array([row_nnz[sets.indices[lo:hi]].sum() for lo, hi, _, _ in chunks])
    largest_set = np.bincount(sets.block_of_entry(), weights=row_nnz[sets.indices]).max()
    assert shares.max() - shares.min() <= 2 * largest_set   # equal to a subdomain or two


def test_threads_sharing_the_vertex_level_form_it_once(monkeypatch):
    """Two threads inside their own sharing_vertex_level() asking for the same A's vertex level (the
    one-level chunks' positions on the side thread beside the extension) get one vertex pattern,
    formed once, equal to the level formed without sharing; it is dropped when both have left."""
    import importlib
    import threading

    gather = importlib.import_module("gtsam_schwarz.solvers.gather")
    prob = lawnmower(10, 10, sigma=0.01, seed=0)
    lin = NativeLinearizer.from_arrays(**prob.arrays)
    H = sp.csr_matrix(lin.linearize(lin.initial_state()).H)
    H.sort_indices()
    alone = gather.vertex_level(H, lin.offsets)
    calls, results, inside = [], [], threading.Barrier(2)
    pattern = gather.vertex_pattern
    monkeypatch.setattr(gather, "vertex_pattern", lambda *a: (calls.append(1), pattern(*a))[1])

    def user():
        with gather.sharing_vertex_level():
            inside.wait()   # both are sharing before either asks
            results.append(gather.vertex_level(H, lin.offsets))
            inside.wait()

    threads = [threading.Thread(target=user) for _ in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(calls) == 1 and len(results) == 2 and results[0] is results[1]
    assert np.array_equal(results[0][0].toarray(), alone[0].toarray()) and np.array_equal(results[0][1], alone[1])
    assert gather._VERTEX_LEVEL == {"users": 0, "entry": None}


@pytest.mark.parametrize("problem, overlap", [(lambda: lawnmower(16, 16, sigma=0.01, seed=1), 0),
                                              (lambda: survey3d(3, 6, 6, sigma=0.01, seed=0), 1)])
def test_fill_reducing_vertex_order_gives_the_same_operator_and_no_more_fill(problem, overlap):
    """Subdomain blocks factorized in the vertex order of CHOLMOD's analysis of their vertex pattern
    (no ordering of their own) apply the same Σ R_iᵀ A_i⁻¹ R_i, their sets hold the same vertices, and
    the factors have no more entries than CHOLMOD's dof-level ordering gives."""
    from gtsam_schwarz.solvers import BlockDiagonalSolver, SPARSE_BACKEND

    prob = problem()
    lin = NativeLinearizer.from_arrays(**prob.arrays)
    H = sp.csr_matrix(lin.linearize(lin.initial_state()).H) + sp.identity(lin.offsets[-1]) * 1e-3
    H = sp.csr_matrix(H)
    dec = decompose(GraphStructure.from_matrix(H, lin.offsets), 5, "metis", overlap)
    sets = dec.index_sets(True)
    ordered = BlockDiagonalSolver(sets)
    reordered = ordered.order_vertices(H)
    ordered.update(H)
    plain = BlockDiagonalSolver(IndexSets(indices=sets.indices, ptr=sets.ptr, n=sets.n), H)  # dof sets: not ordered
    assert plain.ordered is False
    x = np.random.default_rng(0).standard_normal(H.shape[0])
    assert np.allclose(ordered.matvec(x), plain.matvec(x), rtol=1e-10, atol=1e-12)
    if SPARSE_BACKEND != "cholmod":
        return
    assert reordered and ordered.ordered
    new = ordered.sets
    assert np.array_equal(new.ptr, sets.ptr) and np.array_equal(new.vertex_ptr, sets.vertex_ptr)
    assert not np.array_equal(new.vertices, sets.vertices)  # an order of its own …
    for i in range(sets.count):  # … of the same vertices, each set's dofs whole vertices in that order
        a, b = slice(sets.vertex_ptr[i], sets.vertex_ptr[i + 1]), slice(sets.ptr[i], sets.ptr[i + 1])
        assert np.array_equal(np.sort(new.vertices[a]), np.sort(sets.vertices[a]))
        assert np.array_equal(np.sort(new.indices[b]), np.sort(sets.indices[b]))
    nnz = lambda s: sum(int(c[3].column_counts().sum()) for c in s._chunks)  # noqa: E731
    assert nnz(ordered) <= 1.02 * nnz(plain)


def test_chunks_on_the_local_threads_give_the_numbers_of_one_thread():
    """Chunks of subdomains factorized and solved on the local threads (CHOLMOD without the GIL): the
    same operator, bit for bit, as one chunk after the other; a release and a refactorization too."""
    from gtsam_schwarz.solvers import BlockDiagonalSolver, cholmod_native

    prob = lawnmower(16, 16, sigma=0.01, seed=0)
    lin = NativeLinearizer.from_arrays(**prob.arrays)
    H = sp.csr_matrix(lin.linearize(lin.initial_state()).H + sp.identity(lin.offsets[-1]) * 1e-3)
    sets = decompose(GraphStructure.from_matrix(H, lin.offsets), 8, "metis", 1).index_sets(True)
    x = np.random.default_rng(0).standard_normal(H.shape[0])
    solvers = []
    for threaded in (True, False):
        s = BlockDiagonalSolver(sets)
        s.CHUNK_ENTRIES, s.threaded = 2000, threaded
        s.update(H)
        solvers.append(s)
    threaded, serial = solvers
    assert len(threaded._chunks) > 2
    assert all(isinstance(c[3], cholmod_native.SimplicialCholesky) for c in threaded._chunks) == cholmod_native.available()
    assert np.array_equal(threaded.matvec(x), serial.matvec(x))
    threaded.release()
    threaded.update(H * 2.0)
    assert np.allclose(threaded.matvec(x), serial.matvec(x) / 2.0, rtol=1e-12, atol=0)


def test_forgotten_positions_are_found_again_and_the_analyses_kept():
    """With ``keep_positions`` False (each chunk's gather positions dropped once gathered) an update for new numbers in the same
    pattern finds the positions again, keeps every chunk's factor object (its analysis: numbers only)
    and applies the operator of a solver that never forgot; a matrix of another pattern is analysed anew."""
    from gtsam_schwarz.solvers import BlockDiagonalSolver

    prob = lawnmower(16, 16, sigma=0.01, seed=1)
    lin = NativeLinearizer.from_arrays(**prob.arrays)
    H = sp.csr_matrix(lin.linearize(lin.initial_state()).H + sp.identity(lin.offsets[-1]) * 1e-3)
    sets = decompose(GraphStructure.from_matrix(H, lin.offsets), 8, "metis", 1).index_sets(True)
    x = np.random.default_rng(2).standard_normal(H.shape[0])
    forgetful, kept = BlockDiagonalSolver(sets), BlockDiagonalSolver(sets)
    forgetful.keep_positions = False
    for s in (forgetful, kept):
        s.CHUNK_ENTRIES = 2000
        s.update(H)
    assert len(forgetful._chunks) > 2
    factors = [c[3] for c in forgetful._chunks]
    assert all(c[2].pattern is None and c[2].src is None for c in forgetful._chunks)
    H2 = H.copy()
    H2.data = H2.data * (1.0 + 0.1 * np.random.default_rng(3).random(H2.nnz))
    H2 = sp.csr_matrix(0.5 * (H2 + H2.T))   # symmetric again, the same pattern
    assert np.array_equal(H2.indices, H.indices) and np.array_equal(H2.indptr, H.indptr)
    forgetful.update(H2)
    kept.update(H2)
    assert [c[3] for c in forgetful._chunks] == factors   # refactorized, not analysed again
    assert all(c[2].src is None for c in forgetful._chunks) and all(c[2].src is not None for c in kept._chunks)
    assert np.allclose(forgetful.matvec(x), kept.matvec(x), rtol=1e-12, atol=1e-14)
    n = H.shape[0]
    extra = sp.coo_matrix((np.full(3, 1e-6), ([0, 1, 2], [n - 1, n - 2, n - 3])), shape=H.shape)
    H3 = sp.csr_matrix(H + extra + extra.T)   # more entries than H: another pattern
    assert H3.nnz > H.nnz
    forgetful.update(H3)
    assert all(c[3] is not f for c, f in zip(forgetful._chunks, factors))   # analysed anew
    assert np.allclose(forgetful.matvec(x), BlockDiagonalSolver(sets, H3).matvec(x), rtol=1e-10, atol=1e-12)
