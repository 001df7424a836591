"""The PETSc back-end against the serial solver: same preconditioner, same CG counts, same answer.

Everything PETSc runs in ``mpiexec`` subprocesses (1 and 2 ranks, oversubscribed), so the pytest
process never initializes MPI. Skipped, with a one-line reason, when petsc4py, mpi4py or mpiexec
are absent (``pip install -e .`` stays PETSc-free).
"""

from __future__ import annotations

import json
import pathlib
import subprocess

import numpy as np
import pytest

from gtsam_schwarz.backends.petsc.env import launch_command, mpi_environment, mpi_ready, mpiexec_command
from gtsam_schwarz.backends.petsc.layout import rank_layout

READY, WHY = mpi_ready()
needs_mpi = pytest.mark.skipif(not READY, reason=WHY)
pytestmark = pytest.mark.mpi

HERE = pathlib.Path(__file__).resolve().parent
ROOT = HERE.parents[1]
LOOPS, POINTS = 8, 8  # 771 dofs: small enough for a few seconds per run
TIMEOUT = 120


def _mpirun(ranks: int, argv: list[str]) -> dict:
    proc = subprocess.run(argv, capture_output=True, text=True, timeout=TIMEOUT, env=mpi_environment(), cwd=ROOT)
    assert proc.returncode == 0, f"mpiexec -n {ranks} failed ({proc.returncode}):\n{proc.stderr[-3000:]}"
    lines = [line for line in proc.stdout.splitlines() if line.startswith("{")]
    assert len(lines) == 1, f"expected one JSON line on stdout, got:\n{proc.stdout[-3000:]}"
    return json.loads(lines[0])


def _run(ranks: int, *args: str, problem=("--square-loops", str(LOOPS), str(POINTS))) -> dict:
    return _mpirun(ranks, launch_command(ranks, [*problem, "--json", *args], oversubscribe=True))


@pytest.fixture(scope="module")
def serial():
    """The serial optimizer on the model problem (GN, gdsw on one loop per subdomain), every step
    solved to cg_tol as the PETSc back-end does (no Newton-decrement stop)."""
    import gtsam_schwarz as gs

    pb = gs.square_loops(LOOPS, POINTS)
    params = gs.SchwarzParams(method="gn", preconditioner="gdsw", subdomains=LOOPS, partition="segments",
                              newton_decrement=False, forcing="none",  # the driver's default: --inexact off
                              transport_coarse=False)  # the back-end rebuilds its coarse level
    opt = gs.SchwarzOptimizer(pb.graph, pb.initial, params)
    opt.optimize()
    return opt


ARGS = ("--method", "gn", "--preconditioner", "gdsw", "--subdomains", str(LOOPS), "--partition", "segments")


def _assert_matches_serial(report: dict, serial) -> None:
    s = serial.summary()
    assert report["ranks_agree"]
    assert report["iterations"] == s["iterations"]
    assert report["final_error"] == pytest.approx(s["final_error"], rel=1e-8)
    assert report["coarse_size"] == s["coarse_size"]
    ours, theirs = np.array(report["cg_iterations"]), np.array(s["cg_iterations"])
    assert len(ours) == len(theirs)
    assert np.all(np.abs(ours - theirs) <= np.maximum(1, 0.1 * theirs)), (ours, theirs)
    lam = np.array(report["lambda_max"], dtype=float)
    ref = np.array([h.lambda_max for h in serial.history])
    assert np.allclose(lam, ref, rtol=1e-3), (lam, ref)


@needs_mpi
def test_one_rank_equals_serial(serial):
    report = _run(1, *ARGS)
    _assert_matches_serial(report, serial)
    assert report["linearization"] == "distributed"
    assert report["per_rank"][0]["factors"] == serial.graph.size()


@needs_mpi
def test_two_ranks_equal_serial(serial):
    report = _run(2, *ARGS)
    _assert_matches_serial(report, serial)
    assert report["ranks"] == 2 and report["linearization"] == "distributed"
    rows = [r["rows"] for r in report["per_rank"]]
    assert sum(rows) == int(serial.linearizer.offsets[-1]) and min(rows) > 0
    factors = [r["factors"] for r in report["per_rank"]]  # each factor linearized by exactly one rank
    assert sum(factors) == serial.graph.size() and min(factors) > 0
    held = [r["poses_held"] for r in report["per_rank"]]
    assert max(held) < report["poses"] <= sum(held)


@needs_mpi
def test_two_ranks_replicated_linearization_equals_serial(serial):
    report = _run(2, *ARGS, "--replicated")
    _assert_matches_serial(report, serial)
    assert report["linearization"] == "replicated"


LAWNMOWER = (12, 12)


