"""Process-level memory settings: numpy's page size inside our work, glibc's mmap threshold."""

import platform

import numpy as np
import pytest

from gtsam_schwarz.solvers.memory import bound_heap_fragmentation
from gtsam_schwarz.util import small_pages, with_small_pages
from gtsam_schwarz.util.pages import _madvise_setter


def test_small_pages_restore_the_callers_setting():
    setter = _madvise_setter()
    if setter is None:
        pytest.skip("this numpy has no madvise setting to change")
    for before in (True, False):
        setter(before)
        with small_pages():
            assert setter(False) is False  # inside: no huge-page advice
        assert setter(before) is before  # after: the caller's own setting

        @with_small_pages
        def inside():
            return setter(False)

        assert inside() is False and setter(before) is before
    setter(True)


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="mallopt is glibc's")
def test_heap_fragmentation_bound_is_set_once_and_allocation_still_works():
    assert bound_heap_fragmentation() is True
    assert bound_heap_fragmentation() is True  # idempotent
    a = np.ones(3 * 2**20)  # above the threshold: its own pages
    assert float(a.sum()) == 3 * 2**20
