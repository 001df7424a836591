"""The command line as a good Unix tool: --version, | head, output paths checked up front, plot
formats, progress on stderr only, --help everywhere, TUM output, ATE / RPE against a ground truth."""

import argparse
import io
import json
import os
import pathlib
import subprocess
import sys

import gtsam
import numpy as np
import pytest

from conftest import one_line_error, run_cli

import gtsam_schwarz
from gtsam_schwarz import load_graph

REPO = pathlib.Path(__file__).resolve().parents[2]
ENV = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))}
PNG, PDF = b"\x89PNG\r\n\x1a\n", b"%PDF"


def cli(*args, cwd=None, timeout=120, **kw):
    return run_cli(*args, cwd=cwd, timeout=timeout, env=ENV, **kw)


@pytest.fixture(scope="module")
def synth(tmp_path_factory):
    """A small model problem (2D) with its ground truth as TUM and as g2o, and a 3D one."""
    d = tmp_path_factory.mktemp("synth")
    proc = cli("synth", "--loops", 3, "--points-per-side", 4, "--sigma", 0.02, "--seed", 1, "-o", d / "loops.g2o",
               "--ground-truth", d / "truth.tum")
    assert proc.returncode == 0 and "ground truth" in proc.stdout, proc.stderr
    proc = cli("synth", "--loops", 2, "--points-per-side", 3, "--3d", "-o", d / "helix.g2o",
               "--ground-truth", d / "helix_truth.g2o")
    assert proc.returncode == 0, proc.stderr
    return d


# -- --version, --help ------------------------------------------------------------------------------
def test_version():
    proc = cli("--version")
    assert proc.returncode == 0 and proc.stdout.strip() == f"gtsam-schwarz {gtsam_schwarz.__version__}"


def test_every_option_of_every_command_has_help():
    from gtsam_schwarz.apps.cli import build_parser

    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    assert {"solve", "compare", "synth", "demo", "paper", "bench"} <= set(sub.choices)
    missing = [(name, a.option_strings or a.dest) for name, p in [("", parser), *sub.choices.items()]
               for a in p._actions if not a.help or a.help == argparse.SUPPRESS]
    assert not missing, missing
    assert "paper-results" in sub.choices["paper"].format_help()


# -- a closed stdout (| head) -----------------------------------------------------------------------
def test_closed_stdout_ends_quietly(synth):
    read_end, write_end = os.pipe()
    os.close(read_end)  # the reader is gone before the first line: every write is EPIPE
    try:
        proc = subprocess.run([sys.executable, "-m", "gtsam_schwarz.apps.cli", "solve", synth / "loops.g2o", "-q"],
                              stdout=write_end, stderr=subprocess.PIPE, text=True, env=ENV, timeout=120)
    finally:
        os.close(write_end)
    assert proc.returncode == 141, proc.stderr  # 128 + SIGPIPE, as a shell shows a tool killed by SIGPIPE
    assert proc.stderr == ""


