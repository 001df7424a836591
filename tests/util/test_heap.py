"""The heap populated ahead on a helper thread: later allocations find their pages faulted in,
and what is written meanwhile stays as written. Each check runs in a fresh process (the allocator
tuning is process-wide)."""

import json
import os
import subprocess
import sys

import pytest

PROBE = r"""
import json, resource, sys, numpy as np
from gtsam_schwarz.util.heap import populate_ahead, tune_allocator
faults = lambda: resource.getrusage(resource.RUSAGE_SELF).ru_minflt
tuned = tune_allocator() if sys.argv[1] == "tuned" else False
thread = populate_ahead(256 << 20)
early = np.arange(4 << 20, dtype=np.float64)   # 32 MiB written while the helper may still run
second = populate_ahead(128 << 20) if sys.argv[2:] == ["twice"] else None  # queued behind the first
if second is not None:
    second.join()
    assert not thread.is_alive()   # it waited for the first
if thread is not None:
    thread.join()
before = faults()
later = np.ones(192 << 17)                      # 192 MiB from the populated heap
print(json.dumps({"tuned": tuned, "started": thread is not None, "later_faults": faults() - before,
                  "early_intact": bool(np.array_equal(early, np.arange(4 << 20, dtype=np.float64))),
                  "later_sum": float(later.sum()), "second": second is not None}))
"""


def _probe(*mode: str) -> dict:
    out = subprocess.run([sys.executable, "-c", PROBE, *mode], capture_output=True, text=True, check=True,
                         env={**os.environ, "NUMPY_MADVISE_HUGEPAGE": "0"})
    return json.loads(out.stdout.strip().splitlines()[-1])


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's allocator and madvise: Linux only")
def test_populated_heap_needs_no_faults_later_and_keeps_what_was_written():
    r = _probe("tuned")
    if not r["started"]:
        pytest.skip("kernel without MADV_POPULATE_WRITE or allocator not tunable here")
    assert r["early_intact"] and r["later_sum"] == float(192 << 17)
    assert r["later_faults"] < 4096   # 192 MiB of fresh pages would be 49 152 faults


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's allocator and madvise: Linux only")
def test_a_request_while_one_runs_is_queued_behind_it():
    r = _probe("tuned", "twice")
    if not r["started"]:
        pytest.skip("kernel without MADV_POPULATE_WRITE or allocator not tunable here")
    assert r["second"] and r["early_intact"] and r["later_sum"] == float(192 << 17)
    assert r["later_faults"] < 4096


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's allocator: Linux only")
def test_nothing_populated_without_the_tuned_allocator():
    r = _probe("untuned")
    assert not r["started"]
    assert r["later_faults"] > 40000   # numpy's 192 MiB mapped afresh: every page faulted


RECORDING = r"""
import json, sys
from gtsam_schwarz.util import heap
heap.tune_allocator()
real = heap._libc()
calls = []
class Recording:   # the real allocator; madvise recorded, then done
    malloc, free = real.malloc, real.free
    def madvise(self, addr, size, advice):
        calls.append((int(addr), int(size)))
        return real.madvise(addr, size, advice)
heap._libc = lambda: Recording()
"""

