"""The residuals of an error evaluation kept for the same state's linearization give the same system."""

import numpy as np
import pytest

from gtsam_schwarz import lawnmower, survey3d
from gtsam_schwarz.linearization import native
from gtsam_schwarz.linearization.native import NativeLinearizer


@pytest.mark.parametrize("make", [lambda: lawnmower(10, 12, sigma=0.05, seed=1),
                                  lambda: survey3d(2, 5, 5, sigma=0.05, seed=1)])
def test_linearization_after_the_error_uses_its_residuals_and_drops_them(make, monkeypatch):
    """error(state) then linearize(state) of a step's state equals a fresh linearization bit for bit
    (H, g, error), with no residual computed twice; the kept residuals go with that linearization, with
    release_scratch, and are not kept above KEEP_RESIDUALS_BYTES, for a start's state, or when
    keep_residuals is off."""
    prob = make()
    lin = NativeLinearizer.from_arrays(**prob.arrays)
    step = np.random.default_rng(2).normal(scale=0.01, size=lin.dim)
    state = lin.retract(lin.initial_state(), step)
    other_lin = NativeLinearizer.from_arrays(**prob.arrays)
    fresh = other_lin.linearize(other_lin.retract(other_lin.initial_state(), step))

    calls = []
    residual = lin._residual
    monkeypatch.setattr(lin, "_residual", lambda *a: (calls.append(1), residual(*a))[1])
    error = lin.error(state)
    evaluated = len(calls)
    assert evaluated > 0 and lin._kept_residuals is not None and lin._kept_residuals[0] is state
    system = lin.linearize(state)
    assert len(calls) == evaluated   # the linearization computed no residual again
    assert lin._kept_residuals is None
    assert system.error == error == fresh.error
    assert np.array_equal(system.g, fresh.g)
    assert np.array_equal(system.H.indptr, fresh.H.indptr) and np.array_equal(system.H.data, fresh.H.data)

    other = lin.retract(state, np.full(lin.dim, 1e-3))   # another state's evaluation is not used for this one
    lin.error(other)
    lin.linearize(state)
    assert len(calls) > 2 * evaluated
    lin.error(lin.retract(state, np.full(lin.dim, 2e-3)))
    lin.release_scratch()
    assert lin._kept_residuals is None

    monkeypatch.setattr(native, "KEEP_RESIDUALS_BYTES", 0)
    lin.error(lin.retract(state, np.full(lin.dim, 3e-3)))
    assert lin._kept_residuals is None
    monkeypatch.setattr(native, "KEEP_RESIDUALS_BYTES", 1 << 40)
    lin.error(lin.initial_state())   # a start's state (not made by a step) keeps none
    assert lin._kept_residuals is None
    lin.keep_residuals = False
    lin.error(lin.retract(state, np.full(lin.dim, 4e-3)))
    assert lin._kept_residuals is None


def test_a_schwarz_run_keeps_no_residuals_a_direct_run_does():
    """The optimizer turns the keeping off once its linear solver is Schwarz (its memory peak sits beside
    the linearization); with direct it stays on; both reach the same minimum."""
    from gtsam_schwarz import SchwarzOptimizer, SchwarzParams

    prob = lawnmower(12, 12, sigma=0.05, seed=3)
    errors = {}
    for name in ("direct", "rgdsw-linear"):
        lin = NativeLinearizer.from_arrays(**prob.arrays)
        opt = SchwarzOptimizer(prob.graph, prob.initial, SchwarzParams(method="lm", preconditioner=name, subdomain_size=30),
                               linearizer=lin)
        opt.optimize()
        assert lin.keep_residuals == (name == "direct")
        errors[name] = opt.error()
    assert errors["direct"] == pytest.approx(errors["rgdsw-linear"], rel=1e-7)
