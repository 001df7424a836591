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


@pytest.mark.parametrize("dtype", [np.int64, np.int32, np.uint64, np.uint16])
@pytest.mark.parametrize("n,high", [(1, 1), (1000, 7), (1000, 1500), (1000, 5000), (3000, 10**9)])
def test_inverse_alone_equals_numpy_for_labels_of_any_range(dtype, n, high):
    """The inverse alone (counted for labels of a small range, sorted otherwise): numpy's values, dtype
    and inverse; negative integers take the sort."""
    a = np.random.default_rng(n + high).integers(0, min(high, np.iinfo(dtype).max), size=n).astype(dtype)
    u, inv = sorted_unique(a, return_inverse=True)
    nu, ninv = np.unique(a, return_inverse=True)
    assert u.dtype == nu.dtype and np.array_equal(u, nu) and np.array_equal(inv, ninv.ravel())
    b = a.astype(np.int64) - high // 2
    u, inv = sorted_unique(b, return_inverse=True)
    assert np.array_equal(u, np.unique(b)) and np.array_equal(u[inv], b)
