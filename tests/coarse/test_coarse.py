"""General interfaces: components, rigid-body modes, RGDSW, METIS, rank-deficient coarse bases."""

import gtsam
import numpy as np
import pytest
import scipy.sparse as sp

from conftest import dataset
from gtsam_schwarz import (GraphStructure, KeyMap, export_linear_system, find_interface,
                           make_preconditioner, pcg, square_loops)
from gtsam_schwarz.coarse import gdsw_coarse_space, rigid_modes
from gtsam_schwarz.dd import decompose, metis_partition
from gtsam_schwarz.dd import IndexSets
from gtsam_schwarz.schwarz import CoarseCorrection, TwoLevelSchwarz


@pytest.fixture(scope="module")
def m3500():
    graph, initial = gtsam.readG2o(str(dataset("input_M3500_g2o.g2o")), False)
    graph.add(gtsam.PriorFactorPose2(0, initial.atPose2(0), gtsam.noiseModel.Isotropic.Sigma(3, 1e-3)))
    km = KeyMap.from_graph(graph, initial)
    system = export_linear_system(graph.linearize(initial), km)
    structure = GraphStructure.from_matrix(system.H, km.offsets)
    return system, structure, km, km.geometry(initial)


def test_rigid_modes_are_the_null_space_of_between_factors():
    """A rigid motion of all poses leaves every between factor unchanged: J·mode = 0 exactly
    for the linearized between factors (the prior is the only factor that sees it)."""
    prob = square_loops(2, 3, sigma=0.05, seed=1)
    graph = gtsam.NonlinearFactorGraph()
    for i in range(1, prob.graph.size()):
        graph.add(prob.graph.at(i))  # drop the prior
    km = KeyMap.from_graph(graph, prob.initial)
    J = export_linear_system(graph.linearize(prob.initial), km).J
    geo = km.geometry(prob.initial)
    verts = np.arange(km.size)
    modes = rigid_modes(geo, verts, np.array([[0.3, -0.2]]).repeat(km.size, 0), rotation=True)
    for m in range(3):
        v = modes[:, :, m].ravel()
        assert np.abs(J @ v).max() < 1e-9 * np.abs(v).max()


def test_rigid_modes_pose3_are_null_space():
    rng = np.random.default_rng(0)
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    noise = gtsam.noiseModel.Isotropic.Sigma(6, 0.1)
    for i in range(5):
        values.insert(i, gtsam.Pose3(gtsam.Rot3.RzRyRx(*rng.normal(size=3)), rng.normal(size=3)))
    for i, j in [(0, 1), (1, 2), (2, 3), (3, 4), (4, 0), (1, 3)]:
        meas = values.atPose3(i).between(values.atPose3(j)).retract(0.1 * rng.normal(size=6))
        graph.add(gtsam.BetweenFactorPose3(i, j, meas, noise))
    km = KeyMap.from_graph(graph, values)
    J = export_linear_system(graph.linearize(values), km).J
    geo = km.geometry(values)
    modes = rigid_modes(geo, np.arange(5), np.full((5, 3), 0.7), rotation=True)
    assert modes.shape == (5, 6, 6)
    for m in range(6):
        v = modes[:, :, m].ravel()
        assert np.abs(J @ v).max() < 1e-8 * np.abs(v).max()


@pytest.mark.datasets
def test_interface_components_group_by_subdomain_set_and_connectivity(m3500):
    _, structure, _, _ = m3500
    dec = decompose(structure, 8, "metis")
    itf = find_interface(dec)
    comp_sets = itf.component_subdomains().toarray()
    # every vertex of a component shares the component's subdomain set
    assert np.array_equal(itf.subdomains.toarray(), comp_sets[itf.component])
    # components are connected: vertices of one component are linked by graph edges
    pos = {v: i for i, v in enumerate(itf.vertices)}
    for c in range(itf.n_components):
        members = set(itf.vertices[itf.component == c].tolist())
        if len(members) > 1:
            linked = {int(u) for u, v in structure.edges if u in members and v in members} | \
                     {int(v) for u, v in structure.edges if u in members and v in members}
            assert linked == members
    assert itf.n_components < itf.size  # grouping actually merges poses on real graphs


