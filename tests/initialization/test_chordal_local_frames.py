"""Chordal rotations by CG in 3D: the two-level Schwarz's near-null blocks from local frames, and the
automatic choice between that and the direct factorization."""

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.spatial.transform import Rotation

from gtsam_schwarz.initialization import chordal as C
from gtsam_schwarz.initialization.chordal import chordal_initialization
from gtsam_schwarz.linearization.native import NativeLinearizer
from gtsam_schwarz.nonlinear.initialize import rotation_solver
from gtsam_schwarz.problems import survey3d
from gtsam_schwarz.solvers import pattern_cholesky_cost


def survey_graph(*dims, seed=1, sigma=0.01):
    g = NativeLinearizer.from_arrays(**survey3d(*dims, sigma=sigma, seed=seed).arrays).pose_graph()
    b = g["between"]
    return g["n"], np.column_stack([b["i"], b["j"]]), b["R"], b["t"], b["information"]


def test_local_frames_differ_from_the_rotations_by_one_rotation_per_aggregate():
    """Noise-free measurements: within each aggregate R_v R̃_vᵀ is one rotation (its seed's)."""
    rng = np.random.default_rng(0)
    n = 400
    R = Rotation.random(n, random_state=1).as_matrix()
    e = np.unique(np.sort(rng.integers(0, n, size=(1600, 2)), axis=1), axis=0)
    e = np.vstack([np.column_stack([np.arange(n - 1), np.arange(1, n)]), e[e[:, 0] != e[:, 1]]])
    i, j = e.T
    Rij = np.swapaxes(R[i], 1, 2) @ R[j]
    red = C._Reduced(n, 1, np.array([0]))
    layout = C._SchwarzLayout(red, i, j, aggregate_size=16, overlap=0, seed=0)
    frames = C._local_frames(layout, red, i, j, Rij)
    Q = R[red.free_nodes] @ np.swapaxes(frames, 1, 2)
    first = np.zeros(layout.count, dtype=np.int64)
    first[layout.label[::-1]] = np.arange(len(layout.label))[::-1]  # a node of every aggregate
    np.testing.assert_allclose(Q, Q[first[layout.label]], atol=1e-10)
    assert layout.count > 10 and np.max(layout.depth) >= 2  # frames composed over several hops


def test_3d_rotation_cg_converges_fast_and_matches_direct():
    """Noisy 3D surveys: CG with local-frame coarse blocks needs few iterations, hardly more on a
    4.7× larger survey (a global spanning tree's frames took 93 and 148 here), and lands on the
    direct solution."""
    its = []
    for dims in ((6, 12, 12), (8, 16, 16)):
        n, e, R, t, info = survey_graph(*dims)
        cg = chordal_initialization(n, e, R, t, info, solver="cg", overlap=0, tol=1e-6)
        direct = chordal_initialization(n, e, R, t, info, solver="direct")
        assert cg.info["rotation_converged"] and cg.info["translation_converged"]
        its.append(max(cg.info["rotation_iterations"]))
        np.testing.assert_allclose(cg.rotations, direct.rotations, atol=1e-5)
        np.testing.assert_allclose(cg.positions, direct.positions, atol=1e-3)
    assert its[0] <= 32 and its[1] <= 1.25 * its[0], its


def test_translation_solver_can_differ_from_the_rotations():
    n, e, R, t, info = survey_graph(4, 8, 8)
    both = chordal_initialization(n, e, R, t, info, solver="cg", tol=1e-12)
    mixed = chordal_initialization(n, e, R, t, info, solver="cg", translation_solver="direct", tol=1e-12)
    assert len(both.info["translation_iterations"]) == 3 and mixed.info["translation_iterations"] == []
    np.testing.assert_allclose(mixed.positions, both.positions, atol=1e-8)
    with pytest.raises(ValueError, match="unknown solver"):
        chordal_initialization(n, e, R, t, info, translation_solver="qr")


def lattice(k):
    """Edges of a k×k×k grid (each node joined to its +x, +y, +z neighbour): a 3D survey's pattern."""
    idx = np.arange(k ** 3).reshape(k, k, k)
    pairs = [np.column_stack([idx[:-1].ravel(), idx[1:].ravel()]),
             np.column_stack([idx[:, :-1].ravel(), idx[:, 1:].ravel()]),
             np.column_stack([idx[:, :, :-1].ravel(), idx[:, :, 1:].ravel()])]
    return np.vstack(pairs).T


