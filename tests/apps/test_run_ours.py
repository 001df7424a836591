"""run_ours: the loader's arrays released once the native linearizer holds its own copies."""

import numpy as np

from gtsam_schwarz.apps.compare import run_ours
from gtsam_schwarz.nonlinear import SchwarzParams
from gtsam_schwarz.problems import lawnmower


def test_release_arrays_empties_the_callers_dict_and_changes_no_number():
    p = lawnmower(12, 12)
    params = SchwarzParams(preconditioner="direct")
    kept = dict(p.arrays)
    a = run_ours(p.graph, p.initial, params, kept)
    released = dict(p.arrays)
    b = run_ours(p.graph, p.initial, params, released, release_arrays=True)
    assert set(kept) == set(p.arrays)            # the default leaves the caller's dict as it was
    assert released == {}                        # released: nothing held for the rest of the solve
    assert a["iterations"] == b["iterations"]
    assert np.isclose(a["final_error"], b["final_error"], rtol=1e-12)   # (threads may sum in another order)
    assert np.isclose(b["final_error"], p.graph.error(b["values"]), rtol=1e-12)
