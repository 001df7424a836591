"""Every preconditioner is SPD, CG with it solves the system, and Schwarz pieces match the paper."""

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from gtsam_schwarz import (PRECONDITIONERS, GraphStructure, KeyMap, bar_chain, export_linear_system,
                           find_interface, make_preconditioner, pcg, segments, square_loops)


@pytest.fixture(scope="module")
def model():
    prob = square_loops(4, 3, sigma=0.05, seed=7)
    km = KeyMap.from_graph(prob.graph, prob.initial)
    system = export_linear_system(prob.graph.linearize(prob.initial), km)
    dec = segments(GraphStructure.from_matrix(system.H, km.offsets), 4, overlap=1)
    return system, dec, km


@pytest.mark.parametrize("name", PRECONDITIONERS)
def test_preconditioner_is_spd_and_cg_matches_direct(model, name):
    system, dec, km = model
    M = make_preconditioner(name, system.H, dec, km.translation_mask())
    D = M.todense()
    assert np.allclose(D, D.T, atol=1e-10 * np.abs(D).max())
    assert np.linalg.eigvalsh(0.5 * (D + D.T)).min() > 0
    x, info = pcg(system.H, system.rhs, None if name == "none" else M, tol=1e-10)
    assert info.converged
    ref = spla.spsolve(system.H.tocsc(), system.rhs)
    assert np.allclose(x, ref, rtol=1e-6, atol=1e-8 * np.abs(ref).max())
    # usable by scipy's own CG as a LinearOperator
    x2, flag = spla.cg(system.H, system.rhs, M=M.aspreconditioner(), rtol=1e-10, maxiter=5000)
    assert flag == 0 and np.allclose(x2, ref, rtol=1e-5, atol=1e-7 * np.abs(ref).max())


def test_one_level_is_sum_of_local_solves(model):
    """M⁻¹ = Σ R_iᵀ (R_i A R_iᵀ)⁻¹ R_i, checked against an explicit loop over subdomains."""
    system, dec, _ = model
    A = system.H.toarray()
    ref = np.zeros_like(A)
    sets = dec.index_sets(overlapping=True)
    for i in range(sets.count):
        I = sets.get(i)
        ref[np.ix_(I, I)] += np.linalg.inv(A[np.ix_(I, I)])
    D = make_preconditioner("one-level", system.H, dec).todense()
    assert np.allclose(D, ref, atol=1e-10 * np.abs(ref).max())


def test_block_jacobi_inverts_pose_blocks(model):
    system, dec, km = model
    A = system.H.toarray()
    D = make_preconditioner("block-jacobi", system.H, dec).todense()
    for lo, hi in zip(km.offsets[:-1], km.offsets[1:]):
        assert np.allclose(D[lo:hi, lo:hi], np.linalg.inv(A[lo:hi, lo:hi]))
    off = D.copy()
    for lo, hi in zip(km.offsets[:-1], km.offsets[1:]):
        off[lo:hi, lo:hi] = 0
    assert not off.any()


@pytest.mark.parametrize("name, per_pose", [("gdsw", 3), ("gdsw-norot", 2)])
def test_gdsw_coarse_basis_is_discrete_harmonic(model, name, per_pose):
    system, dec, km = model
    M = make_preconditioner(name, system.H, dec, km.translation_mask())
    itf, cs = M.interface, M.coarse_space
    P = 3 * 3  # poses per loop: 4 sides × 3 points; interface = the returns to the start 4Pk
    assert itf.vertices.tolist() == [4 * 3 * k for k in (1, 2, 3)]
    assert cs.size == per_pose * 3
    Phi = cs.Phi.toarray()
    gamma = np.concatenate([np.arange(3 * v, 3 * v + 3) for v in itf.vertices])
    interior = np.setdiff1d(np.arange(km.dim), gamma)
    # interface values: unit vectors (translations only without rotation)
    G = Phi[gamma]
    assert np.allclose(np.sort(G.sum(axis=0)), 1.0) and set(np.unique(G)) <= {0.0, 1.0}
    if per_pose == 2:
        assert not G[2::3].any()  # no mode on the rotation dofs
    # harmonic: A_II Φ_I + A_IΓ Φ_Γ = 0
    A = system.H.toarray()
    R = A[np.ix_(interior, interior)] @ Phi[interior] + A[np.ix_(interior, gamma)] @ G
    assert np.abs(R).max() < 1e-8 * np.abs(A).max()
    # local support: a basis function lives on the two loops next to its interface pose
    v0 = itf.vertices[0]
    col = np.flatnonzero(Phi[3 * v0] == 1.0)[0]
    support = np.flatnonzero(np.abs(Phi[:, col]).reshape(-1, 3).sum(1) > 0)
    assert support.min() >= v0 - P * 4 and support.max() <= v0 + P * 4
    assert np.allclose(cs.A0.toarray(), Phi.T @ A @ Phi)


def test_bar_chain_matches_paper_iteration_counts():
    """Paper Table tab:laplace_scalability: one-level grows, GDSW stays at 6 with λ ∈ [1, 2.1]."""
    paper = {4: (7, 1.82e-2), 16: (32, 1.22e-3), 32: (65, 3.05e-4)}
    for N, (cg_one, lmin_one) in paper.items():
        bc = bar_chain(N)
        dec = bc.decomposition(overlap=1)
        x, one = pcg(bc.K, bc.b, make_preconditioner("one-level", bc.K, dec))
        assert one.iterations == cg_one
        assert one.lambda_min == pytest.approx(lmin_one, rel=0.01)
        x, two = pcg(bc.K, bc.b, make_preconditioner("gdsw", bc.K, dec))
        assert two.iterations == 6
        assert round(two.lambda_min, 2) == 1.00 and round(two.lambda_max, 2) == 2.10
        assert np.allclose(x, bc.solution, atol=1e-5)


def test_unknown_preconditioner_is_refused(model):
    system, dec, _ = model
    with pytest.raises(ValueError, match="unknown preconditioner 'amg'"):
        make_preconditioner("amg", system.H, dec)


def test_two_level_applied_on_two_threads_gives_the_same_numbers(model, monkeypatch):
    """With a coarse basis above the threshold, the coarse correction runs on the side thread while
    the local solves run here: the same vectors, bit for bit, as one after the other, and CG's
    iterates too."""
    from gtsam_schwarz.schwarz.two_level import TwoLevelSchwarz

    system, dec, km = model
    serial = make_preconditioner("rgdsw", system.H, dec, km.translation_mask())
    assert not serial.concurrent
    monkeypatch.setattr(TwoLevelSchwarz, "CONCURRENT_FROM", 1)
    side = make_preconditioner("rgdsw", system.H, dec, km.translation_mask())
    assert side.concurrent and side.coarse_size > 0
    rng = np.random.default_rng(3)
    for x in rng.standard_normal((20, system.H.shape[0])):
        assert np.array_equal(side.apply(x), serial.apply(x))
    x1, info1 = pcg(system.H, system.rhs, serial, tol=1e-10)
    x2, info2 = pcg(system.H, system.rhs, side, tol=1e-10)
    assert info1.converged and info2.iterations == info1.iterations and np.array_equal(x1, x2)
