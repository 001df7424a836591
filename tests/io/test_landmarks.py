"""Landmarks in g2o files: VERTEX_XY / EDGE_SE2_XY and VERTEX_TRACKXYZ / EDGE_SE3_TRACKXYZ (with g2o's
PARAMS_SE3OFFSET) load as Point values and pose -> point CustomFactors, with analytic Jacobians in
GTSAM's tangent conventions, solve like GTSAM's LM (ours too), and write back exactly."""

import math
import re

import gtsam
import numpy as np
import pytest

import gtsam_schwarz as gs
from gtsam_schwarz.io import GraphFileError, load_graph, write_g2o
from gtsam_schwarz.io.landmarks import (PointObservation, landmark_from_observation, observation_of,
                                        point_observation_factor)


def write(tmp_path, name, text):
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


def num(x):
    return repr(float(x))


FILE_2D = """\
VERTEX_SE2 0 0 0 0
VERTEX_SE2 1 1 0 0.1
VERTEX_SE2 2 2 0.1 0.2
VERTEX_XY 10 1 2
EDGE_SE2 0 1 1 0 0.1 100 0 0 100 0 400
EDGE_SE2 1 2 1 0 0.1 100 0 0 100 0 400
EDGE_SE2_XY 0 10 1.1 1.9 50 1 60
EDGE_SE2_XY 1 10 0.2 2.0 50 0 50
EDGE_SE2_XY 2 10 -0.8 1.9 50 0 50
EDGE_SE2_XY 2 11 1 1 50 0 50
"""


def test_2d_file_loads_landmarks_as_points_and_factors(tmp_path):
    g = load_graph(write(tmp_path, "lm.g2o", FILE_2D))
    assert (g.dimension, g.poses, g.edges, g.landmarks, g.landmark_edges) == (2, 3, 2, 2, 4)
    assert g.warnings == []  # no "unknown tag" any more
    assert g.arrays == {}  # CustomFactors: callers linearize through the gtsam graph
    assert g.graph.size() == 2 + 4 + 1 and g.prior_added
    assert sorted(g.initial.keys()) == [0, 1, 2, 10, 11]
    np.testing.assert_array_equal(g.initial.atPoint2(10), [1.0, 2.0])
    # landmark 11 has no VERTEX_XY: it starts where the first edge that sees it puts it, t_2 + R_2 z
    c, s = math.cos(0.2), math.sin(0.2)
    np.testing.assert_allclose(g.initial.atPoint2(11), [2 + c - s, 0.1 + s + c], rtol=0, atol=1e-15)
    assert [type(g.graph.at(k)) for k in range(g.graph.size())] == (
        [gtsam.BetweenFactorPose2] * 2 + [gtsam.CustomFactor] * 4 + [gtsam.PriorFactorPose2])
    f = g.graph.at(2)
    assert list(f.keys()) == [0, 10]
    np.testing.assert_allclose(f.noiseModel().information(), [[50, 1], [1, 60]], rtol=1e-12)
    obs = observation_of(f)
    assert isinstance(obs, PointObservation) and obs.dim == 2
    assert obs.measured.tolist() == [1.1, 1.9] and obs.information.tolist() == [[50, 1], [1, 60]]


def test_plain_pose_graph_has_no_landmarks(tmp_path):
    g = load_graph(write(tmp_path, "p.g2o", "VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\n"
                                            "EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\n"))
    assert (g.landmarks, g.landmark_edges) == (0, 0) and g.arrays  # the native arrays are still given


# --------------------------------------------------------------------------------- the factor

def _rot2(th):
    return np.array([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]])


def test_2d_error_is_the_hand_computation():
    x, y, th = 0.7, -1.2, 2.5
    l = np.array([3.0, 0.5])
    z = np.array([0.4, -0.9])
    info = np.array([[4.0, 1.0], [1.0, 9.0]])
    f = point_observation_factor(3, 8, z, info)
    v = gtsam.Values()
    v.insert(3, gtsam.Pose2(x, y, th))
    v.insert(8, l)
    dx, dy = l[0] - x, l[1] - y
    e = np.array([math.cos(th) * dx + math.sin(th) * dy - z[0], -math.sin(th) * dx + math.cos(th) * dy - z[1]])
    np.testing.assert_allclose(f.unwhitenedError(v), e, rtol=0, atol=1e-14)
    assert f.error(v) == pytest.approx(0.5 * e @ info @ e, rel=1e-12)


