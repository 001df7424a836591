"""Code written for GTSAM's optimizers runs with ours: params, accessors, hooks, defaults, gauge."""

import math
import warnings

import gtsam
import numpy as np
import pytest

import gtsam_schwarz as gs
from conftest import pose2_difference
from gtsam_schwarz import LinearSolverParams, SchwarzOptimizer, SchwarzParams, square_loops


def pose2_slam_example(Optimizer):
    """GTSAM's Pose2SLAMExample (python/gtsam/examples), with the optimizer class as a parameter."""
    graph = gtsam.NonlinearFactorGraph()
    prior_noise = gtsam.noiseModel.Diagonal.Sigmas(gtsam.Point3(0.3, 0.3, 0.1))
    odometry_noise = gtsam.noiseModel.Diagonal.Sigmas(gtsam.Point3(0.2, 0.2, 0.1))
    graph.add(gtsam.PriorFactorPose2(1, gtsam.Pose2(0, 0, 0), prior_noise))
    graph.add(gtsam.BetweenFactorPose2(1, 2, gtsam.Pose2(2, 0, 0), odometry_noise))
    graph.add(gtsam.BetweenFactorPose2(2, 3, gtsam.Pose2(2, 0, math.pi / 2), odometry_noise))
    graph.add(gtsam.BetweenFactorPose2(3, 4, gtsam.Pose2(2, 0, math.pi / 2), odometry_noise))
    graph.add(gtsam.BetweenFactorPose2(4, 5, gtsam.Pose2(2, 0, math.pi / 2), odometry_noise))
    graph.add(gtsam.BetweenFactorPose2(5, 2, gtsam.Pose2(2, 0, math.pi / 2), odometry_noise))
    initial = gtsam.Values()
    initial.insert(1, gtsam.Pose2(0.5, 0.0, 0.2))
    initial.insert(2, gtsam.Pose2(2.3, 0.1, -0.2))
    initial.insert(3, gtsam.Pose2(4.1, 0.1, math.pi / 2))
    initial.insert(4, gtsam.Pose2(4.0, 2.0, math.pi))
    initial.insert(5, gtsam.Pose2(2.1, 2.1, -math.pi / 2))
    parameters = gtsam.GaussNewtonParams()
    parameters.setRelativeErrorTol(1e-5)
    parameters.setMaxIterations(100)
    optimizer = Optimizer(graph, initial, parameters)
    result = optimizer.optimize()
    marginals = gtsam.Marginals(graph, result)  # GTSAM's own tools accept our result
    return graph, result, marginals.marginalCovariance(1)


def test_gtsam_example_runs_with_only_the_optimizer_class_swapped():
    graph, ours, cov_ours = pose2_slam_example(SchwarzOptimizer)
    _, ref, cov_ref = pose2_slam_example(gtsam.GaussNewtonOptimizer)
    assert graph.error(ours) == pytest.approx(graph.error(ref), rel=1e-6, abs=1e-12)
    assert np.abs(pose2_difference(ours, ref)).max() < 1e-6
    assert np.allclose(cov_ours, cov_ref, rtol=1e-5)


def test_gtsam_lm_params_carry_tolerances_lambda_and_hook():
    prob = square_loops(8, 6, sigma=0.05, seed=2)
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(3)
    params.setlambdaInitial(1e-3)
    calls = []
    params.iterationHook = lambda it, before, after: calls.append((it, before, after))
    opt = SchwarzOptimizer(prob.graph, prob.initial, params, linear_solver=LinearSolverParams(preconditioner="gdsw", subdomains=4))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        opt.optimize()
    assert opt.method == "lm" and opt.iterations() <= 3
    assert opt.history[0]["lambda"] == pytest.approx(1e-3)
    assert opt.decomposition.n_subdomains == 4
    accepted = [h for h in opt.history if h["accepted"]]
    assert calls == [(h["iteration"], h["error_before"], h["error"]) for h in accepted]
    assert isinstance(opt.lambda_(), float) and opt.lambda_() < 1e-3  # a method, as GTSAM's


def test_python_default_is_levenberg_marquardt_and_silent(capsys):
    prob = square_loops(4, 4, sigma=0.05, seed=1)
    opt = SchwarzOptimizer(prob.graph, prob.initial)
    opt.optimize()
    assert opt.method == "lm" and opt.converged
    assert capsys.readouterr().out == ""
    SchwarzOptimizer(prob.graph, prob.initial, SchwarzParams(verbose=True, max_iterations=1)).optimize()
    assert capsys.readouterr().out.startswith("  iter   1")


def test_no_convergence_warns_with_the_reason():
    prob = square_loops(4, 4, sigma=0.05, seed=1)
    opt = SchwarzOptimizer(prob.graph, prob.initial, SchwarzParams(preconditioner="gdsw", max_iterations=1))
    with pytest.warns(RuntimeWarning, match="did not converge: maximum of 1 iterations"):
        opt.optimize()
    assert not opt.converged


def test_optimize_safely_returns_the_best_values_on_failure(monkeypatch):
    prob = square_loops(4, 4, sigma=0.05, seed=1)
    opt = SchwarzOptimizer(prob.graph, prob.initial)
    calls = []

    def fail_second(original=opt.iterate):
        calls.append(1)
        if len(calls) == 2:
            raise RuntimeError("boom")
        return original()

    monkeypatch.setattr(opt, "iterate", fail_second)
    with pytest.warns(RuntimeWarning, match="boom"):
        values = opt.optimizeSafely()
    assert prob.graph.error(values) == pytest.approx(opt.error()) and opt.error() < opt.initial_error


