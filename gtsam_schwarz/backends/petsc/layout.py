"""Which rank owns which rows: ownership by subdomain, and the dof permutation that makes every
rank's rows contiguous (PETSc's row distribution).

A vertex belongs to the nonoverlapping vertex sets V_i of one or more subdomains (interface
vertices to several); it is owned by the lowest-numbered of them. Subdomains go to ranks in
contiguous runs balanced by the number of dofs they own. The new dof numbering lists rank 0's
dofs first (in their original order), then rank 1's, …: ``order[new] = old``,
``position[old] = new``. Plain numpy: no PETSc here.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from ...dd.decomposition import Decomposition
from ...dd.index_sets import IndexSets


@dataclass(frozen=True)
class RankLayout:
    ranks: int
    subdomain_rank: np.ndarray  # (N,) rank of each subdomain
    vertex_subdomain: np.ndarray  # (n_vertices,) owning subdomain of each vertex
    dof_rank: np.ndarray  # (n,) owning rank of each (original) dof
    order: np.ndarray  # (n,) new → old dof
    position: np.ndarray  # (n,) old → new dof
    ranges: np.ndarray  # (ranks + 1,) rank r owns new dofs ranges[r]:ranges[r+1]

    @property
    def n(self) -> int:
        return len(self.order)

    def rows(self, rank: int) -> tuple[int, int]:
        return int(self.ranges[rank]), int(self.ranges[rank + 1])

    def owned(self, rank: int) -> np.ndarray:
        """Original dof indices owned by ``rank`` (in the new order)."""
        lo, hi = self.rows(rank)
        return self.order[lo:hi]

    def subdomains(self, rank: int) -> np.ndarray:
        return np.flatnonzero(self.subdomain_rank == rank)

    def permute(self, x: np.ndarray) -> np.ndarray:
        """Original numbering → new numbering."""
        return np.asarray(x)[self.order]

    def unpermute(self, y: np.ndarray) -> np.ndarray:
        """New numbering → original numbering."""
        return np.asarray(y)[self.position]

    def index_sets(self, sets: IndexSets, rank: int) -> list[np.ndarray]:
        """The sets of ``rank``'s subdomains, in the new numbering, each sorted."""
        return [np.sort(self.position[sets.get(i)]) for i in self.subdomains(rank)]


def _balanced_runs(weights: np.ndarray, ranks: int) -> np.ndarray:
    """Item → rank, contiguous runs with about equal total weight (every rank gets at least one
    item when there are at least as many items as ranks)."""
    n = len(weights)
    w = np.maximum(np.asarray(weights, dtype=float), 1e-12)
    before = np.cumsum(w) - w
    mid = (before + 0.5 * w) / w.sum()
    rank = np.minimum((mid * ranks).astype(np.int64), ranks - 1)
    # contiguous and gap-free: each item's rank is its predecessor's or one more, and high enough
    # that the remaining items still reach the last rank
    for i in range(n):
        low = max(rank[i - 1] if i else 0, ranks - (n - i))
        high = rank[i - 1] + 1 if i else 0
        rank[i] = min(max(rank[i], low), high)
    return rank


def rank_layout(decomposition: Decomposition, ranks: int) -> RankLayout:
    """Ownership of vertices, subdomains and dofs for ``ranks`` ranks (needs N ≥ ranks)."""
    N = decomposition.n_subdomains
    if ranks < 1:
        raise ValueError(f"ranks must be >= 1, got {ranks}")
    if N < ranks:
        raise ValueError(f"{N} subdomains for {ranks} ranks: every rank needs at least one subdomain "
                         f"(ask for --subdomains >= {ranks})")
    offsets = decomposition.structure.offsets
    dims = np.diff(offsets)
    S = sp.csr_matrix(decomposition.vertex_subdomains)
    S.sort_indices()
    if np.any(np.diff(S.indptr) == 0):
        raise ValueError("a vertex belongs to no subdomain: decomposition is inconsistent")
    vertex_subdomain = S.indices[S.indptr[:-1]].astype(np.int64)  # the lowest-numbered V_i
    owned = np.bincount(vertex_subdomain, weights=dims, minlength=N)
    subdomain_rank = _balanced_runs(owned, ranks)
    dof_rank = np.repeat(subdomain_rank[vertex_subdomain], dims)
    order = np.argsort(dof_rank, kind="stable")
    position = np.empty_like(order)
    position[order] = np.arange(len(order))
    ranges = np.zeros(ranks + 1, dtype=np.int64)
    np.cumsum(np.bincount(dof_rank, minlength=ranks), out=ranges[1:])
    return RankLayout(ranks=ranks, subdomain_rank=subdomain_rank, vertex_subdomain=vertex_subdomain,
                      dof_rank=dof_rank, order=order, position=position, ranges=ranges)