def test_3d_error_is_the_hand_computation_with_and_without_sensor_offset():
    rng = np.random.default_rng(5)
    T = gtsam.Pose3(gtsam.Rot3.RzRyRx(0.3, -1.1, 2.0), np.array([1.0, -2.0, 0.5]))
    l = np.array([2.0, 1.0, -1.0])
    z = rng.normal(size=3)
    info = np.diag([1.0, 2.0, 3.0])
    q = gtsam.Rot3.RzRyRx(0.1, 0.2, -0.3).toQuaternion()
    offset = [0.2, -0.1, 0.3, q.x(), q.y(), q.z(), q.w()]
    O = gtsam.Pose3(gtsam.Rot3.Quaternion(q.w(), q.x(), q.y(), q.z()), np.array(offset[:3]))
    v = gtsam.Values()
    v.insert(1, T)
    v.insert(2, l)
    plain = point_observation_factor(1, 2, z, info)
    np.testing.assert_allclose(plain.unwhitenedError(v), T.rotation().matrix().T @ (l - T.translation()) - z,
                               rtol=0, atol=1e-14)
    with_offset = point_observation_factor(1, 2, z, info, offset=offset)
    np.testing.assert_allclose(with_offset.unwhitenedError(v), T.compose(O).transformTo(l) - z, rtol=0, atol=1e-13)
    # and the landmark that a measurement puts at a pose is the one with zero error
    for f, off in ((plain, None), (with_offset, offset)):
        w = gtsam.Values(v)
        w.update(2, landmark_from_observation(T, z, off))
        np.testing.assert_allclose(f.unwhitenedError(w), 0, atol=1e-13)


def _random_pose(dim, rng, angle):
    if dim == 2:
        return gtsam.Pose2(*rng.normal(size=2), angle)
    axis = rng.normal(size=3)
    return gtsam.Pose3(gtsam.Rot3.Expmap(angle * axis / np.linalg.norm(axis)), rng.normal(size=3))


def _numeric_jacobian(f, values, keys, dims, h=1e-6):
    """Central differences of the unwhitened error through ``values.retract`` (GTSAM's own charts)."""
    cols = []
    for key, d in zip(keys, dims):
        for k in range(d):
            plus, minus = gtsam.VectorValues(), gtsam.VectorValues()
            for other, od in zip(keys, dims):
                step = np.zeros(od)
                if other == key:
                    step[k] = h
                plus.insert(other, step)
                minus.insert(other, -step)
            cols.append((f.unwhitenedError(values.retract(plus)) - f.unwhitenedError(values.retract(minus))) / (2 * h))
    return np.column_stack(cols)


@pytest.mark.parametrize("dim,offset", [(2, False), (3, False), (3, True)])  # EDGE_SE2_XY has no sensor offset
@pytest.mark.parametrize("angle", [0.0, 0.4, -1.3, 2.9, math.pi - 1e-3, -math.pi + 1e-3])
def test_analytic_jacobians_match_central_differences(dim, angle, offset):
    rng = np.random.default_rng(int(1000 * abs(angle)) + dim)
    for _ in range(3):
        pose = _random_pose(dim, rng, angle)
        point = rng.normal(scale=3.0, size=dim)
        z = rng.normal(size=dim)
        off = None
        if offset:
            q = gtsam.Rot3.Expmap(rng.normal(size=3)).toQuaternion()
            off = list(rng.normal(size=3)) + [q.x(), q.y(), q.z(), q.w()]
        f = point_observation_factor(4, 9, z, np.eye(dim), offset=off, noise=gtsam.noiseModel.Unit.Create(dim))
        v = gtsam.Values()
        v.insert(4, pose)
        v.insert(9, point)
        A, b = f.linearize(v).jacobian()  # unit noise: the raw Jacobians [H_pose H_point], b = -e
        np.testing.assert_allclose(b, -f.unwhitenedError(v), rtol=0, atol=1e-14)
        numeric = _numeric_jacobian(f, v, [4, 9], [3 if dim == 2 else 6, dim])
        np.testing.assert_allclose(A, numeric, rtol=0, atol=1e-7)


