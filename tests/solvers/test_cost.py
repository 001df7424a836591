"""The symbolic cost prediction equals the real factor's size (it drives the automatic solver)."""

import numpy as np
import pytest
import scipy.sparse as sp

from gtsam_schwarz.solvers import SPARSE_BACKEND, cholesky_cost


def block_grid(n: int, d: int, seed: int = 0) -> tuple[sp.csr_matrix, np.ndarray]:
    """SPD block matrix with d×d blocks on an n×n grid graph (fill grows like a 2D grid's)."""
    rng = np.random.default_rng(seed)
    idx = np.arange(n * n).reshape(n, n)
    e = np.r_[np.c_[idx[:, :-1].ravel(), idx[:, 1:].ravel()], np.c_[idx[:-1].ravel(), idx[1:].ravel()]]
    nv = n * n
    B = sp.csr_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(nv, nv))
    B = B + B.T
    blocks = sp.kron(B, np.ones((d, d))) * 0.1 * rng.uniform(0.5, 1, 1)[0]
    A = (blocks + sp.eye(nv * d) * (4 * d)).tocsr()
    return A, np.arange(nv + 1) * d


@pytest.mark.parametrize("d", [3, 6])
def test_predicted_nnz_of_the_factor_matches_cholmod(d):
    if SPARSE_BACKEND != "cholmod":
        pytest.skip("the prediction is exact for CHOLMOD's simplicial factor; SuperLU orders differently")
    from sksparse.cholmod import cholesky
    A, offsets = block_grid(20, d)
    cost = cholesky_cost(A, offsets)
    actual = cholesky(A.tocsc(), mode="simplicial").L().nnz
    assert cost.nnz_L == pytest.approx(actual, rel=0.15)  # block ordering vs scalar ordering
    assert cost.fill > 2  # a grid fills in
    assert cost.flops > cost.nnz_L


def test_a_chain_has_no_fill():
    n, d = 200, 3
    B = sp.diags([np.ones(n - 1), np.ones(n - 1)], [-1, 1])
    A = (sp.kron(B, np.ones((d, d))) + 10 * sp.eye(n * d)).tocsr()
    cost = cholesky_cost(A, np.arange(n + 1) * d)
    assert cost.fill == pytest.approx(1.0, rel=0.05)


def test_supernodal_and_simplicial_surrogates_give_the_same_counts():
    if SPARSE_BACKEND != "cholmod":
        pytest.skip("CHOLMOD only")
    from gtsam_schwarz.solvers import cost

    A, offsets = block_grid(30, 3)
    B = cost.vertex_pattern(A, offsets) + sp.csr_matrix(cost.vertex_pattern(A, offsets) @ cost.vertex_pattern(A, offsets))
    S = cost._surrogate(sp.csr_matrix(B))  # two-hop neighbourhoods: more entries per column than the threshold
    assert S.nnz >= cost.SUPERNODAL_DEGREE * S.shape[0]
    supernodal = cost._factor_column_counts(S)
    from sksparse.cholmod import cholesky
    simplicial = np.diff(sp.csc_matrix(cholesky(S, mode="simplicial").LD()).indptr)
    assert np.array_equal(supernodal, simplicial)


def test_the_2d_chordal_start_answers_the_cost_models_question_about_the_vertex_pattern(monkeypatch):
    """The 2D chordal start factorizes the vertex pattern of H first (simplicially); its column counts,
    remembered, are the ones the cost model computes itself, and the model then computes nothing."""
    if SPARSE_BACKEND != "cholmod":
        pytest.skip("CHOLMOD only")
    from gtsam_schwarz import SchwarzOptimizer, SchwarzParams
    from gtsam_schwarz.problems import square_loops
    from gtsam_schwarz.solvers import cost

    prob = square_loops(8, 6, sigma=0.05, seed=2)
    opt = SchwarzOptimizer(prob.graph, prob.initial, SchwarzParams(max_iterations=1))  # chordal start
    (shape, indptr, indices), recorded = cost._LAST_COUNTS[0]
    system = opt.linearizer.linearize(opt._state)
    S = cost._surrogate(sp.csr_matrix(cost.vertex_pattern(system.H, opt.linearizer.offsets)))
    assert cost._same_pattern(S, (shape, indptr, indices)) and cost.counted_simplicially(S)
    assert np.array_equal(recorded, cost._counts(S))
    monkeypatch.setattr(cost, "_counts", lambda S: pytest.fail("the remembered counts were not used"))
    opt.optimize()
    assert opt.summary()["linear_solver"]["used"] == "direct"


def test_factor_time_model_follows_nnz_of_L_where_the_supernodes_grow():
    """The factorization model: flops at the simplicial rate below CHOLMOD's supernodal switch, at
    the small-supernode rate above it, about SUPERNODE·nnz(L) once flops / nnz(L) passes ~70 (2D and
    3D alike), never faster than the peak rate per flop."""
    from gtsam_schwarz.nonlinear.linear_solver import CostModel

    m = CostModel()
    small = m.factor_seconds(10 * 1e6, 1e6)  # flops / nnz(L) = 10: a chain-like factor
    assert small == pytest.approx(m.ENTRY * 1e6 + m.FLOP_SIMPLICIAL * 1e7)
    supernodal = m.factor_seconds(50 * 1e6, 1e6)  # past the switch: small supernodes
    assert supernodal == pytest.approx(m.ENTRY * 1e6 + m.FLOP * 5e7)
    mid = [m.factor_seconds(c * 1e6, 1e6) for c in (200, 400, 1000)]
    assert mid == pytest.approx([(m.ENTRY + m.SUPERNODE) * 1e6] * 3)  # the same nnz(L), the same time
    huge = m.factor_seconds(1e5 * 1e6, 1e6)
    assert huge == pytest.approx(m.ENTRY * 1e6 + m.FLOP_LARGE * 1e11)
    assert small < supernodal < mid[0] < huge