ORDER_PROBE = RECORDING + r"""
thread = heap.populate_ahead(64 << 20)
if thread is not None:
    thread.join()
print(json.dumps({"started": thread is not None, "calls": calls}))
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's allocator and madvise: Linux only")
def test_the_block_is_populated_from_its_far_end_back():
    """The main thread's allocations are carved from the block's near end: the helper starts at the
    other end and walks back, step by step, over the whole block."""
    out = subprocess.run([sys.executable, "-c", ORDER_PROBE], capture_output=True, text=True, check=True)
    r = json.loads(out.stdout.strip().splitlines()[-1])
    if not r["started"] or not r["calls"]:
        pytest.skip("allocator not tunable here")
    calls = r["calls"]
    if len(calls) == 1:
        pytest.skip("kernel without MADV_POPULATE_WRITE (the first call failed)")
    starts = [a for a, _ in calls]
    assert starts == sorted(starts, reverse=True)                     # far end first, then back
    assert all(a + s == prev for (a, s), prev in zip(calls[1:], starts[:-1]))   # no gap, no overlap
    assert sum(s for _, s in calls) >= (64 << 20) - 2 * 4096          # the whole block


TRIM = r"""
import json, numpy as np
from gtsam_schwarz.util.heap import trim_heap, tune_allocator
rss = lambda: int(open("/proc/self/statm").read().split()[1]) * 4096 >> 20
tune_allocator()                       # freed blocks stay in the heap, never trimmed by themselves
block = np.ones(256 << 17)             # 256 MiB, written
del block
kept = rss()
released = trim_heap()
print(json.dumps({"kept": kept, "after": rss(), "released": released}))
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's malloc_trim: Linux only")
def test_trim_gives_the_tuned_heaps_free_pages_back():
    out = subprocess.run([sys.executable, "-c", TRIM], capture_output=True, text=True, check=True)
    r = json.loads(out.stdout.strip().splitlines()[-1])
    assert r["released"] and r["kept"] - r["after"] >= 200   # MiB: the freed block's pages


CAP_PROBE = RECORDING + r"""
if sys.argv[1] == "free":   # a machine with 100 MiB available
    heap.free_memory = lambda: float(100 << 20)
    thread = heap.populate_ahead(1 << 30)
else:                       # the caller's limit: 64 MiB
    thread = heap.populate_ahead(1 << 30, ceiling=64 << 20)
if thread is not None:
    thread.join()
print(json.dumps({"started": thread is not None, "bytes": sum(size for _, size in calls), "calls": len(calls)}))
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's allocator and madvise: Linux only")
@pytest.mark.parametrize("bound, mib", [("free", 50), ("ceiling", 32)])
def test_the_prefault_takes_at_most_its_share_of_the_memory_there_is(bound, mib):
    """A 1 GiB request on a machine with 100 MiB available, or under a 64 MiB limit, faults in
    POPULATE_SHARE (half) of that room, not the request: an estimate must not take memory the run lacks."""
    from gtsam_schwarz.util.heap import POPULATE_SHARE
    assert POPULATE_SHARE == 0.5
    out = subprocess.run([sys.executable, "-c", CAP_PROBE, bound], capture_output=True, text=True, check=True)
    r = json.loads(out.stdout.strip().splitlines()[-1])
    if not r["started"]:
        pytest.skip("allocator not tunable here")
    if r["calls"] == 1 and r["bytes"] < (mib << 20) - 8192:
        pytest.skip("kernel without MADV_POPULATE_WRITE (the first call failed)")
    assert (mib << 20) - 2 * 4096 <= r["bytes"] <= mib << 20


def test_free_memory_reads_the_machine(monkeypatch):
    """MemAvailable (or a cgroup's room): positive and finite on Linux; solvers.memory's default limit."""
    from gtsam_schwarz.solvers import memory
    from gtsam_schwarz.util.heap import free_memory
    monkeypatch.delenv(memory.ENV, raising=False)
    avail = free_memory()
    if sys.platform.startswith("linux"):
        assert 0 < avail < float("inf")
    assert abs(memory.available_memory() - avail) <= max(0.05 * avail, 64 << 20)


def test_heap_peak_sees_what_the_block_held_and_freed():
    """A 64 MiB array made and freed inside the block counts in the peak of the heap in use (its
    sampler's last sample, at the end, no longer sees it); the sampler thread is gone after the block."""
    import threading
    import time
    import numpy as np
    from gtsam_schwarz.util.heap import HeapPeak, heap_in_use
    before = heap_in_use()
    if before is None:
        pytest.skip("glibc's mallinfo2 not available here")
    with HeapPeak(interval=0.01) as live:
        a = np.ones(8 << 20)   # 64 MiB, written
        time.sleep(0.1)
        del a
    assert live.mib is not None and live.mib >= before / 2**20 + 60
    assert heap_in_use() < before + (16 << 20)   # freed again
    assert not any(t.name == "heap-peak" for t in threading.enumerate())
