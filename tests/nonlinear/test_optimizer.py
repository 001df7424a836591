"""Gauss–Newton with Schwarz-preconditioned CG against GTSAM's own GaussNewtonOptimizer."""

import gtsam
import numpy as np
import pytest

from conftest import dataset, gtsam_gauss_newton, pose2_array, pose2_difference
from gtsam_schwarz import LINEAR_SOLVERS, SchwarzOptimizer, SchwarzParams, square_loops

# a fixed number of exact steps (forcing "none"), compared with GTSAM's step for step
FIXED = dict(initialization="file", relative_error_tol=0.0, absolute_error_tol=-1.0, gradient_tol=0.0, relative_gradient_tol=0.0,
             forcing="none")


@pytest.fixture(scope="module")
def model():
    return square_loops(8, 8, sigma=0.01, seed=0)


@pytest.fixture(scope="module")
def model_reference(model):
    return gtsam_gauss_newton(model.graph, model.initial, 5)


@pytest.mark.parametrize("name", LINEAR_SOLVERS)
def test_model_problem_matches_gtsam_gauss_newton(model, model_reference, name):
    """Same number of steps from the same start: same error (1e-6 rel.) and poses (1e-6)."""
    opt = SchwarzOptimizer(model.graph, model.initial,
                           SchwarzParams(method="gn", preconditioner=name, subdomains=8, max_iterations=5, **FIXED))
    result = opt.optimize()
    assert opt.iterations() == 5
    ref_error = model.graph.error(model_reference)
    assert opt.error() == pytest.approx(ref_error, rel=1e-6)
    assert np.abs(pose2_difference(result, model_reference)).max() < 1e-6
    assert all(h["cg_converged"] for h in opt.history)


def test_default_stopping_converges_to_gtsam_optimum(model, model_reference):
    opt = SchwarzOptimizer(model.graph, model.initial, SchwarzParams(initialization="file", preconditioner="gdsw", method="gn", subdomains=8))
    result = opt.optimize()
    assert opt.converged
    assert 2 <= opt.iterations() <= 10
    default = gtsam.GaussNewtonOptimizer(model.graph, model.initial, gtsam.GaussNewtonParams()).optimize()
    assert opt.error() == pytest.approx(model.graph.error(default), rel=1e-6)
    assert np.abs(pose2_difference(result, model_reference)).max() < 1e-6
    # closer to the ground truth than dead reckoning is
    truth = model.ground_truth
    assert np.abs(pose2_difference(result, truth)).max() < 0.5 * np.abs(pose2_difference(model.initial, truth)).max()


@pytest.fixture(scope="module")
def m3500():
    graph, initial = gtsam.readG2o(str(dataset("input_M3500_g2o.g2o")), False)
    graph.add(gtsam.PriorFactorPose2(0, initial.atPose2(0), gtsam.noiseModel.Isotropic.Sigma(3, 1e-3)))
    ref = gtsam_gauss_newton(graph, initial, 6)
    # GTSAM's own noise floor: how far its poses still move in two more steps
    drift = np.abs(pose2_difference(gtsam_gauss_newton(graph, initial, 8), ref)).max()
    return graph, initial, ref, drift


@pytest.mark.datasets
@pytest.mark.parametrize("name", ["gdsw", "one-level"])
def test_m3500_matches_gtsam_gauss_newton(m3500, name):
    """M3500: error to 1e-6 relative; positions to 1e-6 of the map's extent.

    Absolute pose agreement is limited by conditioning and GTSAM's inexact BetweenFactorPose2
    Jacobian: GTSAM's own GN still moves poses by ~5e-6 in steps 7–8, and two direct solvers
    differ by ~1e-6 after two steps. So the poses must agree to within 10× that drift.
    """
    graph, initial, ref, drift = m3500
    opt = SchwarzOptimizer(graph, initial, SchwarzParams(method="gn", preconditioner=name, subdomains=7,
                                                         max_iterations=6, **FIXED))
    result = opt.optimize()
    assert opt.error() == pytest.approx(graph.error(ref), rel=1e-6)
    extent = np.abs(pose2_array(ref)[:, :2]).max()
    d = pose2_difference(result, ref)
    assert np.abs(d[:, :2]).max() < 1e-6 * extent
    assert np.abs(d).max() < 10 * drift


