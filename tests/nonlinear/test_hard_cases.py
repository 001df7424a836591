"""Degenerate and awkward graphs: the solver either matches GTSAM or says clearly why not."""

import gtsam
import numpy as np
import pytest

from conftest import pose2_difference
from gtsam_schwarz import SchwarzOptimizer, SchwarzParams, load_graph, square_loops


def gtsam_lm_error(graph, initial):
    return graph.error(gtsam.LevenbergMarquardtOptimizer(graph, initial, gtsam.LevenbergMarquardtParams()).optimize())


def shifted(prob, offset, turns=0):
    """The same problem moved by ``offset`` and with every angle written ``turns`` × 2π off."""
    graph = gtsam.NonlinearFactorGraph()
    T = gtsam.Pose2(offset[0], offset[1], 0.0)
    for i in range(prob.graph.size()):
        f = prob.graph.at(i)
        if isinstance(f, gtsam.PriorFactorPose2):
            graph.add(gtsam.PriorFactorPose2(f.keys()[0], T.compose(f.prior()), f.noiseModel()))
        else:
            graph.add(f)
    initial = gtsam.Values()
    for k in prob.initial.keys():
        p = T.compose(prob.initial.atPose2(k))
        initial.insert(k, gtsam.Pose2(p.x(), p.y(), p.theta() + 2 * np.pi * turns))
    return graph, initial


@pytest.mark.parametrize("name", ["gdsw", "rgdsw", "one-level"])
def test_far_from_origin_and_wrapped_angles(name):
    prob = square_loops(8, 8, sigma=0.02, seed=5)
    graph, initial = shifted(prob, (1e6, -1e6), turns=3)
    ref = gtsam_lm_error(graph, initial)
    opt = SchwarzOptimizer(graph, initial, SchwarzParams(method="lm", preconditioner=name, subdomains=8))
    result = opt.optimize()
    assert opt.converged and opt.error() <= ref * (1 + 1e-6)
    # same trajectory as the unshifted problem, moved back
    base = SchwarzOptimizer(prob.graph, prob.initial, SchwarzParams(preconditioner="gdsw", method="lm", subdomains=8)).optimize()
    back = gtsam.Values()
    Tinv = gtsam.Pose2(1e6, -1e6, 0.0).inverse()
    for k in result.keys():
        back.insert(k, Tinv.compose(result.atPose2(k)))
    assert np.abs(pose2_difference(back, base)).max() < 1e-6


def test_single_pose(tmp_path):
    graph = gtsam.NonlinearFactorGraph()
    graph.add(gtsam.PriorFactorPose2(0, gtsam.Pose2(1, 2, 0.3), gtsam.noiseModel.Isotropic.Sigma(3, 0.1)))
    initial = gtsam.Values()
    initial.insert(0, gtsam.Pose2(0, 0, 0))
    for name in ("gdsw", "one-level", "block-jacobi", "direct"):
        opt = SchwarzOptimizer(graph, initial, SchwarzParams(method="lm", preconditioner=name))
        result = opt.optimize()
        assert opt.error() < 1e-12, name
        assert result.atPose2(0).equals(gtsam.Pose2(1, 2, 0.3), 1e-6)


def test_chain_without_loop_closures():
    prob = square_loops(3, 6, sigma=0.02, seed=1)
    graph = gtsam.NonlinearFactorGraph()
    for i in range(prob.graph.size()):
        f = prob.graph.at(i)
        if len(f.keys()) == 1 or f.keys()[1] == f.keys()[0] + 1:
            graph.add(f)
    opt = SchwarzOptimizer(graph, prob.initial, SchwarzParams(preconditioner="gdsw", method="gn", subdomains=3))
    opt.optimize()
    assert opt.error() < 1e-10  # dead reckoning is already optimal for a tree


def test_disconnected_file_is_refused_with_a_clear_message(tmp_path):
    f = tmp_path / "two.g2o"
    f.write_text("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\nVERTEX_SE2 2 5 0 0\nVERTEX_SE2 3 6 0 0\n"
                 "EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\nEDGE_SE2 2 3 1 0 0 1 0 0 1 0 1\n")
    from gtsam_schwarz import GraphFileError
    with pytest.raises(GraphFileError, match=r"two\.g2o:\d+: pose \d is not connected to pose 0"):
        load_graph(f)


def test_cg_cap_is_reported_and_lm_stays_safe():
    prob = square_loops(16, 8, sigma=0.05, seed=2)
    ref = gtsam_lm_error(prob.graph, prob.initial)
    opt = SchwarzOptimizer(prob.graph, prob.initial, SchwarzParams(
        method="lm", preconditioner="none", cg_max_iterations=5, max_iterations=200))
    result = opt.optimize()
    assert not any(h["cg_converged"] for h in opt.history)
    errors = [opt.initial_error] + [h["error"] for h in opt.history if h["accepted"]]
    assert all(b < a for a, b in zip(errors, errors[1:]))  # accepted steps only ever decrease the error
    assert np.all(np.isfinite(gtsam.utilities.extractPose2(result)))
    assert opt.error() < opt.initial_error and opt.error() >= ref * (1 - 1e-9)
