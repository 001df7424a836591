"""Kernels compiled by numba on their first call (nopython, GIL released, cached on disk).

numba is imported only then: a process that never calls a compiled kernel pays nothing (numba's
import: +81 MiB of RSS and ~0.5 s; the first kernel another +51 MiB and ~0.5 s, measured here).
"""

from __future__ import annotations

import importlib.util
import threading

AVAILABLE = importlib.util.find_spec("numba") is not None


class Kernel:
    """A function compiled by numba (nopython, GIL released, cached on disk) when first called."""

    def __init__(self, f):
        self.f, self.compiled = f, None
        self.__doc__ = f.__doc__
        self._lock = threading.Lock()   # a warm-up's thread and a first call: one dispatcher

    def __call__(self, *args):
        if self.compiled is None:
            with self._lock:
                if self.compiled is None:
                    import numba
                    self.compiled = numba.njit(cache=True, nogil=True)(self.f)
        return self.compiled(*args)


def jit(f) -> Kernel:
    """Decorator: ``f`` compiled on its first call (:class:`Kernel`)."""
    return Kernel(f)
