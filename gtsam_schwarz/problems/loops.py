"""The paper's model problem: a robot driving L loops around the unit square (paper Sec. 4)."""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np


@dataclass
class SquareLoops:
    graph: gtsam.NonlinearFactorGraph
    initial: gtsam.Values  # dead reckoning from the noisy odometry
    ground_truth: gtsam.Values
    loops: int
    points_per_side: int
    sigma: float
    seed: int
    arrays: dict | None = None  # the graph as numpy arrays (NativeLinearizer.from_arrays(**arrays)); 2D only

    @property
    def poses(self) -> int:
        return 4 * self.points_per_side * self.loops + 1


def square_trajectory(loops: int, points_per_side: int) -> np.ndarray:
    """Ground-truth poses (x, y, θ): unit steps of 1/P along the square, left turn at each corner.

    Pose t has the heading of the side it starts (θ wrapped to (−π, π]); pose 4Pk is the origin.
    """
    P = points_per_side
    t = np.arange(4 * P * loops + 1)
    side = (t // P) % 4
    frac = (t % P) / P
    corners = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    direction = np.array([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0], [0.0, -1.0]])
    xy = corners[side] + frac[:, None] * direction[side]
    theta = np.array([0.0, np.pi / 2, np.pi, -np.pi / 2])[side]
    return np.column_stack([xy, theta])


def square_loops(loops: int, points_per_side: int, sigma: float = 0.01, seed: int = 0,
                 loop_sigma: float | None = None, odometry_information: float = 20.0,
                 loop_information: float = 100.0, prior_information: float = 100.0) -> SquareLoops:
    """The paper's unit-square multi-loop pose graph.

    Odometry edges (t, t+1) measure the true relative pose plus N(0, σ²) noise on (x, y, θ);
    each return to the start adds a loop closure (4P(k−1), 4Pk) with noise ``loop_sigma``
    (default σ·√(20/100), matching the weights). Weights are W = 20·I (odometry), 100·I (loop
    closure); a prior on pose 0 removes the gauge (its weight does not change the optimum).
    """
    if loops < 1 or points_per_side < 1:
        raise ValueError("loops and points_per_side must be >= 1")
    rng = np.random.default_rng(seed)
    P = points_per_side
    truth = square_trajectory(loops, P)
    n = len(truth)
    steps = n - 1
    # true odometry: 1/P forward, +90° at the step that arrives at a corner
    turn = np.where((np.arange(1, n) % P) == 0, np.pi / 2, 0.0)
    odo = np.column_stack([np.full(steps, 1.0 / P), np.zeros(steps), turn])
    odo_meas = odo + sigma * rng.standard_normal(odo.shape)
    closures = np.arange(1, loops + 1) * 4 * P
    ls = sigma * np.sqrt(odometry_information / loop_information) if loop_sigma is None else loop_sigma
    loop_meas = ls * rng.standard_normal((loops, 3))

    odo_noise = gtsam.noiseModel.Isotropic.Precision(3, odometry_information)
    loop_noise = gtsam.noiseModel.Isotropic.Precision(3, loop_information)
    prior_noise = gtsam.noiseModel.Isotropic.Precision(3, prior_information)
    graph = gtsam.NonlinearFactorGraph()
    graph.add(gtsam.PriorFactorPose2(0, gtsam.Pose2(*truth[0]), prior_noise))
    for t, (dx, dy, dth) in enumerate(odo_meas.tolist()):
        graph.add(gtsam.BetweenFactorPose2(t, t + 1, gtsam.Pose2(dx, dy, dth), odo_noise))
    for j, (dx, dy, dth) in zip(closures.tolist(), loop_meas.tolist()):
        graph.add(gtsam.BetweenFactorPose2(j - 4 * P, j, gtsam.Pose2(dx, dy, dth), loop_noise))

    initial, ground_truth = gtsam.Values(), gtsam.Values()
    pose = gtsam.Pose2(*truth[0])
    initial.insert(0, pose)
    for t, (dx, dy, dth) in enumerate(odo_meas.tolist()):
        pose = pose.compose(gtsam.Pose2(dx, dy, dth))
        initial.insert(t + 1, pose)
    for t, (x, y, th) in enumerate(truth.tolist()):
        ground_truth.insert(t, gtsam.Pose2(x, y, th))
    edges = np.r_[np.column_stack([np.arange(steps), np.arange(1, n)]), np.column_stack([closures - 4 * P, closures])]
    information = np.concatenate([np.broadcast_to(np.eye(3) * odometry_information, (steps, 3, 3)),
                                  np.broadcast_to(np.eye(3) * loop_information, (loops, 3, 3))])
    arrays = {"kind": "pose2", "keys": np.arange(n), "poses": gtsam.utilities.extractPose2(initial),
              "edges": edges, "measurements": np.r_[odo_meas, loop_meas], "information": information,
              "prior_keys": np.array([0]), "prior_measurements": truth[:1], "prior_information": np.eye(3) * prior_information}
    return SquareLoops(graph=graph, initial=initial, ground_truth=ground_truth, loops=loops,
                       points_per_side=P, sigma=sigma, seed=seed, arrays=arrays)


