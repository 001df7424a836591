"""BLAS threads: limited to one while our own loops call BLAS on vectors.

OpenBLAS spreads a dot product or an axpy over its threads from ~10 000 entries; on this project's
2-core machines each such call then costs milliseconds of thread hand-off instead of microseconds
(CG's vector operations on 12k entries: 9 ms a call, a demo's 1 260 block-Jacobi iterations 16-58 s
against 0.3 s on one thread), and threads idling beside CHOLMOD's slowed setup and CG up to 20×.
"""

from __future__ import annotations

import contextlib
import functools
import os

_CONTROLLER: list = []   # one threadpoolctl controller per process, created on first use


def blas_limits(threads: int | None):
    """Context limiting BLAS to ``threads`` (None: a no-op), like ``threadpool_limits(threads, "blas")``
    but through one cached controller: ``threadpool_limits`` rescans the loaded libraries (~1 ms a call)."""
    if threads is None:
        return contextlib.nullcontext()
    if not _CONTROLLER:
        _CONTROLLER.append(_blas_controller())
    if _CONTROLLER[0] is None:
        return contextlib.nullcontext()
    return _CONTROLLER[0].limit(limits=threads, user_api="blas")


# names of the loaded libraries that can be a BLAS (or a link to one); the others are not resolved
_BLAS_NAME_HINTS = ("blas", "mkl", "blis", "lapack", "accelerate")


def _blas_controller():
    """threadpoolctl's controller of the loaded BLAS libraries (None without threadpoolctl).

    Its full scan resolves the real path of every loaded library (~120 here, ~2 ms); only BLAS is
    limited, so libraries whose names cannot be a BLAS are skipped before that. Falls back to the
    full scan if threadpoolctl's internals differ or the filtered scan finds no BLAS. The BLAS
    libraries this package calls (numpy's and scipy's own) are loaded first: the controller is cached,
    and a library loaded after its scan would keep its threads."""
    try:
        from threadpoolctl import ThreadpoolController  # a project dependency; optional here
    except ImportError:
        return None
    import numpy  # noqa: F401
    import scipy.linalg  # noqa: F401
    try:
        class _BlasOnly(ThreadpoolController):
            def _make_controller_from_path(self, filepath):
                name = os.path.basename(filepath).lower()
                if any(h in name for h in _BLAS_NAME_HINTS):
                    super()._make_controller_from_path(filepath)

        controller = _BlasOnly()
        if any(lib.user_api == "blas" for lib in controller.lib_controllers):
            return controller
    except Exception:  # noqa: BLE001 — a threadpoolctl without this hook: the full scan below
        pass
    return ThreadpoolController()


def one_blas_thread(fn):
    """``fn`` run with BLAS on one thread (:func:`blas_limits`; its caller's setting restored after)."""
    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        with blas_limits(1):
            return fn(*args, **kwargs)
    return wrapper