def test_history_records_each_step(model):
    opt = SchwarzOptimizer(model.graph, model.initial, SchwarzParams(initialization="file", preconditioner="gdsw", method="gn", subdomains=8))
    opt.optimize()
    assert opt.history
    for i, h in enumerate(opt.history, 1):
        assert h["iteration"] == i
        for key in ("error", "gradient_norm", "cg_iterations", "lambda_min", "lambda_max"):
            assert np.isfinite(h[key])
        assert set(h["seconds"]) == {"linearize", "export", "setup", "cg", "update"}
        assert all(t >= 0 for t in h["seconds"].values())
        assert 0.5 < h["lambda_min"] <= h["lambda_max"] < 10  # GDSW: well conditioned
        assert len(h["cg_residuals"]) == h["cg_iterations"] + 1
    errors = [opt.initial_error] + [h["error"] for h in opt.history]
    assert all(b <= a for a, b in zip(errors, errors[1:]))


def test_paper_gradient_rule_stops(model):
    opt = SchwarzOptimizer(model.graph, model.initial, SchwarzParams(initialization="file", preconditioner="gdsw", method="gn", 
        subdomains=8, relative_error_tol=0.0, absolute_error_tol=-1.0, max_iterations=30))
    opt.optimize()
    assert opt.converged and "gradient" in opt.stop_reason
    assert opt.final_gradient_norm <= 1e-6 * opt.history[0]["gradient_norm"]
    assert opt.iterations() < 30


def test_iteration_cap_and_cg_cap_are_reported(model):
    opt = SchwarzOptimizer(model.graph, model.initial, SchwarzParams(method="gn", 
        preconditioner="none", max_iterations=2, cg_max_iterations=3, **FIXED))
    opt.optimize()
    assert opt.iterations() == 2 and not opt.converged and "maximum" in opt.stop_reason
    assert [h["cg_iterations"] for h in opt.history] == [3, 3]
    assert not any(h["cg_converged"] for h in opt.history)


def test_gauss_newton_step_that_increases_the_error_falls_back_to_damping():
    """GN never stops at a worse or unchanged point: a rejected step is retried with damping."""
    prob = square_loops(32, 16, sigma=0.1, seed=0)  # too noisy for undamped Gauss–Newton
    opt = SchwarzOptimizer(prob.graph, prob.initial, SchwarzParams(initialization="file", preconditioner="gdsw", method="gn", subdomains=32))
    result = opt.optimize()
    rejected = [h for h in opt.history if not h["accepted"]]
    assert rejected and rejected[0]["lambda"] == 0.0 and rejected[0]["error"] > rejected[0]["error_before"]
    damped = [h for h in opt.history if h["accepted"] and h["lambda"] > 0]
    assert damped  # the fallback took damped steps
    assert opt.error() == pytest.approx(prob.graph.error(result))
    lm = gtsam.LevenbergMarquardtOptimizer(prob.graph, prob.initial, gtsam.LevenbergMarquardtParams()).optimize()
    assert opt.error() <= prob.graph.error(lm) * (1 + 1e-4)
    assert np.all(np.isfinite(pose2_array(result)))


@pytest.mark.parametrize("kwargs, match", [
    (dict(preconditioner="ilu"), "unknown preconditioner 'ilu'"),
    (dict(subdomains=0), "subdomains"),
    (dict(overlap=-1), "overlap"),
    (dict(cg_tol=0.0), "cg_tol"),
])
def test_bad_params_are_refused(kwargs, match):
    with pytest.raises(ValueError, match=match):
        SchwarzParams(**kwargs)


def gtsam_lm(graph, initial):
    opt = gtsam.LevenbergMarquardtOptimizer(graph, initial, gtsam.LevenbergMarquardtParams())
    return opt.optimize()


