"""The BLAS-only threadpoolctl scan finds every BLAS the full scan finds, and limits them."""

import pytest

threadpoolctl = pytest.importorskip("threadpoolctl")

from gtsam_schwarz.util.blas import _blas_controller, blas_limits  # noqa: E402


def test_blas_only_scan_finds_the_same_blas_libraries():
    import scipy.linalg  # noqa: F401 — loaded as the controller loads it before its scan
    full = {lib.filepath for lib in threadpoolctl.ThreadpoolController().lib_controllers if lib.user_api == "blas"}
    ours = {lib.filepath for lib in _blas_controller().lib_controllers if lib.user_api == "blas"}
    assert ours == full


def test_blas_limits_sets_one_thread():
    with blas_limits(1):
        info = threadpoolctl.threadpool_info()
        assert all(lib["num_threads"] == 1 for lib in info if lib["user_api"] == "blas")


def test_cg_runs_its_vector_operations_on_one_blas_thread():
    """pcg and pcg_columns run with BLAS on one thread (OpenBLAS's threads made a demo's 1 260 block-Jacobi
    iterations on 12k unknowns take 16-58 s instead of 0.3 s) and give the caller's setting back."""
    import numpy as np
    import scipy.sparse as sp

    from gtsam_schwarz.krylov import pcg, pcg_columns

    def blas_threads():
        return [lib["num_threads"] for lib in threadpoolctl.threadpool_info() if lib["user_api"] == "blas"]

    n = 20_000
    A = sp.diags(np.linspace(1.0, 50.0, n)).tocsr()
    seen = []

    def M(r):
        if len(seen) < 2:
            seen.append(blas_threads())
        return r / A.diagonal()[:, None] if r.ndim > 1 else r / A.diagonal()

    with threadpoolctl.threadpool_limits(2, user_api="blas"):
        outside = blas_threads()
        x, info = pcg(A, np.ones(n), M=M, tol=1e-10)
        X, infos = pcg_columns(A, np.ones((n, 2)), M=M, tol=1e-10)
        assert blas_threads() == outside   # the caller's setting is back
    assert info.converged and all(i.converged for i in infos)
    assert np.allclose(A @ x, 1.0) and np.allclose(A @ X, 1.0)
    assert len(seen) == 2 and all(t and max(t) == 1 for t in seen)