@needs_mpi
@pytest.mark.parametrize("name", ["gdsw-linear", "rgdsw-linear"])
def test_linear_coarse_spaces_on_two_ranks_equal_serial(name):
    """gdsw-linear / rgdsw-linear (two-hop interface entities, hat functions) on PETSc: the serial
    final error, coarse size and CG counts on a lawnmower survey."""
    import gtsam_schwarz as gs
    from gtsam_schwarz.problems.survey import lawnmower

    pb = lawnmower(*LAWNMOWER)
    serial = gs.SchwarzOptimizer(pb.graph, pb.initial, gs.SchwarzParams(preconditioner=name, subdomains=6,
                                                                         newton_decrement=False, forcing="none",
                                                                         transport_coarse=False))
    serial.optimize()
    report = _run(2, "--preconditioner", name, "--subdomains", "6",
                  problem=("--lawnmower", *(str(v) for v in LAWNMOWER)))
    _assert_matches_serial(report, serial)
    assert report["coarse_size"] > 0 and report["linearization"] == "distributed"


@pytest.fixture(scope="module")
def checks():
    """tests/backends/mpi_checks.py on 2 ranks (one run for the tests below)."""
    if not READY:
        pytest.skip(WHY)
    cmd = mpiexec_command(2, oversubscribe=True) + [
        __import__("sys").executable, str(HERE / "mpi_checks.py"), str(LOOPS), str(POINTS)]
    return _mpirun(2, cmd)


@needs_mpi
def test_per_rank_linearization_equals_the_whole_graph(checks):
    """Each rank linearizes its own factors: the assembled H and g equal the whole graph's, and the
    optimizer gives the serial poses and error (Pose2 with and without a prior, Pose3, GTSAM factors)."""
    cases = checks["distributed"]
    assert [c["problem"] for c in cases] == ["square_loops", "no_prior", "lawnmower", "survey3d", "gtsam_factors"]
    for case in cases:
        assert case["distributed"], case
        assert sum(case["ranks_factors"]) == case["factors"] and min(case["ranks_factors"]) > 0, case
        assert case["H_error"] < 1e-12 and case["g_error"] < 1e-12, case
        ours, theirs = case["final_error"]
        assert ours == pytest.approx(theirs, rel=1e-8), case
        assert len(set(case["errors_on_ranks"])) == 1, case
        a, b = (np.array(c) for c in case["cg"])
        assert len(a) == len(b) and np.all(np.abs(a - b) <= np.maximum(1, 0.1 * b)), case
        assert case["anchored"][0] == case["anchored"][1], case
        assert case["pose_difference"] < 1e-8, case
        assert case["values_on_rank"] == [True, False], case
    assert cases[1]["anchored"][0] == [0]  # the prior-free graph is anchored at its first pose
    # factors the kernels leave to GTSAM are linearized by GTSAM on their first pose's rank, once
    split = cases[4]["gtsam_factors"]
    assert sum(split) == cases[4]["gtsam_factors_whole"] > 0 and min(split) > 0, cases[4]


@needs_mpi
def test_two_ranks_lm_writes_only_on_rank_zero(tmp_path):
    out = tmp_path / "out.g2o"
    report = _run(2, "--subdomains", "4", "-o", str(out))
    assert report["converged"] and report["ranks_agree"]
    assert out.exists() and list(tmp_path.iterdir()) == [out]
    assert out.read_text().count("VERTEX_SE2") == report["poses"]


@needs_mpi
def test_preconditioner_and_cg_equal_serial_on_two_ranks(checks):
    """M⁻¹x of PETSc (ASM + PCMG with Φ) equals the serial TwoLevelSchwarz / AdditiveSchwarz, after the
    first build and after a numeric update; one CG solve gives the serial iterations and solution."""
    out = checks
    for case in out["cases"]:
        assert max(case["apply"]) < 1e-10, case
        assert max(case["x_error"]) < 1e-8, case
        assert case["coarse_size"][0] == case["coarse_size"][1], case
        for a, b in zip(case["cg_petsc"], case["cg_serial"]):
            assert abs(a - b) <= max(1, 0.1 * b), case
        assert all(case["x_same_on_ranks"]), case
    assert {c["coarse_matrix"] for c in out["cases"]} == {"harmonic", "galerkin"}
    # lagging: the same decisions as the serial PreconditionedCG on the same sequence of matrices
    for step in out["lag_sequence"]:
        (a, lag_a, rebuilt_a), (b, lag_b, rebuilt_b) = step["serial"], step["petsc"]
        assert (lag_a, rebuilt_a) == (lag_b, rebuilt_b), out["lag_sequence"]
        assert abs(a - b) <= max(1, 0.1 * a), out["lag_sequence"]
        assert step["x_error"] < 1e-6, out["lag_sequence"]  # both solve to a relative residual of 1e-8
    assert [s["serial"][1:] for s in out["lag_sequence"]] == [[False, True], [True, False], [True, True],
                                                            [True, True], [False, True], [False, True]]