@pytest.mark.datasets
@pytest.mark.parametrize("name", ["gdsw", "rgdsw", "one-level"])
def test_m3500_levenberg_marquardt_matches_gtsam_lm(m3500, name):
    graph, initial, _, _ = m3500
    ref = graph.error(gtsam_lm(graph, initial))
    opt = SchwarzOptimizer(graph, initial, SchwarzParams(initialization="file", method="lm", preconditioner=name,
                                                         partition="metis", subdomains=8))
    opt.optimize()
    assert opt.converged
    assert opt.error() <= ref * (1 + 1e-6)
    assert opt.summary()["subdomains"] == 8


@pytest.mark.parametrize("name", ["block-jacobi", "gdsw", "direct"])
def test_model_problem_levenberg_marquardt_matches_gtsam_lm(name):
    prob = square_loops(8, 8, sigma=0.05, seed=3)
    ref = prob.graph.error(gtsam_lm(prob.graph, prob.initial))
    opt = SchwarzOptimizer(prob.graph, prob.initial, SchwarzParams(initialization="file", method="lm", preconditioner=name, subdomains=8))
    opt.optimize()
    assert opt.error() <= ref * (1 + 1e-6)
    assert all(h["lambda"] > 0 for h in opt.history)


def test_levenberg_marquardt_rejects_bad_steps_and_raises_lambda():
    prob = square_loops(32, 16, sigma=0.1, seed=0)  # Gauss-Newton's first step increases the error
    opt = SchwarzOptimizer(prob.graph, prob.initial, SchwarzParams(initialization="file", preconditioner="gdsw", method="lm", subdomains=32, max_iterations=60))
    opt.optimize()
    rejected = [h for h in opt.history if not h["accepted"]]
    assert rejected, "expected at least one rejected LM step"
    for h in rejected:
        later = [g for g in opt.history if g["iteration"] == h["iteration"] and g is not h]
        assert all(g["lambda"] > h["lambda"] for g in later if opt.history.index(g) > opt.history.index(h))
    ref = prob.graph.error(gtsam_lm(prob.graph, prob.initial))
    assert opt.error() <= ref * (1 + 1e-6)


@pytest.mark.datasets
def test_inexact_newton_saves_cg_iterations_on_m3500(m3500):
    graph, initial, _, _ = m3500
    ref = graph.error(gtsam_lm(graph, initial))
    runs = {}
    for forcing in ("none", "eisenstat-walker"):
        opt = SchwarzOptimizer(graph, initial, SchwarzParams(initialization="file", preconditioner="gdsw", method="lm", partition="metis", subdomains=8,
                                                             forcing=forcing))
        opt.optimize()
        runs[forcing] = opt
    exact, inexact = runs["none"], runs["eisenstat-walker"]
    assert inexact.summary()["cg_total"] < exact.summary()["cg_total"]
    assert any(h["cg_tolerance"] > 1e-8 for h in inexact.history)
    assert inexact.error() <= ref * (1 + 1e-6)


def test_pose3_helix_levenberg_marquardt_matches_gtsam_and_gdsw_stays_bounded():
    """3D: same answer as GTSAM's LM; GDSW iterations flat in the number of loops, one-level not."""
    from gtsam_schwarz import helix_loops
    cg = {}
    for L in (4, 16):
        prob = helix_loops(L, 8, sigma=0.01, seed=0)
        ref = prob.graph.error(gtsam_lm(prob.graph, prob.initial))
        for name in ("gdsw", "one-level"):
            opt = SchwarzOptimizer(prob.graph, prob.initial, SchwarzParams(initialization="file", method="lm", preconditioner=name, subdomains=L))
            opt.optimize()
            assert opt.error() <= ref * (1 + 1e-6)
            cg[name, L] = opt.summary()["cg_mean"]
    assert cg["gdsw", 16] <= 1.3 * cg["gdsw", 4] + 2
    assert cg["one-level", 16] >= 2 * cg["one-level", 4]


