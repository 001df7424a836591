"""Progress through hooks: the optimizer calls them after every linear solve and prints nothing itself."""

from __future__ import annotations

import sys


def iteration_line(record) -> str:
    """One line per linear solve, as the command line prints it."""
    flag = "" if record["accepted"] else "  rejected"
    return (f"  iter {record['iteration']:3d}  error {record['error']:14.8g}  |grad| {record['gradient_norm']:10.3e}"
            f"  cg {record['cg_iterations']:5d}  lambda {record['lambda']:8.1e}  "
            f"{sum(record['seconds'].values()):6.2f} s{flag}")


def verbose_printer(stream=None):
    """A hook that prints :func:`iteration_line` for every linear solve (``verbose=True``)."""
    def hook(record):
        print(iteration_line(record), file=stream or sys.stdout, flush=True)
    return hook
