"""Local and coarse solvers behind one interface: ``factorize(K)`` → a solve callable, by name.

Every solver is constructed from an SPD matrix, may ``refactor`` a matrix with the same pattern
(numbers only), and applies K⁻¹ with ``solve(rhs)`` (also ``solver(rhs)``). The registry maps a
name to its class, so a new factorization (e.g. a GPU or distributed one) is one file plus one line.
"""

from __future__ import annotations

from typing import Callable, Protocol

import numpy as np
import scipy.sparse as sp


class SingularLocalMatrixError(RuntimeError):
    """A local (subdomain, interior or coarse) matrix could not be factorized."""


class LocalSolver(Protocol):
    """A factorization of one SPD matrix: ``refactor`` (same pattern, new numbers), ``solve``."""

    def refactor(self, K: sp.spmatrix) -> "LocalSolver": ...

    def solve(self, rhs: np.ndarray) -> np.ndarray: ...

    def __call__(self, rhs: np.ndarray) -> np.ndarray: ...


LOCAL_SOLVERS: dict[str, Callable[..., LocalSolver]] = {}


def register_solver(name: str):
    """Class decorator: make a local solver constructible by name in :func:`make_solver`."""
    def add(cls):
        LOCAL_SOLVERS[name] = cls
        return cls
    return add


def make_solver(name: str, K: sp.spmatrix, what: str = "local matrix") -> LocalSolver:
    """Factorize K with the solver registered as ``name``."""
    try:
        cls = LOCAL_SOLVERS[name]
    except KeyError:
        raise ValueError(f"unknown local solver {name!r}; choose one of {', '.join(LOCAL_SOLVERS)}") from None
    return cls(K, what)


def check_finite(K: sp.spmatrix, what: str) -> None:
    if not np.all(np.isfinite(K.data)):
        raise SingularLocalMatrixError(f"{what} has non-finite entries")
