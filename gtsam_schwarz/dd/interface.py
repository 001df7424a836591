"""Interface detection: vertices shared by nonoverlapping subdomains, grouped into components.

Like FROSch's interface entities: interface vertices are grouped by the set of subdomains that
share them, then split into connected components of the pose graph. On a trajectory decomposition
of the paper's model problem every component is a single pose (paper Sec. 3.3).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from .decomposition import Decomposition


@dataclass(frozen=True)
class Interface:
    vertices: np.ndarray  # interface vertices Γ, sorted
    subdomains: sp.csr_matrix  # (len(vertices) × N): which subdomains share each interface vertex
    interior_subdomain: np.ndarray  # (n_vertices,): the one subdomain of each interior vertex, −1 on Γ
    component: np.ndarray  # (len(vertices),): interface component of each interface vertex
    # (len(vertices) × len(vertices)): interface vertices at most two graph edges apart (any subdomain
    # sets); filled by find_interface(group="two-hop"), None otherwise
    neighbours: sp.csr_matrix | None = None

    @property
    def size(self) -> int:
        return len(self.vertices)

    @property
    def n_components(self) -> int:
        return int(self.component.max()) + 1 if self.size else 0

    def component_subdomains(self) -> sp.csr_matrix:
        """(n_components × N) incidence: the subdomain set shared by each component."""
        first = np.zeros(self.n_components, dtype=np.int64)
        first[self.component[::-1]] = np.arange(self.size)[::-1]
        return sp.csr_matrix(self.subdomains[first])

    def coarse_nodes(self) -> tuple[np.ndarray, sp.csr_matrix]:
        """RGDSW coarse nodes and ancestors.

        A component is a coarse node if no other component's subdomain set strictly contains its
        own. Returns (is_node per component, ancestors: n_components × n_components incidence
        with ancestors[c, a] = 1 if node a's set ⊇ c's set; a node is its own only ancestor).
        """
        C = self.component_subdomains().astype(np.int64)
        size = np.asarray(C.sum(axis=1)).ravel()
        overlap = (C @ C.T).tocoo()  # |set(a) ∩ set(b)|
        contains = overlap.data == size[overlap.row]  # set(row) ⊆ set(col)
        strict = contains & (size[overlap.col] > size[overlap.row])
        is_node = np.ones(len(size), dtype=bool)
        is_node[overlap.row[strict]] = False
        rows, cols = overlap.row[contains], overlap.col[contains]
        keep = is_node[cols] & (~is_node[rows] | (rows == cols))
        n = len(size)
        anc = sp.csr_matrix((np.ones(int(keep.sum())), (rows[keep], cols[keep])), shape=(n, n))
        return is_node, anc


def _equal_rows(M: sp.csr_matrix) -> np.ndarray:
    """A group id per row of M, equal for rows with equal column sets (by their signature's two
    64-bit words, sorted by ``np.lexsort``: ``np.unique(..., axis=0)`` compares the rows as opaque
    records, 0.17 s for the 400 000 interface poses of a 1M-pose lawnmower)."""
    sig = _row_signature(M)
    if len(sig) == 0:
        return np.zeros(0, dtype=np.int64)
    order = np.lexsort((sig[:, 1], sig[:, 0]))
    s = sig[order]
    new = np.r_[True, np.any(s[1:] != s[:-1], axis=1)]
    group = np.empty(len(sig), dtype=np.int64)
    group[order] = np.cumsum(new) - 1
    return group


def _row_signature(M: sp.csr_matrix, seed: int = 12345) -> np.ndarray:
    """A hash of each row's column set (two random 64-bit projections), for grouping equal rows."""
    rng = np.random.default_rng(seed)
    w = rng.integers(1, 2**62, size=(M.shape[1], 2), dtype=np.int64)
    M = sp.csr_matrix(M)
    rows = np.repeat(np.arange(M.shape[0]), np.diff(M.indptr))
    sig = np.zeros((M.shape[0], 2), dtype=np.int64)
    for k in range(2):
        np.add.at(sig[:, k], rows, w[M.indices, k])  # wraps modulo 2^64: fine for hashing
    return sig


def find_interface(decomposition: Decomposition, group: str = "components") -> Interface:
    """Γ = vertices in two or more nonoverlapping vertex sets V_i, grouped into components.

    ``group="components"``: by equal subdomain sets, then connected along graph edges (FROSch's
    interface entities); ``group="vertices"``: every interface vertex on its own (the paper);
    ``group="two-hop"``: by equal subdomain sets, connected through paths of at most two graph edges
    (the interface of a grid-like graph zigzags: METIS cuts leave the earlier pose of each cut edge
    on Γ, on alternate sides of the cut, so graph connectivity alone splits one interface edge
    into many single poses); also fills ``neighbours``.
    """
    S = decomposition.vertex_subdomains
    shared = np.diff(S.indptr)
    gamma = np.flatnonzero(shared >= 2)
    owner = np.full(S.shape[0], -1, dtype=np.int64)
    single = shared == 1
    owner[single] = S.indices[S.indptr[:-1][single]]
    G = sp.csr_matrix(S[gamma])
    neighbours = None
    if group == "two-hop":
        neighbours = two_hop_neighbours(decomposition.structure.adjacency(), gamma)
    if group == "vertices" or len(gamma) == 0:
        component = np.arange(len(gamma))
    elif group == "two-hop":
        component = _components_within(neighbours, _equal_rows(G))
    elif group == "components":
        group_id = _equal_rows(G)
        edges = decomposition.structure.edges
        pos = np.full(S.shape[0], -1, dtype=np.int64)
        pos[gamma] = np.arange(len(gamma))
        a, b = pos[edges[:, 0]], pos[edges[:, 1]]
        keep = (a >= 0) & (b >= 0)
        a, b = a[keep], b[keep]
        same = group_id[a] == group_id[b]
        adj = sp.csr_matrix((np.ones(int(same.sum())), (a[same], b[same])), shape=(len(gamma),) * 2)
        _, component = connected_components(adj, directed=False)
    else:
        raise ValueError(f"group must be 'components', 'vertices' or 'two-hop', got {group!r}")
    return Interface(vertices=gamma, subdomains=G, interior_subdomain=owner,
                     component=np.asarray(component, dtype=np.int64), neighbours=neighbours)


def two_hop_neighbours(adjacency: sp.csr_matrix, vertices: np.ndarray) -> sp.csr_matrix:
    """Pairs of ``vertices`` at most two edges apart in the graph ``adjacency`` (a symmetric vertex
    adjacency), as a symmetric 0/1 matrix over ``vertices`` without its diagonal."""
    R = sp.csr_matrix(adjacency)[vertices]
    C = (R[:, vertices] + R @ R.T).tocoo()
    off = C.row != C.col
    m = len(vertices)
    N = sp.csr_matrix((np.ones(int(off.sum())), (C.row[off], C.col[off])), shape=(m, m))
    N.data[:] = 1.0
    return N


def _components_within(neighbours: sp.csr_matrix, group_id: np.ndarray) -> np.ndarray:
    """Connected components of ``neighbours`` restricted to pairs in the same group."""
    C = neighbours.tocoo()
    same = group_id[C.row] == group_id[C.col]
    m = neighbours.shape[0]
    adj = sp.csr_matrix((np.ones(int(same.sum())), (C.row[same], C.col[same])), shape=(m, m))
    return connected_components(adj, directed=False)[1]
