"""The coarse level carried to new poses (TwoLevelSchwarz.transport): the rigid-mode map between two
poses, Φ's vertex blocks multiplied in place, and LM with it against LM with full rebuilds."""

import numpy as np
import pytest
import scipy.sparse as sp

from gtsam_schwarz import GraphStructure, KeyMap, SchwarzOptimizer, SchwarzParams, export_linear_system, make_preconditioner
from gtsam_schwarz.coarse import rigid_modes
from gtsam_schwarz.coarse.extension import CoarseBasis
from gtsam_schwarz.coarse.modes import rigid_transport
from gtsam_schwarz.dd import decompose
from gtsam_schwarz.dd.geometry import VertexGeometry
from gtsam_schwarz.problems import lawnmower, survey3d


def _rotations(rng, m, d):
    if d == 2:
        a = rng.normal(size=m)
        return np.stack([np.stack([np.cos(a), -np.sin(a)], 1), np.stack([np.sin(a), np.cos(a)], 1)], 1)
    q = rng.normal(size=(m, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    return np.stack([np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], 1),
                     np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], 1),
                     np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], 1)], 1)


def _moved(geometry, rng, scale=0.3):
    d, m = geometry.d, len(geometry.positions)
    return VertexGeometry(positions=geometry.positions + scale * rng.normal(size=(m, d)),
                          rotations=geometry.rotations @ _rotations(np.random.default_rng(rng.integers(1 << 30)), m, d))


@pytest.mark.parametrize("d", [2, 3])
def test_transport_maps_the_rigid_modes_at_the_old_poses_to_those_at_the_new(d):
    rng = np.random.default_rng(d)
    m = 40
    old = VertexGeometry(positions=5 * rng.normal(size=(m, d)), rotations=_rotations(rng, m, d))
    new = _moved(old, rng, scale=2.0)
    v = np.arange(m)
    centers = rng.normal(size=(m, d))
    T = rigid_transport(old, new, v)
    assert np.abs(T @ rigid_modes(old, v, centers, True) - rigid_modes(new, v, centers, True)).max() < 1e-12
    assert np.abs(rigid_transport(old, old, v) - np.eye(3 if d == 2 else 6)).max() < 1e-15


@pytest.fixture(scope="module", params=[(12, 12), (4, 6, 6)], ids=["2d", "3d"])
def built(request):
    dims = request.param
    prob = (lawnmower if len(dims) == 2 else survey3d)(*dims, sigma=0.01, seed=1)
    km = KeyMap.from_graph(prob.graph, prob.initial)
    H = sp.csr_matrix(export_linear_system(prob.graph.linearize(prob.initial), km).H)
    H.sort_indices()
    dec = decompose(GraphStructure.from_matrix(H, km.offsets), 6, "metis")
    geometry = km.geometry(prob.initial)
    return H, dec, geometry, km.translation_mask()


def _operator(built):
    H, dec, geometry, mask = built
    return H, make_preconditioner("rgdsw-linear", H, dec, mask, geometry=geometry), geometry


def test_vertex_blocks_multiplied_in_place_equal_the_block_diagonal_product(built, monkeypatch):
    """Φ ← diag(T_v) Φ in place, interior rows as dense blocks and interface rows (structural zeros
    in the rotation rows, nested in the other rows' columns) as dense blocks on their union,
    equals the sparse product; storage and pattern kept. A plain sparse Φ (no plan) with random,
    not nested patterns goes entry by entry and gives the product on its pattern."""
    entrywise = []
    real = CoarseBasis._transform_entries
    monkeypatch.setattr(CoarseBasis, "_transform_entries", lambda self, T, verts, *a: (entrywise.append(len(verts)),
                                                                                      real(self, T, verts, *a))[1])
    H, M, geometry = _operator(built)
    basis = M.coarse_space.basis
    d = 3 if geometry.d == 2 else 6
    vertices = basis.vertex_rows(d)
    assert vertices is not None and len(vertices) * d == basis.shape[0]
    T = rigid_transport(geometry, _moved(geometry, np.random.default_rng(5)), vertices)
    D = sp.bsr_matrix((T, np.arange(len(T)), np.arange(len(T) + 1)))
    expected = (D @ basis.local).toarray()
    data, indices = basis.local.data, basis.local.indices.copy()
    basis.transform_vertex_rows(T)
    assert basis.local.data is data and np.array_equal(basis.local.indices, indices)
    assert np.abs(basis.local.toarray() - expected).max() <= 1e-12 * np.abs(expected).max()
    assert not entrywise   # rigid modes: every vertex's rows are nested
    # random patterns, not nested in one row's: any T, no plan
    rng = np.random.default_rng(6)
    full = sp.csr_matrix(np.where(rng.random((8 * d, 5)) < 0.5, rng.normal(size=(8 * d, 5)), 0.0))
    dense_T = rng.normal(size=(8, d, d))
    plain = CoarseBasis(full.copy(), np.arange(8 * d))
    plain.transform_vertex_rows(dense_T)
    D = sp.bsr_matrix((dense_T, np.arange(8), np.arange(9)))
    kept = full.copy()
    kept.data[:] = 1.0
    reference = (D @ full).toarray() * kept.toarray()  # the product on Φ's pattern
    assert np.abs(plain.local.toarray() - reference).max() < 1e-12
    assert entrywise and entrywise[-1] > 0


