"""What the nonlinear loop needs from a linearization: H, g and the error at a point, a retraction.

A :class:`Linearizer` owns the variables' state (``gtsam.Values`` for the GTSAM implementation,
numpy arrays of poses for the native one) and gives the Gauss–Newton system
H δ = −g (paper Sec. 2, Eq. hgn) with H always in one fixed block pattern, so that everything
symbolic downstream (subdomains, gathers, orderings, factorizations) is built once per graph.
"""

from __future__ import annotations

from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
import scipy.sparse as sp

from ..dd.geometry import VertexGeometry
from ..util.gathered import is_gathered


@dataclass
class LinearSystem:
    """Whitened Gauss–Newton system H δ = −g at one linearization point."""

    H: sp.csr_matrix  # JᵀJ (robust: reweighted), symmetric positive (semi)definite
    g: np.ndarray  # gradient Jᵀ W r
    error: float = float("nan")  # graph error ½‖W^½ r‖² (robust: Σρ) at the linearization point
    diagonal: np.ndarray | None = None  # positions of H's diagonal in H.data (for damping H + λD)
    seconds: dict = field(default_factory=dict)  # time per phase of building it (linearize, export)

    def diagonal_positions(self) -> np.ndarray:
        """Positions of H's diagonal in H.data (the linearizer's, or found once)."""
        if self.diagonal is None:
            rows = np.repeat(np.arange(self.H.shape[0]), np.diff(self.H.indptr))
            self.diagonal = np.flatnonzero(rows == self.H.indices)
        return self.diagonal

    @contextmanager
    def damped(self, d: np.ndarray, diagonal_values: np.ndarray | None = None):
        """H + diag(d) in H's own pattern and storage: H's diagonal is raised in place for the
        ``with`` block and restored exactly after it (no copy of H: at 91 125 3D poses 180 MB).
        ``diagonal_values``: H's diagonal when the caller has read it already (one gather less)."""
        diagonal = self.diagonal_positions()
        if is_gathered(self.H):   # the diagonal's numbers in the source array (each its own there)
            H, at = self.H, self.H.compose(diagonal)
            saved = H.take_source(at) if diagonal_values is None else diagonal_values
            H.source[at] = saved + d
            try:
                yield H
            finally:
                H.source[at] = saved
            return
        data = self.H.data
        saved = data[diagonal] if diagonal_values is None else diagonal_values
        D = sp.csr_matrix((data, self.H.indices, self.H.indptr), shape=self.H.shape, copy=False)
        D.has_sorted_indices = self.H.has_sorted_indices
        data[diagonal] = saved + d
        try:
            yield D
        finally:
            data[diagonal] = saved

    @property
    def rhs(self) -> np.ndarray:
        return -self.g


class Linearizer(Protocol):
    """Values + graph → H, g in a fixed block pattern; retraction and error on the same state.

    Variables are numbered in sorted key order; variable v owns dofs ``offsets[v]:offsets[v+1]``.
    ``state`` is whatever the implementation keeps (opaque to the optimizer).
    """

    keys: np.ndarray  # the variables' keys, sorted
    offsets: np.ndarray

    def state(self, values) -> Any:
        """The implementation's state for ``gtsam.Values`` (read once)."""

    def linearize(self, state) -> LinearSystem:
        """H (CSR, the fixed pattern of this graph), g and the error at ``state``."""

    def retract(self, state, x: np.ndarray) -> Any:
        """state ⊕ x with GTSAM's retraction per variable (x in dof order)."""

    def error(self, state) -> float:
        """The graph's error at ``state``, equal to ``graph.error(values)``."""

    def geometry(self, state) -> VertexGeometry | None:
        """Poses (positions, rotations) if all variables are Pose2 or all Pose3, else None."""

    def values(self, state):
        """``gtsam.Values`` of ``state`` (built only when asked for)."""

    def translation_mask(self) -> np.ndarray:
        """True for dofs that are translations (coarse space without rotations)."""