def test_head_one_line(synth):
    proc = subprocess.Popen([sys.executable, "-m", "gtsam_schwarz.apps.cli", "solve", synth / "loops.g2o", "-q"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=ENV)
    first = proc.stdout.readline()
    proc.stdout.close()
    err = proc.stderr.read().decode()
    proc.wait(timeout=120)
    assert b"poses" in first
    assert proc.returncode in (0, 141) and "Traceback" not in err and "BrokenPipe" not in err, err


# -- output paths and formats -------------------------------------------------------------------------
@pytest.mark.parametrize("option, name", [("-o", "x.g2o"), ("--plot", "x.png")])
def test_missing_output_folder_is_a_usage_error_before_the_solve(synth, tmp_path, option, name):
    missing = tmp_path / "no" / "such"
    proc = cli("solve", synth / "loops.g2o", option, missing / name)
    one_line_error(proc, str(missing), "does not exist")
    assert proc.stdout == ""  # nothing was loaded or solved
    assert not (tmp_path / "no").exists()  # and no folder was created


@pytest.mark.parametrize("option, name, words", [("--plot", "x.jpg", [".jpg", ".png", ".pdf", ".svg"]),
                                                 ("-o", "x.txt", [".txt", ".g2o", ".tum"])])
def test_unknown_extension_is_a_usage_error(synth, tmp_path, option, name, words):
    proc = cli("solve", synth / "loops.g2o", option, tmp_path / name)
    one_line_error(proc, *words)
    assert proc.stdout == "" and not (tmp_path / name).exists()


def test_plot_format_follows_the_extension_and_tum_output(synth, tmp_path):
    tum, g2o = tmp_path / "opt.tum", tmp_path / "opt.g2o"
    proc = cli("solve", synth / "loops.g2o", "-o", tum, "--plot", tmp_path / "p.pdf", "--json", "-q")
    assert proc.returncode == 0, proc.stderr
    assert (tmp_path / "p.pdf").read_bytes()[:4] == PDF
    proc = cli("solve", synth / "loops.g2o", "-o", g2o, "--plot", tmp_path / "p.svg", "--json", "-q")
    assert proc.returncode == 0, proc.stderr
    assert b"<svg" in (tmp_path / "p.svg").read_bytes()[:500]
    assert not list(tmp_path.glob(".*")), "temporary files left behind"
    # the TUM file: key tx ty tz qx qy qz qw, the same poses as the g2o output
    rows = np.loadtxt(tum)
    written = load_graph(g2o)
    xyt = gtsam.utilities.extractPose2(written.initial)
    assert rows.shape == (written.poses, 8)
    assert np.array_equal(rows[:, 0], np.arange(written.poses))
    np.testing.assert_allclose(rows[:, 1:3], xyt[:, :2], atol=1e-9)
    assert np.all(rows[:, 3] == 0) and np.all(rows[:, 4:6] == 0)  # Pose2: z = 0, a yaw quaternion
    np.testing.assert_allclose(np.linalg.norm(rows[:, 4:], axis=1), 1, atol=1e-12)
    yaw = 2 * np.arctan2(rows[:, 6], rows[:, 7])
    np.testing.assert_allclose(np.angle(np.exp(1j * (yaw - xyt[:, 2]))), 0, atol=1e-9)


def test_tum_pose3_round_trip(tmp_path):
    from gtsam_schwarz.apps.trajectory import Trajectory, read_trajectory
    from gtsam_schwarz.io.tum import write_tum

    prob = gtsam_schwarz.helix_loops(2, 3, sigma=0.05, seed=3)
    write_tum(tmp_path / "h.tum", prob.initial)
    back, ref = read_trajectory(tmp_path / "h.tum"), Trajectory.from_values(prob.initial)
    assert back.dimension == 3 and np.array_equal(back.keys, ref.keys)
    np.testing.assert_allclose(back.t, ref.t, atol=1e-12)
    np.testing.assert_allclose(back.R, ref.R, atol=1e-12)


# -- paper: never the committed docs/ by default ------------------------------------------------------
def test_paper_default_output_is_a_new_folder_in_the_current_one(tmp_path):
    from gtsam_schwarz.apps.cli import build_parser

    assert build_parser().parse_args(["paper", "--quick"]).out == "paper-results"
    proc = cli("paper", "--quick", "--out", tmp_path / "no" / "such")  # parent missing: refused, nothing made
    one_line_error(proc, "does not exist")
    assert not (tmp_path / "no").exists()


# -- compare: the whole GTSAM error, progress on stderr -----------------------------------------------
def test_compare_shows_gtsam_errors_in_full():
    from gtsam_schwarz.apps.commands import _json_rows, print_table
    from gtsam_schwarz.apps.compare import run_gtsam

    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()  # no prior: an indeterminate system
    graph.add(gtsam.BetweenFactorPose2(0, 1, gtsam.Pose2(1, 0, 0), gtsam.noiseModel.Isotropic.Sigma(3, 0.1)))
    values.insert(0, gtsam.Pose2())
    values.insert(1, gtsam.Pose2(1.1, 0, 0))
    row = run_gtsam(graph, values, "gtsam-gn")
    row["ratio_to_gtsam_lm"] = float("nan")
    lines = [line.strip() for line in row["failed_message"].splitlines() if line.strip()]
    assert len(lines) > 2 and row["failed"] == lines[0]
    out = io.StringIO()
    print_table([row], out)
    table = out.getvalue().splitlines()
    for line in lines:  # every line of the message, indented under the row
        assert any(t.strip() == line and t.startswith(" " * 20) for t in table), line
    assert _json_rows([row])[0]["failed"] == row["failed_message"]


def test_compare_progress_is_on_stderr_and_quiet_silences_it(synth):
    proc = cli("compare", synth / "loops.g2o", "--json", "--ground-truth", synth / "truth.tum")
    assert proc.returncode == 0, proc.stderr
    data = json.loads(proc.stdout)  # stdout is exactly one JSON object
    assert [r["solver"] for r in data["rows"]][:2] == ["gtsam-lm", "gtsam-gn"]
    assert all(r["ate_rmse"] > 0 and r["rpe_rmse"] > 0 for r in data["rows"])
    lines = proc.stderr.splitlines()
    assert lines and all(line.startswith("compare: ") for line in lines), proc.stderr
    assert any("[1/7] gtsam-lm" in line for line in lines) and any("[7/7]" in line for line in lines)
    quiet = cli("compare", synth / "loops.g2o", "--json", "--quiet")
    assert quiet.returncode == 0 and quiet.stderr == "" and json.loads(quiet.stdout)["rows"]


def test_live_progress_on_a_terminal(synth):
    pytest.importorskip("tqdm")
    pty, fcntl, termios, struct = (pytest.importorskip(m) for m in ("pty", "fcntl", "termios", "struct"))
    master, slave = pty.openpty()
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 24, 100, 0, 0))
    proc = subprocess.Popen([sys.executable, "-m", "gtsam_schwarz.apps.cli", "solve", synth / "loops.g2o", "--json"],
                            stdout=subprocess.PIPE, stderr=slave, env=ENV)
    os.close(slave)
    shown = b""
    while True:
        try:
            chunk = os.read(master, 4096)
        except OSError:  # EIO: the child closed the terminal
            break
        if not chunk:
            break
        shown += chunk
    out = proc.stdout.read()
    proc.wait(timeout=120)
    os.close(master)
    assert proc.returncode == 0
    json.loads(out)
    assert b"\r" in shown and b"solve: [" in shown  # a bar redrawn in place