def test_the_maps_made_a_block_of_vertices_at_a_time_give_the_same_basis(built, monkeypatch):
    """T given as a function of vertex positions (the transport's way: no m × d × d array) is asked
    for blocks of vertices only and gives Φ bit for bit as the whole array does; so does the
    entry-by-entry path of a plain sparse Φ."""
    H, M, geometry = _operator(built)
    basis = M.coarse_space.basis
    d = 3 if geometry.d == 2 else 6
    vertices = basis.vertex_rows(d)
    T = rigid_transport(geometry, _moved(geometry, np.random.default_rng(7)), vertices)
    data = basis.local.data.copy()
    basis.transform_vertex_rows(T)
    whole = basis.local.data.copy()
    basis.local.data[:] = data
    monkeypatch.setattr(CoarseBasis, "TRANSFORM_CHUNK", 4 * d * d)   # a few vertices per block
    asked = []
    basis.transform_vertex_rows(lambda idx: (asked.append(len(idx)), T[idx])[1], d)
    assert np.array_equal(basis.local.data, whole)
    assert asked and max(asked) < len(vertices) and sum(asked) >= len(vertices)
    rng = np.random.default_rng(8)
    full = sp.csr_matrix(np.where(rng.random((8 * d, 5)) < 0.5, rng.normal(size=(8 * d, 5)), 0.0))
    dense_T = rng.normal(size=(8, d, d))
    a, b = CoarseBasis(full.copy(), np.arange(8 * d)), CoarseBasis(full.copy(), np.arange(8 * d))
    a.transform_vertex_rows(dense_T)
    b.transform_vertex_rows(lambda idx: dense_T[idx], d)
    assert np.array_equal(a.local.data, b.local.data)


def test_transport_keeps_a0_and_the_subdomain_factors_and_moves_the_interface_values(built):
    """After transport, Φ's interface rows are the rigid modes at the new poses that a fresh build
    writes (the same span per coarse node), A_0's factorization is the old one, and the operator is
    symmetric positive definite."""
    H, M, geometry = _operator(built)
    new = _moved(geometry, np.random.default_rng(7), scale=0.05)
    solver, A0 = M.one_level.solver, M.coarse_space.A0
    coarse = M.coarse
    assert M.can_transport(new)
    M.transport(H, new)
    assert M.coarse is coarse and M.coarse_space.A0 is A0 and M.one_level.solver is solver
    fresh = make_preconditioner("rgdsw-linear", H, M.decomposition, built[3], geometry=new)
    G = M.extension.gamma
    ours, theirs = M.coarse_space.Phi.toarray()[G], fresh.coarse_space.Phi.toarray()[G]
    # the same columns up to a change of basis per coarse node (rotation about another center)
    X, *_ = np.linalg.lstsq(theirs, ours, rcond=None)
    assert np.abs(theirs @ X - ours).max() <= 1e-9 * np.abs(ours).max()
    x = np.random.default_rng(8).standard_normal(H.shape[0])
    y = np.random.default_rng(9).standard_normal(H.shape[0])
    assert np.isclose(y @ M.apply(x), x @ M.apply(y), rtol=1e-10)
    assert x @ M.apply(x) > 0


def test_transport_needs_rigid_modes_at_known_poses(built):
    H, M, geometry = _operator(built)
    assert not M.can_transport(None)
    other = VertexGeometry(positions=geometry.positions[:-1], rotations=geometry.rotations[:-1])
    assert not M.can_transport(other)


def test_lm_with_the_transported_coarse_level_ends_where_rebuilds_do():
    """LM on a lawnmower survey from the chordal start: the second solve carries the coarse level
    (subdomains kept, no rebuild), takes at most a few more CG iterations than a full rebuild, and
    the run ends at the same error."""
    prob = lawnmower(40, 40, sigma=0.01, seed=2)
    runs = {}
    for transport in (True, False):
        opt = SchwarzOptimizer(prob.graph, prob.initial, SchwarzParams(
            method="lm", preconditioner="rgdsw-linear", subdomains=16, transport_coarse=transport))
        opt.optimize()
        runs[transport] = opt
    on, off = runs[True].history, runs[False].history
    assert on[1]["coarse_transported"] and on[1]["subdomains_kept"] and on[1]["preconditioner_rebuilt"]
    assert not any(h["coarse_transported"] for h in off)
    assert on[1]["cg_iterations"] <= off[1]["cg_iterations"] + 3
    assert abs(runs[True].error() - runs[False].error()) <= 1e-8 * runs[False].error()


