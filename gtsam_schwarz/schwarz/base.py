"""Preconditioner operators with one lifecycle, as FROSch's Schwarz operators have.

``create(...)`` takes what the graph fixes (sizes, decomposition); ``setup(A)`` does the symbolic
work from A's pattern once per graph (interface, index sets, gathers, orderings); ``update(A,
geometry)`` recomputes the numbers for each linearization; ``apply(x)`` gives M⁻¹x. Like pyamg,
``aspreconditioner()`` returns a scipy ``LinearOperator``; like FROSch, operators add up.
"""

from __future__ import annotations

import numpy as np
from scipy.sparse.linalg import LinearOperator

from ..dd.geometry import VertexGeometry
from ..util.threads import side_thread


class SchwarzOperator:
    """Base: an SPD operator x ↦ M⁻¹x of dimension n."""

    n: int
    uses_geometry: bool = False  # update() wants the poses (rigid-body coarse modes)

    @classmethod
    def create(cls, n: int, decomposition=None, translation_mask=None, **options) -> "SchwarzOperator":
        """The operator for an n-dof system (symbolic inputs only; no numbers yet)."""
        return cls(n)

    def setup(self, A) -> "SchwarzOperator":
        """Symbolic work from A's pattern, once per graph (default: none)."""
        return self

    def update(self, A, geometry: VertexGeometry | None = None) -> "SchwarzOperator":
        """New numbers in A (same pattern), and new poses for a rigid coarse space."""
        raise NotImplementedError

    def apply(self, x: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def matvec(self, x: np.ndarray) -> np.ndarray:
        return self.apply(x)

    __call__ = matvec

    @property
    def coarse_size(self) -> int:
        """Dimension of the coarse space (0 for one-level operators)."""
        return 0

    def aspreconditioner(self) -> LinearOperator:
        return LinearOperator((self.n, self.n), matvec=self.apply, rmatvec=self.apply, dtype=float)

    def todense(self) -> np.ndarray:
        """M⁻¹ as a dense matrix (for tests on small problems)."""
        return np.column_stack([self.apply(e) for e in np.eye(self.n)])


class SumOperator(SchwarzOperator):
    """Additive combination Σ_k M_k⁻¹ (each part keeps its own lifecycle). ``concurrent``: two parts
    are applied side by side, the second on :func:`~gtsam_schwarz.util.threads.side_thread` (the
    same sum, bit for bit; worth it where the second runs mostly without Python's GIL)."""

    concurrent = False

    def __init__(self, parts):
        self.parts = list(parts)
        self.n = self.parts[0].n

    @property
    def uses_geometry(self) -> bool:
        return any(p.uses_geometry for p in self.parts)

    @property
    def coarse_size(self) -> int:
        return sum(p.coarse_size for p in self.parts)

    def setup(self, A):
        for p in self.parts:
            p.setup(A)
        return self

    def update(self, A, geometry=None):
        for p in self.parts:
            p.update(A, geometry)
        return self

    def apply(self, x):
        if self.concurrent and len(self.parts) == 2:   # the second part on the side thread meanwhile
            later = side_thread().submit(self.parts[1].apply, x)
            y = self.parts[0].apply(x)
            y += later.result()
            return y
        y = self.parts[0].apply(x)
        for p in self.parts[1:]:
            y += p.apply(x)
        return y