def test_remaining_decrease_estimate():
    from gtsam_schwarz.nonlinear.optimizer import remaining_decrease
    assert remaining_decrease(1e-3, None) == float("inf")  # no rate yet: not a reason to stop
    assert remaining_decrease(0.0, 1.0) == 0.0
    assert remaining_decrease(1e-3, 2e-3) == pytest.approx(1e-3)  # r = 1/2: as much again to come
    assert remaining_decrease(1e-6, 1e-3) == pytest.approx(1e-9 / (1 - 1e-3))  # fast convergence
    assert remaining_decrease(2.0, 1.0) == pytest.approx(2.0 * 0.99 / 0.01)  # growing: r capped at 0.99


@pytest.mark.datasets
def test_mit_from_the_file_reaches_gtsam_tight_minimum_with_default_tolerances():
    """MIT converges linearly from the file's guess: GTSAM's relative-decrease rule alone stops 7.5e-6
    above the minimum; the remaining-decrease check goes on to within 1e-6 of GTSAM LM at 1e-10."""
    from gtsam_schwarz.io import load_graph
    loaded = load_graph(dataset("MIT.g2o"))
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-10)
    params.setAbsoluteErrorTol(1e-10)
    params.setMaxIterations(1000)
    ref = loaded.graph.error(gtsam.LevenbergMarquardtOptimizer(loaded.graph, loaded.initial, params).optimize())
    gtsam_rule = SchwarzOptimizer(loaded.graph, loaded.initial,
                                  SchwarzParams(initialization="file", remaining_decrease_tol=0.0))
    gtsam_rule.optimize()
    ours = SchwarzOptimizer(loaded.graph, loaded.initial, SchwarzParams(initialization="file"))
    ours.optimize()
    assert ours.converged and "remaining decrease" in ours.stop_reason
    assert gtsam_rule.error() > ref * (1 + 1e-6)  # the case the check exists for
    assert ref * (1 - 1e-9) <= ours.error() <= ref * (1 + 1e-6)


def test_newton_decrement_stops_the_last_solve_early():
    """Once CG bounds the exact step's decrease so that GTSAM's error rule would stop after it, and has
    reached all of it but remaining_decrease_tol × error, the last solve stops early and the loop
    after it: the final error is the fully solved run's within that (and GTSAM LM's to 1e-6)."""
    from gtsam_schwarz.problems.survey import survey3d

    pb = survey3d(4, 10, 10)
    runs = {}
    for rule in (True, False):
        opt = SchwarzOptimizer(pb.graph, pb.initial, SchwarzParams(preconditioner="rgdsw-linear", newton_decrement=rule,
                                                                   forcing="none"))  # the rule alone
        opt.optimize()
        runs[rule] = opt
    on, off = runs[True], runs[False]
    assert on.converged and off.converged
    assert "Newton decrement" in on.stop_reason and on.history[-1].decrement_stop
    assert "Newton decrement" not in off.stop_reason and not any(h.decrement_stop for h in off.history)
    cg_on, cg_off = on.summary()["cg_iterations"], off.summary()["cg_iterations"]
    assert len(cg_on) == len(cg_off) and cg_on[:-1] == cg_off[:-1] and cg_on[-1] < cg_off[-1]
    e_on, e_off = on.summary()["final_error"], off.summary()["final_error"]
    assert abs(e_on - e_off) <= 1e-7 * e_off
    lm = gtsam.LevenbergMarquardtOptimizer(pb.graph, pb.initial, gtsam.LevenbergMarquardtParams()).optimize()
    assert abs(e_on - pb.graph.error(lm)) <= 1e-6 * pb.graph.error(lm)


def test_automatic_forcing_is_inexact_for_schwarz_cg_and_exact_for_direct():
    """forcing="auto" (the default): Eisenstat–Walker tolerances where Schwarz-preconditioned CG
    solves the steps, cg_tol where the direct factorization does (its lagged CG included); both reach
    GTSAM LM's error to 1e-6."""
    from gtsam_schwarz.nonlinear.linear_solver import Forcing
    from gtsam_schwarz.nonlinear.params import LinearSolverParams
    from gtsam_schwarz.problems.survey import survey3d

    p = LinearSolverParams()
    assert p.forcing == "auto"
    assert Forcing(p, krylov=lambda: False).tolerance(1.0) == p.cg_tol
    assert Forcing(p, krylov=lambda: True).tolerance(1.0) == p.forcing_max
    pb = survey3d(4, 10, 10)
    lm = pb.graph.error(gtsam.LevenbergMarquardtOptimizer(pb.graph, pb.initial, gtsam.LevenbergMarquardtParams()).optimize())
    schwarz = SchwarzOptimizer(pb.graph, pb.initial, SchwarzParams(preconditioner="rgdsw-linear"))
    schwarz.optimize()
    assert any(h.cg_tolerance > p.cg_tol for h in schwarz.history)
    direct = SchwarzOptimizer(pb.graph, pb.initial, SchwarzParams(preconditioner="direct"))
    direct.optimize()
    assert all(h.cg_tolerance <= p.cg_tol for h in direct.history)
    for opt in (schwarz, direct):
        assert opt.converged and abs(opt.error() - lm) <= 1e-6 * lm


