"""One worker thread beside the main one, for work that runs without Python's GIL.

scipy's sparse products release the GIL, CHOLMOD's calls through scikit-sparse hold it: a coarse
correction's Φᵀ / Φ products can run on this thread while the calling thread solves the subdomains
(two cores, the same numbers). Work that holds the GIL gains nothing here: A_0's assembly beside the
subdomain factorizations slowed both (lawnmower 600x600: 0.62 + 1.14 s one after the other, 1.49 and
1.68 s side by side)."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

_POOL: list = []


def side_thread() -> ThreadPoolExecutor:
    """The process's single worker thread (created on first use; it blocks while idle)."""
    if not _POOL:
        _POOL.append(ThreadPoolExecutor(max_workers=1, thread_name_prefix="gtsam-schwarz-side"))
    return _POOL[0]