def test_graph_without_prior_is_anchored_not_a_traceback():
    """Gauge freedom: every component without a prior gets its first pose anchored, as g2o fixes one."""
    prob = square_loops(4, 4, sigma=0.05, seed=1)
    free = gtsam.NonlinearFactorGraph()
    for i in range(prob.graph.size()):
        if len(prob.graph.at(i).keys()) == 2:
            free.add(prob.graph.at(i))
    for method in ("gn", "lm"):
        opt = SchwarzOptimizer(free, prob.initial, SchwarzParams(preconditioner="gdsw", method=method, subdomains=2))
        opt.optimize()
        assert opt.summary()["anchored"] == [int(free.keyVector()[0])]
        ref = gtsam.LevenbergMarquardtOptimizer(prob.graph, prob.initial).optimize()
        assert opt.error() == pytest.approx(prob.graph.error(ref), rel=1e-6)
    anchored = SchwarzOptimizer(prob.graph, prob.initial)
    anchored.optimize()
    assert anchored.summary()["anchored"] == []  # the prior already fixes the gauge


def test_typed_params_and_records():
    prob = square_loops(4, 4, sigma=0.05, seed=1)
    params = gs.LevenbergMarquardtParams(max_iterations=20, linear_solver=LinearSolverParams(preconditioner="rgdsw"))
    opt = SchwarzOptimizer(prob.graph, prob.initial, params)
    opt.optimize()
    h = opt.history[0]
    assert isinstance(h, gs.IterationRecord) and h["cg_iterations"] == h.cg_iterations
    assert dict(h)["lambda"] == h.lambda_ and "lambda_" not in dict(h)
    assert not hasattr(gs.GaussNewtonParams(), "lambda_initial")  # λ only on LM's params


def test_automatic_linear_solver_records_its_choice_and_reason(monkeypatch):
    """The default "auto" picks direct where the factor hardly fills (the model problem) and says why;
    a cost model that favours Schwarz gives its Schwarz candidate (rgdsw-linear) with the same answer."""
    from gtsam_schwarz.nonlinear.linear_solver import CostModel
    prob = square_loops(8, 6, sigma=0.05, seed=2)
    auto = SchwarzOptimizer(prob.graph, prob.initial)
    auto.optimize()
    choice = auto.summary()["linear_solver"]
    assert choice["requested"] == "auto" and choice["used"] == "direct"
    assert "nnz(L)" in choice["reason"] and "predicted" in choice["reason"]
    monkeypatch.setattr(CostModel, "SCHWARZ_OVERHEAD", 0.0)
    monkeypatch.setattr(CostModel, "TWO_LEVEL_OVERHEAD", 0.0)
    schwarz = SchwarzOptimizer(prob.graph, prob.initial, SchwarzParams(subdomains=4))
    schwarz.optimize()
    assert schwarz.summary()["linear_solver"]["used"] == "rgdsw-linear" and schwarz.history[0]["coarse_size"] > 0
    assert schwarz.error() == pytest.approx(auto.error(), rel=1e-8)


def test_linearizer_scratch_is_kept_for_direct_and_dropped_before_a_schwarz_build(monkeypatch):
    """The native linearizer's scratch survives a run that the automatic choice sends to the direct
    solver (no fresh pages each iteration), and is dropped once Schwarz is chosen, before its build;
    both runs drop everything at their end, before the result is built ("end")."""
    from gtsam_schwarz.linearization.native import NativeLinearizer
    from gtsam_schwarz.nonlinear.linear_solver import CostModel, PreconditionedCG
    prob = square_loops(8, 6, sigma=0.05, seed=2)
    events = []
    release = NativeLinearizer.release_scratch

    def record(self, values=False):
        events.append(("end", "S" in self._buffers) if values else "release")
        release(self, values)

    monkeypatch.setattr(NativeLinearizer, "release_scratch", record)
    build = PreconditionedCG.preconditioner
    monkeypatch.setattr(PreconditionedCG, "preconditioner",
                        lambda self, *a, **k: (events.append("build"), build(self, *a, **k))[1])
    auto = SchwarzOptimizer(prob.graph, prob.initial)
    auto.optimize()
    assert auto.summary()["linear_solver"]["used"] == "direct" and auto.iterations() >= 2
    assert events == [("end", True)] and auto.linearizer._buffers == {}
    events.clear()
    monkeypatch.setattr(CostModel, "SCHWARZ_OVERHEAD", 0.0)
    monkeypatch.setattr(CostModel, "TWO_LEVEL_OVERHEAD", 0.0)
    schwarz = SchwarzOptimizer(prob.graph, prob.initial, SchwarzParams(subdomains=4))
    schwarz.optimize()
    assert schwarz.summary()["linear_solver"]["used"] == "rgdsw-linear"
    assert events[:2] == ["release", "build"] and events.count("release") == schwarz.iterations()
    assert events[-1][0] == "end"


BEST_KNOWN = {"input_INTEL_g2o.g2o": 111.05, "input_M3500a_g2o.g2o": 3335.6, "MIT.g2o": 385.1195,
              "torus3D.g2o": 12117.64}  # the best known minima (GTSAM LM with the best of its options)


@pytest.mark.datasets
@pytest.mark.parametrize("name", sorted(BEST_KNOWN))
def test_default_settings_reach_the_best_known_minimum(name):
    """Defaults (chordal initialization, LM) from the file's guess: at or below the best known minimum."""
    from conftest import dataset
    from gtsam_schwarz.io import load_graph
    loaded = load_graph(dataset(name))
    opt = SchwarzOptimizer(loaded.graph, loaded.initial)
    opt.optimize()
    assert opt.initialization["used"] and opt.converged
    assert opt.error() <= BEST_KNOWN[name] * (1 + 1e-6)
    assert opt.iterations() <= 20