@dataclass
class HelixLoops(SquareLoops):
    climb: float = 0.0


def helix_loops(loops: int, points_per_side: int, sigma: float = 0.01, seed: int = 0,
                climb: float = 0.25, loop_sigma: float | None = None, odometry_information: float = 20.0,
                loop_information: float = 100.0, prior_information: float = 100.0) -> HelixLoops:
    """3D model problem: the unit-square loops stacked as a helix climbing ``climb`` per loop.

    Pose3 variables; odometry moves 1/P forward and climb/(4P) up, turning 90° about z at the
    corners; each return above the start adds a loop closure (4P(k−1), 4Pk) measuring (0, 0,
    climb). Noise N(0, σ²) on all six tangent coordinates; weights 20·I and 100·I.
    """
    if loops < 1 or points_per_side < 1:
        raise ValueError("loops and points_per_side must be >= 1")
    rng = np.random.default_rng(seed)
    P = points_per_side
    flat = square_trajectory(loops, P)
    n = len(flat)
    z = np.arange(n) * climb / (4 * P)

    def pose3(x, y, zz, th):
        return gtsam.Pose3(gtsam.Rot3.Rz(th), np.array([x, y, zz]))

    truth = [pose3(x, y, zz, th) for (x, y, th), zz in zip(flat.tolist(), z.tolist())]
    ls = sigma * np.sqrt(odometry_information / loop_information) if loop_sigma is None else loop_sigma
    odo_noise = gtsam.noiseModel.Isotropic.Precision(6, odometry_information)
    loop_noise = gtsam.noiseModel.Isotropic.Precision(6, loop_information)
    graph = gtsam.NonlinearFactorGraph()
    graph.add(gtsam.PriorFactorPose3(0, truth[0], gtsam.noiseModel.Isotropic.Precision(6, prior_information)))
    initial, ground_truth = gtsam.Values(), gtsam.Values()
    initial.insert(0, truth[0])
    pose = truth[0]
    noise = sigma * rng.standard_normal((n - 1, 6))
    for t in range(n - 1):
        meas = truth[t].between(truth[t + 1]).retract(noise[t])
        graph.add(gtsam.BetweenFactorPose3(t, t + 1, meas, odo_noise))
        pose = pose.compose(meas)
        initial.insert(t + 1, pose)
    loop_noise_draw = ls * rng.standard_normal((loops, 6))
    for k in range(1, loops + 1):
        i, j = 4 * P * (k - 1), 4 * P * k
        meas = truth[i].between(truth[j]).retract(loop_noise_draw[k - 1])
        graph.add(gtsam.BetweenFactorPose3(i, j, meas, loop_noise))
    for t, p in enumerate(truth):
        ground_truth.insert(t, p)
    return HelixLoops(graph=graph, initial=initial, ground_truth=ground_truth, loops=loops,
                      points_per_side=P, sigma=sigma, seed=seed, climb=climb)
