"""The Schwarz linear solve on PETSc over MPI (petsc4py, mpi4py): see docs/distributed.md.

``PetscSchwarzSolver`` is a ``LinearSolver`` (``solve(H, rhs, tol, geometry)``);
``DistributedOptimizer`` is the optimizer whose ranks each linearize their own factors; ``python -m
gtsam_schwarz.backends.petsc.run`` is the MPI entry point. Importing this package needs neither
petsc4py nor mpi4py; the names that do are loaded on first use.
"""

from __future__ import annotations

from .env import launch_command, mpi_environment, mpi_ready, mpiexec_command, petsc_available
from .layout import RankLayout, rank_layout

__all__ = ["DistributedOptimizer", "PetscSchwarzSolver", "RankLayout", "launch_command", "make_petsc_solver", "mpi_environment",
           "mpi_ready", "mpiexec_command", "petsc_available", "rank_layout"]


def __getattr__(name):
    if name == "DistributedOptimizer":
        from .distributed import DistributedOptimizer

        return DistributedOptimizer
    if name in ("PetscSchwarzSolver", "make_petsc_solver"):
        from . import solver

        return getattr(solver, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
