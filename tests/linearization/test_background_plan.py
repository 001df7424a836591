"""The native linearizer's pattern and gather plan made on the background thread (while the start is
read and the chordal start runs) are the ones made inline: the same H, g and error."""

import threading

import numpy as np
import pytest

from gtsam_schwarz import lawnmower, survey3d
from gtsam_schwarz.linearization import native


@pytest.mark.parametrize("make", [lambda: lawnmower(20, 20), lambda: survey3d(3, 6, 6)])
def test_background_plan_equals_the_inline_one(make, monkeypatch):
    p = make()
    built = {}
    real = native.NativeLinearizer._make_plan

    def recording(self, rows, cols):
        built.setdefault("threads", []).append(threading.current_thread().name)
        return real(self, rows, cols)

    monkeypatch.setattr(native.NativeLinearizer, "_make_plan", recording)
    for background in (True, False):
        monkeypatch.setattr(native, "BACKGROUND_PLAN_FROM", 0 if background else 10**15)
        lin = native.NativeLinearizer.from_arrays(**p.arrays)
        built[background] = (lin, lin.linearize(lin.initial_state()))
    assert built["threads"][0] != "MainThread" and built["threads"][1] == "MainThread"
    (a, sa), (b, sb) = built[True], built[False]
    assert np.array_equal(a.pattern.indptr, b.pattern.indptr) and np.array_equal(a.pattern.indices, b.pattern.indices)
    assert np.array_equal(a.diagonal, b.diagonal) and a.nnz_estimate == a.pattern.nnz
    assert np.array_equal(sa.H.data, sb.H.data) and np.array_equal(sa.g, sb.g) and sa.error == sb.error


def test_an_error_in_the_background_plan_reaches_the_first_linearization(monkeypatch):
    p = lawnmower(10, 10)
    monkeypatch.setattr(native, "BACKGROUND_PLAN_FROM", 0)

    def broken(self, rows, cols):
        raise RuntimeError("plan failed")

    monkeypatch.setattr(native.NativeLinearizer, "_make_plan", broken)
    lin = native.NativeLinearizer.from_arrays(**p.arrays)
    assert lin.error(lin.initial_state()) > 0   # what needs no pattern works meanwhile
    with pytest.raises(RuntimeError, match="plan failed"):
        lin.linearize(lin.initial_state())
