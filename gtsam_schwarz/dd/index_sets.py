"""Dof index sets of (overlapping) subdomains, concatenated so that no loop over subdomains is needed."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from ..util.arrays import vertex_dofs  # noqa: F401 (re-exported: dd.vertex_dofs)


@dataclass(frozen=True)
class IndexSets:
    """N possibly overlapping dof sets I_i, concatenated: set i is ``indices[ptr[i]:ptr[i+1]]``."""

    indices: np.ndarray
    ptr: np.ndarray
    n: int  # global dimension
    # where the sets are unions of whole vertices (poses): set i is the dofs of vertices[vertex_ptr[i]:
    # vertex_ptr[i+1]] in that order, vertex v owning dofs offsets[v]:offsets[v+1] (None: not known)
    vertices: np.ndarray | None = None
    vertex_ptr: np.ndarray | None = None
    offsets: np.ndarray | None = None

    @property
    def count(self) -> int:
        return len(self.ptr) - 1

    @property
    def sizes(self) -> np.ndarray:
        return np.diff(self.ptr)

    def block_of_entry(self) -> np.ndarray:
        return np.repeat(np.arange(self.count), self.sizes)

    def restriction(self) -> sp.csr_matrix:
        """Stacked restriction R = [R_1; …; R_N] (len(indices) × n)."""
        m = len(self.indices)
        return sp.csr_matrix((np.ones(m), (np.arange(m), self.indices)), shape=(m, self.n))

    def subsets(self, j0: int, j1: int) -> "IndexSets":
        """Sets j0 … j1 − 1 on their own (same global dimension)."""
        lo, hi = int(self.ptr[j0]), int(self.ptr[j1])
        vertices = vertex_ptr = None
        if self.vertices is not None:
            vlo, vhi = int(self.vertex_ptr[j0]), int(self.vertex_ptr[j1])
            vertices, vertex_ptr = self.vertices[vlo:vhi], self.vertex_ptr[j0:j1 + 1] - vlo
        return IndexSets(indices=self.indices[lo:hi], ptr=self.ptr[j0:j1 + 1] - lo, n=self.n,
                         vertices=vertices, vertex_ptr=vertex_ptr, offsets=self.offsets)

    def get(self, i: int) -> np.ndarray:
        return self.indices[self.ptr[i]:self.ptr[i + 1]]