def test_forcing_probe_is_the_first_inexact_solves_only():
    """The looser ``forcing_probe`` applies to the run's first inexact solve alone: not once a forcing
    term exists, not to an exact retry, not for exact solvers, not when off or tighter than the term."""
    from gtsam_schwarz.nonlinear.linear_solver import Forcing
    from gtsam_schwarz.nonlinear.params import LinearSolverParams

    p = LinearSolverParams()
    first = Forcing(p, krylov=lambda: True)
    tol = first.tolerance(1.0)
    assert tol == p.forcing_max and first.probe(tol) == p.forcing_probe > tol
    first.solved(1.0, p.forcing_probe)
    assert first.probe(first.tolerance(0.1)) is None
    retry = Forcing(p, krylov=lambda: True)
    retry.exact_next = True
    assert retry.probe(retry.tolerance(1.0)) is None
    assert Forcing(p, krylov=lambda: False).probe(p.cg_tol) is None
    assert Forcing(LinearSolverParams(forcing_probe=0.0), krylov=lambda: True).probe(p.forcing_max) is None
    assert Forcing(LinearSolverParams(forcing_probe=1e-4), krylov=lambda: True).probe(p.forcing_max) is None


@pytest.mark.parametrize("case", ["nonlinear 2D", "nearly linear 3D"])
def test_first_step_probe_keeps_or_refines_and_reaches_the_same_minimum(case):
    """The first solve goes to ``forcing_probe`` (1e-2) first. A noisy lawnmower's first step has a
    model error (predicted against actual decrease) above what CG left: kept, in fewer CG iterations
    than to the forcing term. A 3D survey's model is nearly exact there: CG continues to the forcing
    term from where it stopped. Both end where the run without the probe does, and at GTSAM LM's error."""
    from gtsam_schwarz.problems import lawnmower
    from gtsam_schwarz.problems.survey import survey3d

    pb = lawnmower(30, 30, sigma=0.05) if case == "nonlinear 2D" else survey3d(4, 10, 10)
    runs = {}
    for probe in (1e-2, 0.0):
        opt = SchwarzOptimizer(pb.graph, pb.initial, SchwarzParams(preconditioner="rgdsw-linear", forcing_probe=probe))
        opt.optimize()
        assert opt.converged
        runs[probe] = opt
    probed, plain = runs[1e-2].history[0], runs[0.0].history[0]
    assert plain.probe == "" and all(h.probe == "" for h in runs[1e-2].history[1:])
    if case == "nonlinear 2D":
        assert probed.probe == "kept" and probed.cg_tolerance == 1e-2
        assert probed.cg_iterations < plain.cg_iterations
        assert abs(probed.error_before - probed.error - probed.predicted_decrease) > 1e-3 * probed.predicted_decrease
    else:
        assert probed.probe == "refined" and probed.cg_tolerance == plain.cg_tolerance == 1e-3
        assert probed.cg_residuals[-1] <= 1e-3 and len(probed.cg_residuals) == probed.cg_iterations + 1   # both parts
    e_probe, e_plain = runs[1e-2].error(), runs[0.0].error()
    assert abs(e_probe - e_plain) <= 1e-8 * e_plain
    lm = pb.graph.error(gtsam.LevenbergMarquardtOptimizer(pb.graph, pb.initial, gtsam.LevenbergMarquardtParams()).optimize())
    assert e_probe <= lm * (1 + 1e-6)


