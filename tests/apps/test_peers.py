"""g2o (g2opy) as a peer in ``gtsam-schwarz bench``: the same problem as ours, the same answer, and a
``not installed`` row (never a crash) without g2opy.

chi2 == 2 × graph.error holds exactly only where g2o's edge errors and GTSAM's Logmap agree: residuals
that are pure translations, or pure rotations (exact in 2D, to θ²/12 in 3D where g2o uses q_vec ≈ ω/2).
Mixed residuals agree to first order; the tests check each part, and the mixed case at small residuals,
where a wrong information conversion would show as an O(1) difference.
"""

import json
import math
import pathlib
import subprocess
import sys

import gtsam
import numpy as np
import pytest

from gtsam_schwarz.apps import bench, peers
from gtsam_schwarz.problems import helix_loops, square_loops

ROOT = pathlib.Path(__file__).resolve().parents[2]
SKIP = "g2opy not installed (pip install 'gtsam-schwarz[peers]')"


@pytest.fixture
def g2o():
    """g2opy, or a skip with a one-line reason (like pytest.importorskip, also for an install that is
    present but fails to import)."""
    try:
        return peers.import_g2o()
    except peers.PeerNotInstalled:
        pytest.skip(SKIP)


def _rel(a, b):
    return abs(a - b) / abs(b)


def _information(rng, dim):
    """A full SPD information matrix: strongly coupled rotation and translation blocks."""
    n = 3 if dim == 2 else 6
    a = rng.normal(size=(n, n))
    return a @ a.T + n * np.eye(n)


def _pose(dim, xyz, angles):
    if dim == 2:
        return gtsam.Pose2(xyz[0], xyz[1], angles[2])
    return gtsam.Pose3(gtsam.Rot3.RzRyRx(*angles), np.asarray(xyz, float))


