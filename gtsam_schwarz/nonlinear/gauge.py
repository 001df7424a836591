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
from ..solvers.cost import vertex_pattern

FREE_TOL = 1e-8  # Rayleigh quotient zᵀHz / zᵀdiag(H)z of a translation mode below this: no anchor


def free_components(H: sp.csr_matrix, offsets: np.ndarray, geometry: VertexGeometry | None) -> np.ndarray:
    """First vertex of every connected component whose rigid translations are in H's null space.

    Needs the poses (``geometry``); without them (other variable types) returns none."""
    offsets = np.asarray(offsets, dtype=np.int64)
    nv = len(offsets) - 1
    if geometry is None or nv == 0:
        return np.zeros(0, dtype=np.int64)
    n_comp, comp = connected_components(vertex_pattern(H, offsets), directed=False)
    d = geometry.d
    modes = rigid_modes(geometry, np.arange(nv), np.zeros((nv, d)), rotation=False)  # (nv, dim, d)
    dim = modes.shape[1]
    rows = (offsets[:-1, None, None] + np.arange(dim)[None, :, None]).repeat(d, 2)
    cols = (comp[:, None, None] * d + np.arange(d)[None, None, :]).repeat(dim, 1)
    Z = sp.csr_matrix((modes.ravel(), (rows.ravel(), cols.ravel())), shape=(H.shape[0], n_comp * d))
    zHz = np.asarray(Z.multiply(H @ Z).sum(axis=0)).ravel()
    zDz = np.asarray(Z.multiply(sp.diags(H.diagonal()) @ Z).sum(axis=0)).ravel()
    ratio = (zHz / np.where(zDz > 0, zDz, 1.0)).reshape(n_comp, d).max(axis=1)
    free = np.flatnonzero(ratio < FREE_TOL)
    first = np.full(n_comp, nv, dtype=np.int64)
    np.minimum.at(first, comp, np.arange(nv))
    return first[free]

