"""One-level overlapping Schwarz: Σ_i R_iᵀ A_i⁻¹ R_i over the overlapping subdomains."""

from __future__ import annotations

import numpy as np

from ..dd.index_sets import IndexSets
from ..solvers import BlockDiagonalSolver
from .base import SchwarzOperator


def _need(decomposition, name: str):
    if decomposition is None:
        raise ValueError(f"{name} needs a decomposition")
    return decomposition


class AdditiveSchwarz(SchwarzOperator):
    """One-level additive Schwarz Σ_i R_iᵀ A_i⁻¹ R_i, A_i = R_i A R_iᵀ (paper Eq. OS-preconditioner)."""

    def __init__(self, sets: IndexSets, A=None):
        self.n = sets.n
        self.solver = BlockDiagonalSolver(sets)
        if A is not None:
            self.update(A)

    @property
    def sets(self) -> IndexSets:
        """The subdomains' index sets (each set's vertices in its factorization's order)."""
        return self.solver.sets

    @classmethod
    def create(cls, n, decomposition=None, translation_mask=None, **options):
        return cls(_need(decomposition, "one-level").index_sets(overlapping=True))

    def update(self, A, geometry=None):
        """Same subdomains, new numbers: numeric refactorization only (symbolic work on the first call)."""
        self.solver.update(A)
        return self

    def apply(self, x):
        return self.solver.matvec(x)


class BlockJacobi(AdditiveSchwarz):
    """One block per variable (pose): Schwarz with nonoverlapping single-pose subdomains."""

    def __init__(self, offsets: np.ndarray, A=None):
        offsets = np.asarray(offsets)
        n = int(offsets[-1])
        super().__init__(IndexSets(indices=np.arange(n), ptr=offsets, n=n), A)

    @classmethod
    def create(cls, n, decomposition=None, translation_mask=None, **options):
        if decomposition is None:
            raise ValueError("block-jacobi needs the variables' dof ranges (a decomposition)")
        return cls(decomposition.structure.offsets)
