"""Pose-graph file I/O: datasets vs gtsam.readG2o, TORO/Pose3 information order, spanning-tree guess,
gauge prior, atomic g2o writing, and a one-line GraphFileError for every kind of bad input."""

import os
import pathlib
import re

import gtsam
import numpy as np
import pytest
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from conftest import dataset
import gtsam_schwarz.io.atomic as gatomic
import gtsam_schwarz.io.g2o as gio
from gtsam_schwarz.io import GraphFileError, LoadedGraph, load_graph, write_g2o

# name: (dimension, poses, edges, format, initial guess) -- the datasets README
DATASETS = {
    "input_M3500_g2o.g2o": (2, 3500, 5453, "g2o", "file"),
    "input_M3500a_g2o.g2o": (2, 3500, 5453, "g2o", "file"),
    "input_INTEL_g2o.g2o": (2, 1228, 1483, "g2o", "file"),
    "MIT.g2o": (2, 808, 827, "g2o", "file"),
    "CSAIL_P_toro.graph": (2, 1045, 1172, "toro", "file"),
    "city10000.g2o": (2, 10000, 20687, "g2o", "file"),
    "kitti_00.g2o": (2, 4541, 4677, "g2o", "spanning-tree"),
    "sphere2500.g2o": (3, 2500, 4949, "g2o", "file"),
    "torus3D.g2o": (3, 5000, 9048, "g2o", "file"),
    "parking-garage.g2o": (3, 1661, 6275, "g2o", "file"),
    "smallGrid3D.g2o": (3, 125, 297, "g2o", "file"),
    "tinyGrid3D.g2o": (3, 9, 11, "g2o", "file"),
}
G2O_DATASETS = [name for name in DATASETS if name.endswith(".g2o")]

_cache: dict[tuple, LoadedGraph] = {}


def loaded(name: str, add_prior: bool = True) -> LoadedGraph:
    """load_graph of a dataset, cached across tests (the loader is deterministic)."""
    key = (name, add_prior)
    if key not in _cache:
        _cache[key] = load_graph(dataset(name), add_prior=add_prior)
    return _cache[key]


def perturbed(values: gtsam.Values, seed: int) -> gtsam.Values:
    """A copy of the values with every pose moved randomly (GTSAM's own perturbation)."""
    out = gtsam.Values(values)
    if gtsam.utilities.allPose2s(values).size():
        gtsam.utilities.perturbPose2(out, 0.1, 0.05, seed)
    else:
        gtsam.utilities.perturbPose3(out, 0.1, 0.05, seed)
    return out


def factor_keys(graph: gtsam.NonlinearFactorGraph) -> list[tuple[int, ...]]:
    return [tuple(graph.at(k).keys()) for k in range(graph.size())]


def assert_same_error(a: gtsam.NonlinearFactorGraph, b: gtsam.NonlinearFactorGraph, values: gtsam.Values,
                      seeds=(1, 2, 3), rtol=1e-9):
    """Same error at the values and at a few random perturbations of them."""
    for v in [values] + [perturbed(values, s) for s in seeds]:
        ea, eb = a.error(v), b.error(v)
        assert abs(ea - eb) <= rtol * abs(eb), (ea, eb)


def assert_same_graph(a: LoadedGraph, b: LoadedGraph):
    """Same factors (keys, errors) and the same initial values."""
    assert (a.dimension, a.poses, a.edges) == (b.dimension, b.poses, b.edges)
    assert factor_keys(a.graph) == factor_keys(b.graph)
    assert a.initial.equals(b.initial, 1e-9)
    assert_same_error(a.graph, b.graph, a.initial)


def write(tmp_path: pathlib.Path, name: str, text: str) -> pathlib.Path:
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


def count_priors(graph) -> list:
    return [graph.at(k) for k in range(graph.size())
            if isinstance(graph.at(k), (gtsam.PriorFactorPose2, gtsam.PriorFactorPose3))]


# ------------------------------------------------------------------------------------ datasets

