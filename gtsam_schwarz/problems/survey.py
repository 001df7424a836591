"""Survey pose graphs on which sparse direct factorization fills in: a lawnmower (boustrophedon)
survey of an R × C grid in 2D, and a stack of such floors in 3D.

Unlike the paper's multi-loop model problem, whose Cholesky factor has hardly more entries than H,
these graphs are grids: each pose is linked to its neighbour along the row (odometry) and to the
pose directly below it in the previous row (loop closure), and in 3D also to the pose directly
below it on the floor beneath. A nested-dissection factor of an n-pose grid has O(n log n) entries
in 2D and O(n^{4/3}) in 3D, and its factorization costs O(n^{3/2}) and O(n²) flops.

Noise and weights follow :func:`~gtsam_schwarz.problems.loops.square_loops`: odometry measures the
true relative pose plus N(0, σ²) noise on every tangent coordinate with weight 20·I, loop closures
with noise σ·√(20/100) and weight 100·I, and a prior (weight 100·I) on pose 0 at its true value.
The initial guess is dead reckoning (the noisy odometry composed from pose 0).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import gtsam
import numpy as np


@dataclass
class Survey:
    """A survey problem: its numbers in ``arrays``, its GTSAM objects (``graph``, ``initial``,
    ``ground_truth``) built from them on first use — a solve from the arrays never needs them
    (1M 2D poses: ~0.6 GB of GTSAM factors and Values, ~35 s to build)."""

    floors: int
    rows: int
    cols: int
    sigma: float
    seed: int
    closures: int  # loop-closure factors (within floors and between floors)
    spacing: float = 1.0
    floor_height: float = 1.0
    # the graph as numpy arrays (NativeLinearizer.from_arrays(**arrays)), as square_loops gives them
    arrays: dict | None = None
    _make: dict[str, Callable] = field(default_factory=dict, repr=False, compare=False)  # name → builder
    _made: dict = field(default_factory=dict, repr=False, compare=False)

    def _gtsam(self, name: str):
        if name not in self._made:
            self._made[name] = self._make.pop(name)()
        return self._made[name]

    @property
    def graph(self) -> gtsam.NonlinearFactorGraph:
        return self._gtsam("graph")

    @property
    def initial(self) -> gtsam.Values:
        """Dead reckoning from the noisy odometry."""
        return self._gtsam("initial")

    @property
    def ground_truth(self) -> gtsam.Values:
        return self._gtsam("ground_truth")

    @property
    def poses(self) -> int:
        return self.floors * self.rows * self.cols

    @property
    def dimension(self) -> int:
        """2 (Pose2, :func:`lawnmower`) or 3 (Pose3, :func:`survey3d`)."""
        return 2 if isinstance(self, Lawnmower) else 3


class Lawnmower(Survey):
    """A 2D lawnmower survey (``floors == 1``, Pose2)."""


class Survey3D(Survey):
    """A 3D survey of stacked lawnmower floors (Pose3)."""


def lawnmower_cells(rows: int, cols: int) -> tuple[np.ndarray, np.ndarray]:
    """(row, column) of pose t of a boustrophedon sweep: row r left to right for even r, right to
    left for odd r, so that consecutive poses are grid neighbours."""
    t = np.arange(rows * cols)
    r, k = t // cols, t % cols
    return r, np.where(r % 2 == 0, k, cols - 1 - k)


def _grid_edges(lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """Closures between the poses ``lower`` and ``upper`` (arrays of pose numbers, side by side in
    the grid), as (earlier, later) pairs, except pairs that are consecutive along the trajectory
    (a row turn, or the climb to the next floor): odometry already links those."""
    a, b = np.minimum(lower, upper).ravel(), np.maximum(lower, upper).ravel()
    keep = b != a + 1
    return np.stack([a[keep], b[keep]], axis=1)


def _wrap(a):
    return (a + np.pi) % (2 * np.pi) - np.pi


def _between2(p, q):
    """Pose2 between(p_i, q_i) for arrays of (x, y, θ)."""
    c, s = np.cos(p[:, 2]), np.sin(p[:, 2])
    dx, dy = q[:, 0] - p[:, 0], q[:, 1] - p[:, 1]
    return np.column_stack([c * dx + s * dy, -s * dx + c * dy, _wrap(q[:, 2] - p[:, 2])])


def _dead_reckoning2(start, odo):
    """Compose Pose2 steps (dx, dy, dθ) from ``start``: θ by a cumulative sum, then positions."""
    theta = start[2] + np.r_[0.0, np.cumsum(odo[:, 2])]
    c, s = np.cos(theta[:-1]), np.sin(theta[:-1])
    step = np.column_stack([c * odo[:, 0] - s * odo[:, 1], s * odo[:, 0] + c * odo[:, 1]])
    xy = start[:2] + np.vstack([np.zeros((1, 2)), np.cumsum(step, axis=0)])
    return np.column_stack([xy, _wrap(theta)])


def _noise_sigmas(sigma, loop_sigma, odometry_information, loop_information):
    ls = sigma * np.sqrt(odometry_information / loop_information) if loop_sigma is None else loop_sigma
    return float(sigma), float(ls)


def _check(**sizes):
    for name, v in sizes.items():
        if int(v) != v or v < 1:
            raise ValueError(f"{name} must be an integer >= 1, got {v!r}")


def lawnmower(rows: int, cols: int, sigma: float = 0.01, seed: int = 0, spacing: float = 1.0,
              loop_sigma: float | None = None, odometry_information: float = 20.0,
              loop_information: float = 100.0, prior_information: float = 100.0) -> Lawnmower:
    """A robot surveying an R × C grid row by row (boustrophedon), Pose2.

    Pose t = r·C + k sits at row r, column k (even r) or C−1−k (odd r), position ``spacing`` ×
    (column, row), heading 0 on even rows and π on odd rows. Odometry links consecutive poses
    (along the row, and one step up with a half turn at the row ends); a loop closure links every
    pose of row r ≥ 1 to the pose directly below it in row r−1, except the first pose of each row,
    whose pose below is its odometry predecessor. Factors: 1 prior, R·C − 1 odometry,
    (R − 1)(C − 1) closures.
    """
    _check(rows=rows, cols=cols)
    rng = np.random.default_rng(seed)
    sigma, ls = _noise_sigmas(sigma, loop_sigma, odometry_information, loop_information)
    n = rows * cols
    r, c = lawnmower_cells(rows, cols)
    truth = np.column_stack([spacing * c, spacing * r, np.where(r % 2 == 0, 0.0, np.pi)])
    index = np.empty((rows, cols), dtype=np.int64)
    index[r, c] = np.arange(n)
    loops = _grid_edges(index[:-1], index[1:])

    odo = _between2(truth[:-1], truth[1:])
    odo_meas = odo + sigma * rng.standard_normal(odo.shape)
    loop_meas = _between2(truth[loops[:, 0]], truth[loops[:, 1]]) + ls * rng.standard_normal((len(loops), 3))
    dead = _dead_reckoning2(truth[0], odo_meas)

    edges = np.r_[np.column_stack([np.arange(n - 1), np.arange(1, n)]), loops]
    measurements = np.r_[odo_meas, loop_meas]
    information = np.r_[np.full(n - 1, odometry_information), np.full(len(loops), loop_information)]
    arrays = {"kind": "pose2", "keys": np.arange(n), "poses": dead, "edges": edges,
              "measurements": measurements, "information": information[:, None, None] * np.eye(3),
              "prior_keys": np.array([0]), "prior_measurements": truth[:1],
              "prior_information": np.eye(3) * prior_information}

    def make_graph() -> gtsam.NonlinearFactorGraph:
        graph = gtsam.NonlinearFactorGraph()
        graph.add(gtsam.PriorFactorPose2(0, gtsam.Pose2(*truth[0]),
                                         gtsam.noiseModel.Isotropic.Precision(3, prior_information)))
        Between, Pose2 = gtsam.BetweenFactorPose2, gtsam.Pose2
        for weight, part in ((odometry_information, slice(0, n - 1)), (loop_information, slice(n - 1, None))):
            noise = gtsam.noiseModel.Isotropic.Precision(3, weight)
            for (i, j), (dx, dy, dth) in zip(edges[part].tolist(), measurements[part].tolist()):
                graph.add(Between(i, j, Pose2(dx, dy, dth), noise))
        return graph

    return Lawnmower(floors=1, rows=rows, cols=cols, sigma=sigma, seed=seed, closures=len(loops),
                     spacing=spacing, arrays=arrays, _make={"graph": make_graph, "initial": lambda: _values2(dead),
                                                           "ground_truth": lambda: _values2(truth)})


def _values2(poses: np.ndarray) -> gtsam.Values:
    """gtsam Values of Pose2 rows (x, y, θ), keys 0..n−1."""
    values = gtsam.Values()
    for t, (x, y, th) in enumerate(poses.tolist()):
        values.insert(t, gtsam.Pose2(x, y, th))
    return values


# -- Pose3 helpers on arrays: rotations (m, 3, 3), translations (m, 3) ---------------------------
def _hat(w):
    W = np.zeros(w.shape[:-1] + (3, 3))
    W[..., 0, 1], W[..., 0, 2], W[..., 1, 2] = -w[..., 2], w[..., 1], -w[..., 0]
    return W - np.swapaxes(W, -1, -2)


def _expmap3(xi):
    """SE(3) exponential of GTSAM tangent vectors (ω, v): (R, t) arrays."""
    w, v = xi[:, :3], xi[:, 3:]
    th = np.linalg.norm(w, axis=1)[:, None, None]
    small = th < 1e-8
    ths = np.where(small, 1.0, th)
    A = np.where(small, 1.0, np.sin(ths) / ths)
    B = np.where(small, 0.5, (1 - np.cos(ths)) / ths**2)
    C = np.where(small, 1.0 / 6.0, (ths - np.sin(ths)) / ths**3)
    W = _hat(w)
    W2 = W @ W
    eye = np.eye(3)[None]
    R = eye + A * W + B * W2
    V = eye + B * W + C * W2
    return R, np.einsum("mij,mj->mi", V, v)


def _rz(theta):
    c, s = np.cos(theta), np.sin(theta)
    R = np.zeros((len(theta), 3, 3))
    R[:, 0, 0], R[:, 0, 1], R[:, 1, 0], R[:, 1, 1], R[:, 2, 2] = c, -s, s, c, 1.0
    return R


def _between3(Ra, ta, Rb, tb):
    RaT = np.swapaxes(Ra, 1, 2)
    return RaT @ Rb, np.einsum("mij,mj->mi", RaT, tb - ta)


def _pose3(R, t):
    return gtsam.Pose3(gtsam.Rot3(R), t)


def survey3d(floors: int, rows: int, cols: int, sigma: float = 0.01, seed: int = 0,
             spacing: float = 1.0, floor_height: float = 1.0, loop_sigma: float | None = None,
             odometry_information: float = 20.0, loop_information: float = 100.0,
             prior_information: float = 100.0) -> Survey3D:
    """A drone mapping a building floor by floor, Pose3: ``floors`` lawnmower surveys of an
    R × C grid stacked ``floor_height`` apart.

    Floor f sweeps its grid as :func:`lawnmower` does on even floors and in reverse order on odd
    floors (heading turned by π), so the first pose of each floor lies directly above the last
    pose of the floor beneath, and odometry climbs straight up between them. Loop closures link
    each pose to the pose directly below it in the previous row of its floor (as in
    :func:`lawnmower`) and to the pose directly below it on the floor beneath (except where that
    pose is its odometry predecessor). Noise N(0, σ²) on all six tangent coordinates (measured
    = true ⊕ Exp(noise)), weights 20·I (odometry) and 100·I (closures), a prior on pose 0.
    """
    _check(floors=floors, rows=rows, cols=cols)
    rng = np.random.default_rng(seed)
    sigma, ls = _noise_sigmas(sigma, loop_sigma, odometry_information, loop_information)
    m = rows * cols
    n = floors * m
    r, c = lawnmower_cells(rows, cols)
    heading = np.where(r % 2 == 0, 0.0, np.pi)
    f = np.repeat(np.arange(floors), m)
    k = np.tile(np.arange(m), floors)
    cell = np.where(f % 2 == 0, k, m - 1 - k)  # odd floors retrace the sweep backwards
    th = np.where(f % 2 == 0, heading[cell], heading[cell] + np.pi)
    pos = np.column_stack([spacing * c[cell], spacing * r[cell], floor_height * f])
    R = _rz(_wrap(th))
    index = np.empty((floors, rows, cols), dtype=np.int64)
    index[f, r[cell], c[cell]] = np.arange(n)
    loops = np.concatenate([_grid_edges(index[:, :-1], index[:, 1:]),  # rows side by side on a floor
                            _grid_edges(index[:-1], index[1:])])  # floors on top of each other

    # measurements: true relative pose ⊕ Exp(noise)
    Ro, to = _between3(R[:-1], pos[:-1], R[1:], pos[1:])
    Rn, tn = _expmap3(sigma * rng.standard_normal((n - 1, 6)))
    Ro, to = Ro @ Rn, to + np.einsum("mij,mj->mi", Ro, tn)
    Rl, tl = _between3(R[loops[:, 0]], pos[loops[:, 0]], R[loops[:, 1]], pos[loops[:, 1]])
    Rn, tn = _expmap3(ls * rng.standard_normal((len(loops), 6)))
    Rl, tl = Rl @ Rn, tl + np.einsum("mij,mj->mi", Rl, tn)

    # the dead-reckoning start, composed by GTSAM (its Pose3 compose), read back for the arrays
    initial = gtsam.Values()
    pose = _pose3(R[0], pos[0])
    initial.insert(0, pose)
    for t, (a, b) in enumerate(zip(Ro, to)):
        pose = pose.compose(_pose3(a, b))
        initial.insert(t + 1, pose)
    edges = np.r_[np.column_stack([np.arange(n - 1), np.arange(1, n)]), loops]
    rotations, translations = np.r_[Ro, Rl], np.r_[to, tl]
    information = np.r_[np.full(n - 1, odometry_information), np.full(len(loops), loop_information)]
    arrays = {"kind": "pose3", "keys": np.arange(n), "poses": gtsam.utilities.extractPose3(initial),
              "edges": edges, "measurements": (rotations, translations),
              "information": information[:, None, None] * np.eye(6), "prior_keys": np.array([0]),
              "prior_measurements": (R[:1], pos[:1]), "prior_information": np.eye(6) * prior_information}

    def make_graph() -> gtsam.NonlinearFactorGraph:
        graph = gtsam.NonlinearFactorGraph()
        graph.add(gtsam.PriorFactorPose3(0, _pose3(R[0], pos[0]),
                                         gtsam.noiseModel.Isotropic.Precision(6, prior_information)))
        for weight, part in ((odometry_information, slice(0, n - 1)), (loop_information, slice(n - 1, None))):
            noise = gtsam.noiseModel.Isotropic.Precision(6, weight)
            for (i, j), a, b in zip(edges[part].tolist(), rotations[part], translations[part]):
                graph.add(gtsam.BetweenFactorPose3(i, j, _pose3(a, b), noise))
        return graph

    def make_ground_truth() -> gtsam.Values:
        ground_truth = gtsam.Values()
        for t in range(n):
            ground_truth.insert(t, _pose3(R[t], pos[t]))
        return ground_truth

    return Survey3D(floors=floors, rows=rows, cols=cols, sigma=sigma, seed=seed, closures=len(loops),
                    spacing=spacing, floor_height=floor_height, arrays=arrays,
                    _make={"graph": make_graph, "ground_truth": make_ground_truth}, _made={"initial": initial})
