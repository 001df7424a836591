"""The pose graph as the decomposition sees it: vertices, their dof ranges, coupling edges."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from ..util import as_csr, sorted_unique, vertex_pattern


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
        """Edges from the block sparsity of H (vertex i ~ j iff block H_ij ≠ 0).

        H's fixed pattern holds whole blocks: then the vertex pattern is read from the first row of
        every vertex (``util.vertex_pattern``, a 36th of the entries for Pose3), accepted when its
        whole blocks account for every stored entry of H and it is symmetric; any other pattern
        (blocks with dropped entries) takes every entry's vertex pair."""
        offsets = np.asarray(offsets, dtype=np.int64)
        nv = len(offsets) - 1
        H = as_csr(H)
        dims = np.diff(offsets)
        if H.has_sorted_indices:
            V = vertex_pattern(H, offsets)
            rows = np.repeat(np.arange(nv), np.diff(V.indptr))
            if int(np.sum(dims[rows] * dims[V.indices])) == H.nnz and _symmetric(V):
                return cls.from_vertex_pattern(V, offsets)
        owner = np.repeat(np.arange(nv), dims)
        C = H.tocoo()
        u, v = owner[C.row], owner[C.col]
        keep = u < v
        pairs = sorted_unique(u[keep] * np.int64(nv) + v[keep])
        edges = np.stack([pairs // nv, pairs % nv], axis=1)
        return cls(offsets=offsets, edges=edges, odometry=edges[:, 1] == edges[:, 0] + 1)

    @classmethod
    def from_vertex_pattern(cls, V: sp.csr_matrix, offsets: np.ndarray) -> "GraphStructure":
        """Edges from a symmetric vertex pattern with sorted rows (H's, from :func:`util.vertex_pattern`
        or the linearizer's fixed block pattern before any numbers)."""
        rows = np.repeat(np.arange(V.shape[0]), np.diff(V.indptr))
        upper = V.indices > rows
        # rows ascending, sorted columns within a row: the upper pairs come out sorted
        edges = np.stack([rows[upper], V.indices[upper].astype(np.int64)], axis=1)
        return cls(offsets=np.asarray(offsets, dtype=np.int64), edges=edges, odometry=edges[:, 1] == edges[:, 0] + 1)

    def adjacency(self, mask: np.ndarray | None = None) -> sp.csr_matrix:
        """Symmetric vertex adjacency of the edges selected by ``mask`` (all edges if None)."""
        e = self.edges if mask is None else self.edges[mask]
        nv = self.n_vertices
        ones = np.ones(2 * len(e))
        return sp.csr_matrix((ones, (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])), shape=(nv, nv))


def _symmetric(V: sp.csr_matrix) -> bool:
    """Whether the vertex pattern V (sorted CSR, no duplicates) is symmetric: equal
    to its transpose, whose CSR arrays scipy's O(nnz) conversion writes with sorted indices (a
    sort of the entries' keys instead: 1M 2D poses, 0.33 s)."""
    T = V.T.tocsr()
    return bool(np.array_equal(V.indptr, T.indptr) and np.array_equal(V.indices, T.indices))