@pytest.mark.datasets
@pytest.mark.parametrize("name", list(DATASETS))
def test_dataset_loads_with_readme_counts(name):
    dim, poses, edges, fmt, guess = DATASETS[name]
    g = loaded(name)
    assert (g.dimension, g.poses, g.edges, g.format, g.initial_guess) == (dim, poses, edges, fmt, guess)
    assert g.initial.size() == poses
    assert g.prior_added and g.graph.size() == edges + 1 and len(count_priors(g.graph)) == 1
    assert g.warnings == []
    assert g.path == str(dataset(name))


@pytest.mark.datasets
@pytest.mark.parametrize("name", G2O_DATASETS)
def test_agrees_with_gtsam_readG2o(name):
    g = loaded(name, add_prior=False)
    ref_graph, ref_values = gtsam.readG2o(str(dataset(name)), g.dimension == 3)
    assert g.graph.size() == ref_graph.size() == g.edges
    assert factor_keys(g.graph) == factor_keys(ref_graph)
    if g.initial_guess == "file":
        assert g.initial.equals(ref_values, 1e-9)
    else:  # kitti: readG2o chains edges in file order, we chain along a BFS tree: same poses, other guess
        assert sorted(g.initial.keys()) == sorted(ref_values.keys())
    assert_same_error(g.graph, ref_graph, g.initial)
    assert_same_error(g.graph, ref_graph, ref_values, seeds=(4,))


@pytest.mark.datasets
def test_toro_dataset_agrees_with_gtsam_load2D_toro_order():
    g = loaded("CSAIL_P_toro.graph", add_prior=False)
    ref_graph, ref_values = gtsam.load2D(str(dataset("CSAIL_P_toro.graph")),
                                         noiseFormat=gtsam.NoiseFormat.NoiseFormatTORO)
    assert factor_keys(g.graph) == factor_keys(ref_graph)
    assert g.initial.equals(ref_values, 1e-9)
    assert_same_error(g.graph, ref_graph, g.initial)


def test_toro_information_order_matches_equivalent_g2o(tmp_path):
    # information matrix [[xx xy xt], [xy yy yt], [xt yt tt]] with all entries distinct
    xx, xy, xt, yy, yt, tt = 10.0, 1.0, 2.0, 20.0, 3.0, 30.0
    vertices = "VERTEX2 0 0 0 0\nVERTEX2 1 1.0 0.5 0.1\n"
    toro = write(tmp_path, "two.graph", vertices + f"EDGE2 0 1 1.1 0.4 0.2 {xx} {xy} {yy} {tt} {xt} {yt}\n")
    g2o = write(tmp_path, "two.g2o", vertices.replace("VERTEX2", "VERTEX_SE2")
                + f"EDGE_SE2 0 1 1.1 0.4 0.2 {xx} {xy} {xt} {yy} {yt} {tt}\n")
    a, b = load_graph(toro), load_graph(g2o)
    assert (a.format, b.format) == ("toro", "g2o")
    expected = np.array([[xx, xy, xt], [xy, yy, yt], [xt, yt, tt]])
    for g in (a, b):
        np.testing.assert_allclose(g.graph.at(0).noiseModel().information(), expected, rtol=1e-12)
    assert_same_graph(a, b)


