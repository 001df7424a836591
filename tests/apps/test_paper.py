"""``gtsam-schwarz paper --quick``: the paper's tables and figures, reproduced end to end."""

import json
import subprocess
import sys

import pytest

from gtsam_schwarz.apps.paper import PAPER_BARS1D


def _cli(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "gtsam_schwarz.apps.cli", *args], capture_output=True, text=True,
                          cwd=cwd, timeout=240)


@pytest.fixture(scope="module")
def quick(tmp_path_factory):
    out = tmp_path_factory.mktemp("paper")
    proc = _cli("paper", "--quick", "--json", "--out", str(out))
    assert proc.returncode == 0, proc.stderr
    return out, proc


@pytest.mark.slow
def test_stdout_is_one_json_object(quick):
    _, proc = quick
    decoder = json.JSONDecoder()
    text = proc.stdout.strip()
    data, end = decoder.raw_decode(text)
    assert end == len(text), "anything after the JSON object on stdout"
    assert isinstance(data, dict) and {"bars1d", "model"} <= data.keys()


@pytest.mark.slow
def test_bar_chain_cg_counts_equal_the_paper(quick):
    data = json.loads(quick[1].stdout)
    paper = {int(r[0]): r for r in PAPER_BARS1D}
    assert [r["subdomains"] for r in data["bars1d"]] == sorted(paper)
    for row in data["bars1d"]:
        p = paper[row["subdomains"]]
        assert row["bars"] == int(p[1])
        assert row["one_level"]["cg"] == int(p[2])
        assert row["gdsw"]["cg"] == int(p[5])
        # GDSW: λmin = 1 and λmax ≈ 2.10 at every size, as printed in the paper
        assert f"{row['gdsw']['lambda_min']:.2f}" == "1.00"
        assert f"{row['gdsw']['lambda_max']:.2f}" == "2.10"
        assert row["one_level"]["lambda_min"] == pytest.approx(p[3], rel=0.01)


@pytest.mark.slow
def test_model_gdsw_bounded_and_below_one_level(quick):
    model = json.loads(quick[1].stdout)["model"]
    for r in model:
        assert {"loops", "points_per_side", "preconditioner", "gn_iterations", "cg_mean"} <= r.keys()
        assert r["preconditioner"] in ("none", "one-level", "gdsw", "gdsw-norot")
        assert r["converged"] and not r["capped"], r
    ov1 = {(r["loops"], r["preconditioner"]): r["cg_mean"] for r in model
           if r["points_per_side"] == 16 and r["overlap"] == 1}
    largest = max(L for L, _ in ov1)
    assert largest >= 16
    assert all(cg <= 18 for (L, pc), cg in ov1.items() if pc == "gdsw")
    assert ov1[(largest, "gdsw")] < ov1[(largest, "one-level")] < ov1[(largest, "none")]
    assert ov1[(largest, "gdsw")] < ov1[(largest, "gdsw-norot")]
    # one-level grows with the number of loops, GDSW does not (much)
    assert ov1[(largest, "one-level")] > 2 * ov1[(4, "one-level")]
    assert ov1[(largest, "gdsw")] < 1.6 * ov1[(4, "gdsw")]


@pytest.mark.slow
def test_report_and_figures_written(quick):
    out, proc = quick
    files = json.loads(proc.stdout)["files"]
    report = out / "paper_results.md"
    assert files["report"] == str(report)
    text = report.read_text()
    for label in ("tab:laplace_scalability", "tab:numerical_performance", "tab:weak_numerical", "tab:weak_null",
                  "more than 20 %"):
        assert label in text
    pngs = sorted(out.glob("*.png"))
    assert len(pngs) == 4
    for png in pngs:
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 10_000
        assert f"]({png.name})" in text
    assert not list(out.glob(".*")), "temporary files left behind"


@pytest.mark.parametrize("args", [["paper", "--sigma", "-1"], ["paper", "--budget", "zero"], ["paper", "--bogus"],
                                  ["nosuchcommand"]])
def test_bad_options_exit_2_with_one_line(args, tmp_path):
    proc = _cli(*args, "--out", str(tmp_path)) if args[0] == "paper" else _cli(*args)
    assert proc.returncode == 2
    assert proc.stdout == ""
    assert len(proc.stderr.strip().splitlines()) == 1 and "error" in proc.stderr
    assert "Traceback" not in proc.stderr


def test_out_that_is_a_file_exits_2(tmp_path):
    f = tmp_path / "file"
    f.write_text("x")
    proc = _cli("paper", "--quick", "--out", str(f))
    assert proc.returncode == 2 and len(proc.stderr.strip().splitlines()) == 1