@pytest.mark.datasets
@pytest.mark.parametrize("name", ["gdsw", "gdsw-norot", "rgdsw"])
def test_two_level_on_metis_partition_is_spd_and_solves(m3500, name):
    system, structure, km, geo = m3500
    dec = decompose(structure, 8, "metis")
    M = make_preconditioner(name, system.H, dec, km.translation_mask(), geometry=geo)
    x, info = pcg(system.H, system.rhs, M)
    assert info.converged
    ref = sp.linalg.spsolve(system.H.tocsc(), system.rhs)
    assert np.linalg.norm(x - ref) <= 1e-5 * np.linalg.norm(ref)
    rng = np.random.default_rng(0)
    u, v = rng.normal(size=km.dim), rng.normal(size=km.dim)
    assert u @ M.matvec(v) == pytest.approx(v @ M.matvec(u), rel=1e-8)
    assert u @ M.matvec(u) > 0


@pytest.mark.datasets
def test_rgdsw_is_smaller_than_gdsw_and_rigid_modes_beat_unit_modes(m3500):
    system, structure, km, geo = m3500
    dec = decompose(structure, 16, "metis")
    its, size = {}, {}
    for label, name, g in [("gdsw", "gdsw", geo), ("rgdsw", "rgdsw", geo), ("unit", "gdsw", None)]:
        M = make_preconditioner(name, system.H, dec, km.translation_mask(), geometry=g)
        its[label] = pcg(system.H, system.rhs, M)[1].iterations
        size[label] = M.coarse_space.size
    assert size["rgdsw"] < size["gdsw"]
    assert its["gdsw"] < its["unit"]  # rigid-body modes about centroids matter on real graphs
    assert its["gdsw"] <= 40 and its["rgdsw"] <= 60


@pytest.mark.datasets
def test_metis_partition_covers_all_edges(m3500):
    _, structure, _, _ = m3500
    part = metis_partition(structure, 16)
    assert part.shape == (len(structure.edges),) and set(np.unique(part)) == set(range(16))


def test_rank_deficient_coarse_basis_drops_dependent_vectors():
    prob = square_loops(4, 3, sigma=0.05, seed=2)
    km = KeyMap.from_graph(prob.graph, prob.initial)
    system = export_linear_system(prob.graph.linearize(prob.initial), km)
    dec = decompose(GraphStructure.from_matrix(system.H, km.offsets), 4)
    M = make_preconditioner("gdsw", system.H, dec)
    cs = M.coarse_space
    # duplicate every coarse vector: Φ' = [Φ Φ] is rank deficient, A_0' singular
    Phi2 = sp.hstack([cs.Phi, cs.Phi]).tocsr()
    bad = type(cs)(basis=Phi2, A0=(Phi2.T @ system.H @ Phi2).tocsr(),
                   column_component=np.r_[cs.column_component, cs.column_component])
    C = CoarseCorrection(bad)
    assert C.dropped == cs.size
    r = np.random.default_rng(0).normal(size=km.dim)
    assert np.allclose(C.matvec(r), M.coarse.matvec(r), rtol=1e-6, atol=1e-9 * np.abs(r).max())


def test_default_subdomain_size_by_dimension_and_graph_size():
    """About 250 poses per 2D subdomain for exact steps, 100 for inexact ones; 32 per 3D subdomain,
    64 on 3D graphs under 16 384 poses."""
    from gtsam_schwarz.dd import default_subdomains
    assert default_subdomains(360_000, None, 3) == 1440
    assert default_subdomains(360_000, None, 3, inexact=True) == 3600
    assert default_subdomains(4_608, None, 6) == 72
    assert default_subdomains(4_608, None, 6, inexact=True) == 72
    assert default_subdomains(91_125, None, 6) == 2848
    assert default_subdomains(91_125, None, 6, inexact=True) == 2848
    assert default_subdomains(91_125, 1000, 6) == 91  # an explicit size wins
    assert default_subdomains(360_000, 1000, 3, inexact=True) == 360