def test_pose3_information_is_permuted_like_readG2o(tmp_path):
    rng = np.random.default_rng(0)
    A = rng.normal(size=(6, 6))
    info = A @ A.T + 6 * np.eye(6)  # g2o order (x y z rx ry rz), all entries distinct
    upper = " ".join(repr(float(x)) for x in info[np.triu_indices(6)])
    q = gtsam.Rot3.Ypr(0.3, -0.2, 0.1).toQuaternion()
    text = ("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nVERTEX_SE3:QUAT 1 1 2 3 0 0 0 1\n"
            f"EDGE_SE3:QUAT 0 1 1.0 2.0 3.0 {q.x()!r} {q.y()!r} {q.z()!r} {q.w()!r} {upper}\n")
    path = write(tmp_path, "pair.g2o", text)
    g = load_graph(path, add_prior=False)
    p = [3, 4, 5, 0, 1, 2]  # GTSAM tangent order (rx ry rz x y z)
    np.testing.assert_allclose(g.graph.at(0).noiseModel().information(), info[np.ix_(p, p)], rtol=1e-10)
    ref_graph, ref_values = gtsam.readG2o(str(path), True)
    np.testing.assert_allclose(ref_graph.at(0).noiseModel().information(), info[np.ix_(p, p)], rtol=1e-10)
    assert_same_error(g.graph, ref_graph, g.initial)
    out = tmp_path / "written.g2o"
    write_g2o(out, g.graph, g.initial)  # written back in g2o's (t, r) order
    edge = out.read_text().splitlines()[2].split()
    np.testing.assert_allclose([float(x) for x in edge[10:]], info[np.triu_indices(6)], rtol=1e-10)


def test_quaternion_near_unit_is_normalized(tmp_path):
    q = np.array([0.1, -0.2, 0.3, 0.9])
    q /= np.linalg.norm(q)
    s = 1 + 5e-4  # within the 1e-3 tolerance
    text = ("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\n"
            f"VERTEX_SE3:QUAT 1 1 0 0 {' '.join(repr(float(x * s)) for x in q)}\n"
            "EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1 1 0 0 0 0 0 1 0 0 0 0 1 0 0 0 1 0 0 1 0 1\n")
    g = load_graph(write(tmp_path, "q.g2o", text))
    R = g.initial.atPose3(1).rotation().matrix()
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-14)
    np.testing.assert_allclose(R, gtsam.Rot3.Quaternion(q[3], *q[:3]).matrix(), atol=1e-14)


# --------------------------------------------------------------------------- spanning tree, prior

def test_kitti_spanning_tree_guess_is_exact_on_a_spanning_tree():
    g = loaded("kitti_00.g2o")
    first = min(g.initial.keys())
    assert g.initial.atPose2(first).equals(gtsam.Pose2(), 0.0)
    ids = np.array(sorted(g.initial.keys()))
    exact = []
    for k in range(g.graph.size()):
        f = g.graph.at(k)
        if isinstance(f, gtsam.BetweenFactorPose2) and f.error(g.initial) < 1e-12:
            exact.append(np.searchsorted(ids, f.keys()))
    exact = np.array(exact)
    assert len(exact) >= g.poses - 1
    tree = sp.coo_matrix((np.ones(len(exact)), (exact[:, 0], exact[:, 1])), shape=(g.poses, g.poses))
    assert connected_components(tree, directed=False)[0] == 1  # the exact edges reach every pose


def test_spanning_tree_chains_edges_in_both_directions(tmp_path):
    # 5 -> 7 and 9 -> 7 (backwards), ids not contiguous, edges listed out of order
    text = ("EDGE_SE2 9 7 -1 0 0 1 0 0 1 0 1\n"
            "EDGE_SE2 5 7 1 0 1.5707963267948966 1 0 0 1 0 1\n")
    g = load_graph(write(tmp_path, "chain.g2o", text))
    assert g.initial_guess == "spanning-tree" and g.poses == 3
    assert g.initial.atPose2(5).equals(gtsam.Pose2(), 0.0)
    assert g.initial.atPose2(7).equals(gtsam.Pose2(1, 0, np.pi / 2), 1e-12)
    assert g.initial.atPose2(9).equals(gtsam.Pose2(1, 1, np.pi / 2), 1e-12)  # 7 * inverse(-1, 0, 0)
    assert g.graph.error(g.initial) < 1e-20


