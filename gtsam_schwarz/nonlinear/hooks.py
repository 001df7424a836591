"""Progress through hooks: the optimizer calls them after every linear solve and prints nothing itself."""

from __future__ import annotations

import sys


def verbose_printer(stream=None):
    """A hook that prints one line per linear solve (``verbose=True``)."""
    def hook(record):
        flag = "" if record.accepted else "  (rejected)"
        print(f"iter {record.iteration:3d}  error {record.error:.6e}  |g| {record.gradient_norm:.3e}"
              f"  lambda {record.lambda_:.1e}  cg {record.cg_iterations:5d}"
              f"  {sum(record.seconds.values()):.2f}s{flag}", file=stream or sys.stdout, flush=True)
    return hook