def test_whitened_error_uses_the_information_matrix():
    info = np.array([[4.0, 1.0], [1.0, 2.0]])
    f = point_observation_factor(0, 1, [1.0, 0.5], info)
    v = gtsam.Values()
    v.insert(0, gtsam.Pose2(0.2, 0.3, 0.4))
    v.insert(1, np.array([1.5, 1.0]))
    e = f.unwhitenedError(v)
    assert f.error(v) == pytest.approx(0.5 * e @ info @ e, rel=1e-12)
    assert observation_of(f) is observation_of(f) and observation_of(f).information.tolist() == info.tolist()
    assert observation_of(gtsam.BetweenFactorPose2(0, 1, gtsam.Pose2(), gtsam.noiseModel.Unit.Create(3))) is None


# ------------------------------------------------------------------------------ synthetic problems

def synthetic(dim: int, seed: int = 0, noise: float = 0.02, poses: int = 12, landmarks: int = 8,
              offset: bool = False, vertices_for_all_landmarks: bool = False):
    """g2o text of a loop of poses seeing landmarks (each landmark by >= 2 poses); VERTEX values are
    the truth perturbed (pose 0 exact), measurements the truth plus ``noise``. Returns (text, truth)."""
    rng = np.random.default_rng(seed)
    truth = {}
    lines = []
    off_pose = None
    if dim == 3 and offset:
        q = gtsam.Rot3.RzRyRx(0.05, -0.1, 0.2).toQuaternion()
        off = [0.1, 0.05, 0.2, q.x(), q.y(), q.z(), q.w()]
        off_pose = gtsam.Pose3(gtsam.Rot3.Quaternion(q.w(), q.x(), q.y(), q.z()), np.array(off[:3]))
        lines.append("PARAMS_SE3OFFSET 7 " + " ".join(num(x) for x in off))
    for k in range(poses):
        a = 2 * math.pi * k / poses
        if dim == 2:
            truth[k] = gtsam.Pose2(5 * math.cos(a), 5 * math.sin(a), a + math.pi / 2)
        else:
            truth[k] = gtsam.Pose3(gtsam.Rot3.RzRyRx(0.1 * math.sin(a), 0.05, a + math.pi / 2),
                                   np.array([5 * math.cos(a), 5 * math.sin(a), 0.3 * math.sin(2 * a)]))
    ids = list(range(100, 100 + landmarks))
    for j in ids:
        truth[j] = rng.uniform(-6, 6, size=dim)
    for k in range(poses):
        p = truth[k]
        if dim == 2:
            if k == 0:
                lines.append(f"VERTEX_SE2 {k} {num(p.x())} {num(p.y())} {num(p.theta())}")
            else:
                g = p.retract(rng.normal(scale=0.05, size=3))
                lines.append(f"VERTEX_SE2 {k} {num(g.x())} {num(g.y())} {num(g.theta())}")
        else:
            g = p if k == 0 else p.retract(rng.normal(scale=0.05, size=6))
            t, q = g.translation(), g.rotation().toQuaternion()
            lines.append(f"VERTEX_SE3:QUAT {k} " + " ".join(num(x) for x in [*t, q.x(), q.y(), q.z(), q.w()]))
    for n, j in enumerate(ids):
        if vertices_for_all_landmarks or n % 2 == 0:  # the others start from their first edge
            tag = "VERTEX_XY" if dim == 2 else "VERTEX_TRACKXYZ"
            lines.append(f"{tag} {j} " + " ".join(num(x) for x in truth[j] + rng.normal(scale=0.1, size=dim)))
    for k in range(poses):
        i, j = k, (k + 1) % poses
        z = truth[i].between(truth[j])
        if dim == 2:
            z = z.retract(rng.normal(scale=noise, size=3))
            lines.append(f"EDGE_SE2 {i} {j} {num(z.x())} {num(z.y())} {num(z.theta())} 400 0 0 400 0 900")
        else:
            z = z.retract(rng.normal(scale=noise, size=6))
            t, q = z.translation(), z.rotation().toQuaternion()
            info = np.diag([400.0, 400, 400, 900, 900, 900])
            lines.append(f"EDGE_SE3:QUAT {i} {j} " + " ".join(num(x) for x in [*t, q.x(), q.y(), q.z(), q.w()])
                         + " " + " ".join(num(x) for x in info[np.triu_indices(6)]))
    for n, j in enumerate(ids):
        for k in sorted({(3 * n) % poses, (3 * n + 5) % poses, (7 * n + 1) % poses}):
            frame = truth[k] if off_pose is None else truth[k].compose(off_pose)
            l = truth[j]
            if dim == 2:
                z = frame.transformTo(l) + rng.normal(scale=noise, size=2)
                a, b = rng.uniform(20, 60, size=2)
                c = rng.uniform(-5, 5)
                lines.append(f"EDGE_SE2_XY {k} {j} {num(z[0])} {num(z[1])} {num(a)} {num(c)} {num(b)}")
            else:
                z = frame.transformTo(l) + rng.normal(scale=noise, size=3)
                info = np.diag(rng.uniform(20, 60, size=3))
                info[0, 1] = info[1, 0] = rng.uniform(-5, 5)
                param = "7 " if off_pose is not None else "0 "
                lines.append(f"EDGE_SE3_TRACKXYZ {k} {j} {param}" + " ".join(num(x) for x in z) + " "
                             + " ".join(num(x) for x in info[np.triu_indices(3)]))
    if dim == 3 and not offset:
        lines.insert(0, "PARAMS_SE3OFFSET 0 0 0 0 0 0 0 1")
    return "\n".join(lines) + "\n", truth


