"""The pose graph as the decomposition sees it: vertices, their dof ranges, coupling edges."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from ..util import sorted_unique


@dataclass(frozen=True)
class GraphStructure:
    """Vertices (variables in key order), their dof ranges, and edges between coupled vertices.

    An edge (u, v), u < v, joins two variables that share a factor; it is *odometry* when the
    two are consecutive in key order (the trajectory), otherwise a loop closure.
    """

    offsets: np.ndarray  # n_vertices + 1
    edges: np.ndarray  # (E, 2), u < v
    odometry: np.ndarray  # (E,) bool

    @property
    def n_vertices(self) -> int:
        return len(self.offsets) - 1

    @property
    def n_dofs(self) -> int:
        return int(self.offsets[-1])

    @classmethod
    def from_matrix(cls, H: sp.spmatrix, offsets: np.ndarray) -> "GraphStructure":
        """Edges from the block sparsity of H (vertex i ~ j iff block H_ij ≠ 0)."""
        offsets = np.asarray(offsets, dtype=np.int64)
        nv = len(offsets) - 1
        owner = np.repeat(np.arange(nv), np.diff(offsets))
        C = sp.coo_matrix(H)
        u, v = owner[C.row], owner[C.col]
        keep = u < v
        pairs = sorted_unique(u[keep] * np.int64(nv) + v[keep])
        edges = np.stack([pairs // nv, pairs % nv], axis=1)
        return cls(offsets=offsets, edges=edges, odometry=edges[:, 1] == edges[:, 0] + 1)

    def adjacency(self, mask: np.ndarray | None = None) -> sp.csr_matrix:
        """Symmetric vertex adjacency of the edges selected by ``mask`` (all edges if None)."""
        e = self.edges if mask is None else self.edges[mask]
        nv = self.n_vertices
        ones = np.ones(2 * len(e))
        return sp.csr_matrix((ones, (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])), shape=(nv, nv))
