"""The geometric partition (cells of a coordinate multisection) and the automatic choice among
trajectory segments, geometric cells and METIS."""

import numpy as np
import pytest
import scipy.sparse as sp

import gtsam_schwarz as gs
import gtsam_schwarz.dd.partition as P
from gtsam_schwarz import GraphStructure, KeyMap, export_linear_system, square_loops
from gtsam_schwarz.dd import coordinate_cells, decompose, geometric_partition, interface_count, metis_partition
from gtsam_schwarz.problems import lawnmower


def _structure(prob, values=None):
    """The graph's structure and the poses' positions in ``values`` (default: the initial ones)."""
    km = KeyMap.from_graph(prob.graph, prob.initial)
    H = sp.csr_matrix(export_linear_system(prob.graph.linearize(prob.initial), km).H)
    H.sort_indices()
    return GraphStructure.from_matrix(H, km.offsets), km.geometry(values or prob.initial).positions


@pytest.fixture(scope="module")
def survey():
    """Lawnmower 40 x 40 with its true positions (dead reckoning's drift shears the rows: there METIS
    cuts less, 245 against 380 interface poses, and auto takes it)."""
    prob = lawnmower(40, 40, sigma=0.01, seed=0)
    structure, X = _structure(prob, prob.ground_truth)
    dead = _structure(prob)[1]
    assert P.choose_partition(structure, 16, dead)[0] == "metis"
    return structure, X


def test_cells_are_balanced_and_follow_the_longer_axis():
    """Equal-count cells, about as many as asked, more slabs along the longer side of a 4:1 box."""
    X = np.random.default_rng(0).uniform(size=(8000, 2)) * [4.0, 1.0]
    cells = coordinate_cells(X, 64)
    sizes = np.bincount(cells)
    assert len(sizes) == 64 and sizes.min() >= 8000 // 64 - 1 and sizes.max() <= 8000 // 64 + 1
    # each cell's extent: about as long as wide (16 slabs along x, 4 along y in a 4 x 1 box)
    width = np.array([np.ptp(X[cells == c], axis=0) for c in range(64)])
    assert np.median(width[:, 0] / width[:, 1]) == pytest.approx(1.0, rel=0.35)


def test_a_flat_axis_gets_no_cut():
    """A thin slab in 3D (one floor): the cells cut only the two long axes."""
    rng = np.random.default_rng(1)
    X = np.c_[rng.uniform(size=(5000, 2)) * 10.0, rng.uniform(size=5000) * 0.01]
    cells = coordinate_cells(X, 25)
    assert len(np.unique(cells)) == 25
    for c in range(25):
        assert np.ptp(X[cells == c, 2]) > 0.008   # every cell spans the whole thickness
    assert np.array_equal(coordinate_cells(X, 1), np.zeros(5000, dtype=np.int64))
    with pytest.raises(ValueError, match="finite"):
        coordinate_cells(np.r_[X, [[np.nan, 0.0, 0.0]]], 25)


def test_geometric_partition_needs_coordinates(survey):
    structure, X = survey
    with pytest.raises(ValueError, match="coordinates"):
        geometric_partition(structure, 16)
    with pytest.raises(ValueError, match="coordinates"):
        geometric_partition(structure, 16, X[:-1])   # not one row per vertex


def test_geometric_cells_cut_a_survey_no_worse_than_metis(survey):
    """Lawnmower 40 x 40 into 16: compact cells with a smaller interface than METIS's, chosen by
    auto, and the decomposition records the choice."""
    structure, X = survey
    geo = geometric_partition(structure, 16, X)
    assert len(np.unique(geo)) == 16
    assert interface_count(structure, geo) <= interface_count(structure, metis_partition(structure, 16))
    name, part = P.choose_partition(structure, 16, X)
    assert name == "geometric" and np.array_equal(part, geo)
    assert decompose(structure, 16, "auto", coordinates=X).partition == "geometric"
    assert decompose(structure, 16, "auto").partition == "metis"   # no coordinates: not a candidate


def test_auto_keeps_segments_and_metis_where_they_cut_less(survey):
    """The model problem (every loop around the same square): segments; positions shuffled (a map
    that does not follow the graph): METIS."""
    prob = square_loops(8, 4, sigma=0.01, seed=0)
    structure, X = _structure(prob)
    assert P.choose_partition(structure, 8, X)[0] == "segments"
    structure, X = survey
    shuffled = X[np.random.default_rng(0).permutation(len(X))]
    assert P.choose_partition(structure, 16, shuffled)[0] == "metis"
    # poses all at one place (no start computed): one cell, no interface, but not a candidate
    assert P.choose_partition(structure, 16, np.zeros_like(X))[0] == "metis"


def test_large_graphs_skip_metis_where_a_window_vouches_for_the_cells(survey, monkeypatch):
    """From WINDOW_FROM vertices METIS cuts only a central window of the cells; where the cells cut it
    about as well the whole-graph METIS is not run, where they do not (shuffled positions) it is."""
    structure, X = survey
    monkeypatch.setattr(P, "WINDOW_FROM", 100)
    monkeypatch.setattr(P, "WINDOW_SHARE", 4)
    calls = []
    real = P.metis_partition
    monkeypatch.setattr(P, "metis_partition", lambda *a, **k: calls.append(1) or real(*a, **k))
    assert P.choose_partition(structure, 64, X)[0] == "geometric" and not calls
    shuffled = X[np.random.default_rng(0).permutation(len(X))]
    assert P.choose_partition(structure, 64, shuffled)[0] == "metis" and calls


def test_the_optimizer_partitions_by_the_poses():
    """LM with Schwarz on a lawnmower: auto takes the geometric cells from the poses at the first
    solve, and ends at the error of the METIS-partitioned run."""
    prob = lawnmower(30, 30, sigma=0.01, seed=0)
    runs = {}
    for partition in ("auto", "metis"):
        opt = gs.SchwarzOptimizer(prob.graph, prob.initial, gs.SchwarzParams(method="lm", preconditioner="rgdsw-linear",
                                                                             subdomains=9, partition=partition))
        opt.optimize()
        runs[partition] = opt.summary()
    assert runs["auto"]["partition"] == "geometric" and runs["metis"]["partition"] == "metis"
    assert runs["auto"]["converged"] and runs["metis"]["converged"]
    assert runs["auto"]["final_error"] == pytest.approx(runs["metis"]["final_error"], rel=1e-8)


def test_the_window_spans_only_the_cut_axes(monkeypatch):
    """One floor of a 3D survey: no slab along the height, so the window is a square of cells and
    the cells win without METIS on the whole graph."""
    from gtsam_schwarz.problems import survey3d
    prob = survey3d(1, 24, 24, sigma=0.01, seed=0)
    structure, X = _structure(prob, prob.ground_truth)
    cells, slabs = P._multisection(X, 36)
    assert sorted(slabs.tolist()) == [1, 6, 6]
    monkeypatch.setattr(P, "WINDOW_FROM", 100)
    monkeypatch.setattr(P, "WINDOW_SHARE", 4)
    assert P._geometric_holds(structure, cells, X, slabs)
    monkeypatch.setattr(P, "metis_partition", lambda *a, **k: pytest.fail("METIS ran on the whole graph"))
    assert P.choose_partition(structure, 36, X)[0] == "geometric"