def _lm(graph, initial):
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-12)
    params.setAbsoluteErrorTol(1e-15)
    params.setMaxIterations(200)
    result = gtsam.LevenbergMarquardtOptimizer(graph, initial, params).optimize()
    return result, graph.error(result)


@pytest.mark.parametrize("dim", [2, 3])
def test_gtsam_lm_recovers_the_truth_from_exact_measurements(tmp_path, dim):
    text, truth = synthetic(dim, seed=1, noise=0.0)
    g = load_graph(write(tmp_path, "exact.g2o", text))
    assert (g.poses, g.landmarks, g.warnings) == (12, 8, [])
    assert g.graph.error(g.initial) > 1.0
    result, error = _lm(g.graph, g.initial)
    assert error < 1e-12
    for key, value in truth.items():
        if key < 100:
            at = result.atPose2 if dim == 2 else result.atPose3
            assert at(key).equals(value, 1e-6)
        else:
            at = result.atPoint2 if dim == 2 else result.atPoint3
            np.testing.assert_allclose(at(key), value, atol=1e-6)


@pytest.mark.parametrize("dim,offset", [(2, False), (3, False), (3, True)])
@pytest.mark.parametrize("preconditioner", ["auto", "gdsw"])
def test_schwarz_optimizer_reaches_gtsam_lm_error(tmp_path, dim, offset, preconditioner):
    text, _ = synthetic(dim, seed=2, noise=0.02, offset=offset)
    g = load_graph(write(tmp_path, "noisy.g2o", text))
    _, reference = _lm(g.graph, g.initial)
    assert reference > 1e-3  # noisy: a non-trivial optimum
    params = gs.SchwarzParams(initialization="file", preconditioner=preconditioner,
                              subdomains=2 if preconditioner == "gdsw" else None)
    optimizer = gs.SchwarzOptimizer(g.graph, g.initial, params)
    result = optimizer.optimize()
    assert optimizer.error() == pytest.approx(reference, rel=1e-6)
    assert g.graph.error(result) == pytest.approx(reference, rel=1e-6)
    assert result.size() == g.initial.size()