def test_gauge_prior_added_once_on_first_pose(tmp_path):
    path = write(tmp_path, "p.g2o", "VERTEX_SE2 3 1 2 0.5\nVERTEX_SE2 4 2 2 0.5\n"
                                    "EDGE_SE2 3 4 1 0 0 1 0 0 1 0 1\n")
    g = load_graph(path, prior_sigma=0.25)
    priors = count_priors(g.graph)
    assert g.prior_added and len(priors) == 1
    assert priors[0].keys() == [3] and priors[0].prior().equals(gtsam.Pose2(1, 2, 0.5), 0.0)
    np.testing.assert_allclose(priors[0].noiseModel().sigmas(), [0.25] * 3)
    g = load_graph(path, add_prior=False)
    assert not g.prior_added and count_priors(g.graph) == [] and g.graph.size() == 1


def test_fix_lines_become_priors_and_replace_the_gauge_prior(tmp_path):
    path = write(tmp_path, "fix.g2o", "VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\nVERTEX_SE2 2 2 0 0\n"
                                      "EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\nEDGE_SE2 1 2 1 0 0 1 0 0 1 0 1\n"
                                      "FIX 2 1\nFIX 2\n")
    g = load_graph(path)
    assert not g.prior_added
    assert sorted(p.keys()[0] for p in count_priors(g.graph)) == [1, 2]
    assert g.warnings == ["FIX 2 at line 7 repeats line 6; it is applied once"]


def test_fix_anchors_every_component(tmp_path):
    path = write(tmp_path, "two.g2o", "EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\nEDGE_SE2 5 6 1 0 0 1 0 0 1 0 1\n"
                                      "FIX 0 5\n")
    g = load_graph(path)
    assert g.poses == 4 and len(count_priors(g.graph)) == 2 and g.initial_guess == "spanning-tree"
    assert g.initial.atPose2(0).equals(gtsam.Pose2(), 0.0) and g.initial.atPose2(5).equals(gtsam.Pose2(), 0.0)
    assert g.graph.error(g.initial) < 1e-20


@pytest.mark.datasets
def test_prior_sigma_must_be_positive(tmp_path):
    with pytest.raises(ValueError, match="prior_sigma"):
        load_graph(dataset("tinyGrid3D.g2o"), prior_sigma=0.0)


def test_comments_blank_lines_crlf_and_unknown_tags(tmp_path):
    plain = ("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\nVERTEX_SE2 2 2 0 0\n"
             "EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\nEDGE_SE2 1 2 1 0 0 1 0 0 1 0 1\n")
    messy = ("# a comment\r\n\r\n   \t \r\nVERTEX_SE2 0 0 0 0   # trailing comment\r\nFOO 1 2\r\n"
             "VERTEX_SE2 1 1 0 0\r\nPARAMS_X 1\r\nVERTEX_SE2 2 2 0 0\r\nFOO\r\n"
             "EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\r\nFOO 3\r\n\r\nEDGE_SE2 1 2 1 0 0 1 0 0 1 0 1")
    a = load_graph(write(tmp_path, "plain.g2o", plain))
    b = load_graph(write(tmp_path, "messy.g2o", messy))
    assert_same_graph(a, b)
    assert b.warnings == ["skipped 3 lines with unknown tag 'FOO' (first at line 5)",
                          "skipped 1 line with unknown tag 'PARAMS_X' (first at line 7)"]


# -------------------------------------------------------------------------------------- writing

@pytest.mark.datasets
@pytest.mark.parametrize("name", ["input_INTEL_g2o.g2o", "CSAIL_P_toro.graph", "kitti_00.g2o",
                                  "smallGrid3D.g2o", "sphere2500.g2o"])
def test_round_trip_load_write_load(tmp_path, name):
    a = loaded(name)
    out = tmp_path / "out.g2o"
    write_g2o(out, a.graph, a.initial, input_path=dataset(name))
    b = load_graph(out)
    assert b.format == "g2o" and b.initial_guess == "file" and not b.prior_added  # the prior came back as FIX
    assert_same_graph(a, b)
    if a.dimension == 3:  # GTSAM's own reader sees the same graph in our file (Pose3 order written back)
        ref_graph, ref_values = gtsam.readG2o(str(out), True)
        assert ref_values.equals(a.initial, 1e-9)
        assert factor_keys(ref_graph) == factor_keys(a.graph)[:a.edges]
        between = gtsam.NonlinearFactorGraph()  # readG2o ignores FIX: compare the between factors
        for k in range(a.edges):
            between.add(b.graph.at(k))
        assert_same_error(between, ref_graph, a.initial)


