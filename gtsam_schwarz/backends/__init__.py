"""Back-ends that run the Schwarz linear solve outside this process's numpy/scipy.

``backends.petsc``: the same two-level Schwarz preconditioned CG on PETSc over MPI (petsc4py,
mpi4py). Importing this package imports neither; :func:`available` says whether a back-end can run.
See docs/distributed.md.
"""

from __future__ import annotations

BACKENDS = ("serial", "petsc")


def available(name: str) -> tuple[bool, str]:
    """(True, "") when back-end ``name`` can run here, else (False, a one-line reason)."""
    if name == "serial":
        return True, ""
    if name == "petsc":
        from .petsc.env import petsc_available

        return petsc_available()
    return False, f"unknown backend {name!r}; choose one of {', '.join(BACKENDS)}"


__all__ = ["BACKENDS", "available"]