def test_cost_model_counts_the_forcing_terms_cg_iterations():
    """The automatic choice predicts Schwarz with the CG iterations its solves will take: fewer under
    the forcing term ("auto", the default) than to cg_tol ("none"); a prediction within the margin
    keeps the direct solver."""
    from gtsam_schwarz.nonlinear.linear_solver import AutoSolver, CostModel
    from gtsam_schwarz.nonlinear.params import LinearSolverParams

    exact, inexact = CostModel(), CostModel(inexact=True)
    assert inexact.two_level_iterations < exact.two_level_iterations
    assert inexact.schwarz_floor(10**6) == exact.schwarz_floor(10**6)  # the shortcut to direct stays where it was
    offsets, mask = np.arange(0, 31, 3), np.ones(30, bool)
    assert AutoSolver(LinearSolverParams(), offsets, mask).model.two_level_iterations == inexact.two_level_iterations
    assert AutoSolver(LinearSolverParams(forcing="none"), offsets, mask).model.two_level_iterations == exact.two_level_iterations
    assert 0 < AutoSolver.SCHWARZ_MARGIN < 1


@pytest.mark.parametrize("name", ["direct", "rgdsw-linear"])
def test_a_run_releases_its_solver_and_can_go_on(name):
    """optimize() drops the linear solver's numbers before building the result; iterating on from
    there builds them anew (a fresh factorization or preconditioner, not a lagged one) and keeps the
    optimum (the error does not rise)."""
    from gtsam_schwarz.problems import lawnmower
    prob = lawnmower(20, 20, sigma=0.01, seed=0)
    opt = SchwarzOptimizer(prob.graph, prob.initial, SchwarzParams(method="lm", preconditioner=name, subdomains=4))
    opt.optimize()
    solver = opt.linear_solver
    if name == "direct":
        assert solver._released and solver._factor._factor is None
    else:
        assert solver.operator.coarse_space is None and not solver.operator.subdomains_factored
    error = opt.error()
    opt.iterate()
    assert opt.error() <= error * (1 + 1e-12)
    record = opt.history[-1]
    assert not record.preconditioner_lagged and record.preconditioner_rebuilt


@pytest.mark.parametrize("lam", [0.0, 1e-3, 10.0])
def test_model_change_of_an_exact_step_needs_no_product_by_h(model, lam):
    """For a step that solves the damped system (H + diag(d))δ = −g exactly (direct factorization),
    the undamped model's change ½gᵀδ − ½δᵀdiag(d)δ equals gᵀδ + ½δᵀHδ; the direct solver says its
    solves are exact, CG's are not; and a direct LM run predicts what its steps then did."""
    import scipy.sparse as sp
    import scipy.sparse.linalg as spla

    opt = SchwarzOptimizer(model.graph, model.initial, SchwarzParams(method="lm", preconditioner="direct"))
    system = opt._linearize()   # also fixes the gauge anchors the damping adds
    d, diag = opt._damping(system, lam)
    A = system.H + (sp.diags(d) if d is not None else 0)
    dx = spla.spsolve(sp.csc_matrix(A), system.rhs)
    _, _, exact = opt._evaluate(system, dx, (d, diag))
    _, _, explicit = opt._evaluate(system, dx)
    assert exact < 0 and exact == pytest.approx(explicit, rel=1e-9)
    with opt._damped(system, lam) as H:
        assert opt.linear_solver.solve(H, system.rhs, 1e-8, None).exact
    cg = SchwarzOptimizer(model.graph, model.initial, SchwarzParams(method="lm", preconditioner="gdsw", subdomains=8))
    cg_system = cg._linearize()
    with cg._damped(cg_system, lam) as H:
        assert not cg.linear_solver.solve(H, cg_system.rhs, 1e-8, lambda: cg.linearizer.geometry(cg._state)).exact
    opt.optimize()
    for h in opt.history:
        if h["accepted"] and h["error_before"] - h["error"] > 1e-9 * h["error_before"]:
            assert h["model_fidelity"] == pytest.approx(1.0, abs=0.2)