def _graph(dim, residual, scale=1.0, seed=0, n=6):
    """A loop of ``n`` poses with exact measurements and full information matrices, plus a prior on
    pose 0 at its value, and an initial point whose residuals are ``residual``: "translation" (positions
    moved by ``scale``, rotations exact), "rotation" (every pose at one position, measurements without
    translation, rotations moved by ``scale`` rad) or "mixed" (both moved by ``scale``)."""
    rng = np.random.default_rng(seed)
    angles = rng.uniform(-np.pi, np.pi, size=(n, 3))
    xyz = np.zeros((n, 3)) if residual == "rotation" else rng.normal(size=(n, 3)) * 3
    truth = [_pose(dim, xyz[i], angles[i]) for i in range(n)]
    graph, initial = gtsam.NonlinearFactorGraph(), gtsam.Values()
    between = gtsam.BetweenFactorPose2 if dim == 2 else gtsam.BetweenFactorPose3
    prior = gtsam.PriorFactorPose2 if dim == 2 else gtsam.PriorFactorPose3
    edges = [(i, (i + 1) % n) for i in range(n)] + [(0, n // 2), (1, n - 2)]
    for i, j in edges:
        noise = gtsam.noiseModel.Gaussian.Information(_information(rng, dim))
        graph.add(between(i, j, truth[i].between(truth[j]), noise))
    graph.add(prior(0, truth[0], gtsam.noiseModel.Isotropic.Sigma(3 if dim == 2 else 6, 1e-3)))
    initial.insert(0, truth[0])
    for i in range(1, n):
        dx = rng.normal(size=3) * scale if residual in ("translation", "mixed") else np.zeros(3)
        dr = rng.normal(size=3) * scale if residual in ("rotation", "mixed") else np.zeros(3)
        initial.insert(i, _pose(dim, xyz[i] + dx, angles[i] + dr))
    return graph, initial


def _chi2(graph, initial):
    problem = peers.build_g2o(graph, initial, "gn")
    assert problem.optimizer.initialize_optimization()
    return problem.chi2()


# -- building the g2o problem: chi2 == 2 × graph.error at the initial point ----------------------
@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("residual, scale", [("translation", 0.5), ("rotation", 1e-5)])
def test_chi2_is_twice_the_gtsam_error_at_the_initial_point(g2o, dim, residual, scale):
    graph, initial = _graph(dim, residual, scale)
    error = graph.error(initial)
    assert error > 1e-12  # a real residual, not an exact point
    assert _rel(_chi2(graph, initial), 2 * error) <= 1e-9


def test_pose2_rotation_residuals_agree_at_any_size(g2o):
    graph, initial = _graph(2, "rotation", 0.5)
    assert _rel(_chi2(graph, initial), 2 * graph.error(initial)) <= 1e-12


@pytest.mark.parametrize("dim", [2, 3])
def test_mixed_small_residuals_agree_to_first_order(g2o, dim):
    """Rotation and translation residuals of 1e-7 together: the rotation–translation block of the
    information counts, and the difference is second order (relative ~1e-7)."""
    graph, initial = _graph(dim, "mixed", 1e-7)
    assert _rel(_chi2(graph, initial), 2 * graph.error(initial)) <= 1e-5


def test_without_the_se3_conversion_it_is_a_different_problem(g2o, monkeypatch):
    """Only permuting (r, t) -> (t, r), as g2o's own file reader effectively does, misses the factor 2
    on the rotation part: chi2 is off by O(1). So the conversion is what makes the tests above pass."""
    graph, initial = _graph(3, "rotation", 1e-5)
    perm = np.r_[3:6, 0:3]
    monkeypatch.setattr(peers, "information_to_g2o",
                        lambda omega, dim: np.asarray(omega)[np.ix_(perm, perm)] if dim == 3 else omega)
    assert _rel(_chi2(graph, initial), 2 * graph.error(initial)) > 0.5


def test_information_conversion_formula():
    omega = _information(np.random.default_rng(3), 3)
    converted = peers.information_to_g2o(omega, 3)
    # (t, q) order: tt = Ω_vv, tq = 2 Ω_vω, qq = 4 Ω_ωω
    np.testing.assert_allclose(converted[:3, :3], omega[3:, 3:])
    np.testing.assert_allclose(converted[:3, 3:], 2 * omega[3:, :3])
    np.testing.assert_allclose(converted[3:, 3:], 4 * omega[:3, :3])
    np.testing.assert_array_equal(peers.information_to_g2o(omega[:3, :3], 2), omega[:3, :3])


def test_values_round_trip_keys_and_the_fixed_prior_pose(g2o):
    """Keys that are not 0..n-1 map to g2o ids and back; the prior's pose is the (only) fixed vertex."""
    p = helix_loops(1, 3)
    graph, initial = gtsam.NonlinearFactorGraph(), gtsam.Values()
    shift = gtsam.symbol("x", 0)
    for i in range(p.graph.size()):
        f = p.graph.at(i)
        keys = [k + shift for k in f.keys()]
        if isinstance(f, gtsam.PriorFactorPose3):
            graph.add(gtsam.PriorFactorPose3(keys[0], f.prior(), f.noiseModel()))
        else:
            graph.add(gtsam.BetweenFactorPose3(keys[0], keys[1], f.measured(), f.noiseModel()))
    for k in p.initial.keys():
        initial.insert(k + shift, p.initial.atPose3(k))
    problem = peers.build_g2o(graph, initial, "lm")
    assert problem.fixed == [shift] and problem.optimizer.vertex(0).fixed()
    assert not problem.optimizer.vertex(1).fixed()
    back = problem.values()
    assert sorted(back.keys()) == sorted(initial.keys())
    assert all(back.atPose3(k).equals(initial.atPose3(k), 1e-12) for k in initial.keys())


def test_unsupported_factors_are_refused(g2o):
    graph, initial = _graph(2, "translation", 0.1)
    graph.add(gtsam.BetweenFactorPoint2(0, 1, gtsam.Point2(1, 0), gtsam.noiseModel.Unit.Create(2)))
    with pytest.raises(ValueError, match="unsupported factor BetweenFactorPoint2"):
        peers.build_g2o(graph, initial)


# -- solving: g2o reaches GTSAM LM's minimum ------------------------------------------------------
@pytest.mark.parametrize("method", ["gn", "lm"])
@pytest.mark.parametrize("make", [lambda: square_loops(4, 4), lambda: helix_loops(2, 4)], ids=["pose2", "pose3"])
def test_g2o_reaches_gtsam_lm_final_error(g2o, method, make):
    p = make()
    e_lm = p.graph.error(gtsam.LevenbergMarquardtOptimizer(p.graph, p.initial).optimize())
    r = peers.solve_g2o(p.graph, p.initial, method)
    assert "failed" not in r and 1 <= r["iterations"] < peers.MAX_ITERATIONS and r["converged"]
    assert r["seconds"] > 0 and r["g2o_initial_chi2"] > r["g2o_chi2"]
    e = p.graph.error(r["values"])
    assert _rel(e, e_lm) <= 1e-6
    # at the optimum g2o's (dx, dy, dθ) / (t, q_vec) errors and GTSAM's Logmap agree: chi2 ≈ 2 × error
    assert _rel(r["g2o_chi2"], 2 * e) <= 1e-5


# -- the bench: rows, and "not installed" without g2opy --------------------------------------------
def test_bench_rows_for_g2o(g2o):
    assert {"g2o-gn", "g2o-lm"} <= set(bench.SOLVERS)  # installed: they run by default
    proc = subprocess.run([sys.executable, "-m", "gtsam_schwarz.apps.cli", "bench", "--size", "tiny", "--cases",
                           "sq8x16", "--solvers", "ours,gtsam-lm,g2o-gn,g2o-lm", "--json"],
                          capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert proc.returncode == 0, proc.stderr
    report = json.loads(proc.stdout)
    assert report["machine"]["g2opy"]
    runs = {r["solver"]: r for r in report["runs"]}
    for name in ("g2o-gn", "g2o-lm"):
        r = runs[name]
        assert r["status"] == "ok", r
        assert r["same_error"] is True and r["rel_error_diff"] <= 1e-6
        assert math.isfinite(r["ratio_to_gtsam_lm"]) and r["ratio_to_gtsam_lm"] > 0
        assert math.isfinite(r["over_ours"]) and r["over_ours"] > 0
        assert r["peak_mib"] >= r["loaded_mib"] > 0 and r["iterations"] >= 1
        assert _rel(r["g2o_chi2"], 2 * r["final_error"]) <= 1e-5


def test_not_installed_in_process(monkeypatch, tmp_path):
    monkeypatch.setitem(sys.modules, "g2opy", None)
    assert not peers.available()
    with pytest.raises(peers.PeerNotInstalled, match="pip install"):
        peers.import_g2o()
    row = bench.solve(bench.ALL_CASES["sq8x16"], "g2o-lm", {}, tmp_path)  # nothing is loaded
    assert "g2opy" in row["not_installed"]


def test_not_installed_row_from_a_child(tmp_path):
    """A g2opy that fails to import (shadowed on PYTHONPATH) makes the child's row 'not installed'."""
    fake = tmp_path / "g2opy"
    fake.mkdir()
    (fake / "__init__.py").write_text("raise ImportError('hidden by the test')\n")
    env = {"PYTHONPATH": f"{tmp_path}{':'}{bench.CHECKOUT}"}
    row = bench.run_solver(bench.ALL_CASES["sq8x16"], "g2o-gn", {}, tmp_path, timeout=60, env=env)
    assert row["status"] == "not installed", row
    assert "hidden by the test" in row["not_installed"]
    bench.add_comparisons([row])
    assert row["same_error"] is None and math.isnan(row["ratio_to_gtsam_lm"])
    report = {"runs": [row], "cases": [{"name": "sq8x16", "poses": 513}], "size": "tiny", "command": "x",
              "date": "d", "timeout": 60, "params": {}, "solvers": ["g2o-gn"],
              "machine": {"cpu_count": 2, "cpu": "c", "memory_gib": 1, "platform": "p", "python": "3",
                          "gtsam": "4", "numpy": "2", "scipy": "1", "gtsam_schwarz": "0", "g2opy": None}}
    assert "| sq8x16 | 513 | g2o-gn | not installed |" in bench.markdown(report)


def test_default_solvers_leave_out_g2o_when_it_is_not_importable():
    code = ("import sys; sys.modules['g2opy'] = None\n"
            "from gtsam_schwarz.apps import bench\n"
            "print(list(bench.SOLVERS)); print(list(bench.KNOWN_SOLVERS))")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=60)
    assert proc.returncode == 0, proc.stderr
    default, known = (json.loads(l.replace("'", '"')) for l in proc.stdout.splitlines())
    assert default == ["ours", "ours-direct", "ours-schwarz", "gtsam-lm", "gtsam-lm-pcg", "gtsam-lm-subgraph"]
    assert known == default + ["g2o-gn", "g2o-lm"]  # still accepted by --solvers: a "not installed" row
