"""sorted_unique against np.unique (values, first index, inverse)."""

import numpy as np
import pytest

from gtsam_schwarz.util import sorted_unique


@pytest.mark.parametrize("n,high", [(0, 5), (1, 5), (1000, 7), (5000, 10**9)])
def test_sorted_unique_equals_numpy(n, high):
    a = np.random.default_rng(n).integers(0, high, size=n)
    assert np.array_equal(sorted_unique(a), np.unique(a))
    u, first, inv = sorted_unique(a, return_index=True, return_inverse=True)
    nu, nfirst, ninv = np.unique(a, return_index=True, return_inverse=True)
    assert np.array_equal(u, nu) and np.array_equal(first, nfirst) and np.array_equal(inv, ninv.ravel())
    assert np.array_equal(u[inv], a)