def _first_H(graph, initial):
    """The optimizer (chordal start) and its first Gauss-Newton matrix."""
    from gtsam_schwarz import SchwarzOptimizer, SchwarzParams

    opt = SchwarzOptimizer(graph, initial, SchwarzParams(max_iterations=1))
    return opt, opt.linearizer.linearize(opt._state).H


@pytest.mark.slow
def test_auto_takes_direct_on_a_small_lawnmower_survey():
    """lawnmower 100x100 (10 000 2D poses, nnz(L) 7.7x nnz(H)): since CHOLMOD's OpenMP runs one thread,
    direct measured 0.324 s against Schwarz's 0.443 s (docs/benchmarks.md, thirteenth session; before,
    with its four threads, Schwarz won, 0.39-0.51 against 0.44-0.60 s): the automatic choice estimates
    both and takes direct."""
    if SPARSE_BACKEND != "cholmod":
        pytest.skip("CHOLMOD's analysis")
    from gtsam_schwarz.nonlinear.linear_solver import AutoSolver
    from gtsam_schwarz.nonlinear.params import LinearSolverParams
    from gtsam_schwarz.problems import lawnmower

    prob = lawnmower(100, 100)
    opt, H = _first_H(prob.graph, prob.initial)
    auto = AutoSolver(LinearSolverParams(), opt.linearizer.offsets, np.ones(H.shape[0], bool))
    auto.choose(H, lambda: opt.linearizer.geometry(opt._state))
    assert auto.choice == "direct", auto.reason


@pytest.mark.datasets
def test_auto_screens_sphere2500_to_direct_without_a_schwarz_estimate():
    """sphere2500 (nnz(L) 6.6x nnz(H), 3D): direct measured 0.29-0.38 s against Schwarz's 0.37-0.48 s;
    its predicted direct solve is below the screen, so no decomposition is made for the estimate."""
    if SPARSE_BACKEND != "cholmod":
        pytest.skip("CHOLMOD's analysis")
    from conftest import dataset
    from gtsam_schwarz.io import load_graph
    from gtsam_schwarz.nonlinear.linear_solver import AutoSolver
    from gtsam_schwarz.nonlinear.params import LinearSolverParams

    g = load_graph(dataset("sphere2500.g2o"))
    opt, H = _first_H(g.graph, g.initial)
    auto = AutoSolver(LinearSolverParams(), opt.linearizer.offsets, np.ones(H.shape[0], bool))
    auto.choose(H)
    assert auto.choice == "direct" and "cannot win" in auto.reason, auto.reason


@pytest.mark.parametrize("d", [3, 6])
def test_symbolic_column_counts_equal_the_numeric_surrogates(d, monkeypatch):
    """CHOLMOD's symbolic analysis (through its C interface) gives the same column counts as the
    numeric factorization of the surrogate it replaces, for the sparse and the filled-in path."""
    if SPARSE_BACKEND != "cholmod":
        pytest.skip("CHOLMOD only")
    from gtsam_schwarz.solvers import cholmod_symbolic, cost

    if not cholmod_symbolic.available():
        pytest.skip("no CHOLMOD 3-5 library to call (the surrogate is used instead)")
    A, offsets = block_grid(30, d)
    V = cost.vertex_pattern(A, offsets)
    for B in (V, sp.csr_matrix(V @ V)):  # a grid (simplicial) and its two-hop pattern (supernodal)
        S = cost._surrogate(sp.csr_matrix(B))
        symbolic = cholmod_symbolic.column_counts(S)
        monkeypatch.setattr(cholmod_symbolic, "column_counts", lambda S: None)
        numeric = cost._counts(S)
        monkeypatch.undo()
        assert symbolic is not None and symbolic.sum() > S.shape[0]
        assert np.array_equal(symbolic, numeric)


def test_natural_order_is_taken_only_where_it_fills_in_as_little_as_cholmods():
    """The natural order's column counts (elimination tree only) equal a numeric factorization in
    that order; a chain of loops numbered along the trajectory keeps its order (the same factor as
    AMD's), the same graph with shuffled keys does not."""
    if SPARSE_BACKEND != "cholmod":
        pytest.skip("CHOLMOD only")
    from sksparse.cholmod import analyze
    from gtsam_schwarz.solvers import cholmod_symbolic, cost

    if not cholmod_symbolic.available():
        pytest.skip("no CHOLMOD 3-5 library to call")
    n, d = 3000, 3
    rng = np.random.default_rng(1)
    i = np.r_[np.arange(n - 1), np.arange(0, n - 40, 40)]   # odometry and a closure every 40 poses
    j = np.r_[np.arange(1, n), np.arange(39, n - 1, 40)]
    for order in (np.arange(n), rng.permutation(n)):
        a, b = order[i], order[j]
        B = sp.csr_matrix((np.ones(2 * len(a)), (np.r_[a, b], np.r_[b, a])), shape=(n, n))
        blocks = sp.kron(B, np.ones((d, d))) * 0.1
        A = (blocks + sp.eye(n * d) * (4 * d)).tocsr()
        offsets = np.arange(n + 1) * d
        S = cost._surrogate(cost.vertex_pattern(A, offsets))
        counts = cholmod_symbolic.natural_column_counts(S)
        numeric = np.diff(sp.csc_matrix(analyze(S, mode="simplicial", ordering_method="natural").cholesky(S).LD()).indptr)
        assert np.array_equal(counts, numeric)
        natural = cholesky_cost(A, offsets, natural=True).natural_suffices
        assert natural == bool(np.array_equal(order, np.arange(n))), counts.sum()