def test_plain_progress_lines_are_rate_limited():
    from gtsam_schwarz.apps.progress import Progress

    now = [0.0]
    out = io.StringIO()
    p = Progress("compare", 2, stream=out, live=False, interval=5.0, clock=lambda: now[0])
    p.start("gtsam-lm")
    for t in range(1, 13):  # a note every second: a line only every 5 s
        now[0] = float(t)
        p.note(f"iteration {t}")
    p.done()
    lines = out.getvalue().splitlines()
    assert lines[0] == "compare: [1/2] gtsam-lm ..."
    assert [line for line in lines if "iteration" in line] == [
        "compare: [1/2] gtsam-lm iteration 5 (5 s)", "compare: [1/2] gtsam-lm iteration 10 (10 s)"]
    assert lines[-1].startswith("compare: [1/2] gtsam-lm done in 12.0 s")
    silent = io.StringIO()
    q = Progress("x", 1, stream=silent, enabled=False)
    q.start("a"), q.note("b"), q.done(), q.close()
    assert silent.getvalue() == ""


# -- plots ---------------------------------------------------------------------------------------------
def test_trajectory_plot_labels_and_distinct_subdomain_colours():
    import matplotlib.pyplot as plt

    from gtsam_schwarz.apps.solve_plots import draw_trajectory, subdomain_colors

    for n in (3, 12, 20, 37, 300):
        colors = subdomain_colors(n)
        assert colors.shape == (n, 4) and len(np.unique(np.round(colors, 6), axis=0)) == n, n
    prob = gtsam_schwarz.square_loops(2, 3)
    fig, ax = plt.subplots()
    draw_trajectory(ax, prob.initial, prob.ground_truth)
    assert ax.get_xlabel() == "x [m]" and ax.get_ylabel() == "y [m]"
    plt.close(fig)


def test_convergence_legend_has_no_identical_overlapping_entries():
    import matplotlib.pyplot as plt

    from gtsam_schwarz.apps.solve_plots import draw_convergence

    def history(errors, cg):
        return [{"error_before": errors[0] * 10, "error": e, "accepted": True, "cg_residuals": cg} for e in errors]

    same = [3.0, 2.0, 1.0]
    runs = {"none": history(same, [1, 0.5, 0.1]), "gdsw": history(same, [1, 0.01]),
            "other": history([3.0, 1.5, 0.5], [1, 0.1])}
    fig, (ax_err, ax_cg) = plt.subplots(1, 2)
    draw_convergence(ax_err, ax_cg, runs)
    labels = [t.get_text() for t in ax_err.get_legend().get_texts()]
    assert labels == ["none, gdsw (same curve)", "other"]
    styles = {(line.get_marker(), line.get_linestyle(), line.get_color()) for line in ax_cg.lines}
    assert len(styles) == 3  # each solver its own colour, marker and line style
    plt.close(fig)


# -- ATE / RPE -------------------------------------------------------------------------------------------
def test_ate_rpe_of_a_rigidly_moved_trajectory_are_zero():
    from gtsam_schwarz.apps.trajectory import Trajectory, ate_errors, evaluate

    for prob, alignment in ((gtsam_schwarz.square_loops(2, 4, sigma=0.03, seed=1), "SE(2)"),
                            (gtsam_schwarz.helix_loops(2, 4, sigma=0.03), "SE(3)")):
        ref = Trajectory.from_values(prob.ground_truth)
        moved = Trajectory.from_values(prob.ground_truth)
        a = 0.7
        Rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
        moved.t, moved.R = moved.t @ Rz.T + [1.0, -2.0, 0.0], np.einsum("ij,njk->nik", Rz, moved.R)
        res = evaluate(moved, ref)
        assert res["ate_rmse"] < 1e-12 and res["rpe_rmse"] < 1e-12
        assert ate_errors(moved, ref, aligned=False).min() > 0.5  # the alignment did the work
        noisy = evaluate(prob.initial, prob.ground_truth)
        assert noisy["ate_rmse"] > 0 and noisy["rpe_rmse"] > 0 and noisy["alignment"] == alignment


