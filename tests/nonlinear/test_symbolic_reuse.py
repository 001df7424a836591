"""Symbolic reuse across nonlinear iterations: every cached shortcut equals the fresh computation."""

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from gtsam_schwarz import (GraphStructure, KeyMap, SchwarzOptimizer, SchwarzParams, export_linear_system,
                           find_interface, make_preconditioner, square_loops)
from gtsam_schwarz.coarse import HarmonicExtension, gdsw_coarse_space
from gtsam_schwarz.dd import auto_partition, decompose, interface_count, segment_partition
from gtsam_schwarz.io import load_graph
from gtsam_schwarz.linearization import HessianPattern, LinearSystem
from gtsam_schwarz.solvers import (SPARSE_BACKEND, BlockDiagonalSolver, Gather, SingularLocalMatrixError,
                                         SparseCholesky, Submatrix, block_diagonal)

from conftest import dataset


def _system(prob, values):
    km = KeyMap.from_graph(prob.graph, prob.initial)
    return km, export_linear_system(prob.graph.linearize(values), km)


@pytest.fixture(scope="module")
def two_points():
    """The model problem linearized at two different points (same graph, so same block pattern)."""
    prob = square_loops(6, 4, sigma=0.05, seed=3)
    km, first = _system(prob, prob.initial)
    opt = SchwarzOptimizer(prob.graph, prob.initial, SchwarzParams(preconditioner="gdsw", method="gn", max_iterations=1))
    opt.optimize()
    _, second = _system(prob, opt.values())
    return km, first.H, second.H


def test_hessian_pattern_keeps_one_pattern_and_the_numbers(two_points):
    km, H1, H2 = two_points
    pattern = HessianPattern(H1, km.offsets)
    F1, F2 = pattern.fit(H1), pattern.fit(H2)
    assert np.array_equal(F1.indices, F2.indices) and np.array_equal(F1.indptr, F2.indptr)
    assert abs(F1 - H1).max() == 0 and abs(F2 - H2).max() == 0
    assert pattern.fit(H2) is not None  # cached positions, same answer
    assert abs(pattern.fit(H2) - H2).max() == 0
    before = F2.data.copy()
    with LinearSystem(F2, np.zeros(F2.shape[0]), diagonal=pattern.diagonal).damped(np.full(F2.shape[0], 0.5)) as D:
        assert np.array_equal(D.indices, F2.indices) and np.shares_memory(D.data, F2.data)  # in place: no copy of H
        assert abs(D - (H2 + 0.5 * sp.eye(H2.shape[0]))).max() < 1e-12
    assert np.array_equal(F2.data, before)  # restored exactly
    # an entry outside every coupled block does not fit
    n = H1.shape[0]
    outside = sp.csr_matrix(([1.0, 1.0], ([0, n - 1], [n - 1, 0])), shape=(n, n))
    assert pattern.fit((H1 + outside).tocsr()) is None


def test_gather_follows_new_numbers_and_new_patterns(two_points):
    km, H1, H2 = two_points
    rows = np.arange(0, H1.shape[0], 2)
    g = Gather(lambda M: M[rows][:, rows])
    for H in (H1, H2, H1):
        assert abs(g(H) - sp.csr_matrix(H)[rows][:, rows]).max() == 0


