"""H in the factor form: the compiled product from the source array and the GatheredCSR that carries it,
against the CSR matrix the same linearizer gathers (products, entries, damping, gathers, optimizer runs)."""

import gtsam
import numpy as np
import pytest
import scipy.sparse as sp

import gtsam_schwarz.nonlinear.optimizer as optimizer_module
from gtsam_schwarz.linearization import factor_form
from gtsam_schwarz.linearization.native import NativeLinearizer
from gtsam_schwarz.nonlinear import SchwarzOptimizer, SchwarzParams
from gtsam_schwarz.problems import lawnmower, survey3d
from gtsam_schwarz.solvers import EntryChange, Submatrix
from gtsam_schwarz.util.gathered import GatheredCSR, entries, is_gathered, stored

pytestmark = pytest.mark.skipif(not factor_form.AVAILABLE, reason="numba is not installed")


def _both(lin, state):
    """(the CSR system, the factor-form system) of one linearizer at one state."""
    lin.factor_form = False
    plain = lin.linearize(state)
    lin.factor_form = True
    gathered = lin.linearize(state)
    lin.factor_form = False
    return plain, gathered


def _repeated_pairs(kind: str):
    """A chain whose every pair of neighbours is measured twice (summed per pair in the source), one loop."""
    p = lawnmower(4, 5) if kind == "pose2" else survey3d(2, 3, 3)
    a = dict(p.arrays)
    edges = np.asarray(a["edges"])
    twice = np.concatenate([edges, edges[:, ::-1][: len(edges) // 2]])
    if kind == "pose2":
        z = np.asarray(a["measurements"])
        zi = z[: len(edges) // 2].copy()
        zi[:, :2] = -zi[:, :2]   # any numbers: H is compared with H
        a["measurements"] = np.concatenate([z, zi])
    else:
        R, t = a["measurements"]
        a["measurements"] = (np.concatenate([R, R[: len(edges) // 2]]), np.concatenate([t, t[: len(edges) // 2]]))
    a["edges"] = twice
    for key in ("information", "sqrt_information"):
        if a.get(key) is not None and np.ndim(a[key]) == 3:
            a[key] = np.concatenate([a[key], a[key][: len(edges) // 2]])
    return NativeLinearizer.from_arrays(**a)


def _mixed_graph():
    """Pose2 and Pose3 variables with interleaved keys (each kind's dofs through its table)."""
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    noise2, noise3 = gtsam.noiseModel.Diagonal.Sigmas([0.1, 0.2, 0.05]), gtsam.noiseModel.Isotropic.Sigma(6, 0.1)
    rng = np.random.default_rng(3)
    for k in range(8):
        values.insert(2 * k, gtsam.Pose2(*rng.normal(size=3)))
        values.insert(2 * k + 1, gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(size=3)), rng.normal(size=3)))
    graph.add(gtsam.PriorFactorPose2(0, gtsam.Pose2(), noise2))
    graph.add(gtsam.PriorFactorPose3(1, gtsam.Pose3(), noise3))
    for k in range(7):
        graph.add(gtsam.BetweenFactorPose2(2 * k, 2 * k + 2, gtsam.Pose2(1, 0, 0.1), noise2))
        graph.add(gtsam.BetweenFactorPose3(2 * k + 1, 2 * k + 3, gtsam.Pose3(gtsam.Rot3(), [1, 0, 0]), noise3))
    graph.add(gtsam.BetweenFactorPose2(0, 10, gtsam.Pose2(5, 0, 0.5), noise2))
    graph.add(gtsam.BetweenFactorPose3(3, 13, gtsam.Pose3(gtsam.Rot3(), [5, 0, 0]), noise3))
    return NativeLinearizer(graph, values), values


def _cases():
    yield "lawnmower", NativeLinearizer.from_arrays(**lawnmower(12, 15).arrays), None
    yield "survey3d", NativeLinearizer.from_arrays(**survey3d(3, 5, 6).arrays), None
    yield "pairs2d", _repeated_pairs("pose2"), None
    yield "pairs3d", _repeated_pairs("pose3"), None
    lin, values = _mixed_graph()
    yield "mixed", lin, values


@pytest.mark.parametrize("name", ["lawnmower", "survey3d", "pairs2d", "pairs3d", "mixed"])
def test_the_factor_form_product_is_the_csr_product(name, monkeypatch):
    lin, values = next((lin, v) for n, lin, v in _cases() if n == name)
    state = lin.state(values) if values is not None else lin.initial_state()
    plain, gathered = _both(lin, state)
    H, G = plain.H, gathered.H
    assert isinstance(G, GatheredCSR) and is_gathered(G) and not is_gathered(H)
    assert np.isnan(G.data).all() and G.data.strides == (0,)   # no values stored
    np.testing.assert_array_equal(gathered.g, plain.g)
    assert gathered.error == plain.error
    rng = np.random.default_rng(0)
    x = rng.standard_normal(H.shape[0])
    scale = np.linalg.norm(H @ x)
    assert np.linalg.norm(G @ x - H @ x) <= 1e-14 * scale
    X = rng.standard_normal((H.shape[0], 3))
    assert np.abs(G @ X - H @ X).max() <= 1e-13 * np.abs(H @ X).max()
    monkeypatch.setattr(factor_form.FactorProduct, "THREADED_FROM", 1)   # the blocks split over two threads
    assert np.linalg.norm(G @ x - H @ x) <= 1e-14 * scale
    # every entry, read through the source
    np.testing.assert_array_equal(stored(G).data, H.data)
    np.testing.assert_array_equal(G.diagonal(), H.diagonal())
    G.diagonal_at = None   # found from the pattern, a chunk of rows at a time
    np.testing.assert_array_equal(G.diagonal(), H.diagonal())
    at = rng.integers(0, H.nnz, 50)
    np.testing.assert_array_equal(entries(G, at), H.data[at])


@pytest.mark.parametrize("name", ["lawnmower", "survey3d", "pairs2d", "pairs3d"])
def test_the_block_map_gives_every_entry_its_place_in_the_source(name):
    """One offset per block instead of one per entry; the per-entry index is dropped while H comes
    gathered and made again from the map when a stored H is asked for."""
    lin = next(lin for n, lin, _ in _cases() if n == name)
    state = lin.initial_state()
    full = lin._src.copy()
    block_map = lin._block_map
    assert block_map is not None and block_map.nbytes < full.nbytes / 3
    np.testing.assert_array_equal(block_map.entries(0, len(full)), full)
    rng = np.random.default_rng(2)
    at = rng.permutation(len(full))[: len(full) // 3]          # any order
    np.testing.assert_array_equal(block_map.compose(at), full[at])
    np.testing.assert_array_equal(block_map.compose(at.astype(np.int32)), full[at])
    plain, gathered = _both(lin, state)
    assert gathered.H.index is block_map
    np.testing.assert_array_equal(gathered.H.materialize().data, plain.H.data)
    assert lin._src is None                                     # dropped by the gathered linearization
    again = lin.linearize(state)                                # stored values: the index made again
    np.testing.assert_array_equal(lin._src, full)
    np.testing.assert_array_equal(again.H.data, plain.H.data)


def test_mixed_block_sizes_keep_the_per_entry_index():
    lin, _ = _mixed_graph()
    assert lin._block_map is None and isinstance(lin._src, np.ndarray)


def test_a_matrix_that_is_not_gathered_is_not_changed_by_the_helpers():
    lin = NativeLinearizer.from_arrays(**lawnmower(5, 6).arrays)
    H = lin.linearize(lin.initial_state()).H
    at = np.arange(0, H.nnz, 7)
    np.testing.assert_array_equal(entries(H, at), H.data[at])
    assert (stored(H) != H).nnz == 0


def test_scipy_operations_on_a_gathered_matrix_are_computed_from_its_values_or_refused():
    lin = NativeLinearizer.from_arrays(**lawnmower(5, 6).arrays)
    H, G = (s.H for s in _both(lin, lin.initial_state()))
    P = sp.random(H.shape[0], 4, density=0.3, format="csr", random_state=0)
    for f in (lambda A: P.T @ A @ P, lambda A: P.T.tocsr() @ A, lambda A: A[3:9], lambda A: A.T, lambda A: A + H,
              lambda A: A * 2.0, lambda A: H - A, lambda A: A.multiply(H), lambda A: sp.csr_matrix(A),
              lambda A: sp.csc_matrix(A), lambda A: A.tocoo()):
        assert abs(sp.csr_matrix(f(G)) - f(H)).max() == 0.0
    np.testing.assert_array_equal(G.toarray(), H.toarray())
    with pytest.raises(TypeError, match="source"):
        abs(G)


def test_damping_a_gathered_system_raises_its_diagonal_in_the_source_and_restores_it_exactly():
    lin = NativeLinearizer.from_arrays(**survey3d(2, 4, 4).arrays)
    plain, gathered = _both(lin, lin.initial_state())
    before = gathered.H.source.copy()
    d = np.linspace(1.0, 2.0, plain.H.shape[0])
    x = np.random.default_rng(1).standard_normal(len(d))
    with plain.damped(d) as A, gathered.damped(d) as B:
        assert B is gathered.H
        np.testing.assert_allclose(B @ x, A @ x, rtol=0, atol=1e-12 * np.abs(A @ x).max())
        np.testing.assert_array_equal(B.diagonal(), A.diagonal())
    np.testing.assert_array_equal(gathered.H.source, before)


def test_gathers_compose_their_positions_with_the_source_and_find_them_again_for_a_stored_matrix():
    lin = NativeLinearizer.from_arrays(**lawnmower(6, 7).arrays)
    plain, gathered = _both(lin, lin.initial_state())
    H, G = plain.H, gathered.H
    n = H.shape[0]
    rows = np.arange(0, n // 2)
    cols = np.arange(n // 4, n)
    for offsets in (None, lin.offsets):
        gather = Submatrix(rows, cols, n, offsets=offsets)
        reference = gather(H)
        assert gather.composed is None
        B = gather(G)                       # positions composed with G's index once
        assert gather.composed is G.index
        assert (B != reference).nnz == 0 and np.array_equal(B.data, reference.data)
        again = gather(H)                   # a stored matrix again: positions into its data
        assert gather.composed is None and np.array_equal(again.data, reference.data)
    change = EntryChange(H)
    assert change(G) == 0.0 and EntryChange(G)(H) == 0.0


def test_the_factor_form_is_refused_where_gtsam_linearizes_some_factors():
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    noise = gtsam.noiseModel.Isotropic.Sigma(3, 0.1)
    values.insert(0, gtsam.Pose2())
    values.insert(1, gtsam.Pose2(1, 0, 0))
    values.insert(gtsam.symbol("l", 0), gtsam.Point2(1, 1))
    graph.add(gtsam.PriorFactorPose2(0, gtsam.Pose2(), noise))
    graph.add(gtsam.BetweenFactorPose2(0, 1, gtsam.Pose2(1, 0, 0), noise))
    graph.add(gtsam.BearingRangeFactor2D(1, gtsam.symbol("l", 0), gtsam.Rot2(1.0), 1.4,
                                         gtsam.noiseModel.Isotropic.Sigma(2, 0.1)))
    lin = NativeLinearizer(graph, values)
    assert not lin.factor_form_possible()
    lin.factor_form = True
    assert not is_gathered(lin.linearize(lin.state(values)).H)


@pytest.mark.parametrize("problem, preconditioner", [(lambda: lawnmower(30, 30), "rgdsw-linear"),
                                                     (lambda: survey3d(4, 6, 6), "rgdsw-linear"),
                                                     (lambda: lawnmower(20, 20), "gdsw"),
                                                     (lambda: lawnmower(20, 20), "auto")])
def test_an_optimizer_run_in_the_factor_form_is_the_run_with_csr_values(problem, preconditioner, monkeypatch):
    """The same iterations and the same result, with H handed out gathered (CG) or stored (direct)."""
    arrays = problem().arrays
    runs = []
    for start in (10**12, 0):
        monkeypatch.setattr(optimizer_module, "FACTOR_FORM_FROM", start)
        lin = NativeLinearizer.from_arrays(**arrays)
        forms = []
        original = lin.linearize

        def linearize(state, original=original, forms=forms):
            system = original(state)
            forms.append(is_gathered(system.H))
            return system

        lin.linearize = linearize
        opt = SchwarzOptimizer(None, None, SchwarzParams(preconditioner=preconditioner), linearizer=lin)
        opt.optimize()
        runs.append((opt, forms))
    (csr, csr_forms), (ff, ff_forms) = runs
    assert not any(csr_forms)
    if preconditioner == "auto" and ff.linear_solver.choice == "direct":
        assert not any(ff_forms)            # the direct solver gets stored values (its lagged solves depend
    else:                                   # on measured times: no count to compare)
        assert all(ff_forms[1:]) and (ff_forms[0] or preconditioner == "auto")   # auto: gathered once chosen
        assert [h.cg_iterations for h in ff.history] == [h.cg_iterations for h in csr.history]
    assert ff.error() == pytest.approx(csr.error(), rel=1e-9)
    assert ff.converged and csr.converged