@pytest.mark.parametrize("dim,offset", [(2, False), (3, False), (3, True)])
def test_write_load_round_trip_keeps_landmarks_and_error(tmp_path, dim, offset):
    text, _ = synthetic(dim, seed=3, offset=offset)
    src = write(tmp_path, "in.g2o", text)
    a = load_graph(src)
    result, error = _lm(a.graph, a.initial)
    out = tmp_path / "out.g2o"
    write_g2o(out, a.graph, result, input_path=src)
    b = load_graph(out)
    assert (b.poses, b.edges, b.landmarks, b.landmark_edges) == (a.poses, a.edges, a.landmarks, a.landmark_edges)
    assert b.initial_guess == "file" and not b.prior_added and b.warnings == []
    assert sorted(b.initial.keys()) == sorted(result.keys())
    assert b.initial.equals(result, 1e-12)
    assert b.graph.error(result) == pytest.approx(error, rel=1e-9)
    assert b.graph.error(a.initial) == pytest.approx(a.graph.error(a.initial), rel=1e-9)
    # landmark edges come back with exactly the file's numbers
    tag = "EDGE_SE2_XY" if dim == 2 else "EDGE_SE3_TRACKXYZ"

    def records(t):
        return [[float(x) for x in line.split()[1:]] for line in t.splitlines() if line.startswith(tag)]
    assert records(out.read_text()) == records(text)
    if offset:
        assert "PARAMS_SE3OFFSET 7 " in out.read_text()
    vertex = "VERTEX_XY" if dim == 2 else "VERTEX_TRACKXYZ"
    assert sum(line.startswith(vertex) for line in out.read_text().splitlines()) == a.landmarks


def test_writer_takes_the_noise_model_over_a_different_stored_information(tmp_path):
    # (a CustomFactor cannot be cloned in gtsam 4.3; a factor made with another noise model stands in for
    # one whose model was replaced)
    a = load_graph(write(tmp_path, "lm.g2o", FILE_2D))
    graph = gtsam.NonlinearFactorGraph()
    for k in range(a.graph.size()):
        f = a.graph.at(k)
        obs = observation_of(f)
        if obs is not None:
            i, j = f.keys()
            f = point_observation_factor(i, j, obs.measured, obs.information,
                                         noise=gtsam.noiseModel.Gaussian.Information(np.diag([7.0, 3.0])))
        graph.add(f)
    write_g2o(tmp_path / "out.g2o", graph, a.initial)
    xy = [line for line in (tmp_path / "out.g2o").read_text().splitlines() if line.startswith("EDGE_SE2_XY")]
    assert len(xy) == 4
    np.testing.assert_allclose([[float(x) for x in line.split()[5:]] for line in xy], [[7.0, 0.0, 3.0]] * 4,
                               rtol=1e-12, atol=1e-12)  # the model's information() is R^T R: not bit-exact


def test_landmarks_join_pose_chains_that_share_no_pose_edge(tmp_path):
    # poses 0-1 and 2-3 meet only at landmarks 8 and 9: one component, one gauge prior, a well-posed problem
    # (with a single shared landmark the second chain could still turn about it: connectivity is necessary,
    # not sufficient)
    truth = {0: (0, 0), 1: (1, 0), 2: (0, 2), 3: (1, 2)}
    marks = {8: (1.5, 1.0), 9: (0.5, 1.5)}
    obs = "".join(f"EDGE_SE2_XY {i} {j} {num(l[0] - t[0])} {num(l[1] - t[1])} 10 0 10\n"
                  for j, l in marks.items() for i, t in truth.items())
    text = ("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1.1 0 0\nVERTEX_SE2 2 0.1 2.1 0.05\nVERTEX_SE2 3 1.2 1.9 -0.05\n"
            "EDGE_SE2 0 1 1 0 0 100 0 0 100 0 100\nEDGE_SE2 2 3 1 0 0 100 0 0 100 0 100\n" + obs)
    g = load_graph(write(tmp_path, "join.g2o", text))
    assert g.prior_added and (g.landmarks, g.landmark_edges) == (2, 8)
    result, error = _lm(g.graph, g.initial)
    assert error < 1e-12
    for key, (x, y) in truth.items():
        assert result.atPose2(key).equals(gtsam.Pose2(x, y, 0), 1e-6)
    # without the landmarks the chains fall apart: the usual connectivity error
    cut = "\n".join(line for line in text.splitlines() if "_XY" not in line) + "\n"
    with pytest.raises(GraphFileError, match=r"join\.g2o:3: pose 2 is not connected to pose 0"):
        load_graph(write(tmp_path, "join.g2o", cut))


