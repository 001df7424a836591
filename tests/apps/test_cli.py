"""The gtsam-schwarz command line, run as a user would (subprocess)."""

import json

import gtsam
import pytest

from conftest import dataset, one_line_error, run_cli
from gtsam_schwarz import load_graph


def cli(*args, cwd=None, timeout=600):
    return run_cli(*args, cwd=cwd, timeout=timeout)


@pytest.fixture(scope="module")
def small_g2o(tmp_path_factory):
    path = tmp_path_factory.mktemp("synth") / "loops.g2o"
    proc = cli("synth", "--loops", 4, "--points-per-side", 4, "--sigma", 0.02, "--seed", 1, "-o", path)
    assert proc.returncode == 0, proc.stderr
    assert "wrote" in proc.stdout
    return path


def test_synth_writes_the_model_problem_with_dead_reckoning(small_g2o):
    loaded = load_graph(small_g2o)
    assert loaded.poses == 4 * 4 * 4 + 1 and loaded.edges == 64 + 4
    assert loaded.initial_guess == "file"
    # the VERTEX lines are dead reckoning: every odometry factor has zero error there
    g = loaded.graph
    odo = [g.at(i) for i in range(g.size()) if len(g.at(i).keys()) == 2
           and g.at(i).keys()[1] == g.at(i).keys()[0] + 1]
    assert len(odo) == 64 and max(f.error(loaded.initial) for f in odo) < 1e-12


def test_synth_refuses_to_overwrite_without_force(small_g2o):
    one_line_error(cli("synth", "--loops", 2, "--points-per-side", 2, "-o", small_g2o), "exists")


def test_solve_json_matches_gtsam_lm(small_g2o, tmp_path):
    out, plot = tmp_path / "opt.g2o", tmp_path / "opt.png"
    proc = cli("solve", small_g2o, "--json", "--preconditioner", "gdsw", "--subdomains", 4, "--partition", "segments",
               "-o", out, "--plot", plot)
    assert proc.returncode == 0, proc.stderr
    report = json.loads(proc.stdout)
    for key in ("poses", "edges", "dimension", "method", "preconditioner", "subdomains", "overlap", "iterations",
                "cg_iterations", "cg_mean", "initial_error", "final_error", "converged", "seconds"):
        assert key in report
    assert set(report["seconds"]) >= {"total", "linearize", "setup", "cg"}
    assert report["method"] == "lm" and report["preconditioner"] == "gdsw" and report["subdomains"] == 4
    assert report["converged"] and report["final_error"] < report["initial_error"]
    assert report["linear_solver"] == {"requested": "gdsw", "used": "gdsw", "reason": ""}
    loaded = load_graph(small_g2o)
    ref = gtsam.LevenbergMarquardtOptimizer(loaded.graph, loaded.initial, gtsam.LevenbergMarquardtParams()).optimize()
    assert report["final_error"] <= loaded.graph.error(ref) * (1 + 1e-6)
    written = load_graph(out)
    assert written.graph.error(written.initial) == pytest.approx(report["final_error"], rel=1e-6)
    assert plot.stat().st_size > 1000


def test_solve_human_output_has_a_line_per_iteration(small_g2o):
    proc = cli("solve", small_g2o, "--method", "gn", "--preconditioner", "one-level", "--subdomains", 2)
    assert proc.returncode == 0, proc.stderr
    iters = [line for line in proc.stdout.splitlines() if line.strip().startswith("iter")]
    assert iters and "converged" in proc.stdout.splitlines()[-1] or "stopped" in proc.stdout


def test_solve_refuses_to_overwrite_its_input(small_g2o):
    before = small_g2o.read_bytes()
    one_line_error(cli("solve", small_g2o, "-o", small_g2o), "input")
    assert small_g2o.read_bytes() == before


@pytest.mark.parametrize("args, words", [
    (("solve", "/no/such/file.g2o"), ["no such file"]),
    (("solve", "{data}", "--preconditioner", "ilu"), ["invalid choice", "ilu"]),
    (("solve", "{data}", "--subdomains", "zero"), ["expected an integer"]),
    (("solve", "{data}", "--cg-tol", "-1"), ["expected a number > 0"]),
    (("compare", "/no/such/file.g2o"), ["no such file"]),
    (("synth", "--loops", "2"), ["required"]),
])
def test_bad_input_is_one_line_exit_2(small_g2o, args, words):
    args = [a.replace("{data}", str(small_g2o)) for a in args]
    one_line_error(cli(*args), *words)


