"""Gauge freedom: connected components of the pose graph that no prior anchors.

The error of a component without a unary factor is invariant under moving all its poses rigidly,
so H has those rigid-body modes in its null space (paper Sec. 2). Such a component gets its first
pose anchored in the linear solves, as g2o fixes a vertex: H + diag(H_aa) on the anchor's dofs,
which removes the null space without changing the objective.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from ..coarse.modes import rigid_modes
from ..dd.geometry import VertexGeometry

FREE_TOL = 1e-8  # Rayleigh quotient zᵀHz / zᵀdiag(H)z of a translation mode below this: no anchor


def free_components(H: sp.csr_matrix, offsets: np.ndarray, geometry: VertexGeometry | None) -> np.ndarray:
    """First vertex of every connected component whose rigid translations are in H's null space.

    Needs the poses (``geometry``); without them (other variable types) returns none."""
    offsets = np.asarray(offsets, dtype=np.int64)
    nv = len(offsets) - 1
    if geometry is None or nv == 0:
        return np.zeros(0, dtype=np.int64)
    H = sp.csr_matrix(H)
    n_comp, comp = connected_components(_vertex_graph(H, offsets), directed=False)
    d = geometry.d
    dims = np.diff(offsets)
    modes = rigid_modes(geometry, np.arange(nv), np.zeros((nv, d)), rotation=False)  # (nv, dim, d)
    dim = modes.shape[1]
    if np.all(dims == dim):  # components are decoupled: all their modes in d columns, one product
        Z = modes.reshape(nv * dim, d)
        owner = np.repeat(comp, dim)
    else:
        Z = np.zeros((H.shape[0], d))
        rows = (offsets[:-1, None] + np.arange(dim)).ravel()
        Z[rows] = modes.reshape(nv * dim, d)
        owner = np.repeat(comp, dims)
    HZ = H @ Z
    DZ = H.diagonal()[:, None] * Z
    zHz = np.stack([np.bincount(owner, Z[:, k] * HZ[:, k], minlength=n_comp) for k in range(d)], -1)
    zDz = np.stack([np.bincount(owner, Z[:, k] * DZ[:, k], minlength=n_comp) for k in range(d)], -1)
    ratio = (zHz / np.where(zDz > 0, zDz, 1.0)).max(axis=1)
    free = np.flatnonzero(ratio < FREE_TOL)
    first = np.full(n_comp, nv, dtype=np.int64)
    np.minimum.at(first, comp, np.arange(nv))
    return first[free]


def _vertex_graph(H: sp.csr_matrix, offsets: np.ndarray) -> sp.csr_matrix:
    """Vertex adjacency (with repeats) from the first dof row of every vertex: H holds whole blocks."""
    nv = len(offsets) - 1
    owner = np.repeat(np.arange(nv), np.diff(offsets))
    starts = H.indptr[offsets[:-1]].astype(np.int64)
    lengths = H.indptr[offsets[:-1] + 1] - starts
    indptr = np.zeros(nv + 1, dtype=np.int64)
    np.cumsum(lengths, out=indptr[1:])
    pos = np.repeat(starts - indptr[:-1], lengths) + np.arange(indptr[-1])
    cols = owner[H.indices[pos]]
    return sp.csr_matrix((np.ones(len(cols)), cols, indptr), shape=(nv, nv))
