"""``gtsam-schwarz bench``: the tiny size end to end (subprocess), and the child runner's crash/timeout rows.

No timing assertions: only that every figure is there and sane.
"""

import ast
import json
import math
import pathlib
import resource
import subprocess
import sys

import pytest

from conftest import DATASETS
from gtsam_schwarz.apps.bench import PHASES, SOLVERS, run_child

ROOT = pathlib.Path(__file__).resolve().parents[2]
STACK = resource.getrlimit(resource.RLIMIT_STACK)  # (soft, hard) that the bench's children inherit


def _limit(value):
    return None if value == resource.RLIM_INFINITY else value


def bench(*args, timeout=300):
    return subprocess.run([sys.executable, "-m", "gtsam_schwarz.apps.cli", "bench", "--size", "tiny",
                           "--datasets", str(DATASETS), *map(str, args)],
                          capture_output=True, text=True, cwd=ROOT, timeout=timeout)


@pytest.fixture(scope="module")
def report():
    proc = bench("--json")
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.strip().splitlines()
    assert len(lines) == 1, proc.stdout  # exactly one JSON object, nothing else
    return json.loads(lines[0])


@pytest.mark.datasets
@pytest.mark.slow
def test_every_run_is_ok_and_ours_matches_gtsam_lm(report):
    runs = report["runs"]
    assert [c["name"] for c in report["cases"]] == ["sq8x16", "smallGrid3D"]
    assert {(r["case"], r["solver"]) for r in runs} == {(c, s) for c in ("sq8x16", "smallGrid3D") for s in SOLVERS}
    assert all(r["status"] == "ok" for r in runs), [(r["case"], r["solver"], r["status"]) for r in runs]
    for case in ("sq8x16", "smallGrid3D"):
        by = {r["solver"]: r for r in runs if r["case"] == case}
        lm = by["gtsam-lm"]
        for solver in ("ours", "ours-direct", "ours-schwarz"):
            ours = by[solver]
            assert abs(ours["final_error"] - lm["final_error"]) <= 1e-6 * lm["final_error"], solver
            assert ours["rel_error_diff"] <= 1e-6 and ours["same_error"] is True, solver


@pytest.mark.datasets
@pytest.mark.slow
def test_ratios_memory_and_stack_figures(report):
    for r in report["runs"]:
        assert math.isfinite(r["ratio_to_gtsam_lm"]) and r["ratio_to_gtsam_lm"] > 0
        assert r["seconds"] > 0 and r["iterations"] >= 1 and r["poses"] > 0
        assert r["peak_mib"] >= r["loaded_mib"] > 0 and 0 < r["solve_peak_mib"] <= r["peak_mib"]
        if sys.platform.startswith("linux"):   # the heap in use (glibc): below the RSS but for untouched pages
            assert 0 < r["live_peak_mib"] <= r["peak_mib"] + 64, (r["solver"], r["live_peak_mib"], r["peak_mib"])
        if r["solver"] in ("gtsam-lm-pcg", "gtsam-lm-subgraph", "ours-direct", "ours-schwarz"):
            assert math.isfinite(r["over_ours"]) and r["over_ours"] > 0
        # GTSAM's children run with the stack limit raised as far as allowed, ours with the inherited one
        expected = STACK[1] if not r["solver"].startswith("ours") else STACK[0]
        assert r["stack"]["bytes"] == _limit(expected)


@pytest.mark.datasets
@pytest.mark.slow
def test_our_split_has_the_five_phases(report):
    requested = {"ours": "auto", "ours-direct": "direct", "ours-schwarz": "rgdsw-linear"}
    for r in (r for r in report["runs"] if r["solver"] in requested):
        assert set(r["split"]) == set(PHASES) and set(r["split_per_iteration"]) == set(PHASES)
        for k in PHASES:
            assert r["split"][k] >= 0
            assert r["split_per_iteration"][k] == pytest.approx(r["split"][k] / r["iterations"])
        assert r["linear_solver"]["requested"] == requested[r["solver"]]
        if r["solver"] == "ours":
            assert "predicted" in r["linear_solver"]["reason"]
        else:
            assert r["linear_solver"]["used"] == requested[r["solver"]]
        if r["linear_solver"]["used"] == "direct":
            assert r["cg_mean"] >= 0 and r["subdomains"] is None  # (CG preconditioned with a lagged factor)
        else:
            assert r["cg_mean"] > 0 and r["subdomains"] >= 1 and r["coarse_size"] >= 0


@pytest.mark.datasets
@pytest.mark.slow
def test_direct_vs_schwarz_section_per_case(report):
    pairs = {p["case"]: p for p in report["direct_vs_schwarz"]}
    assert set(pairs) == {"sq8x16", "smallGrid3D"}
    for case, p in pairs.items():
        by = {r["solver"]: r for r in report["runs"] if r["case"] == case}
        assert p["schwarz_over_direct"] == pytest.approx(by["ours-schwarz"]["seconds"] / by["ours-direct"]["seconds"])
        assert p["faster"] == ("schwarz" if p["schwarz_over_direct"] < 1 else "direct")
        assert p["auto_chose"] == by["ours"]["linear_solver"]["used"]
        assert isinstance(p["auto_picked_faster"], bool) and p["schwarz_cg_mean"] > 0