def test_a_transported_coarse_level_beyond_the_cap_is_rebuilt_in_full(monkeypatch):
    """A transport that makes M useless (Φ scrambled) lets CG reach its cap: the operator is then
    rebuilt in full (coarse level and subdomains for H) and CG converges from its iterate."""
    from gtsam_schwarz.schwarz.two_level import TwoLevelSchwarz

    real = TwoLevelSchwarz.transport

    def scrambled(self, A, geometry):
        out = real(self, A, geometry)
        basis = self.coarse_space.basis
        basis.local.data[:] = np.random.default_rng(0).standard_normal(basis.local.nnz)
        return out

    monkeypatch.setattr(TwoLevelSchwarz, "transport", scrambled)
    prob = lawnmower(40, 40, sigma=0.01, seed=2)
    opt = SchwarzOptimizer(prob.graph, prob.initial, SchwarzParams(method="lm", preconditioner="rgdsw-linear",
                                                                   subdomains=16))
    opt.optimize()
    second = opt.history[1]
    assert second["preconditioner_rebuilt"] and not second["coarse_transported"] and second["cg_converged"]
    reference = SchwarzOptimizer(prob.graph, prob.initial, SchwarzParams(
        method="lm", preconditioner="rgdsw-linear", subdomains=16, transport_coarse=False))
    reference.optimize()
    assert abs(opt.error() - reference.error()) <= 1e-8 * reference.error()


def test_transport_started_ahead_equals_transport_and_is_undone_for_a_lagged_solve(built):
    """Φ multiplied on the side thread (transport_ahead) and taken by transport to the same poses is
    exactly Φ transported in place; to other poses, or settled for a lagged solve, Φ is carried back
    to the build's poses first (to rounding)."""
    H, M, geometry = _operator(built)
    rng = np.random.default_rng(11)
    new, other = _moved(geometry, rng, scale=0.05), _moved(geometry, rng, scale=0.05)
    built_phi = M.coarse_space.basis.local.data.copy()
    reference, _, _ = _operator(built)[1], None, None
    reference.transport(H, new)
    M.transport_ahead(new)
    same = VertexGeometry(positions=new.positions.copy(), rotations=new.rotations.copy())  # equal poses, another object
    M.transport(H, same)
    assert np.array_equal(M.coarse_space.basis.local.data, reference.coarse_space.basis.local.data)
    assert M._geometry is same
    # ahead to `other`, then a lagged solve: Φ back at `same`'s poses
    at_same = M.coarse_space.basis.local.data.copy()
    M.transport_ahead(other)
    assert not M.settle_transport()
    assert np.abs(M.coarse_space.basis.local.data - at_same).max() <= 1e-12 * np.abs(at_same).max()
    # ahead to `other`, transport to `new` (not the poses multiplied to): the result of transport alone
    M2 = _operator(built)[1]
    M2.transport_ahead(other)
    M2.transport(H, new)
    assert np.abs(M2.coarse_space.basis.local.data - reference.coarse_space.basis.local.data).max() <= \
        1e-12 * np.abs(built_phi).max()


def test_lm_with_the_transport_ahead_is_the_run_without_it(monkeypatch):
    """LM on a lawnmower: the second solve's Φ multiplied ahead (beside the linearization) gives the
    run of the transport made in the solve, iterate for iterate."""
    from gtsam_schwarz.nonlinear.linear_solver import PreconditionedCG

    prob = lawnmower(40, 40, sigma=0.01, seed=2)
    calls = []
    real = PreconditionedCG.ahead
    monkeypatch.setattr(PreconditionedCG, "ahead", lambda self, g: (calls.append(1), real(self, g))[1])
    params = SchwarzParams(method="lm", preconditioner="rgdsw-linear", subdomains=16)
    on = SchwarzOptimizer(prob.graph, prob.initial, params)
    on.optimize()
    assert calls and on.history[1]["coarse_transported"]
    monkeypatch.setattr(PreconditionedCG, "ahead", lambda self, g: None)
    off = SchwarzOptimizer(prob.graph, prob.initial, params)
    off.optimize()
    assert [h["cg_iterations"] for h in on.history] == [h["cg_iterations"] for h in off.history]
    assert [h["cg_residuals"] for h in on.history] == [h["cg_residuals"] for h in off.history]
    assert on.error() == off.error()