def test_ate_rpe_equal_evo():
    evo_metrics = pytest.importorskip("evo.core.metrics")
    from evo.core.trajectory import PoseTrajectory3D

    from gtsam_schwarz.apps.trajectory import Trajectory, evaluate
    from gtsam_schwarz.io.tum import rotation_to_quaternion

    def to_evo(tr):
        q = rotation_to_quaternion(tr.R)
        return PoseTrajectory3D(positions_xyz=tr.t, orientations_quat_wxyz=q[:, [3, 0, 1, 2]],
                                timestamps=tr.keys.astype(float))

    for prob in (gtsam_schwarz.square_loops(3, 5, sigma=0.05, seed=2), gtsam_schwarz.helix_loops(3, 5, sigma=0.05)):
        est, ref = Trajectory.from_values(prob.initial), Trajectory.from_values(prob.ground_truth)
        ours = evaluate(est, ref)
        e, r = to_evo(est), to_evo(ref)
        rpe = evo_metrics.RPE(evo_metrics.PoseRelation.translation_part, delta=1,
                              delta_unit=evo_metrics.Unit.frames, all_pairs=False)
        rpe.process_data((r, e))
        e.align(r, correct_scale=False)  # evo_ape --align
        ape = evo_metrics.APE(evo_metrics.PoseRelation.translation_part)
        ape.process_data((r, e))
        rmse = evo_metrics.StatisticsType.rmse
        assert ours["ate_rmse"] == pytest.approx(ape.get_statistic(rmse), rel=1e-9)
        assert ours["rpe_rmse"] == pytest.approx(rpe.get_statistic(rmse), rel=1e-9)


def test_solve_reports_ate_rpe_against_a_ground_truth(synth):
    proc = cli("solve", synth / "loops.g2o", "--ground-truth", synth / "truth.tum", "--json", "-q")
    assert proc.returncode == 0, proc.stderr
    g = json.loads(proc.stdout)["ground_truth"]
    assert g["poses"] == 4 * 4 * 3 + 1 and g["alignment"] == "SE(2)"
    assert 0 < g["ate_rmse"] < g["initial_ate_rmse"] and g["rpe_rmse"] > 0
    proc = cli("solve", synth / "helix.g2o", "--ground-truth", synth / "helix_truth.g2o", "-q")
    assert proc.returncode == 0, proc.stderr
    line = next(line for line in proc.stdout.splitlines() if line.startswith("against"))
    assert "ATE" in line and "RPE" in line and "SE(3)" in line
    unmatched = synth / "unmatched.tum"  # timestamps that are not pose keys, and too few poses
    unmatched.write_text("0.5 0 0 0 0 0 0 1\n1.5 1 0 0 0 0 0 1\n")
    one_line_error(cli("solve", synth / "loops.g2o", "--ground-truth", unmatched), "--ground-truth", "cannot match")
    one_line_error(cli("solve", synth / "loops.g2o", "--ground-truth", synth / "nothing.tum"), "no such file")


def test_loader_warnings_are_printed_and_strict_refuses(tmp_path):
    f = tmp_path / "extra.g2o"
    f.write_text("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\nFOO 1\nEDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\n")
    ok = subprocess.run([sys.executable, "-m", "gtsam_schwarz.apps.cli", "solve", str(f), "-q"],
                        capture_output=True, text=True)
    assert ok.returncode == 0 and "warning: skipped 1 line with unknown tag 'FOO' (first at line 3)" in ok.stderr
    strict = subprocess.run([sys.executable, "-m", "gtsam_schwarz.apps.cli", "solve", str(f), "--strict"],
                            capture_output=True, text=True)
    assert strict.returncode == 2 and strict.stderr.count("\n") <= 2 and "(strict)" in strict.stderr


def test_memory_limit_too_small_is_one_line_and_exit_2(tmp_path):
    f = tmp_path / "lawn.g2o"
    assert cli("synth", "--lawnmower", "30x30", "-o", f).returncode == 0
    one_line_error(cli("solve", f, "--preconditioner", "rgdsw-linear", "--memory-limit", "1K", "-q"),
                   "needs about", "GiB", "use preconditioner='direct'")
    one_line_error(cli("solve", f, "--memory-limit", "lots"), "--memory-limit", "expected a size")
    assert cli("solve", f, "--preconditioner", "rgdsw-linear", "--memory-limit", "4G", "-q").returncode == 0