def test_fix_on_a_landmark_is_a_point_prior_and_written_back(tmp_path):
    g = load_graph(write(tmp_path, "fix.g2o", FILE_2D + "FIX 10\n"))
    assert not g.prior_added
    last = g.graph.at(g.graph.size() - 1)
    assert isinstance(last, gtsam.PriorFactorPoint2) and list(last.keys()) == [10]
    write_g2o(tmp_path / "out.g2o", g.graph, g.initial)
    assert (tmp_path / "out.g2o").read_text().splitlines()[-1] == "FIX 10"


def test_edges_only_file_starts_landmarks_from_the_spanning_tree(tmp_path):
    text = "EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\nEDGE_SE2_XY 1 5 0 2 1 0 1\nEDGE_SE2_XY 0 5 1 2 1 0 1\n"
    g = load_graph(write(tmp_path, "edges.g2o", text))
    assert g.initial_guess == "spanning-tree" and g.graph.error(g.initial) == pytest.approx(0, abs=1e-9)
    np.testing.assert_allclose(g.initial.atPoint2(5), [1.0, 2.0])


def test_write_refuses_foreign_custom_factors(tmp_path):
    g = load_graph(write(tmp_path, "lm.g2o", FILE_2D))
    graph = gtsam.NonlinearFactorGraph(g.graph)
    graph.add(gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(2), [0, 10], lambda this, v, H: np.zeros(2)))
    out = tmp_path / "out.g2o"
    with pytest.raises(GraphFileError, match=re.escape(f"{out}: cannot write factor 7 (CustomFactor)")):
        write_g2o(out, graph, g.initial)
    assert not out.exists()


# ------------------------------------------------------------------------------ bad input

V = "VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\nEDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\n"
V3 = ("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nVERTEX_SE3:QUAT 1 1 0 0 0 0 0 1\n"
      "EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1 " + " ".join(["1", "0", "0", "0", "0", "0"] * 3 + ["1", "0", "1"]) + "\n")
