"""The paper's 1D bar chain (appendix): linear elastic bars ↔ a 1D SLAM problem with end closure.

N subdomains of 63 bars each on the free nodes, one extra bar to each Dirichlet end node:
63N + 2 bars, 63N + 3 nodes. Dirichlet values x_0 = 0 and x_end = number of bars are eliminated
symmetrically (identity rows, paper's K̂), so the exact solution is x_k = k.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from ..dd import Decomposition, GraphStructure

BARS_PER_SUBDOMAIN = 63


@dataclass
class BarChain:
    K: sp.csr_matrix  # K̂: stiffness with Dirichlet rows/columns eliminated
    b: np.ndarray  # b̂
    solution: np.ndarray  # x_k = k
    structure: GraphStructure  # nodes = vertices (1 dof), bars = edges
    edge_subdomain: np.ndarray  # bar → subdomain

    @property
    def bars(self) -> int:
        return len(self.structure.edges)

    def decomposition(self, overlap: int = 1) -> Decomposition:
        return Decomposition.build(self.structure, self.edge_subdomain, overlap=overlap)


def bar_chain(subdomains: int, bars_per_subdomain: int = BARS_PER_SUBDOMAIN) -> BarChain:
    """Bar chain with ``subdomains`` subdomains (paper Table tab:laplace_scalability)."""
    N = int(subdomains)
    if N < 1 or bars_per_subdomain < 1:
        raise ValueError("subdomains and bars_per_subdomain must be >= 1")
    nb = bars_per_subdomain * N + 2
    nn = nb + 1
    # assembled stiffness Σ_e R_eᵀ [[1, −1], [−1, 1]] R_e, then symmetric Dirichlet elimination
    main = np.full(nn, 2.0)
    off = -np.ones(nn - 1)
    off[0] = off[-1] = 0.0  # couplings to the Dirichlet nodes are eliminated
    main[0] = main[-1] = 1.0
    K = sp.diags([main, off, off], [0, 1, -1], format="csr")
    K.eliminate_zeros()
    x_end = float(nb)
    b = np.zeros(nn)
    b[0], b[-1] = 0.0, x_end
    b[-2] += x_end  # column elimination moves the Dirichlet value to the neighbour's right side
    edges = np.stack([np.arange(nb), np.arange(1, nb + 1)], axis=1)
    structure = GraphStructure(offsets=np.arange(nn + 1), edges=edges, odometry=np.ones(nb, dtype=bool))
    # free bars 1..nb−2 in blocks of 63; each Dirichlet bar joins its neighbouring block
    part = np.clip((np.arange(nb) - 1) // bars_per_subdomain, 0, N - 1)
    return BarChain(K=K, b=b, solution=np.arange(nn, dtype=float), structure=structure, edge_subdomain=part)
