"""Export of GTSAM's linearization to scipy, and steps back to gtsam.Values."""

import gtsam
import numpy as np
import pytest

from gtsam_schwarz import KeyMap, export_linear_system, square_loops


def mixed_graph():
    """Pose2, Point2 and Pose3 variables with non-consecutive and symbol keys (dims 3, 2, 6)."""
    X, L, P = (lambda i: gtsam.symbol("x", i)), (lambda i: gtsam.symbol("l", i)), (lambda i: gtsam.symbol("p", i))
    rng = np.random.default_rng(1)
    g, v = gtsam.NonlinearFactorGraph(), gtsam.Values()
    n3 = gtsam.noiseModel.Diagonal.Sigmas(np.array([0.1, 0.2, 0.05]))
    g.add(gtsam.PriorFactorPose2(X(0), gtsam.Pose2(0, 0, 0), n3))
    for i in range(4):
        g.add(gtsam.BetweenFactorPose2(X(i), X(i + 1), gtsam.Pose2(1.0, 0.1, 0.2), n3))
    g.add(gtsam.BetweenFactorPose2(X(4), X(0), gtsam.Pose2(-3.5, -1.0, -0.7), n3))
    for i in range(5):
        v.insert(X(i), gtsam.Pose2(*(rng.normal(size=3) + [i, 0, 0])))
    n2 = gtsam.noiseModel.Isotropic.Sigma(2, 0.3)
    for j in (7, 3):
        g.add(gtsam.PriorFactorPoint2(L(j), np.array([j, 1.0]), n2))
        v.insert(L(j), rng.normal(size=2))
    n6 = gtsam.noiseModel.Isotropic.Sigma(6, 0.5)
    g.add(gtsam.PriorFactorPose3(P(0), gtsam.Pose3(), n6))
    g.add(gtsam.BetweenFactorPose3(P(0), P(5), gtsam.Pose3(gtsam.Rot3.Rz(0.3), np.array([1.0, 2, 3])), n6))
    for k in (0, 5):
        v.insert(P(k), gtsam.Pose3(gtsam.Rot3.RzRyRx(*rng.normal(size=3)), rng.normal(size=3)))
    return g, v


@pytest.mark.parametrize("make", ["mixed", "square"])
def test_export_matches_gtsam_dense_jacobian_and_hessian(make):
    if make == "mixed":
        graph, values = mixed_graph()
    else:
        prob = square_loops(2, 3, sigma=0.05, seed=3)
        graph, values = prob.graph, prob.initial
    keymap = KeyMap.from_graph(graph, values)
    lin = graph.linearize(values)
    system = export_linear_system(lin, keymap)
    A, b = lin.jacobian()  # GTSAM's natural (sorted-key) ordering
    Lam, eta = lin.hessian()
    assert system.J.shape[1] == A.shape[1] == keymap.dim
    assert np.allclose(system.J.toarray(), A, atol=1e-12)
    assert np.allclose(system.b, b, atol=1e-12)
    assert np.allclose(system.H.toarray(), Lam, atol=1e-9)
    assert np.allclose(system.rhs, np.ravel(eta), atol=1e-9)  # rhs = −g = Jᵀb = η
    assert system.error == pytest.approx(graph.error(values), rel=1e-12)


def test_keymap_dims_offsets_and_order():
    graph, values = mixed_graph()
    km = KeyMap.from_graph(graph, values)
    assert np.all(km.keys[1:] > km.keys[:-1])  # sorted like GTSAM's Ordering(keys())
    dims = values.dims()
    assert [int(d) for d in km.dims] == [dims[int(k)] for k in km.keys]
    assert km.dim == sum(dims.values())
    assert sorted(set(km.dims.tolist())) == [2, 3, 6]
    mask = km.translation_mask()
    for key, lo, d in zip(km.keys, km.offsets[:-1], km.dims):
        expect = {3: [1, 1, 0], 2: [1, 1], 6: [0, 0, 0, 1, 1, 1]}[int(d)]
        assert mask[lo:lo + d].astype(int).tolist() == expect


def test_step_round_trip_through_vector_values_and_retract():
    graph, values = mixed_graph()
    km = KeyMap.from_graph(graph, values)
    x = np.random.default_rng(2).normal(size=km.dim) * 0.1
    vv = km.to_vector_values(x)
    for key, lo, hi in zip(km.keys, km.offsets[:-1], km.offsets[1:]):
        assert np.array_equal(vv.at(int(key)), x[lo:hi])
    # the linear model predicts the change of the error for a small step
    lin = graph.linearize(values)
    system = export_linear_system(lin, km)
    step = 1e-6 * x
    new = km.retract(values, step)
    predicted = system.error + system.g @ step
    assert graph.error(new) == pytest.approx(predicted, rel=1e-6)
    # retract equals gtsam's own retract of the same VectorValues
    direct = values.retract(km.to_vector_values(step))
    assert new.equals(direct, 1e-15)


def test_step_with_wrong_shape_is_refused():
    graph, values = mixed_graph()
    km = KeyMap.from_graph(graph, values)
    with pytest.raises(ValueError, match="shape"):
        km.to_vector_values(np.zeros(km.dim + 1))


def test_missing_initial_value_is_named():
    graph, values = mixed_graph()
    values.erase(gtsam.symbol("l", 7))
    with pytest.raises(KeyError, match="l7"):
        KeyMap.from_graph(graph, values)