def test_round_trip_without_prior_and_with_fix(tmp_path):
    a = load_graph(write(tmp_path, "fix.g2o", "VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0.1\nVERTEX_SE2 2 2 0 0\n"
                                               "EDGE_SE2 0 1 1 0 0 2 0.5 0.1 3 0.2 4\n"
                                               "EDGE_SE2 1 2 1 0 0 1 0 0 1 0 1\nFIX 1\n"))
    write_g2o(tmp_path / "out.g2o", a.graph, a.initial)
    assert (tmp_path / "out.g2o").read_text().splitlines()[-1] == "FIX 1"
    assert_same_graph(a, load_graph(tmp_path / "out.g2o"))
    c = load_graph(tmp_path / "fix.g2o", add_prior=False)
    c.graph.remove(c.graph.size() - 1)  # drop the FIX prior: no prior at all is written
    write_g2o(tmp_path / "bare.g2o", c.graph, c.initial)
    assert "FIX" not in (tmp_path / "bare.g2o").read_text()


def _small_graph(tmp_path):
    return load_graph(write(tmp_path, "in.g2o", "VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\n"
                                                "EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\n"))


def _dir_listing(path):
    return sorted(os.listdir(path))


@pytest.mark.parametrize("existing", [True, False])
def test_atomic_write_failure_mid_write_keeps_old_file(tmp_path, monkeypatch, existing):
    g = _small_graph(tmp_path)
    out = tmp_path / "result.g2o"
    if existing:
        out.write_text("old result\n")
    before = _dir_listing(tmp_path)
    real_lines = gio._g2o_lines

    def failing_lines(*args):
        for k, line in enumerate(real_lines(*args)):
            if k == 2:
                raise RuntimeError("disk on fire")
            yield line

    monkeypatch.setattr(gio, "_g2o_lines", failing_lines)
    with pytest.raises(RuntimeError, match="disk on fire"):
        write_g2o(out, g.graph, g.initial)
    assert _dir_listing(tmp_path) == before  # no temporary file left, nothing created
    if existing:
        assert out.read_text() == "old result\n"


def test_atomic_write_interrupt_and_os_errors(tmp_path, monkeypatch):
    g = _small_graph(tmp_path)
    out = tmp_path / "result.g2o"
    out.write_text("old result\n")
    before = _dir_listing(tmp_path)

    def interrupt(fd):
        raise KeyboardInterrupt

    monkeypatch.setattr(gatomic.os, "fsync", interrupt)
    with pytest.raises(KeyboardInterrupt):
        write_g2o(out, g.graph, g.initial)
    assert _dir_listing(tmp_path) == before and out.read_text() == "old result\n"
    monkeypatch.undo()

    def no_replace(src, dst):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(gatomic.os, "replace", no_replace)
    with pytest.raises(GraphFileError, match=re.escape(f"{out}: cannot write: Permission denied")):
        write_g2o(out, g.graph, g.initial)
    assert _dir_listing(tmp_path) == before and out.read_text() == "old result\n"


def test_write_unsupported_factor_fails_cleanly(tmp_path):
    g = _small_graph(tmp_path)
    out = tmp_path / "result.g2o"
    out.write_text("old result\n")
    before = _dir_listing(tmp_path)
    graph = gtsam.NonlinearFactorGraph(g.graph)
    robust = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(1.0),
                                            gtsam.noiseModel.Unit.Create(3))
    graph.add(gtsam.BetweenFactorPose2(0, 1, gtsam.Pose2(), robust))
    with pytest.raises(GraphFileError, match=re.escape(f"{out}: cannot write factor 2: its Robust noise model")):
        write_g2o(out, graph, g.initial)
    graph = gtsam.NonlinearFactorGraph(g.graph)
    graph.add(gtsam.BetweenFactorPose2(0, 7, gtsam.Pose2(), gtsam.noiseModel.Unit.Create(3)))
    with pytest.raises(GraphFileError, match="key 7 has no value"):
        write_g2o(out, graph, g.initial)
    assert _dir_listing(tmp_path) == before and out.read_text() == "old result\n"


