"""The process heap: glibc's allocator kept from returning memory, and fresh heap faulted in ahead.

:func:`tune_allocator` is process tuning (the application calls it, the library does not);
:func:`populate_ahead` acts only once it has been applied, as only then does freed memory stay
in the heap for the next allocation.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import os
import sys
import threading

# glibc mallopt parameters (malloc.h)
_M_TRIM_THRESHOLD, _M_TOP_PAD, _M_MMAP_THRESHOLD, _M_MMAP_MAX, _M_ARENA_MAX = -1, -2, -3, -4, -8
_MMAP_THRESHOLD_MAX = 32 * 1024 * 1024  # mallopt(3)'s documented largest value on 64-bit (glibc 2.36 accepts more)
_MADV_POPULATE_WRITE = 23  # Linux 5.14
_PAGE = 4096
# bytes per madvise call: each holds the process's memory-map lock, which every thread start (its
# stack's mmap) and heap growth (brk) of the main thread waits for. With 64 MiB steps (~40 ms of faults
# each) a thread started during a populate waited 20-30 ms (model problem 128x64: the chordal start's
# side thread, 22-29 ms against 4 ms); lawnmower 600x600 ran 13.6 / 13.0 / 15.0 s against 11.3 / 12.6 /
# 13.6 s with 4 MiB steps (interleaved, in-process)
_STEP = 4 << 20
# the most a prefault takes of the memory available (MemAvailable, the cgroup's room, or the caller's
# ceiling): it faults in memory the run is expected to use, never memory a short machine lacks
POPULATE_SHARE = 0.5
_state: dict = {"tuned": False, "populating": None}


class _Mallinfo2(ctypes.Structure):
    _fields_ = [(name, ctypes.c_size_t) for name in ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks",
                                                       "fsmblks", "uordblks", "fordblks", "keepcost")]


@functools.lru_cache(maxsize=1)
def _libc():
    libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
    libc.malloc.argtypes, libc.malloc.restype = [ctypes.c_size_t], ctypes.c_void_p
    libc.free.argtypes = [ctypes.c_void_p]
    libc.madvise.argtypes, libc.madvise.restype = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int], ctypes.c_int
    libc.mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    if hasattr(libc, "mallinfo2"):   # glibc 2.33 and later
        libc.mallinfo2.restype = _Mallinfo2
    return libc


def tune_allocator() -> bool:
    """Keep freed blocks in the heap instead of unmapping them: blocks up to 32 MiB, and (no
    mmap at all) the larger ones too; the heap is never trimmed.

    Every nonlinear iteration allocates the same large temporaries again (J, H, local
    matrices); with glibc's defaults most go back to the kernel and return as fresh, page-faulting
    memory. Measured on the 262k-pose model problem: 18.4 s → 15.5 s. Blocks above 32 MiB (glibc's
    largest mmap threshold; a Schwarz build's gathers and extension at 360 000 2D poses) were still
    mapped afresh each time: taken from the heap instead, lawn600x600 with Schwarz ran 25.0 against
    28.7 s (medians of 3 interleaved bench children, every pair faster) for a 4–8 % higher peak.
    One arena for every thread: the local threads' CHOLMOD factors and solutions, freed, are then
    memory the main thread reuses (with a heap per thread, lawnmower 600x600 peaked at 2 545 MiB
    against 1 977 MiB). Returns True if applied; GTSAM_SCHWARZ_MALLOPT=0 keeps glibc's defaults,
    GTSAM_SCHWARZ_MMAP=1 keeps mmap for the large blocks.
    """
    if _state["tuned"]:
        return True
    if not sys.platform.startswith("linux") or os.environ.get("GTSAM_SCHWARZ_MALLOPT", "1") == "0":
        return False
    try:
        mallopt = _libc().mallopt
    except (OSError, AttributeError):
        return False
    keep_mmap = os.environ.get("GTSAM_SCHWARZ_MMAP", "0") == "1"
    ok = (mallopt(_M_MMAP_THRESHOLD, _MMAP_THRESHOLD_MAX) == 1
          and mallopt(_M_TRIM_THRESHOLD, -1) == 1   # -1: never trim (a populated top may exceed 2 GiB)
          and mallopt(_M_TOP_PAD, 256 * 1024 * 1024) == 1
          and (keep_mmap or mallopt(_M_MMAP_MAX, 0) == 1)
          and mallopt(_M_ARENA_MAX, 1) == 1)
    _state["tuned"] = ok and not keep_mmap   # with mmap kept, large freed blocks leave the heap
    return ok


def _read_number(path: str) -> float | None:
    try:
        with open(path) as f:
            text = f.read().strip()
        return None if text == "max" else float(text)
    except (OSError, ValueError):
        return None


def free_memory() -> float:
    """Bytes this process could still take: ``MemAvailable``, capped by the cgroup's ``memory.max``
    less its ``memory.current`` when one is set (inf where neither can be read)."""
    avail = float("inf")
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    avail = float(line.split()[1]) * 1024
                    break
    except OSError:
        pass
    cap, used = _read_number("/sys/fs/cgroup/memory.max"), _read_number("/sys/fs/cgroup/memory.current")
    if cap is not None and used is not None:
        avail = min(avail, cap - used)
    return avail


def trim_heap() -> bool:
    """Give the heap's free pages back to the kernel (glibc's ``malloc_trim``), so that what comes
    next faults its memory afresh instead of reusing pages warm: a bench child that drops the objects
    its solver does not use (a GTSAM graph g2o's was built from) then runs as if they had never been
    there. Returns whether anything was released."""
    try:
        return bool(_libc().malloc_trim(0))
    except (OSError, AttributeError):
        return False


def populate_ahead(nbytes: float, ceiling: float | None = None) -> threading.Thread | None:
    """Fault in ``nbytes`` of fresh heap on a helper thread while this one works on.

    A fresh page costs its first writer a fault: 2-15 µs here (a virtual machine's host backs it
    then), 3-4 s of a 16 s Schwarz run on 360 000 poses that touches 1.45 GB it never had. The
    block is taken from the heap and freed at once (it stays the heap's free top: tuned allocator,
    never trimmed); ``madvise(MADV_POPULATE_WRITE)`` then faults it in without writing a byte, so
    the allocations carved from it meanwhile are untouched. It is faulted in from its far end back:
    the main thread's allocations are carved from its near end, and two threads faulting the same
    region contend (the 1M-pose model problem, fresh bench children alternated: 13.4-15.1 s, median
    13.9, against 14.8-16.9 s, median 15.7, front to back; the other cases unchanged). A request
    made while an earlier one still runs takes its block now and waits for that thread (one helper
    at a time: the main thread keeps the other core). Returns the thread; None (nothing done)
    unless :func:`tune_allocator` applied, for less than 16 MiB, or with GTSAM_SCHWARZ_POPULATE=0.
    On kernels before 5.14 the thread's first madvise fails and it stops. At most ``POPULATE_SHARE``
    of ``ceiling`` (the caller's memory limit; default :func:`free_memory`) is faulted in: the
    request is an estimate, and a machine short of memory must not lose it to a guess."""
    if not _state["tuned"] or os.environ.get("GTSAM_SCHWARZ_POPULATE", "1") == "0":
        return None
    room = free_memory() if ceiling is None else min(float(ceiling), free_memory())
    nbytes = int(min(float(nbytes), POPULATE_SHARE * max(room, 0.0))) // _PAGE * _PAGE
    earlier = _state["populating"]
    if nbytes < (16 << 20):
        return None
    libc = _libc()
    start = libc.malloc(nbytes)
    if not start:
        return None
    libc.free(start)

    def populate(begin=(start + _PAGE - 1) // _PAGE * _PAGE, end=(start + nbytes) // _PAGE * _PAGE):
        if earlier is not None:
            earlier.join()
        while begin < end:  # from the far end back (ctypes releases the GIL for each call)
            size = min(_STEP, end - begin)
            if libc.madvise(end - size, size, _MADV_POPULATE_WRITE) != 0:
                return   # EINVAL: kernel without it; ENOMEM: no longer mapped
            end -= size

    thread = threading.Thread(target=populate, name="populate-heap", daemon=True)
    thread.start()
    _state["populating"] = thread
    return thread


def heap_in_use() -> float | None:
    """Bytes the process's heap holds in use (glibc's ``mallinfo2``: allocated chunks and mapped
    blocks; the free pieces between them and the pages outside the heap not counted), or None where
    glibc does not give it."""
    try:
        libc = _libc()
        if not hasattr(libc, "mallinfo2"):
            return None
        m = libc.mallinfo2()
    except OSError:
        return None
    return float(m.uordblks + m.hblkhd)


class HeapPeak:
    """``with HeapPeak() as live: …``; then ``live.mib``: the most heap in use (:func:`heap_in_use`)
    while the block ran, sampled on a helper thread every ``interval`` seconds and at both ends
    (None where unavailable). Beside the peak RSS it tells memory a run used from its heap's free
    pieces and from pages faulted in ahead (docs/survey.md, thirty-ninth pass)."""

    def __init__(self, interval: float = 0.05):
        self.interval = interval
        self.peak: float | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def _sample(self) -> None:
        used = heap_in_use()
        if used is not None and (self.peak is None or used > self.peak):
            self.peak = used

    def _run(self) -> None:
        while not self._stop.wait(self.interval):
            self._sample()

    def __enter__(self) -> "HeapPeak":
        self._sample()
        if self.peak is not None:
            self._thread = threading.Thread(target=self._run, name="heap-peak", daemon=True)
            self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        self._sample()

    @property
    def mib(self) -> float | None:
        return None if self.peak is None else self.peak / 2**20