def test_rotation_solver_picks_cg_where_the_factor_fills_in():
    """Direct on small graphs and on long corridors (no fill); CG on a 3D grid of 32 768 poses (its
    3×3-block factor: ~4 s here, CG ~2 s) and on a 2D grid of 90 000 (the complex factorizations
    0.75 s, CG 0.45 s), not on a 2D grid of 10 000 (both ~0.05 s)."""
    i, j = lattice(32)
    assert rotation_solver(32 ** 3, i, j, 3)[0] == "cg"
    k = np.arange(20000)
    chain_i = np.r_[k[:-1], k[:-50:50]]
    chain_j = np.r_[k[1:], k[50::50]]
    assert rotation_solver(20000, chain_i, chain_j, 3)[0] == "direct"
    assert rotation_solver(20000, chain_i, chain_j, 2) == ("direct", "")   # nearly a tree: not analysed
    small_i, small_j = lattice(12)
    assert rotation_solver(12 ** 3, small_i, small_j, 3) == ("direct", "")
    grid = np.arange(300 * 300).reshape(300, 300)
    gi = np.r_[grid[:, :-1].ravel(), grid[:-1].ravel()]
    gj = np.r_[grid[:, 1:].ravel(), grid[1:].ravel()]
    assert rotation_solver(300 * 300, gi, gj, 2)[0] == "cg"
    grid = np.arange(100 * 100).reshape(100, 100)
    assert rotation_solver(100 * 100, np.r_[grid[:, :-1].ravel(), grid[:-1].ravel()],
                           np.r_[grid[:, 1:].ravel(), grid[1:].ravel()], 2) == ("direct", "")


def test_the_vertex_pattern_analysis_is_done_once():
    """The chordal choice and the automatic linear solver analyse the same pattern: the second
    analysis returns the first one's column counts."""
    i, j = lattice(10)
    n = 1000
    B = sp.csr_matrix((np.ones(2 * len(i) + n), (np.r_[i, j, np.arange(n)], np.r_[j, i, np.arange(n)])),
                      shape=(n, n))
    first = pattern_cholesky_cost(B, np.full(n, 3))
    from gtsam_schwarz.solvers import cost
    kept = cost._LAST_COUNTS[0][1]
    again = pattern_cholesky_cost(B.astype(np.float32), np.full(n, 6))  # other numbers and blocks, same pattern
    assert cost._LAST_COUNTS[0][1] is kept
    assert again.flops == pytest.approx(8 * first.flops)


def test_chordal_state_follows_the_linear_solver():
    """Runs whose linear solver is Schwarz-CG by choice solve large 3D chordal systems by CG without
    an analysis (to ``CG_TOL`` = 1e-2: a start for LM, which ends at the same error from it on the
    3D surveys); its error is within 25 % of the exact start's (here 53.9 against 45.8), and both
    are far below dead reckoning's."""
    from gtsam_schwarz.nonlinear.initialize import CG_MIN_POSES, chordal_state

    lin = NativeLinearizer.from_arrays(**survey3d(4, 32, 32, sigma=0.01, seed=2).arrays)
    assert lin.pose_graph()["n"] >= CG_MIN_POSES
    start = lin.initial_state()
    cg, note_cg = chordal_state(lin, start, solver="cg-3d")
    direct, note_direct = chordal_state(lin, start, solver="direct")
    assert "CG" in note_cg and "(direct" in note_direct
    assert lin.error(cg) == pytest.approx(lin.error(direct), rel=0.25)
    assert lin.error(cg) < 0.01 * lin.error(start)


def test_the_choice_prepared_on_the_side_thread_is_the_one_made_in_place(monkeypatch):
    """prepare_chordal analyses the rotation system on the side thread (the optimizer calls it before
    reading the start); chordal_state given its result makes the choice and the start it makes alone."""
    import threading

    import gtsam_schwarz.nonlinear.initialize as init
    from gtsam_schwarz.problems import lawnmower

    monkeypatch.setattr(init, "CG_MIN_POSES_2D", 1000)   # a 40 x 40 lawnmower is analysed
    lin = NativeLinearizer.from_arrays(**lawnmower(40, 40, sigma=0.01, seed=3).arrays)
    real, threads = init.rotation_solver, []

    def recorded(*args):
        threads.append(threading.current_thread().name)
        return real(*args)

    monkeypatch.setattr(init, "rotation_solver", recorded)
    graph, choice = init.prepare_chordal(lin, "auto")
    solver, why = choice()
    assert threads == ["gtsam-schwarz-side_0"] and why.startswith(f"rotations {solver}")
    b = graph["between"]
    assert (solver, why) == real(graph["n"], np.asarray(b["i"]), np.asarray(b["j"]), 2)
    start = lin.initial_state()
    ahead, note_ahead = init.chordal_state(lin, start, "auto", prepared=init.prepare_chordal(lin, "auto"))
    alone, note_alone = init.chordal_state(lin, start, "auto")
    assert note_ahead.split("(")[1] == note_alone.split("(")[1]   # the same solver and reason
    assert np.array_equal(ahead.pose2, alone.pose2)