def test_write_keeps_mode_of_replaced_file(tmp_path):
    g = _small_graph(tmp_path)
    out = tmp_path / "result.g2o"
    out.write_text("old\n")
    out.chmod(0o640)
    write_g2o(out, g.graph, g.initial)
    assert (out.stat().st_mode & 0o777) == 0o640


def test_refuses_to_overwrite_input_without_force(tmp_path):
    g = _small_graph(tmp_path)
    src = tmp_path / "in.g2o"
    original = src.read_text()
    (tmp_path / "sub").mkdir()
    (tmp_path / "link.g2o").symlink_to(src)
    for spelling in [src, str(src), tmp_path / "sub" / ".." / "in.g2o", tmp_path / "link.g2o"]:
        with pytest.raises(GraphFileError, match="refusing to overwrite the input file"):
            write_g2o(spelling, g.graph, g.initial, input_path=src)
        assert src.read_text() == original
    write_g2o(tmp_path / "other.g2o", g.graph, g.initial, input_path=src)
    write_g2o(src, g.graph, g.initial, input_path=src, force=True)
    assert_same_graph(load_graph(src), g)


# ------------------------------------------------------------------------------------ bad input

V3 = "VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\nVERTEX_SE2 2 2 0 0\n"
E01 = "EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\n"
E12 = "EDGE_SE2 1 2 1 0 0 1 0 0 1 0 1\n"
Q3 = "VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nVERTEX_SE3:QUAT 1 1 0 0 0 0 0 1\n"
INFO6 = "1 0 0 0 0 0 1 0 0 0 0 1 0 0 0 1 0 0 1 0 1"

