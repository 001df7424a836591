"""Survey problems: the 2D lawnmower and the 3D stack of lawnmower floors."""

import gtsam
import numpy as np
import pytest

from gtsam_schwarz.problems import lawnmower, lawnmower_cells, survey3d


def _pairs(graph):
    """(keys, precision) of every two-key factor, and the count of one-key factors."""
    pairs, priors = [], 0
    for i in range(graph.size()):
        f = graph.at(i)
        keys = tuple(f.keys())
        if len(keys) == 1:
            priors += 1
        else:
            pairs.append((keys, float(np.linalg.inv(f.noiseModel().covariance())[0, 0])))
    return pairs, priors


def test_lawnmower_sweeps_rows_back_and_forth():
    r, c = lawnmower_cells(3, 4)
    assert r.tolist() == [0, 0, 0, 0, 1, 1, 1, 1, 2, 2, 2, 2]
    assert c.tolist() == [0, 1, 2, 3, 3, 2, 1, 0, 0, 1, 2, 3]
    prob = lawnmower(3, 4, sigma=0.0)
    xy = gtsam.utilities.extractPose2(prob.ground_truth)
    assert np.allclose(xy[:, :2], np.column_stack([c, r]))  # unit spacing
    assert np.allclose(np.abs(np.diff(xy[:, :2], axis=0)).sum(1), 1.0)  # consecutive poses are neighbours


@pytest.mark.parametrize("rows, cols", [(1, 5), (4, 3), (5, 6)])
def test_lawnmower_factor_counts(rows, cols):
    prob = lawnmower(rows, cols, sigma=0.01, seed=3)
    n = rows * cols
    assert prob.poses == n == prob.initial.size() == prob.ground_truth.size()
    assert prob.closures == (rows - 1) * (cols - 1)
    assert prob.graph.size() == 1 + (n - 1) + prob.closures
    assert prob.dimension == 2 and prob.floors == 1
    pairs, priors = _pairs(prob.graph)
    assert priors == 1 and isinstance(prob.graph.at(0), gtsam.PriorFactorPose2)
    odometry = [k for k, w in pairs if k[1] == k[0] + 1]
    closures = [k for k, w in pairs if k[1] != k[0] + 1]
    assert len(odometry) == n - 1 and len(closures) == prob.closures
    assert all(w == pytest.approx(20.0) for k, w in pairs if k[1] == k[0] + 1)
    assert all(w == pytest.approx(100.0) for k, w in pairs if k[1] != k[0] + 1)
    # every closure joins a pose to the pose directly below it, one row earlier
    r, c = lawnmower_cells(rows, cols)
    for i, j in closures:
        assert (r[j], c[j]) == (r[i] + 1, c[i])


def test_lawnmower_zero_noise_is_consistent_and_noise_is_seeded():
    prob = lawnmower(4, 5, sigma=0.0)
    assert prob.graph.error(prob.ground_truth) == pytest.approx(0.0, abs=1e-20)
    assert prob.graph.error(prob.initial) == pytest.approx(0.0, abs=1e-18)  # dead reckoning = truth
    a, b, c = lawnmower(4, 5, seed=1), lawnmower(4, 5, seed=1), lawnmower(4, 5, seed=2)
    assert a.initial.equals(b.initial, 0.0) and not a.initial.equals(c.initial, 1e-9)
    odometry = [a.graph.at(i) for i in range(1, 4 * 5)]
    assert max(f.error(a.initial) for f in odometry) < 1e-18  # the initial guess is dead reckoning
    assert a.graph.error(a.initial) > 0  # the closures disagree with it


