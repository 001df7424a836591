"""Worker threads for work that runs without Python's GIL: one side thread, two local threads.

scipy's sparse products release the GIL, CHOLMOD's calls through scikit-sparse hold it (through
``solvers.cholmod_native`` they do not): a coarse correction's Φᵀ / Φ products run on the side thread
while the local threads solve the subdomains (two cores, the same numbers). Work that holds the GIL gains nothing here: A_0's assembly beside the
subdomain factorizations slowed both (lawnmower 600x600: 0.62 + 1.14 s one after the other, 1.49 and
1.68 s side by side)."""

from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor

_POOLS: dict = {}
_PREFIX = "gtsam-schwarz"
WORKERS = 2  # the local solves' threads (this project's machines have two cores)


def side_thread() -> ThreadPoolExecutor:
    """The process's single side thread (created on first use; it blocks while idle)."""
    return _pool("side", 1)


def background_thread() -> ThreadPoolExecutor:
    """A thread for construction work that nobody waits for soon (the native linearizer's pattern and
    gather plan, needed at the first linearization): apart from the side thread, whose jobs are
    waited for within the step that starts them."""
    return _pool("background", 1)


def local_threads() -> ThreadPoolExecutor:
    """The threads that factorize and solve independent local blocks (CHOLMOD without the GIL)."""
    return _pool("local", WORKERS)


def on_local_thread() -> bool:
    """Whether the caller is one of the local threads (work it gives them might wait on itself)."""
    return threading.current_thread().name.startswith(f"{_PREFIX}-local")


def _pool(name: str, workers: int) -> ThreadPoolExecutor:
    if name not in _POOLS:
        _POOLS[name] = ThreadPoolExecutor(max_workers=workers, thread_name_prefix=f"{_PREFIX}-{name}")
    return _POOLS[name]


def run_all(pool: ThreadPoolExecutor, jobs: list) -> list:
    """Results of the callables ``jobs`` run on ``pool``, in order; every job has finished when this
    returns or raises (the first failure is raised after the others have ended)."""
    return wait_all([pool.submit(job) for job in jobs])


def wait_all(futures: list) -> list:
    """Results of ``futures`` in order, once all have ended (the first failure raised after that)."""
    results, error = [], None
    for f in futures:
        try:
            results.append(f.result())
        except BaseException as exc:  # noqa: BLE001 — re-raised once all have ended
            results.append(None)
            error = error or exc
    if error is not None:
        raise error
    return results