def test_preconditioned_cg_sizes_subdomains_by_the_forcing():
    """The linear solver passes whether its steps are inexact: forcing "auto" (the default) and
    "eisenstat-walker" take the inexact size, "none" the exact one."""
    from gtsam_schwarz.nonlinear.linear_solver import PreconditionedCG
    from gtsam_schwarz.nonlinear.params import LinearSolverParams
    offsets = np.arange(0, 3 * 10_000 + 1, 3)
    counts = {f: PreconditionedCG(LinearSolverParams(preconditioner="rgdsw-linear", forcing=f), offsets,
                                  np.ones(30_000, dtype=bool)).n_subdomains()
              for f in ("auto", "eisenstat-walker", "none")}
    assert counts == {"auto": 100, "eisenstat-walker": 100, "none": 40}


def test_rows_to_csr_reads_column_major_rows_in_blocks():
    """The extension's solution (column-major) copied to Φ's CSR rows block by block equals the
    row-major selection of every row's first k_r entries, for blocks that do not divide the rows."""
    from gtsam_schwarz.coarse.extension import _rows_to_csr

    rng = np.random.default_rng(3)
    X = np.asfortranarray(rng.normal(size=(1001, 7)))
    k_row = rng.integers(0, 8, 1001)
    expected = X[np.arange(7)[None, :] < k_row[:, None]]
    for block in (1, 64, 1000, 5000):
        out = np.full(len(expected), np.nan)
        _rows_to_csr(X, k_row, out, rows_per_block=block)
        assert np.array_equal(out, expected)


@pytest.mark.parametrize("name, overlap", [("rgdsw-linear", 0), ("gdsw", 1)])
def test_extension_in_the_subdomains_fill_reducing_order_is_the_same_basis(monkeypatch, name, overlap):
    """Interior dofs in the one-level blocks' vertex order (A_II factorized in it, no ordering of its
    own) give the same Φ, A_0 and preconditioner as the interior in dof order."""
    from gtsam_schwarz.linearization.native import NativeLinearizer
    from gtsam_schwarz.problems import lawnmower
    from gtsam_schwarz.solvers import SPARSE_BACKEND, BlockDiagonalSolver

    prob = lawnmower(14, 14, sigma=0.01, seed=2)
    lin = NativeLinearizer.from_arrays(**prob.arrays)
    state = lin.initial_state()
    H = sp.csr_matrix(lin.linearize(state).H) + sp.identity(lin.offsets[-1]) * 1e-3
    dec = decompose(GraphStructure.from_matrix(H, lin.offsets), 6, "metis", overlap)
    mask = np.tile([True, True, False], len(lin.offsets) - 1)
    ordered = make_preconditioner(name, H, dec, mask, geometry=lin.geometry(state))
    monkeypatch.setattr(BlockDiagonalSolver, "order_vertices", lambda self, A, ahead=None: False)
    plain = make_preconditioner(name, H, dec, mask, geometry=lin.geometry(state))
    assert not plain.extension.ordered
    assert ordered.extension.ordered == (SPARSE_BACKEND == "cholmod")
    if ordered.extension.ordered:
        assert not np.array_equal(ordered.extension.interior, plain.extension.interior)
    P1, P2 = ordered.coarse_space.basis.tocsr(), plain.coarse_space.basis.tocsr()
    assert abs(P1 - P2).max() <= 1e-9 * abs(P2).max()
    assert abs(ordered.coarse_space.A0 - plain.coarse_space.A0).max() <= 1e-8 * abs(plain.coarse_space.A0).max()
    x = np.random.default_rng(1).standard_normal(H.shape[0])
    assert np.allclose(ordered.matvec(x), plain.matvec(x), rtol=1e-8, atol=1e-10)