def test_layout_owns_every_dof_once_with_contiguous_ranks():
    """Ownership by subdomain (no PETSc needed): a permutation, contiguous rank ranges, every rank
    owning the dofs of whole vertices, overlapping index sets renumbered consistently."""
    import scipy.sparse as sp

    import gtsam_schwarz as gs
    from gtsam_schwarz.dd import GraphStructure, decompose
    from gtsam_schwarz.linearization.gtsam_export import GtsamLinearizer

    pb = gs.square_loops(LOOPS, POINTS)
    lin = GtsamLinearizer(pb.graph, pb.initial)
    H = sp.csr_matrix(lin.linearize(lin.state(pb.initial)).H)
    dec = decompose(GraphStructure.from_matrix(H, lin.offsets), 6, "metis", 1)
    for ranks in (1, 2, 3, 6):
        lay = rank_layout(dec, ranks)
        assert np.array_equal(np.sort(lay.order), np.arange(H.shape[0]))
        assert np.array_equal(lay.position[lay.order], np.arange(H.shape[0]))
        assert np.all(np.diff(lay.ranges) > 0) and lay.ranges[-1] == H.shape[0]
        assert np.all(np.diff(lay.dof_rank[lay.order]) >= 0)
        assert sorted(np.unique(lay.subdomain_rank)) == list(range(ranks))
        sets = dec.index_sets(overlapping=True)
        x = np.random.default_rng(0).standard_normal(H.shape[0])
        for r in range(ranks):
            for local, i in zip(lay.index_sets(sets, r), lay.subdomains(r)):
                assert np.array_equal(np.sort(lay.permute(x)[local]), np.sort(x[sets.get(i)]))
    with pytest.raises(ValueError, match="subdomains"):
        rank_layout(dec, 7)


def test_local_coarse_basis_rows_add_up_to_the_serial_basis():
    """Each rank's rows of Φ (extended into its own subdomains' interiors) equal the serial GDSW/RGDSW
    basis on those rows (no PETSc needed)."""
    import scipy.sparse as sp

    import gtsam_schwarz as gs
    from gtsam_schwarz.backends.petsc.coarse import LocalCoarseBasis
    from gtsam_schwarz.coarse import gdsw_coarse_space
    from gtsam_schwarz.dd import GraphStructure, decompose, find_interface
    from gtsam_schwarz.linearization.gtsam_export import GtsamLinearizer

    pb = gs.square_loops(LOOPS, POINTS)
    lin = GtsamLinearizer(pb.graph, pb.initial)
    state = lin.state(pb.initial)
    H = sp.csr_matrix(lin.linearize(state).H)
    geometry = lin.geometry(state)
    for partition, kind, N, ranks in (("segments", "gdsw", 8, 2), ("metis", "gdsw", 6, 3), ("metis", "rgdsw", 7, 4),
                                      ("metis", "gdsw-linear", 6, 2), ("metis", "rgdsw-linear", 6, 3)):
        dec = decompose(GraphStructure.from_matrix(H, lin.offsets), N, partition, 1)
        interface = find_interface(dec, "two-hop" if kind.endswith("linear") else "components")
        ref = gdsw_coarse_space(H, dec, interface, kind, geometry, True, lin.translation_mask()).Phi
        lay = rank_layout(dec, ranks)
        total = sp.csr_matrix(ref.shape)
        for r in range(ranks):
            basis = LocalCoarseBasis(dec, interface, lay.subdomains(r), lay.dof_rank == r, kind, True,
                                     lin.translation_mask())
            for _ in range(2):  # the second call reuses the factorizations' patterns
                rows, cols, vals, nc = basis(H, geometry)
            assert np.all(lay.dof_rank[rows] == r)
            total = total + sp.csr_matrix((vals, (rows, cols)), shape=(H.shape[0], nc))
        assert abs(total - ref).max() < 1e-12 * abs(ref).max()


def test_replicated_reason_names_what_cannot_be_split():
    """Pure native pose graphs are linearized per rank; GTSAM's linearizer falls back (no PETSc needed)."""
    import gtsam_schwarz as gs
    from gtsam_schwarz.backends.petsc.distributed import replicated_reason
    from gtsam_schwarz.linearization.gtsam_export import GtsamLinearizer
    from gtsam_schwarz.linearization.native import NativeLinearizer

    import gtsam

    pb = gs.square_loops(LOOPS, POINTS)
    assert replicated_reason(NativeLinearizer(pb.graph, pb.initial)) == ""
    assert "not the native" in replicated_reason(GtsamLinearizer(pb.graph, pb.initial))
    graph, values = gtsam.NonlinearFactorGraph(pb.graph), gtsam.Values(pb.initial)
    landmark = gtsam.symbol("l", 0)
    values.insert(landmark, gtsam.Point2(1.0, 2.0))
    graph.add(gtsam.PriorFactorPoint2(landmark, gtsam.Point2(1.0, 2.0), gtsam.noiseModel.Isotropic.Sigma(2, 1.0)))
    assert "not poses" in replicated_reason(NativeLinearizer(graph, values))


def test_mpiexec_command_has_the_open_mpi_flags(monkeypatch):
    from gtsam_schwarz.backends.petsc import env

    monkeypatch.setattr(env, "_is_open_mpi", lambda exe: True)
    monkeypatch.setattr(env.os, "geteuid", lambda: 0)
    cmd = env.mpiexec_command(64, exe="mpiexec")
    assert cmd[:3] == ["mpiexec", "-n", "64"] and "--allow-run-as-root" in cmd and "--oversubscribe" in cmd
    monkeypatch.setattr(env.os, "geteuid", lambda: 1000)
    assert env.mpiexec_command(1, exe="mpiexec", oversubscribe=False) == ["mpiexec", "-n", "1"]
