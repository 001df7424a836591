"""Krylov solvers: preconditioned CG with residual history and Lanczos eigenvalue estimates."""

from .cg import STOPPING_NORMS, CGInfo, lanczos_extremes, pcg, pcg_columns

__all__ = ["CGInfo", "STOPPING_NORMS", "lanczos_extremes", "pcg", "pcg_columns"]
