"""One OpenMP thread for CHOLMOD, set before CHOLMOD loads.

CHOLMOD 3 (SuiteSparse 5, Debian's) runs the supernodal factorization's assembly and zeroing in
OpenMP regions with ``num_threads(CHOLMOD_OMP_NUM_THREADS)``, a compile-time 4, which neither
``OMP_NUM_THREADS`` nor ``omp_set_num_threads`` overrides. On two cores its four threads wake and
sleep through the kernel per supernode: lawnmower 600x600's H factorized in 7.6-10.6 s against
3.7-5.4 s with one thread (two threads: as fast as one, twice the CPU). Only the thread limit caps
a ``num_threads`` clause, and libgomp reads ``OMP_THREAD_LIMIT`` once, when it is loaded: so it is
set for that load and taken out of the environment again (child processes do not inherit it).
A limit the user set is kept; where libgomp was loaded before this package, it cannot be changed.
"""

from __future__ import annotations

import ctypes
import os

THREAD_LIMIT = 1  # BLAS runs single-threaded too (the project's rule): the factorization is one thread
_state: dict = {}


def limit_threads() -> int | None:
    """Load libgomp with ``OMP_THREAD_LIMIT`` = :data:`THREAD_LIMIT` unless the user set one;
    returns OpenMP's thread limit in this process (None without libgomp). Idempotent."""
    if "limit" not in _state:
        lib = None
        user = os.environ.get("OMP_THREAD_LIMIT")
        if user is None:
            os.environ["OMP_THREAD_LIMIT"] = str(THREAD_LIMIT)
        try:
            lib = ctypes.CDLL("libgomp.so.1")  # its constructor reads the environment now
        except OSError:
            lib = None
        finally:
            if user is None:
                del os.environ["OMP_THREAD_LIMIT"]
        limit = None
        if lib is not None and hasattr(lib, "omp_get_thread_limit"):
            lib.omp_get_thread_limit.restype = ctypes.c_int
            limit = int(lib.omp_get_thread_limit())
        _state["limit"] = limit
    return _state["limit"]
