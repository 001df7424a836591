"""Interface detection: vertices shared by nonoverlapping subdomains (paper Sec. 3.3).

Like FROSch's interface entities, each interface vertex is tagged with the set of subdomains that
share it; on a trajectory decomposition every interface is a single pose.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from .decomposition import Decomposition, vertex_dofs


@dataclass(frozen=True)
class Interface:
    vertices: np.ndarray  # interface vertices Γ, sorted
    subdomains: sp.csr_matrix  # (len(vertices) × N): which subdomains share each interface vertex
    interior_subdomain: np.ndarray  # (n_vertices,): the one subdomain of each interior vertex, −1 on Γ

    @property
    def size(self) -> int:
        return len(self.vertices)

    def dofs(self, offsets: np.ndarray) -> np.ndarray:
        return vertex_dofs(self.vertices, offsets)


def find_interface(decomposition: Decomposition) -> Interface:
    """Γ = vertices that belong to two or more nonoverlapping vertex sets V_i."""
    S = decomposition.vertex_subdomains
    shared = np.diff(S.indptr)
    gamma = np.flatnonzero(shared >= 2)
    owner = np.full(S.shape[0], -1, dtype=np.int64)
    single = shared == 1
    owner[single] = S.indices[S.indptr[:-1][single]]
    return Interface(vertices=gamma, subdomains=sp.csr_matrix(S[gamma]), interior_subdomain=owner)