# id: (file text, line at fault or None, expected text of the message after "path:line: ")
BAD_INPUTS = {
    "too-few-numbers": (V3 + E01 + "EDGE_SE2 1 2 1 0 0 1 0 0 1 0\n", 5,
                        "too few fields for EDGE_SE2: expected 11 (i j dx dy dtheta I11 I12 I13 I22 I23 I33), got 10"),
    "too-many-numbers": (V3 + "EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1 7\n" + E12, 4,
                         "too many fields for EDGE_SE2: expected 11 (i j dx dy dtheta I11 I12 I13 I22 I23 I33), "
                         "got 12"),
    "vertex-too-few": ("VERTEX_SE2 0 0 0\n" + E01, 1,
                       "too few fields for VERTEX_SE2: expected 4 (id x y theta), got 3"),
    "se3-too-few": (Q3 + "EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1 1 0 0\n", 3,
                    "too few fields for EDGE_SE3:QUAT: expected 30 (i j dx dy dz qx qy qz qw I11 I12 I13 I14 I15 "
                    "I16 I22 I23 I24 I25 I26 I33 I34 I35 I36 I44 I45 I46 I55 I56 I66), got 12"),
    "non-numeric": (V3 + E01 + "EDGE_SE2 1 2 1 0 abc 1 0 0 1 0 1\n", 5,
                    "EDGE_SE2 1 -> 2: field 'dtheta' is not a number: 'abc'"),
    "non-numeric-vertex": ("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1.0.0 0 0\n" + E01, 2,
                           "VERTEX_SE2 1: field 'x' is not a number: '1.0.0'"),
    "underscore-number": (V3 + "EDGE_SE2 0 1 1_0 0 0 1 0 0 1 0 1\n", 4,
                          "EDGE_SE2 0 -> 1: field 'dx' is not a number: '1_0'"),
    "bad-id": ("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 x1 1 0 0\n" + E01, 2,
               "VERTEX_SE2 field 'id' is not a vertex id (a non-negative integer below 2^63): 'x1'"),
    "negative-id": (V3 + "EDGE_SE2 0 -1 1 0 0 1 0 0 1 0 1\n", 4,
                    "EDGE_SE2 field 'j' is not a vertex id (a non-negative integer below 2^63): '-1'"),
    "huge-id": ("VERTEX_SE2 99999999999999999999 0 0 0\n", 1,
                "VERTEX_SE2 field 'id' is not a vertex id (a non-negative integer below 2^63): "
                "'99999999999999999999'"),
    "nan": (V3 + E01 + "EDGE_SE2 1 2 1 0 0 1 0 0 nan 0 1\n", 5, "EDGE_SE2 1 -> 2: field 'I22' is not finite: 'nan'"),
    "inf-vertex": ("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 -inf 0\n" + E01, 2,
                   "VERTEX_SE2 1: field 'y' is not finite: '-inf'"),
    "overflow": (V3 + "EDGE_SE2 0 1 1e999 0 0 1 0 0 1 0 1\n", 4, "EDGE_SE2 0 -> 1: field 'dx' is not finite: '1e999'"),
    "missing-vertex": (V3 + E01 + "EDGE_SE2 1 7 1 0 0 1 0 0 1 0 1\n" + E12, 5,
                       "edge 1 -> 7 references vertex 7, which has no VERTEX_SE2 line"),
    "duplicate-vertex": (V3 + "VERTEX_SE2 1 5 5 0\n" + E01 + E12, 4, "duplicate vertex id 1 (first defined at line 2)"),
    "not-positive-definite": (V3 + E01 + "EDGE_SE2 1 2 1 0 0 1 0 0 -1 0 1\n", 5,
                              "information matrix of edge 1 -> 2 is not symmetric positive definite "
                              "(Cholesky fails or is numerically singular)"),
    "singular-information": (V3 + "EDGE_SE2 0 1 1 0 0 1 1 1 1 1 1\n" + E12, 4,
                             "information matrix of edge 0 -> 1 is not symmetric positive definite "
                             "(Cholesky fails or is numerically singular)"),
    "se3-not-positive-definite": (Q3 + "EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1 " + INFO6.replace("1", "0", 1) + "\n", 3,
                                  "information matrix of edge 0 -> 1 is not symmetric positive definite "
                                  "(Cholesky fails or is numerically singular)"),
    "empty-file": ("", None, "no edges (no records): nothing to optimize"),
    "whitespace-only": ("\n   \n\t\n# just a comment\n", None, "no edges (no records): nothing to optimize"),
    "vertices-only": (V3, None, "no edges (only 3 vertices): nothing to optimize"),
    "unknown-only": ("FOO 1\nFOO 2\n", None, "no edges (no pose-graph records; skipped 2 lines with unknown tag "
                                             "'FOO' (first at line 1)): nothing to optimize"),
    "mixed-2d-3d": (V3 + "VERTEX_SE3:QUAT 3 0 0 0 0 0 0 1\n" + E01, 4,
                    "VERTEX_SE3:QUAT is a 3D record but the file is 2D (VERTEX_SE2 at line 1); "
                    "2D and 3D records cannot be mixed"),
    "mixed-toro-g2o": (V3 + "EDGE2 0 1 1 0 0 1 0 1 1 0 0\n", 4,
                       "EDGE2 is a TORO record but the file uses g2o records (VERTEX_SE2 at line 1); "
                       "they cannot be mixed"),
    "self-loop": (V3 + E01 + "EDGE_SE2 2 2 1 0 0 1 0 0 1 0 1\n" + E12, 5,
                  "EDGE_SE2 2 -> 2 is a self-loop (both ends are pose 2)"),
    "zero-quaternion": (Q3 + "EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 0 " + INFO6 + "\n", 3,
                        "EDGE_SE3:QUAT 0 -> 1: quaternion (qx qy qz qw) has zero norm"),
    "non-unit-quaternion": ("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nVERTEX_SE3:QUAT 1 1 0 0 0 0 0 2\n", 2,
                            "VERTEX_SE3:QUAT 1: quaternion (qx qy qz qw) has norm 2, not 1 "
                            "(only norms within 0.001 of 1 are normalized)"),
    "disconnected": ("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\nVERTEX_SE2 17 0 0 0\nVERTEX_SE2 18 0 0 0\n"
                     + E01 + "EDGE_SE2 17 18 1 0 0 1 0 0 1 0 1\n", 3,
                     "pose 17 is not connected to pose 0 (the graph has 2 connected components; "
                     "a component without a FIX makes the Hessian singular)"),
    "isolated-vertex": (V3 + "VERTEX_SE2 3 0 0 0\n" + E01 + E12, 4,
                        "pose 3 is not connected to pose 0 (the graph has 2 connected components; "
                        "a component without a FIX makes the Hessian singular)"),
    "disconnected-edges-only": (E01 + "\nEDGE_SE2 4 5 1 0 0 1 0 0 1 0 1\n", 3,
                                "pose 4 is not connected to pose 0 (the graph has 2 connected components; "
                                "a component without a FIX makes the Hessian singular)"),
    "fix-unknown-pose": (V3 + E01 + E12 + "FIX 9\n", 6, "FIX refers to pose 9, which does not appear in the file"),
    "fix-without-id": (V3 + E01 + E12 + "FIX\n", 6, "too few fields for FIX: expected at least one vertex id"),
}


