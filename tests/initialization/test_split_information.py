"""The chordal start's information as the pair it reduces to (rotation weights, translation blocks):
the same weights and the same start as from the full blocks, and bad pairs refused."""

import numpy as np
import pytest

from gtsam_schwarz.initialization import chordal as ch
from gtsam_schwarz.initialization.chordal import chordal_initialization
from gtsam_schwarz.linearization.native import NativeLinearizer
from gtsam_schwarz.problems import lawnmower, survey3d


@pytest.mark.parametrize("make", [lambda: lawnmower(20, 20), lambda: survey3d(2, 6, 6)])
def test_split_information_gives_the_full_blocks_weights_and_start(make):
    lin = NativeLinearizer.from_arrays(**make().arrays)
    full, split = lin.pose_graph(), lin.pose_graph(split_information=True)
    b, s = full["between"], split["between"]
    m, d = len(b["i"]), full["d"]
    w_rot, W_t = s["information"]
    assert w_rot.shape == (m,) and W_t.shape == (m, d, d)
    w0, W0 = ch._edge_weights(b["information"], m, d)
    w1, W1 = ch._edge_weights(s["information"], m, d)
    np.testing.assert_allclose(w1, w0, rtol=1e-14)
    np.testing.assert_allclose(W1, W0, rtol=1e-14, atol=1e-14 * np.abs(W0).max())
    edges = np.column_stack([b["i"], b["j"]])
    r0 = chordal_initialization(full["n"], edges, b["R"], b["t"], b["information"])
    r1 = chordal_initialization(full["n"], edges, s["R"], s["t"], s["information"])
    np.testing.assert_allclose(r1.rotations, r0.rotations, atol=1e-12)
    np.testing.assert_allclose(r1.positions, r0.positions, atol=1e-9 * (1 + np.abs(r0.positions).max()))


def test_bad_split_information_is_refused():
    m, d = 4, 2
    W = np.broadcast_to(np.eye(d), (m, d, d)).copy()
    with pytest.raises(ValueError, match="shapes"):
        ch._edge_information((np.ones(m - 1), W), m, d)
    W[0, 0, 1] = 0.5   # not symmetric
    with pytest.raises(ValueError, match="symmetric"):
        ch._edge_information((np.ones(m), W), m, d)
    with pytest.raises(ValueError, match="pair"):
        ch._edge_information((np.ones(m), W, W), m, d)