def test_survey3d_floors_stack_and_counts():
    F, R, C = 3, 3, 4
    prob = survey3d(F, R, C, sigma=0.0)
    n = F * R * C
    assert prob.poses == n == prob.initial.size() and prob.dimension == 3
    within = F * (R - 1) * (C - 1)
    between = (F - 1) * (R * C - 1)  # the first pose of a floor sits on the last of the one beneath
    assert prob.closures == within + between
    assert prob.graph.size() == 1 + (n - 1) + prob.closures
    assert isinstance(prob.graph.at(0), gtsam.PriorFactorPose3)
    T = np.array([prob.ground_truth.atPose3(t).translation() for t in range(n)])
    assert np.allclose(T[:, 2], np.repeat(np.arange(F), R * C))  # floor f at height f
    assert np.allclose(np.linalg.norm(np.diff(T, axis=0), axis=1), 1.0)  # unit steps, also upstairs
    pairs, _ = _pairs(prob.graph)
    for (i, j), w in pairs:
        if j != i + 1:  # a closure: directly below on the floor beneath, or one row back on the floor
            d = T[j] - T[i]
            assert np.allclose(np.abs(d), [0, 0, 1]) or np.allclose(np.abs(d), [0, 1, 0])
    assert prob.graph.error(prob.ground_truth) == pytest.approx(0.0, abs=1e-20)
    assert prob.graph.error(prob.initial) == pytest.approx(0.0, abs=1e-16)


def test_bad_sizes_are_refused():
    with pytest.raises(ValueError):
        lawnmower(0, 4)
    with pytest.raises(ValueError):
        survey3d(2, 3, 0)


def _gtsam_lm(prob):
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(50)
    return gtsam.LevenbergMarquardtOptimizer(prob.graph, prob.initial, params).optimize()


def test_gtsam_lm_from_dead_reckoning_converges_lawnmower():
    prob = lawnmower(12, 12, sigma=0.01, seed=0)
    result = _gtsam_lm(prob)
    start, end, truth = prob.graph.error(prob.initial), prob.graph.error(result), prob.graph.error(prob.ground_truth)
    assert end < 1e-2 * start and end <= truth  # the optimum is at most as bad as the ground truth
    xy = gtsam.utilities.extractPose2(result)[:, :2] - gtsam.utilities.extractPose2(prob.ground_truth)[:, :2]
    assert np.abs(xy).max() < 0.1  # within a tenth of the grid spacing everywhere


def test_gtsam_lm_from_dead_reckoning_converges_survey3d():
    prob = survey3d(3, 5, 5, sigma=0.01, seed=0)
    result = _gtsam_lm(prob)
    start, end, truth = prob.graph.error(prob.initial), prob.graph.error(result), prob.graph.error(prob.ground_truth)
    assert end < 1e-2 * start and end <= truth
    T = np.array([result.atPose3(t).translation() - prob.ground_truth.atPose3(t).translation()
                  for t in range(prob.poses)])
    assert np.abs(T).max() < 0.1


def test_arrays_describe_the_same_graph():
    """``arrays`` (for the native linearizer, as square_loops gives them) hold the graph's factors."""
    from gtsam_schwarz.linearization.native import NativeLinearizer
    for prob in (lawnmower(4, 5, seed=2), survey3d(2, 3, 4, seed=2)):
        lin = NativeLinearizer.from_arrays(**prob.arrays)
        assert lin.error(lin.initial_state()) == pytest.approx(prob.graph.error(prob.initial), rel=1e-12)
        assert len(prob.arrays["edges"]) == prob.graph.size() - 1


def test_gtsam_objects_are_built_on_first_use():
    """A solve from ``arrays`` never needs GTSAM's objects: the 2D survey builds none of them until asked,
    the 3D one only its start (read back for the arrays); both build each object once."""
    p2, p3 = lawnmower(3, 4), survey3d(2, 2, 3)
    assert p2._made == {} and set(p3._made) == {"initial"}
    initial = p2.initial
    assert set(p2._made) == {"initial"} and p2.initial is initial
    graph = p2.graph
    assert set(p2._made) == {"graph", "initial"} and p2.graph is graph
    assert graph.size() == 1 + (12 - 1) + 2 * 3 and p2.initial.size() == p2.ground_truth.size() == 12
    assert p3.graph.size() == len(p3.arrays["edges"]) + 1 and p3.ground_truth.size() == 12
