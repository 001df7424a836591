"""Memory the linear solvers may use, and the error when a configuration cannot fit.

The limit is ``GTSAM_SCHWARZ_MEMORY_LIMIT`` (bytes, or with a suffix: ``512M``, ``2.5G``) when set, else
what the machine has available now (``MemAvailable``, and the cgroup's limit minus its usage when
one is set). Solvers estimate their peak from the symbolic analysis before the heavy work and either
adapt (fewer columns at a time) or raise :class:`InsufficientMemoryError` with one line naming
what to change.
"""

from __future__ import annotations

import os

from ..util.heap import free_memory

GIB = float(2**30)
ENV = "GTSAM_SCHWARZ_MEMORY_LIMIT"
FACTOR_BYTES = 8 * 1.5 + 1.0  # per predicted entry of a CHOLMOD supernodal factor (padding, row indices)
MATRIX_BYTES = 4 + 4 + 4  # per entry of a gathered submatrix: column index and source position kept, values (8) only while used


class InsufficientMemoryError(MemoryError):
    """A solver's estimated peak exceeds the memory available; the message (one line) says what
    needs how much and what to change."""


def parse_bytes(text: str | float | int) -> float:
    """``"512M"``, ``"2.5G"``, ``"1e9"`` or a number → bytes."""
    if isinstance(text, (int, float)):
        return float(text)
    s = str(text).strip().upper().removesuffix("B")
    scale = {"K": 2.0**10, "M": 2.0**20, "G": 2.0**30, "T": 2.0**40}.get(s[-1:], 1.0)
    try:
        return float(s[:-1] if scale != 1.0 else s) * scale
    except ValueError:
        raise ValueError(f"{ENV}: cannot read {text!r} as a size (e.g. 512M, 2.5G)") from None


def available_memory(limit: float | str | None = None) -> float:
    """Bytes the solver may still allocate: ``limit`` if given, else $GTSAM_SCHWARZ_MEMORY_LIMIT,
    else MemAvailable (capped by the cgroup's memory.max − memory.current)."""
    if limit is not None:
        return parse_bytes(limit)
    if os.environ.get(ENV):
        return parse_bytes(os.environ[ENV])
    return free_memory()


def gib(nbytes: float) -> str:
    return f"{nbytes / GIB:.2f} GiB"


MMAP_THRESHOLD = 4 * 2**20  # bytes: larger allocations get pages of their own, returned when freed
_M_MMAP_THRESHOLD = -3  # glibc's mallopt parameter number
_heap_bounded = [False]


def bound_heap_fragmentation() -> bool:
    """Fix glibc's mmap threshold at ``MMAP_THRESHOLD`` for this process (once; False where there is
    no glibc). By default glibc raises the threshold up to 32 MiB after freeing a large block, and
    the many 4–32 MiB temporaries of a Schwarz build then stay in the heap after use: at 91 125 3D
    poses 100 MiB more at the peak (measured), the same time. Set by the two-level preconditioners,
    whose builds are the memory-bound path; the direct path keeps glibc's default (faster there)."""
    if _heap_bounded[0]:
        return True
    try:
        import ctypes
        import ctypes.util

        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        _heap_bounded[0] = bool(libc.mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD))
    except (OSError, AttributeError):
        return False
    return _heap_bounded[0]
