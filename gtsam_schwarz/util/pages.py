"""Page size of numpy's large arrays while we work (below every layer)."""

from __future__ import annotations

import functools
from contextlib import contextmanager

import numpy as np


def _madvise_setter():
    core = getattr(np, "_core", None) or getattr(np, "core", None)
    return getattr(getattr(core, "multiarray", None), "_set_madvise_hugepage", None)


@contextmanager
def small_pages():
    """numpy's new large arrays without madvise(MADV_HUGEPAGE) inside the block (restored after it).

    Where the kernel compacts memory on a huge-page fault (transparent huge pages with defrag
    "madvise", this project's machines), the first touch of a fresh array cost 0.3–2 ms per MiB,
    depending on the machine's fragmentation: LM on the 262 145-pose model problem took 2.4–4.9 s,
    its first linearization's gather 0.6 s instead of 15 ms. With 4 KiB pages the first touch costs
    0.35 ms per MiB, steadily (2.36–2.41 s), and the CG and factorization times are unchanged."""
    setter = _madvise_setter()
    if setter is None:
        yield
        return
    previous = setter(False)
    try:
        yield
    finally:
        setter(previous)


def with_small_pages(method):
    """Decorator: run ``method`` inside :func:`small_pages`."""
    @functools.wraps(method)
    def wrapper(*args, **kwargs):
        with small_pages():
            return method(*args, **kwargs)
    return wrapper