BAD = {
    "unknown-pose": (V + "EDGE_SE2_XY 7 10 1 1 1 0 1\n", 4,
                     "landmark edge 7 -> 10 references pose 7, which has no VERTEX_SE2 line"),
    "unknown-pose-edges-only": ("EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\nEDGE_SE2_XY 7 10 1 1 1 0 1\n", 2,
                                "landmark edge 7 -> 10 references pose 7, which has no VERTEX_SE2 line and no "
                                "pose-pose edge (no initial guess for it)"),
    "duplicate-id": (V + "VERTEX_XY 1 3 4\n", 4, "duplicate vertex id 1 (first defined at line 2)"),
    "pose-as-landmark": (V + "EDGE_SE2_XY 0 1 1 1 1 0 1\n", 4, "landmark edge 0 -> 1 references pose 1 as its landmark"),
    "landmark-as-pose": (V + "VERTEX_XY 5 1 1\nEDGE_SE2_XY 0 5 1 1 1 0 1\nEDGE_SE2_XY 5 6 1 1 1 0 1\n", 6,
                         "landmark edge 5 -> 6 references landmark 5 as its pose"),
    "landmark-in-pose-edge": (V + "VERTEX_XY 5 1 1\nEDGE_SE2 0 5 1 0 0 1 0 0 1 0 1\n", 5,
                              "edge 0 -> 5 references landmark 5, not a pose"),
    "self-observation": (V + "EDGE_SE2_XY 1 1 1 1 1 0 1\n", 4, "observes itself"),
    "unseen-landmark": (V + "VERTEX_XY 5 1 1\n", 4, "landmark 5 is not seen by any pose (no EDGE_SE2_XY names it)"),
    "too-few-fields": (V + "EDGE_SE2_XY 0 5 1 1 1 0\n", 4, "too few fields for EDGE_SE2_XY: expected 7"),
    "bad-number": (V + "EDGE_SE2_XY 0 5 1 x 1 0 1\n", 4, "EDGE_SE2_XY 0 -> 5: field 'dy' is not a number"),
    "3d-in-2d": (V + "VERTEX_TRACKXYZ 5 1 1 1\n", 4, "VERTEX_TRACKXYZ is a 3D record but the file is 2D"),
    "3d-no-param-id": (V3 + "EDGE_SE3_TRACKXYZ 0 5 1 1 1 1 0 0 1 0 1\n", 4,
                       "too few fields for EDGE_SE3_TRACKXYZ: expected 12 (i j param dx dy dz"),
    "3d-unknown-param": (V3 + "EDGE_SE3_TRACKXYZ 0 5 3 1 1 1 1 0 0 1 0 1\n", 4,
                         "EDGE_SE3_TRACKXYZ uses sensor offset parameter 3, which has no PARAMS_SE3OFFSET line"),
    "3d-duplicate-param": ("PARAMS_SE3OFFSET 0 0 0 0 0 0 0 1\nPARAMS_SE3OFFSET 0 0 0 0 0 0 0 1\n" + V3, 2,
                           "duplicate parameter id 0 (first defined at line 1)"),
    "3d-bad-offset-quaternion": ("PARAMS_SE3OFFSET 0 0 0 0 0 0 0 2\n" + V3, 1,
                                 "PARAMS_SE3OFFSET 0: quaternion (qx qy qz qw) has norm 2"),
}


@pytest.mark.parametrize("case", list(BAD))
def test_bad_landmark_input_gives_one_line_error(tmp_path, case):
    text, line, what = BAD[case]
    path = write(tmp_path, "bad.g2o", text)
    with pytest.raises(GraphFileError) as info:
        load_graph(path)
    message = str(info.value)
    assert "\n" not in message
    assert message.startswith(f"{path}:{line}: "), message
    assert what in message, message


def test_landmark_information_not_positive_definite_is_repaired_or_refused(tmp_path):
    path = write(tmp_path, "pd.g2o", FILE_2D.replace("EDGE_SE2_XY 1 10 0.2 2.0 50 0 50",
                                                     "EDGE_SE2_XY 1 10 0.2 2.0 1 2 1"))
    g = load_graph(path)
    assert len(g.warnings) == 1
    assert g.warnings[0].startswith(f"{path}:8: information matrix of landmark edge 1 -> 10 is not symmetric "
                                    f"positive definite; 1 information matrix repaired")
    assert np.all(np.linalg.eigvalsh(g.graph.at(3).noiseModel().information()) > 0)
    with pytest.raises(GraphFileError, match=re.escape(f"{path}:8: information matrix of landmark edge 1 -> 10 "
                                                       f"is not symmetric positive definite")):
        load_graph(path, strict=True)


def test_landmark_edges_alone_with_a_single_pose(tmp_path):
    text = "VERTEX_SE2 0 0 0 0\nEDGE_SE2_XY 0 1 1 2 1 0 1\nEDGE_SE2_XY 0 2 3 4 1 0 1\n"
    g = load_graph(write(tmp_path, "one.g2o", text))
    assert (g.poses, g.edges, g.landmarks, g.landmark_edges) == (1, 0, 2, 2)
    np.testing.assert_allclose(g.initial.atPoint2(2), [3, 4])
