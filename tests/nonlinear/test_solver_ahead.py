"""The linear solver's decomposition started ahead of the first linearization (on the side thread,
from the linearizer's fixed pattern) is the one the first solve would make, and the run is the same."""

import importlib
import threading

import numpy as np
import pytest

from gtsam_schwarz import SchwarzOptimizer, SchwarzParams, lawnmower
from gtsam_schwarz.dd.structure import GraphStructure
from gtsam_schwarz.linearization.native import NativeLinearizer
from gtsam_schwarz.nonlinear import linear_solver as ls
from gtsam_schwarz.util import vertex_pattern

DECOMPOSE = ls.decompose
block_diagonal_module = importlib.import_module("gtsam_schwarz.solvers.block_diagonal")   # (the package exports a function of that name)
ORDER = block_diagonal_module.vertex_block_order


def _run(problem, preconditioner, ahead: bool, monkeypatch, orders: list | None = None):
    monkeypatch.setattr(ls.PreconditionedCG, "AHEAD_FROM", 0 if ahead else 10**12)
    threads = []

    def recording(*args, **kwargs):
        threads.append(threading.current_thread().name)
        return DECOMPOSE(*args, **kwargs)

    monkeypatch.setattr(ls, "decompose", recording)
    if orders is not None:   # where (on which thread, ahead or in the operator's setup) the blocks' order is found
        def ordering(*args, **kwargs):
            orders.append(threading.current_thread().name)
            return ORDER(*args, **kwargs)

        monkeypatch.setattr(ls, "vertex_block_order", ordering)
        monkeypatch.setattr(block_diagonal_module, "vertex_block_order", ordering)
    lin = NativeLinearizer.from_arrays(**problem.arrays)
    opt = SchwarzOptimizer(problem.graph, problem.initial, SchwarzParams(method="lm", preconditioner=preconditioner),
                           linearizer=lin)
    opt.optimize()
    return opt, threads


def test_the_fixed_pattern_gives_the_vertex_pattern_and_structure_of_h():
    p = lawnmower(6, 7)
    lin = NativeLinearizer.from_arrays(**p.arrays)
    H = lin.linearize(lin.initial_state()).H
    V = lin.pattern.vertex_pattern()
    W = vertex_pattern(H, lin.offsets)
    assert V.has_sorted_indices and np.array_equal(V.indptr, W.indptr) and np.array_equal(V.indices, W.indices)
    a, b = GraphStructure.from_vertex_pattern(V, lin.offsets), GraphStructure.from_matrix(H, lin.offsets)
    assert np.array_equal(a.edges, b.edges) and np.array_equal(a.odometry, b.odometry)


@pytest.mark.parametrize("preconditioner", ["auto", "rgdsw-linear"])
def test_decomposition_ahead_is_the_first_solves_and_the_run_is_the_same(preconditioner, monkeypatch):
    p = lawnmower(30, 30)
    if preconditioner == "auto":   # direct predicted slow (as on large surveys): auto takes Schwarz
        monkeypatch.setattr(ls.CostModel, "direct", lambda self, cost: 1e9)
    orders_on, orders_off = [], []
    ahead, on = _run(p, preconditioner, True, monkeypatch, orders_on)
    alone, off = _run(p, preconditioner, False, monkeypatch, orders_off)
    assert len(on) == len(off) == 1   # decomposed once either way
    # the subdomain blocks' order: found once either way, ahead right after the decomposition on its thread
    assert len(orders_on) == len(orders_off) == 1 and orders_on[0] == on[0]
    s1, s2 = (getattr(o.linear_solver, "chosen", o.linear_solver).operator.one_level.sets for o in (ahead, alone))
    assert np.array_equal(s1.vertices, s2.vertices)   # the same order of every subdomain's vertices
    assert not on[0].startswith("MainThread") and off[0] == "MainThread"   # ahead: on the side thread
    assert ahead.linear_solver.choice == alone.linear_solver.choice != "direct"
    d1, d2 = ahead.decomposition, alone.decomposition
    assert (d1.overlapping != d2.overlapping).nnz == 0 and np.array_equal(d1.edge_subdomain, d2.edge_subdomain)
    assert [h.cg_iterations for h in ahead.history] == [h.cg_iterations for h in alone.history]
    assert ahead.error() == pytest.approx(alone.error(), rel=1e-12)


def test_auto_keeps_direct_without_a_decomposition_where_the_screen_says_so(monkeypatch):
    from gtsam_schwarz import square_loops
    p = square_loops(4, 16)   # the paper's model problem: almost no fill, the screen keeps direct
    opt, threads = _run(p, "auto", True, monkeypatch)
    assert opt.linear_solver.choice == "direct" and threads == []