STRICT_ONLY = {"not-positive-definite", "singular-information", "se3-not-positive-definite"}  # repaired by default


@pytest.mark.parametrize("case", list(BAD_INPUTS))
def test_bad_input_gives_one_line_error(tmp_path, case):
    text, line, what = BAD_INPUTS[case]
    path = write(tmp_path, f"{case}.g2o", text)
    with pytest.raises(GraphFileError) as info:
        load_graph(path, strict=case in STRICT_ONLY)
    message = str(info.value)
    where = f"{path}:{line}" if line is not None else f"{path}"
    assert message == f"{where}: {what}"
    assert "\n" not in message and f"{case}.g2o" in message


def test_unreadable_files(tmp_path):
    missing = tmp_path / "nope.g2o"
    with pytest.raises(GraphFileError, match=re.escape(f"{missing}: cannot read: No such file or directory")):
        load_graph(missing)
    with pytest.raises(GraphFileError, match=re.escape(f"{tmp_path}: cannot read: Is a directory")):
        load_graph(tmp_path)
    binary = tmp_path / "binary.g2o"
    binary.write_bytes(b"VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\n\xff\xfe\n")
    with pytest.raises(GraphFileError, match=re.escape(f"{binary}:3: not a UTF-8 text file (invalid byte 0xff)")):
        load_graph(binary)


def test_error_is_a_value_error():
    assert issubclass(GraphFileError, ValueError)


@pytest.mark.parametrize("case", sorted(STRICT_ONLY))
def test_information_not_positive_definite_is_repaired_with_a_warning(tmp_path, case):
    text, line, _ = BAD_INPUTS[case]
    path = write(tmp_path, f"{case}.g2o", text)
    g = load_graph(path)
    assert len(g.warnings) == 1 and g.warnings[0].startswith(f"{path}:{line}: information matrix of edge")
    assert "1 information matrix repaired by eigenvalue clipping" in g.warnings[0]
    for i in range(g.graph.size()):  # every factor now has a positive definite information matrix
        model = g.graph.at(i).noiseModel()
        info = model.information() if hasattr(model, "information") else np.eye(model.dim())
        assert np.linalg.eigvalsh(info).min() > 0
    assert np.isfinite(g.graph.error(g.initial))


def test_unknown_records_are_refused_with_strict(tmp_path):
    path = write(tmp_path, "extra.g2o", "VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\nFOO 1 2\n"
                 "EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\n")
    assert "unknown tag 'FOO'" in load_graph(path).warnings[0]
    with pytest.raises(GraphFileError, match="unknown tag 'FOO'.*strict"):
        load_graph(path, strict=True)
