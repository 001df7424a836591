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
from ..util import sorted_unique, vertex_dofs
from ..util.gathered import entries, is_gathered
from ..util.sparse import as_csr

FREE_TOL = 1e-8  # Rayleigh quotient zᵀHz / zᵀdiag(H)z of a translation mode below this: no anchor


def free_components(H: sp.csr_matrix, offsets: np.ndarray, geometry: VertexGeometry | None,
                    diagonal: np.ndarray | None = None, sources: np.ndarray | None = None) -> np.ndarray:
    """First vertex of every connected component whose rigid translations are in H's null space.

    Needs the poses (``geometry``); without them (other variable types) returns none. ``diagonal``:
    the positions of H's diagonal in ``H.data`` where the caller knows them (else H.diagonal()).
    ``sources``: where the caller knows them, the only vertices whose rows of Hz can be nonzero for a
    rigid translation z (the vertices of priors: a between factor's Jacobian maps z to zero, so its
    rows of Hz vanish): zᵀHz is summed over those rows alone (1M 2D poses with one prior: 0.09
    against 0.23 s; none: every component is free)."""
    offsets = np.asarray(offsets, dtype=np.int64)
    nv = len(offsets) - 1
    if geometry is None or nv == 0:
        return np.zeros(0, dtype=np.int64)
    H = as_csr(H)   # (a gathered H stays one: its product reads its source)
    n_comp, comp = connected_components(_vertex_graph(H, offsets), directed=False)
    if sources is not None and len(sources) == 0:
        return _first_vertices(comp, n_comp)
    d = geometry.d
    dims = np.diff(offsets)
    dim = 3 if d == 2 else 6
    if np.all(dims == dim):  # components are decoupled: all their modes in d columns, one product
        modes = np.zeros((nv, dim, d))   # translation t ↦ Rᵀt: Pose2 dofs (x, y), Pose3 dofs (v)
        modes[:, slice(0, 2) if d == 2 else slice(3, 6), :] = np.swapaxes(geometry.rotations, 1, 2)
        Z = modes.reshape(nv * dim, d)
    else:
        modes = rigid_modes(geometry, np.arange(nv), np.zeros((nv, d)), rotation=False)  # (nv, dim, d)
        dim = modes.shape[1]
        Z = np.zeros((H.shape[0], d))
        Z[(offsets[:-1, None] + np.arange(dim)).ravel()] = modes.reshape(nv * dim, d)
    diag = entries(H, diagonal) if diagonal is not None else H.diagonal()
    rows = slice(None) if sources is None else vertex_dofs(sorted_unique(sources), offsets)
    if sources is None:
        HZ = H @ Z
    else:   # the rows of the sources alone (a gathered H: the whole product, its rows taken)
        HZ = (H @ Z)[rows] if is_gathered(H) else H[rows] @ Z
    HZ *= Z[rows]
    ZZ = Z * Z
    ZZ *= diag[:, None]
    if n_comp == 1:   # zᵀHz and zᵀdiag(H)z of the d modes as column sums (no per-vertex sums)
        zHz, zDz = HZ.sum(axis=0)[None], ZZ.sum(axis=0)[None]
    else:
        owner = np.repeat(comp, dims)
        zHz = np.stack([np.bincount(owner[rows], HZ[:, k], minlength=n_comp) for k in range(d)], -1)
        zDz = np.stack([np.bincount(owner, ZZ[:, k], minlength=n_comp) for k in range(d)], -1)
    ratio = (zHz / np.where(zDz > 0, zDz, 1.0)).max(axis=1)
    return _first_vertices(comp, n_comp)[ratio < FREE_TOL]


def _first_vertices(comp: np.ndarray, n_comp: int) -> np.ndarray:
    """The lowest vertex of every component (``comp``: each vertex's component)."""
    first = np.full(n_comp, len(comp), dtype=np.int64)
    np.minimum.at(first, comp, np.arange(len(comp)))
    return first


def _vertex_graph(H: sp.csr_matrix, offsets: np.ndarray) -> sp.csr_matrix:
    """Vertex adjacency (with repeats) from the first dof row of every vertex: H holds whole blocks
    (with d dofs everywhere, only the first column of every block is read)."""
    nv = len(offsets) - 1
    dims = np.diff(offsets)
    starts = H.indptr[offsets[:-1]].astype(np.int64)
    lengths = H.indptr[offsets[:-1] + 1] - starts
    step = int(dims[0]) if nv and np.all(dims == dims[0]) else 1
    count = lengths // step
    indptr = np.zeros(nv + 1, dtype=np.int64)
    np.cumsum(count, out=indptr[1:])
    pos = np.repeat(starts - step * indptr[:-1], count) + step * np.arange(indptr[-1])
    cols = H.indices[pos]
    cols = cols // step if step > 1 else np.repeat(np.arange(nv), dims)[cols]
    return sp.csr_matrix((np.ones(len(cols)), cols, indptr), shape=(nv, nv))