@pytest.mark.datasets
@pytest.mark.slow
def test_report_records_machine_command_and_params(report):
    m = report["machine"]
    assert m["cpu_count"] >= 1 and m["gtsam"] and m["numpy"] and m["scipy"]
    assert 0 < m["first_touch_ms_per_mib"] < 1e3  # measured: the machine's cost of fresh memory
    assert report["command"].startswith("gtsam-schwarz bench --size tiny")
    assert report["params"] == {"method": "lm", "preconditioner": "auto"}
    assert report["params_full"]["max_iterations"] == 100


def test_markdown_table_and_out_file(tmp_path):
    out = tmp_path / "sub" / "bench.md"
    proc = bench("--cases", "sq8x16", "--solvers", "ours,gtsam-lm", "--param", "subdomains=2", "--out", out)
    assert proc.returncode == 0, proc.stderr
    assert "| case | poses | solver |" in proc.stdout and "| sq8x16 | 513 | ours | ok |" in proc.stdout
    assert "| peak MiB | live MiB | Δ MiB |" in proc.stdout
    assert "time split per nonlinear iteration" in proc.stdout and "subdomains=2" in proc.stdout
    assert "Direct vs Schwarz" not in proc.stdout  # no ours-direct / ours-schwarz rows asked for
    text = out.read_text()
    assert text.startswith("# Benchmark: size tiny") and "| sq8x16 | 513 | gtsam-lm | ok |" in text
    assert "--param subdomains=2" in text


@pytest.mark.parametrize("args, words", [(("--cases", "sq8x16,nope"), ("nope", "sq8x16", "smallGrid3D")),
                                         (("--solvers", "ours,cholmod"), ("cholmod", "gtsam-lm-pcg")),
                                         (("--param", "no_such=1"), ("no_such",))])
def test_bad_names_are_one_line_usage_errors(args, words):
    proc = bench(*args)
    assert proc.returncode == 2 and proc.stdout == ""
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert all(w in lines[0] for w in words), lines[0]


def test_run_child_reports_a_crash_as_a_crash():
    r = run_child([sys.executable, "-c", "import os, signal; os.kill(os.getpid(), signal.SIGSEGV)"], timeout=60)
    assert r["status"] == "crashed (SIGSEGV)"
    r = run_child([sys.executable, "-c", "import os, signal; os.kill(os.getpid(), signal.SIGSEGV)"], timeout=60,
                  unlimited_stack=True)
    assert r["status"] == "crashed (SIGSEGV)"


def test_run_child_reports_a_timeout_and_kills_the_child():
    r = run_child([sys.executable, "-c", "import time; time.sleep(60)"], timeout=0.5)
    assert r["status"] == "timeout after 0.5 s"
    assert r["child_seconds"] < 30


def test_run_child_reports_an_error_with_the_last_stderr_line():
    r = run_child([sys.executable, "-c", "import sys; print('first', file=sys.stderr); sys.exit('last words')"],
                  timeout=60)
    assert r["status"] == "error (exit 1): last words"


def test_run_child_raises_the_stack_limit_only_when_asked():
    code = "import resource; print(resource.getrlimit(resource.RLIMIT_STACK))"
    default = run_child([sys.executable, "-c", code], timeout=60)
    raised = run_child([sys.executable, "-c", code], timeout=60, unlimited_stack=True)
    assert raised["status"] == default["status"] == "ok"
    assert ast.literal_eval(default["stdout"].strip()) == STACK
    assert ast.literal_eval(raised["stdout"].strip()) == (STACK[1], STACK[1])  # unlimited where the hard limit allows


def test_a_direct_run_that_would_not_fit_is_a_row_and_pairs_with_schwarz():
    """The forced direct solver refuses (predicted) to factorize beyond the memory limit: its row
    says so, and the Direct vs Schwarz table counts Schwarz finishing as the faster."""
    from gtsam_schwarz.apps.bench import OUT_OF_MEMORY, _pair_row, direct_vs_schwarz

    proc = bench("--cases", "sq8x16", "--solvers", "ours-direct", "--param", "memory_limit=1K", "--json")
    assert proc.returncode == 0, proc.stderr
    (row,) = json.loads(proc.stdout)["runs"]
    assert row["status"].startswith(f"failed: {OUT_OF_MEMORY}") and "direct factorization needs about" in row["status"]
    schwarz = {"case": "sq8x16", "solver": "ours-schwarz", "status": "ok", "seconds": 1.0, "peak_mib": 10.0,
               "cg_mean": 20.0, "subdomains": 4, "coarse_size": 12}
    auto = {**schwarz, "solver": "ours", "linear_solver": {"used": "rgdsw-linear"}}
    (pair,) = direct_vs_schwarz([row, schwarz, auto])
    assert pair["faster"] == "schwarz" and pair["auto_picked_faster"] is True
    assert math.isnan(pair["schwarz_over_direct"]) and _pair_row(pair)[1] == "does not fit"
    assert direct_vs_schwarz([schwarz, auto]) == []  # no direct row at all: nothing to compare