def test_malformed_file_names_the_line(tmp_path):
    bad = tmp_path / "bad.g2o"
    bad.write_text("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\nEDGE_SE2 0 1 1 0 abc 1 0 0 1 0 1\n")
    one_line_error(cli("solve", bad), "bad.g2o:3", "dtheta")


@pytest.mark.datasets
@pytest.mark.slow
def test_compare_json_rows(tmp_path):
    proc = cli("compare", dataset("MIT.g2o"), "--json")
    assert proc.returncode == 0, proc.stderr
    rows = json.loads(proc.stdout)["rows"]
    names = [r["solver"] for r in rows]
    for want in ("gtsam-lm", "gtsam-gn", "gtsam-lm-pcg", "gtsam-lm-subgraph"):
        assert want in names
    assert any(n.endswith("gdsw") for n in names) and any(n.endswith("block-jacobi") for n in names)
    for r in rows:
        assert {"solver", "final_error", "iterations", "seconds"} <= set(r)
    ref = next(r for r in rows if r["solver"] == "gtsam-lm")["final_error"]
    gdsw = next(r for r in rows if r["solver"].endswith("gdsw"))
    assert gdsw["final_error"] <= ref * (1 + 1e-6)


def test_demo_quick_json_reports_the_three_parts_and_writes_the_figure(tmp_path):
    proc = cli("demo", "--quick", "--json", "--out", tmp_path, "-q")
    assert proc.returncode == 0, proc.stderr
    report = json.loads(proc.stdout)
    rows = {r["solver"]: r for r in report["solve"]["rows"]}
    ref = rows["GTSAM LM"]["final_error"]
    ours = rows["ours (auto)"]
    assert abs(ours["final_error"] - ref) <= 1e-6 * ref and ours["converged"]
    assert ours["ate_rmse"] < report["solve"]["initial"]["ate_rmse"]
    largest = report["scaling"][-1]
    assert largest["gdsw"] < largest["one-level"] < largest["block-jacobi"]  # the paper's ordering
    for r in report["fill"]:
        assert r["fill"] > 1 and r["rgdsw-linear"]["residual"] < 1e-7 and r["direct"]["residual"] < 1e-9
        assert r["auto_choice"] in ("direct", "gdsw", "rgdsw-linear") and isinstance(r["auto_picks_faster"], bool)
    assert (tmp_path / "demo.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_demo_prints_tables(tmp_path):
    proc = cli("demo", "--quick", "--out", tmp_path / "demo", "-q")
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr == ""
    for text in ("1. Same answer", "2. Bounded CG", "3. Where fill explodes", "GTSAM LM", "ours (auto)", "demo.png"):
        assert text in proc.stdout


@pytest.mark.datasets
@pytest.mark.parametrize("pre", ["gdsw", "gdsw-norot", "rgdsw", "one-level", "block-jacobi", "direct"])
def test_solve_3d_file_every_preconditioner(pre):
    path = dataset("smallGrid3D.g2o")
    proc = cli("solve", path, "--json", "--preconditioner", pre, "--subdomains", 4)
    assert proc.returncode == 0, proc.stderr
    report = json.loads(proc.stdout)
    assert report["dimension"] == 3 and report["poses"] == 125
    loaded = load_graph(path)
    ref = gtsam.LevenbergMarquardtOptimizer(loaded.graph, loaded.initial, gtsam.LevenbergMarquardtParams()).optimize()
    assert report["final_error"] <= loaded.graph.error(ref) * (1 + 1e-6)


def test_default_linear_solver_is_automatic_and_says_why(small_g2o):
    proc = cli("solve", small_g2o, "--json", "-q")
    assert proc.returncode == 0, proc.stderr
    report = json.loads(proc.stdout)
    assert report["preconditioner"] == "auto" and report["linear_solver"]["requested"] == "auto"
    assert report["linear_solver"]["used"] in ("direct", "gdsw") and "predicted" in report["linear_solver"]["reason"]
    human = cli("solve", small_g2o, "-q")
    assert f"linear solver: {report['linear_solver']['used']} (auto: nnz(L)" in human.stdout