def test_submatrix_gather_equals_scipy_indexing(two_points):
    """Positions from row ranges and a column map: the same entries, pattern and order as scipy's
    A[rows][:, cols], also with empty rows (the last one included)."""
    km, H1, H2 = two_points
    n = H1.shape[0]
    A = sp.csr_matrix(H1).tolil()
    A[n - 1, :] = 0.0
    A[3, :] = 0.0
    A = sp.csr_matrix(A)
    A.eliminate_zeros()
    rng = np.random.default_rng(0)
    rows = np.unique(np.r_[3, rng.choice(n, n // 3, replace=False), n - 1])
    cols = np.sort(rng.choice(n, n // 2, replace=False))
    g = Submatrix(rows, cols, n)
    for M in (A, H2, A):
        M = sp.csr_matrix(M)
        M.sort_indices()
        B, ref = g(M), M[rows][:, cols]
        ref.sort_indices()
        assert np.array_equal(B.indptr, ref.indptr) and np.array_equal(B.indices, ref.indices)
        assert np.array_equal(B.data, ref.data)
    # two submatrices of the same rows sharing the rows' entries (A_II and A_IΓ): the second takes
    # the first one's, and each still equals scipy's indexing, for every new pattern
    shared: dict = {}
    other = np.setdiff1d(np.arange(n), cols)
    g1, g2 = Submatrix(rows, cols, n, shared), Submatrix(rows, other, n, shared)
    for M in (A, H2, A):
        M = sp.csr_matrix(M)
        M.sort_indices()
        B1, B2 = g1(M), g2(M)
        for B, c in ((B1, cols), (B2, other)):
            ref = M[rows][:, c]
            ref.sort_indices()
            assert np.array_equal(B.indptr, ref.indptr) and np.array_equal(B.indices, ref.indices)
            assert np.array_equal(B.data, ref.data)
    assert not shared   # taken by the second
    # rows and columns in an order of their own (the interiors in a fill-reducing order): each row's
    # entries still come sorted, as the flag B carries says (a block factor reads it)
    perm_rows, perm_cols = rng.permutation(rows), rng.permutation(cols)
    M = sp.csr_matrix(H2)
    M.sort_indices()
    B, ref = Submatrix(perm_rows, perm_cols, n)(M), sp.csr_matrix(M[perm_rows][:, perm_cols])
    ref.sort_indices()
    assert B.has_sorted_indices and all(np.all(np.diff(B.indices[B.indptr[r]:B.indptr[r + 1]]) > 0) for r in range(B.shape[0]))
    assert np.array_equal(B.indptr, ref.indptr) and np.array_equal(B.indices, ref.indices)
    assert np.array_equal(B.data, ref.data)



def test_submatrix_of_whole_vertices_by_blocks():
    """Rows and columns of whole poses (offsets given) take their positions from the vertex-level
    submatrix expanded in blocks: the same entries, pattern and order as scipy's indexing; sets that
    split a pose fall back to the entry-level positions."""
    from gtsam_schwarz.linearization.native import NativeLinearizer
    from gtsam_schwarz.problems import lawnmower
    from gtsam_schwarz.solvers.gather import sharing_vertex_level, submatrix_positions

    lin = NativeLinearizer.from_arrays(**lawnmower(10, 10, sigma=0.01, seed=0).arrays)
    H1 = sp.csr_matrix(lin.linearize(lin.initial_state()).H)   # whole 3×3 blocks
    H1.sort_indices()
    n = H1.shape[0]
    d = 3
    offsets = np.arange(0, n + 1, d)
    rng = np.random.default_rng(2)
    rv = np.sort(rng.choice(n // d, n // d // 3, replace=False))
    cv = np.setdiff1d(np.arange(n // d), rv[::2])
    rows, cols = (rv[:, None] * d + np.arange(d)).ravel(), (cv[:, None] * d + np.arange(d)).ravel()
    for r, c, whole in ((rows, cols, True), (rows, cols[1:], False)):
        g = Submatrix(r, c, n, offsets=offsets)
        assert (g.vertex_sets is not None) == whole
        with sharing_vertex_level():
            B = g(H1)
            by_blocks = submatrix_positions(H1, *g.vertex_sets, offsets, d) if whole else None
        if whole:   # the block path answered (H is made of whole 3×3 blocks)
            assert by_blocks is not None and np.array_equal(by_blocks.indices, B.indices)
        ref = H1[r][:, c]
        ref.sort_indices()
        assert np.array_equal(B.indptr, ref.indptr) and np.array_equal(B.indices, ref.indices)
        assert np.array_equal(B.data, ref.data)


@pytest.mark.parametrize("backend", ["superlu"] + (["cholmod"] if SPARSE_BACKEND == "cholmod" else []))
def test_sparse_cholesky_refactor_matches_direct_solve(two_points, backend):
    _, H1, H2 = two_points
    f = SparseCholesky(H1, "H", backend=backend)
    b = np.arange(H1.shape[0], dtype=float)
    assert np.allclose(f.solve(b), spla.spsolve(H1.tocsc(), b), rtol=1e-8)
    f.refactor(H2)
    assert np.allclose(f.solve(b), spla.spsolve(H2.tocsc(), b), rtol=1e-8)
    singular = sp.csr_matrix(np.diag([1.0, 0.0, 1.0]))
    with pytest.raises(SingularLocalMatrixError):
        SparseCholesky(singular, "a singular matrix", backend=backend)


def test_block_diagonal_solver_update_equals_a_fresh_one(two_points):
    km, H1, H2 = two_points
    dec = decompose(GraphStructure.from_matrix(H1, km.offsets), 3, "segments", 1)
    sets = dec.index_sets()
    solver = BlockDiagonalSolver(sets, H1)
    solver.update(H2)
    fresh = BlockDiagonalSolver(sets, H2)
    x = np.linspace(-1, 1, H1.shape[0])
    assert np.allclose(solver.matvec(x), fresh.matvec(x), rtol=1e-10)
    B = block_diagonal(H2, sets).toarray()
    xl = x[sets.indices]
    assert np.allclose(solver.matvec(x), np.bincount(sets.indices, np.linalg.solve(B, xl), minlength=len(x)))
    chunked = BlockDiagonalSolver(sets)
    chunked.CHUNK_ENTRIES = 1  # one factor per subdomain: the same operator
    chunked.update(H1)
    chunked.update(H2)
    assert len(chunked._chunks) == sets.count and np.allclose(chunked.matvec(x), fresh.matvec(x), rtol=1e-10)


def test_harmonic_extension_reuse_and_interface_only_coarse_matrix(two_points):
    """A_0 from the interface rows equals Φᵀ A Φ; a reused plan equals a fresh extension; A Φ = 0 inside."""
    km, H1, H2 = two_points
    dec = decompose(GraphStructure.from_matrix(H1, km.offsets), 3, "segments", 1)
    iface = find_interface(dec)
    ext = HarmonicExtension(dec, iface)
    mask = km.translation_mask()
    gdsw_coarse_space(H1, dec, iface, "gdsw", None, True, mask, ext)  # builds the plan
    reused = gdsw_coarse_space(H2, dec, iface, "gdsw", None, True, mask, ext)
    fresh = gdsw_coarse_space(H2, dec, iface, "gdsw", None, True, mask)
    assert abs(reused.Phi - fresh.Phi).max() < 1e-12
    full = (reused.Phi.T @ H2 @ reused.Phi).toarray()
    assert np.allclose(reused.A0.toarray(), full, rtol=1e-9, atol=1e-9 * np.abs(full).max())
    APhi = (H2 @ reused.Phi).toarray()
    assert np.abs(APhi[ext.interior]).max() < 1e-8 * np.abs(APhi).max()


def test_two_level_update_equals_a_fresh_preconditioner(two_points):
    km, H1, H2 = two_points
    dec = decompose(GraphStructure.from_matrix(H1, km.offsets), 3, "segments", 1)
    M = make_preconditioner("gdsw", H1, dec, km.translation_mask())
    M.update(H2)
    fresh = make_preconditioner("gdsw", H2, dec, km.translation_mask())
    x = np.cos(np.arange(H1.shape[0]))
    assert np.allclose(M.matvec(x), fresh.matvec(x), rtol=1e-9, atol=1e-12)


@pytest.mark.datasets
def test_auto_partition_picks_the_smaller_interface():
    """Model problem: segments (2 interface poses per loop); M3500: METIS cuts far fewer poses."""
    prob = square_loops(8, 4)
    km, system = _system(prob, prob.initial)
    s = GraphStructure.from_matrix(system.H, km.offsets)
    assert np.array_equal(auto_partition(s, 8), segment_partition(s, 8))
    g = load_graph(dataset("input_M3500_g2o.g2o"))
    km = KeyMap.from_graph(g.graph, g.initial)
    s = GraphStructure.from_matrix(export_linear_system(g.graph.linearize(g.initial), km).H, km.offsets)
    seg, auto = segment_partition(s, 7), auto_partition(s, 7)
    assert interface_count(s, auto) < interface_count(s, seg) / 2


def test_two_level_coarse_update_keeps_the_subdomain_factors_of_the_earlier_matrix(two_points):
    """update_coarse(H2) = one-level part of H1 + coarse level of H2; refactor_subdomains(H2) then
    equals a fresh preconditioner for H2."""
    km, H1, H2 = two_points
    dec = decompose(GraphStructure.from_matrix(H1, km.offsets), 3, "segments", 1)
    M = make_preconditioner("gdsw", H1, dec, km.translation_mask())
    solver = M.one_level.solver
    M.update_coarse(H2)
    assert M.one_level.solver is solver and M.subdomains_factored
    old, fresh = (make_preconditioner("gdsw", H, dec, km.translation_mask()) for H in (H1, H2))
    x = np.cos(np.arange(H1.shape[0]))
    assert not np.allclose(old.one_level.apply(x), fresh.one_level.apply(x), rtol=1e-6)  # H2 is another matrix
    assert np.allclose(M.matvec(x), old.one_level.apply(x) + fresh.coarse.apply(x), rtol=1e-9, atol=1e-12)
    M.refactor_subdomains(H2)
    assert np.allclose(M.matvec(x), fresh.matvec(x), rtol=1e-9, atol=1e-12)
    M.release(factors=True)  # released factors are refactorized even by a coarse update
    assert not M.subdomains_factored
    M.update_coarse(H1)
    assert M.subdomains_factored and np.allclose(M.matvec(x), old.matvec(x), rtol=1e-9, atol=1e-12)


def test_lagged_preconditioner_is_rebuilt_when_the_poses_move_and_reused_for_rejected_steps():
    prob = square_loops(8, 8, sigma=0.05, seed=1)
    opt = SchwarzOptimizer(prob.graph, prob.initial, SchwarzParams(preconditioner="gdsw", method="lm", subdomains=4, lag_distance=1.0))
    opt.optimize()
    h = opt.history
    assert h[0]["preconditioner_rebuilt"]
    assert any(r["preconditioner_lagged"] for r in h), "the lag never applied"
    moved = 0.0
    for prev, cur in zip(h, h[1:]):
        moved = (0.0 if prev["preconditioner_rebuilt"] else moved) + (prev["step_max"] if prev["accepted"] else 0.0)
        if moved >= 1.0:
            assert not cur["preconditioner_lagged"]
        assert cur["cg_converged"] or cur["decrement_stop"]  # (the last solve may stop on its decrement)
    off = SchwarzOptimizer(prob.graph, prob.initial, SchwarzParams(method="lm", subdomains=4,
                                                                   lagged_preconditioner=False))
    off.optimize()
    assert all(r["preconditioner_rebuilt"] for r in off.history)
    assert abs(opt.error() - off.error()) <= 1e-6 * off.error()


def test_symbolic_reuse_gives_the_same_iterates_as_rebuilding_from_scratch():
    prob = square_loops(8, 8, sigma=0.05, seed=2)
    runs = []
    for reuse in (True, False):
        opt = SchwarzOptimizer(prob.graph, prob.initial, SchwarzParams(
            method="lm", subdomains=4, reuse_symbolic=reuse, lagged_preconditioner=False))
        opt.optimize()
        runs.append(opt)
    a, b = runs
    assert [h["cg_iterations"] for h in a.history] == [h["cg_iterations"] for h in b.history]
    assert abs(a.error() - b.error()) <= 1e-9 * b.error()


def _far_matrix_sequence(**params):
    """A PreconditionedCG that solved H once, and a matrix far from H (rescaled rows and columns)."""
    from gtsam_schwarz.linearization.native import NativeLinearizer
    from gtsam_schwarz.nonlinear.linear_solver import PreconditionedCG
    from gtsam_schwarz.nonlinear.params import LinearSolverParams

    prob = square_loops(8, 16, sigma=0.01, seed=0)
    lin = NativeLinearizer.from_arrays(**prob.arrays)
    state = lin.initial_state()
    system = lin.linearize(state)
    H, g = system.H.tocsr(), system.rhs
    solver = PreconditionedCG(LinearSolverParams(preconditioner="gdsw", subdomains=8, partition="segments",
                                                 lag_distance=10.0, lag_growth=3.0, **params),
                              lin.offsets, lin.translation_mask())
    geometry = lambda: lin.geometry(state)  # noqa: E731
    first = solver.solve(H, g, 1e-8, geometry)
    d = np.random.default_rng(0).uniform(1.0, 30.0, H.shape[0])
    H2 = H.copy()  # D^½ H D^½ in H's pattern: far from H, M is stale
    H2.data *= np.sqrt(d[np.repeat(np.arange(H.shape[0]), np.diff(H.indptr))] * d[H.indices])
    fresh = PreconditionedCG(solver.params, lin.offsets, lin.translation_mask()).solve(H2, g, 1e-8, geometry)
    return solver, first, H, H2, g, geometry, fresh


def test_a_matrix_far_from_the_build_gets_a_new_preconditioner_without_a_lagged_try():
    """H's entries changed far beyond lag_change: M is rebuilt before CG (the fresh solve's count)."""
    solver, first, H, H2, g, geometry, fresh = _far_matrix_sequence()
    assert solver._change(H) == 0.0 and 1.0 < solver._change(H2) < float("inf")
    assert solver._lag_cap() == int(3.0 * first.iterations) + 2  # the distance alone would lag
    second = solver.solve(H2, g, 1e-8, geometry)
    assert not second.lagged and second.rebuilt and second.converged
    assert second.iterations == fresh.iterations
    assert solver._change(H2) == 0.0  # the new build's reference


def test_a_lagged_solve_beyond_its_cap_is_rebuilt_and_continued():
    """With the change test off (lag_change inf) the stale M is tried: CG stops at the cap
    (lag_growth × the fresh count + 2), M is rebuilt and CG continues from its iterate."""
    solver, first, H, H2, g, geometry, fresh = _far_matrix_sequence(lag_change=float("inf"))
    cap = solver._lag_cap(H2)
    assert cap == int(3.0 * first.iterations) + 2
    second = solver.solve(H2, g, 1e-8, geometry)
    assert second.lagged and second.rebuilt and second.converged
    assert np.linalg.norm(H2 @ second.x - g) <= 1e-7 * np.linalg.norm(g)
    assert cap < second.iterations < cap + fresh.iterations + 10


def test_subdomain_factors_are_kept_only_while_the_matrix_is_close_and_refactorized_beyond_the_cap():
    """A rebuild for a far matrix refactorizes the subdomains (the fresh count). With the change
    test off they are kept: CG stops at the cap, the subdomains are refactorized for the coarse
    level already built, and CG continues to the tolerance."""
    solver, first, H, H2, g, geometry, fresh = _far_matrix_sequence(lag_change=0.0)
    second = solver.solve(H2, g, 1e-8, geometry)
    assert second.rebuilt and not second.lagged and not second.subdomains_kept
    assert second.iterations == fresh.iterations
    third = solver.solve(H2 * (1 + 1e-4), g, 1e-8, geometry)  # a close matrix: coarse level only
    assert third.rebuilt and third.subdomains_kept and third.converged
    solver, first, H, H2, g, geometry, fresh = _far_matrix_sequence(lag_change=0.0, subdomain_lag_change=float("inf"))
    cap = int(3.0 * first.iterations) + 2
    second = solver.solve(H2, g, 1e-8, geometry)
    assert second.rebuilt and not second.subdomains_kept and second.converged
    assert np.linalg.norm(H2 @ second.x - g) <= 1e-7 * np.linalg.norm(g)
    assert cap < second.iterations < cap + fresh.iterations + 10
    assert solver._subdomain_change(H2) == 0.0  # refactorized for H2


def test_entry_change_is_the_scaled_rms_change_of_the_entries():
    import scipy.sparse as sp

    from gtsam_schwarz.solvers import EntryChange

    rng = np.random.default_rng(3)
    B = sp.random(300, 300, density=0.02, random_state=4, format="csr")
    R = sp.csr_matrix(B @ B.T + sp.diags(rng.uniform(1.0, 5.0, 300)))
    R.sort_indices()
    change = EntryChange(R)
    assert change(R) == 0.0
    eps = 1e-3
    A = sp.csr_matrix(R + eps * sp.diags(R.diagonal()))  # diagonal entries × (1 + eps): δ = eps·√(n/nnz)
    A.sort_indices()
    assert np.isclose(change(A), eps * np.sqrt(R.shape[0] / R.nnz), rtol=1e-9)
    A2 = R.copy()
    A2.data *= 1.0 + eps  # every entry: δ² = eps² mean(R_ij² / (R_ii R_jj))
    r, c = R.nonzero()
    expected = eps * np.sqrt(np.mean(np.asarray(R[r, c]).ravel() ** 2 / (R.diagonal()[r] * R.diagonal()[c])))
    assert np.isclose(change(A2), expected, rtol=1e-9)
    assert change(sp.csr_matrix(R + sp.eye(300, k=150))) == float("inf")  # another pattern
    EntryChange.SAMPLES, saved = 500, EntryChange.SAMPLES  # a sample of the entries: the same estimate, roughly
    try:
        assert abs(EntryChange(R)(A2) / expected - 1.0) < 0.3
    finally:
        EntryChange.SAMPLES = saved


def _dense_extension(H, ext, rows, cols, vals, nc):
    """Reference Φ: interface values, interior rows −A_II⁻¹ A_IΓ Φ_Γ by a dense solve."""
    n = H.shape[0]
    Phi = np.zeros((n, nc))
    np.add.at(Phi, (rows, cols), vals)
    A = H.toarray()
    I, G = ext.interior, ext.gamma
    Phi[I] = -np.linalg.solve(A[np.ix_(I, I)], A[np.ix_(I, G)] @ Phi[G])
    return Phi


def test_extension_with_cancelling_products_and_in_column_blocks_equals_a_dense_solve(two_points):
    """Φ_Γ values that make whole columns of A_IΓ Φ_Γ vanish (entries dropped by the sparse product,
    positions found anew), and the extension in blocks of one column: both equal a dense solve."""
    from gtsam_schwarz.coarse import coarse_columns

    km, H1, H2 = two_points
    dec = decompose(GraphStructure.from_matrix(H1, km.offsets), 3, "segments", 1)
    iface = find_interface(dec)
    rows, cols, vals, _, col_subdomains = coarse_columns(dec, iface, "gdsw", None, True, km.translation_mask())
    nc = col_subdomains.shape[0]
    ext = HarmonicExtension(dec, iface)
    ext(H1, rows, cols, vals, col_subdomains)  # the plan and the structural positions
    zeroed = np.where(cols % 3 == 0, 0.0, vals)  # a third of the columns vanish: products cancel to 0
    Phi, _ = ext(H2, rows, cols, zeroed, col_subdomains)
    ref = _dense_extension(H2, ext, rows, cols, zeroed, nc)
    assert np.abs(Phi.tocsr().toarray() - ref).max() <= 1e-9 * np.abs(ref).max()
    blocked = HarmonicExtension(dec, iface, block_columns=1)
    Phi_b, A0_b = blocked(H2, rows, cols, vals, col_subdomains)
    ref = _dense_extension(H2, ext, rows, cols, vals, nc)
    assert np.abs(Phi_b.tocsr().toarray() - ref).max() <= 1e-9 * np.abs(ref).max()
    assert np.allclose(A0_b.toarray(), ref.T @ H2.toarray() @ ref, rtol=1e-8, atol=1e-9 * np.abs(A0_b).max())


def test_extension_in_pieces_of_whole_subdomains_equals_a_dense_solve(two_points, monkeypatch):
    """Interior rows factorized in pieces (the local threads' jobs): every piece holds whole
    subdomains, keeps its rows in their order, and Φ and A_0 equal a dense solve's."""
    import gtsam_schwarz.coarse.extension as E
    from gtsam_schwarz.coarse import coarse_columns

    km, H1, _ = two_points
    dec = decompose(GraphStructure.from_matrix(H1, km.offsets), 6, "segments", 1)
    iface = find_interface(dec)
    rows, cols, vals, _, col_subdomains = coarse_columns(dec, iface, "gdsw", None, True, km.translation_mask())
    nc = col_subdomains.shape[0]
    monkeypatch.setattr(E, "GROUP_PIECES", 12)
    ext = HarmonicExtension(dec, iface)
    Phi, A0 = ext(H1, rows, cols, vals, col_subdomains)
    ref = _dense_extension(H1, ext, rows, cols, vals, nc)
    assert np.abs(Phi.tocsr().toarray() - ref).max() <= 1e-9 * np.abs(ref).max()
    assert np.allclose(A0.toarray(), ref.T @ H1.toarray() @ ref, rtol=1e-8, atol=1e-9 * np.abs(A0).max())
    assert len(ext.groups) > ext.max_groups   # the column groups cut in pieces
    assert sum(len(g.interior) for g in ext.groups) == len(ext.interior)
    owner = {}
    place = np.empty(H1.shape[0], dtype=np.int64)
    place[ext.interior] = np.arange(len(ext.interior))
    for k, g in enumerate(ext.groups):
        for sub in np.unique(g.sub):
            assert owner.setdefault(int(sub), k) == k   # a subdomain's interior in one piece
        assert np.all(np.diff(place[g.interior]) > 0)   # its rows in the interior's order
    assert len(owner) == len(np.unique(ext.sub))


def _direct(lagged):
    from gtsam_schwarz.nonlinear.linear_solver import DirectSolver
    solver = DirectSolver(lagged=lagged)
    solver.LAG_MIN_ITERATIONS = 1  # the small test matrices factorize as fast as a few solves
    return solver


def test_lagged_direct_solver_uses_the_last_factor_and_refactors_when_cg_falls_behind(two_points):
    """A nearby matrix is solved by CG preconditioned with the last factor (no refactorization) to the
    tolerance; a far one makes CG fall behind, and H is refactorized: both answers are the exact ones."""
    _, H1, _ = two_points
    n = H1.shape[0]
    H1 = (H1 + 1e-3 * sp.eye(n)).tocsr()
    b = np.random.default_rng(0).standard_normal(n)
    near = (H1 + 1e-4 * sp.diags(H1.diagonal())).tocsr()  # the last H + λD with a changed λ
    far = (H1 + 100.0 * sp.diags(H1.diagonal())).tocsr()  # same pattern, a spectrum far from H1's
    solver = _direct(True)
    first = solver.solve(H1, b, 1e-10, lambda: None)
    assert first.iterations == 0 and not first.lagged and np.allclose(H1 @ first.x, b, rtol=0, atol=1e-9 * np.linalg.norm(b))
    solver._refactor_seconds = 1.0  # a factorization costs as much as many solves
    lagged = solver.solve(near, b, 1e-10, lambda: None)
    assert lagged.lagged and not lagged.rebuilt and lagged.setup_seconds == 0.0 and 1 <= lagged.iterations <= 5
    assert np.linalg.norm(near @ lagged.x - b) <= 1e-10 * np.linalg.norm(b)
    solver._refactor_seconds, solver._iteration_seconds = 1.0, 0.1  # a cap of 7 CG iterations
    fallback = solver.solve(far, b, 1e-10, lambda: None)
    assert fallback.lagged and fallback.rebuilt and fallback.iterations <= 7 and fallback.setup_seconds > 0
    assert np.allclose(fallback.x, spla.spsolve(far.tocsc(), b), rtol=1e-8, atol=1e-12)
    plain = _direct(False)
    plain.solve(H1, b, 1e-10, lambda: None)
    assert plain.lag_cap() == 0 and plain.solve(near, b, 1e-10, lambda: None).iterations == 0


def test_lagged_direct_solver_budgets_by_the_prediction_not_a_first_factorization(two_points):
    """A first factorization also allocates the factor (at 1M 2D poses 3.4 s against 0.4 s to
    refactorize): the lag budget takes the cost model's prediction where it is smaller, and a measured
    refactorization after that."""
    _, H1, _ = two_points
    H1 = (H1 + 1e-3 * sp.eye(H1.shape[0])).tocsr()
    b = np.ones(H1.shape[0])
    solver = _direct(True)
    solver.predicted_seconds = 1e-9
    solver.solve(H1, b, 1e-10, lambda: None)
    assert solver._refactor_seconds == 1e-9 and solver.lag_cap() == 0
    solver._iteration_seconds = 1e9  # no lagged attempt: the next solve refactorizes and is measured
    solver.solve(H1, b, 1e-10, lambda: None)
    assert solver._refactor_seconds > 1e-9


def test_lm_on_a_lawnmower_keeps_the_preconditioner_for_the_solve_that_confirms_convergence():
    """The first step moves H (its entries change ~3e-4, rebuild); the second hardly (< lag_change):
    the last solve runs with the second build's M, and LM ends where rebuilding every solve ends."""
    from gtsam_schwarz.linearization.native import NativeLinearizer
    from gtsam_schwarz.problems.survey import lawnmower

    prob = lawnmower(40, 40)
    runs = {}
    for change in (1e-4, 0.0):  # the default, and a rebuild (with the subdomains) for every changed H
        lin = NativeLinearizer.from_arrays(**prob.arrays)
        opt = SchwarzOptimizer(None, None, SchwarzParams(preconditioner="rgdsw-linear", lag_change=change,
                                                         subdomain_lag_change=2e-3 if change else 0.0),
                               linearizer=lin)
        opt.optimize()
        assert opt.converged
        runs[change] = opt
    lagged, rebuilt = runs[1e-4].history, runs[0.0].history
    assert [h["preconditioner_rebuilt"] for h in rebuilt] == [True] * len(rebuilt)
    assert lagged[0]["preconditioner_rebuilt"] and lagged[1]["preconditioner_rebuilt"]  # after the first step
    assert lagged[1]["subdomains_kept"] and not any(h["subdomains_kept"] for h in rebuilt)  # coarse level only
    assert lagged[1]["cg_iterations"] <= rebuilt[1]["cg_iterations"] + 1
    assert lagged[-1]["preconditioner_lagged"] and not lagged[-1]["preconditioner_rebuilt"]
    assert lagged[-1]["cg_iterations"] <= int(1.5 * lagged[-2]["cg_iterations"]) + 2  # within its cap
    assert abs(runs[1e-4].error() - runs[0.0].error()) <= 1e-9 * runs[0.0].error()