def test_repeat_interleaves_the_solvers_and_keeps_each_median_run(monkeypatch):
    """--repeat N: every (case, solver) N times, the solvers' order rotated each round; each row is its
    median run with every run's seconds listed; a failed run is the row (never hidden by a median)."""
    from gtsam_schwarz.apps import bench as B
    calls, times = [], {"ours": iter([3.0, 1.0, 2.0]), "gtsam-lm": iter([5.0, 4.0, 6.0])}

    def fake(case, solver, overrides, datasets, timeout, env=None):
        calls.append(solver)
        t = next(times[solver])
        return {"case": case.name, "solver": solver, "status": "ok", "seconds": t, "final_error": 1.0, "tag": t}

    monkeypatch.setattr(B, "run_solver", fake)
    rows = B.benchmark([B.ALL_CASES["sq8x16"]], ["ours", "gtsam-lm"], {}, DATASETS, 60, repeat=3)
    assert calls == ["ours", "gtsam-lm", "gtsam-lm", "ours", "ours", "gtsam-lm"]
    by = {r["solver"]: r for r in rows}
    assert by["ours"]["tag"] == 2.0 and by["ours"]["seconds_runs"] == [3.0, 1.0, 2.0] and by["ours"]["repeats"] == 3
    assert by["gtsam-lm"]["seconds"] == 5.0 and by["ours"]["ratio_to_gtsam_lm"] == pytest.approx(0.4)
    text = B.markdown({"runs": rows, "cases": [{"name": "sq8x16", "poses": 513}], "size": "tiny", "command": "c",
                       "date": "d", "machine": B.machine(), "params": {}, "timeout": 60, "solvers": ["ours"]})
    assert "median of 3 runs" in text and "- sq8x16 ours: 3.000, 1.000, 2.000" in text
    bad = {"status": "crashed (SIGKILL)", "seconds": None}
    assert B.median_run([{"status": "ok", "seconds": 1.0}, bad])["status"] == "crashed (SIGKILL)"
    assert "seconds_runs" not in B.median_run([{"status": "ok", "seconds": 1.0}])


def test_our_child_solves_without_the_gtsam_graph(monkeypatch):
    """Our runs solve from the loader's arrays: no GTSAM graph is held (a survey's is not even built)
    until GTSAM evaluates the result after the solve; GTSAM's runs get the graph."""
    from gtsam_schwarz.apps import bench
    from gtsam_schwarz.problems import survey as survey_module

    seen, built = [], []
    real_ours, real_gtsam, real_make = bench._solve_ours, bench._solve_gtsam, survey_module.Survey._gtsam

    def ours(graph, initial, overrides, arrays=None):
        seen.append(("ours", graph, bool(arrays), list(built)))
        return real_ours(graph, initial, overrides, arrays)

    def gtsam_run(graph, initial, name):
        seen.append(("gtsam", graph is not None, None, list(built)))
        return real_gtsam(graph, initial, name)

    def make(self, name):
        built.append(name)
        return real_make(self, name)

    monkeypatch.setattr(bench, "_solve_ours", ours)
    monkeypatch.setattr(bench, "_solve_gtsam", gtsam_run)
    monkeypatch.setattr(survey_module.Survey, "_gtsam", make)
    case = bench.ALL_CASES["lawn100x100"]
    mine = bench.solve(case, "ours-direct", {}, DATASETS)
    assert seen[0] == ("ours", None, True, ["initial"])       # the start Values only, no graph
    assert "graph" in built                                       # built after the solve, for the check
    gtsam_lm = bench.solve(case, "gtsam-lm", {}, DATASETS)
    assert seen[1][:2] == ("gtsam", True)
    assert mine["final_error"] == pytest.approx(gtsam_lm["final_error"], rel=1e-6)
    assert mine["peak_mib"] >= mine["solve_peak_mib"] > 0


def test_g2o_child_solves_its_own_graph_only(monkeypatch):
    """g2o's runs get g2o's graph (built from GTSAM's before the solve, not timed), not GTSAM's; GTSAM
    evaluates the result after the solve."""
    from gtsam_schwarz.apps import bench, peers

    if not peers.available():
        pytest.skip("g2opy is not installed (the [peers] extra)")
    seen = []
    real = bench._solve_peer

    def peer(problem, name):
        seen.append(type(problem).__name__)
        return real(problem, name)

    monkeypatch.setattr(bench, "_solve_peer", peer)
    row = bench.solve(bench.ALL_CASES["M3500"], "g2o-gn", {}, DATASETS)
    assert seen == ["G2oProblem"] and row["iterations"] >= 1
    assert row["final_error"] == pytest.approx(68.9574, rel=1e-5)   # GTSAM LM's on M3500: 68.95743913
