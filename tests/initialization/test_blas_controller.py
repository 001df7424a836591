"""The BLAS-only threadpoolctl scan finds every BLAS the full scan finds, and limits them."""

import pytest

threadpoolctl = pytest.importorskip("threadpoolctl")

from gtsam_schwarz.initialization.chordal import _blas_controller, blas_limits  # noqa: E402


def test_blas_only_scan_finds_the_same_blas_libraries():
    full = {lib.filepath for lib in threadpoolctl.ThreadpoolController().lib_controllers if lib.user_api == "blas"}
    ours = {lib.filepath for lib in _blas_controller().lib_controllers if lib.user_api == "blas"}
    assert ours == full


def test_blas_limits_sets_one_thread():
    with blas_limits(1):
        info = threadpoolctl.threadpool_info()
        assert all(lib["num_threads"] == 1 for lib in info if lib["user_api"] == "blas")
