"""The paper's unit-square model problem."""

import gtsam
import numpy as np
import pytest

from gtsam_schwarz import square_loops, square_trajectory


def test_ground_truth_square():
    T = square_trajectory(2, 4)
    assert T.shape == (33, 3)
    assert np.allclose(T[[0, 4, 8, 12, 16, 32]], [[0, 0, 0], [1, 0, np.pi / 2], [1, 1, np.pi],
                                                  [0, 1, -np.pi / 2], [0, 0, 0], [0, 0, 0]])
    steps = np.linalg.norm(np.diff(T[:, :2], axis=0), axis=1)
    assert np.allclose(steps, 0.25)


def test_graph_factors_weights_and_closures():
    L, P = 3, 4
    prob = square_loops(L, P, sigma=0.02, seed=5)
    n = 4 * P * L + 1
    assert prob.poses == n == prob.initial.size() == prob.ground_truth.size()
    g = prob.graph
    assert g.size() == 1 + (n - 1) + L  # prior + odometry + one closure per loop
    closures = []
    for i in range(g.size()):
        f = g.at(i)
        keys = f.keys()
        info = np.linalg.inv(f.noiseModel().covariance()) if len(keys) == 2 else None
        if len(keys) == 2 and keys[1] != keys[0] + 1:
            closures.append(tuple(keys))
            assert np.allclose(info, 100 * np.eye(3))
        elif len(keys) == 2:
            assert np.allclose(info, 20 * np.eye(3))
    assert closures == [(0, 16), (16, 32), (32, 48)]
    assert isinstance(g.at(0), gtsam.PriorFactorPose2)


def test_zero_noise_gives_zero_error_at_ground_truth_and_dead_reckoning():
    prob = square_loops(2, 5, sigma=0.0, loop_sigma=0.0)
    assert prob.graph.error(prob.ground_truth) == pytest.approx(0.0, abs=1e-20)
    assert prob.graph.error(prob.initial) == pytest.approx(0.0, abs=1e-18)


def test_seeded_noise_and_dead_reckoning_initial_guess():
    a, b, c = square_loops(2, 4, seed=1), square_loops(2, 4, seed=1), square_loops(2, 4, seed=2)
    assert a.initial.equals(b.initial, 0.0) and not a.initial.equals(c.initial, 1e-9)
    # dead reckoning composes the odometry measurements: odometry factors have zero error there
    g = a.graph
    odometry = [g.at(i) for i in range(1, 1 + 4 * 4 * 2)]
    assert max(f.error(a.initial) for f in odometry) < 1e-20
    assert g.error(a.initial) > 0  # the loop closures disagree with dead reckoning


def test_bad_sizes_are_refused():
    with pytest.raises(ValueError):
        square_loops(0, 4)


def test_helix_is_3d_square_loops_climbing():
    from gtsam_schwarz import helix_loops
    prob = helix_loops(2, 3, sigma=0.0, loop_sigma=0.0, climb=0.5)
    n = 4 * 3 * 2 + 1
    assert prob.initial.size() == n and prob.graph.size() == 1 + (n - 1) + 2
    last = prob.ground_truth.atPose3(n - 1)
    assert np.allclose(last.translation(), [0, 0, 1.0]) and np.allclose(last.rotation().matrix(), np.eye(3))
    assert prob.graph.error(prob.initial) == pytest.approx(0.0, abs=1e-18)
    noisy = helix_loops(2, 3, sigma=0.02, seed=4)
    assert noisy.graph.error(noisy.initial) > 0
