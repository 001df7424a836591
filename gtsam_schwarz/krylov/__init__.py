"""Krylov solvers: preconditioned CG with residual history and Lanczos eigenvalue estimates; large
sparse products on the local threads."""

from .cg import STOPPING_NORMS, CGInfo, lanczos_extremes, pcg, pcg_columns
from .spmv import RowBlockMatrix, threaded

__all__ = ["CGInfo", "RowBlockMatrix", "STOPPING_NORMS", "lanczos_extremes", "pcg", "pcg_columns", "threaded"]
