"""Export a linearized GTSAM graph to scipy (H = JᵀJ, gradient) and map steps back to gtsam.

GTSAM whitens every factor, so ``GaussianFactorGraph.sparseJacobian_()`` gives the whitened
Jacobian J and right-hand side b (= minus the whitened residual) of ½‖J δ − b‖². The Gauss–Newton
matrix is A = JᵀJ and the gradient of the objective is g = −Jᵀb (paper Sec. 2, Eq. hgn).
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np
import scipy.sparse as sp

# Tangent coordinates that are translations, per gtsam value type (GTSAM's own order:
# Pose2 = (x, y, θ), Pose3 = (ω, v): rotation first, then translation).
_TRANSLATION_DOFS = {3: (0, 1), 6: (3, 4, 5)}


@dataclass(frozen=True)
class VertexGeometry:
    """Variable positions and rotations at the linearization point (Pose2: d = 2, Pose3: d = 3),
    used for the rigid-body modes of the coarse space."""

    positions: np.ndarray  # (n_vertices, d)
    rotations: np.ndarray  # (n_vertices, d, d), world-from-body

    @property
    def d(self) -> int:
        return self.positions.shape[1]


@dataclass(frozen=True)
class KeyMap:
    """Map from gtsam keys (sorted, as GTSAM orders columns) to contiguous dof ranges."""

    keys: np.ndarray  # uint64, sorted ascending
    dims: np.ndarray  # int64, dimension of each variable
    offsets: np.ndarray  # int64, len(keys)+1, first dof of each variable

    @classmethod
    def from_graph(cls, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values) -> "KeyMap":
        """Keys of ``graph`` in GTSAM's natural (sorted) order, dimensions from ``values``."""
        keys = graph.keyVector()
        all_dims = values.dims()
        missing = [k for k in keys if k not in all_dims]
        if missing:
            raise KeyError(f"graph key {gtsam.DefaultKeyFormatter(missing[0])} has no initial value")
        return cls.from_dims(keys, [all_dims[k] for k in keys])

    @classmethod
    def from_dims(cls, keys, dims) -> "KeyMap":
        keys = np.asarray(keys, dtype=np.uint64)
        dims = np.asarray(dims, dtype=np.int64)
        order = np.argsort(keys, kind="stable")
        keys, dims = keys[order], dims[order]
        offsets = np.zeros(len(keys) + 1, dtype=np.int64)
        np.cumsum(dims, out=offsets[1:])
        return cls(keys=keys, dims=dims, offsets=offsets)

    @property
    def dim(self) -> int:
        return int(self.offsets[-1])

    @property
    def size(self) -> int:
        return len(self.keys)

    def dof_to_variable(self) -> np.ndarray:
        """Index of the variable that owns each dof."""
        return np.repeat(np.arange(self.size), self.dims)

    def translation_mask(self) -> np.ndarray:
        """True for dofs that are translations (used by the coarse space without rotation)."""
        mask = np.ones(self.dim, dtype=bool)
        for d, tdofs in _TRANSLATION_DOFS.items():
            first = self.offsets[:-1][self.dims == d]
            if len(first):
                mask[(first[:, None] + np.arange(d)).ravel()] = False
                mask[(first[:, None] + np.asarray(tdofs)).ravel()] = True
        return mask

    def geometry(self, values: gtsam.Values) -> VertexGeometry | None:
        """Poses of all variables in key order, if they are all Pose2 or all Pose3; else None."""
        if self.size == 0 or not (np.all(self.dims == 3) or np.all(self.dims == 6)):
            return None
        planar = bool(self.dims[0] == 3)
        table = (gtsam.utilities.extractPose2 if planar else gtsam.utilities.extractPose3)(values)
        typed = [k for k in values.keys()] if len(table) != values.size() else None
        if typed is not None:  # other value types present: find the poses' keys one by one
            at = values.atPose2 if planar else values.atPose3
            ok = []
            for k in typed:
                try:
                    at(k)
                    ok.append(k)
                except RuntimeError:
                    pass
            keys = np.asarray(ok, dtype=np.uint64)
        else:
            keys = np.asarray(values.keys(), dtype=np.uint64)
        pos = np.searchsorted(keys, self.keys)
        if len(keys) != len(table) or np.any(pos >= len(keys)) or np.any(keys[np.minimum(pos, len(keys) - 1)] != self.keys):
            return None
        rows = table[pos]
        if planar:
            c, s_ = np.cos(rows[:, 2]), np.sin(rows[:, 2])
            R = np.stack([np.stack([c, -s_], 1), np.stack([s_, c], 1)], 1)
            return VertexGeometry(positions=rows[:, :2].copy(), rotations=R)
        return VertexGeometry(positions=rows[:, 9:12].copy(), rotations=rows[:, :9].reshape(-1, 3, 3))

    def to_vector_values(self, x: np.ndarray) -> gtsam.VectorValues:
        """Numpy step → ``gtsam.VectorValues`` (gtsam offers no bulk constructor: one insert per key)."""
        x = np.asarray(x, dtype=float)
        if x.shape != (self.dim,):
            raise ValueError(f"step has shape {x.shape}, expected ({self.dim},)")
        vv = gtsam.VectorValues()
        if self.size and np.all(self.dims == self.dims[0]):  # one row per key: map, no slicing
            list(map(vv.insert, self.keys.tolist(), x.reshape(self.size, int(self.dims[0]))))
            return vv
        for key, lo, hi in zip(self.keys.tolist(), self.offsets[:-1].tolist(), self.offsets[1:].tolist()):
            vv.insert(key, x[lo:hi])
        return vv

    def retract(self, values: gtsam.Values, x: np.ndarray) -> gtsam.Values:
        """values ⊕ x, GTSAM's retraction per variable."""
        return values.retract(self.to_vector_values(x))


@dataclass
class LinearSystem:
    """Whitened Gauss–Newton system H δ = −g of one linearization point."""

    H: sp.csr_matrix  # JᵀJ, symmetric positive (semi)definite
    g: np.ndarray  # gradient Jᵀ W r = −Jᵀb
    J: sp.csr_matrix
    b: np.ndarray

    @property
    def error(self) -> float:
        """½‖b‖², equal to graph.error(values) at the linearization point."""
        return 0.5 * float(self.b @ self.b)

    @property
    def rhs(self) -> np.ndarray:
        return -self.g


def export_linear_system(lin: gtsam.GaussianFactorGraph, keymap: KeyMap) -> LinearSystem:
    """``GaussianFactorGraph`` → scipy (J, b, H, g) from one ``sparseJacobian_`` call, no per-factor loop.

    ``sparseJacobian_`` returns 1-based (row, col, value) triplets in GTSAM's natural key order;
    column ``n+1`` holds the right-hand side b.
    """
    n = keymap.dim
    S = lin.sparseJacobian_()
    if S.size == 0:
        return LinearSystem(sp.csr_matrix((n, n)), np.zeros(n), sp.csr_matrix((0, n)), np.zeros(0))
    rows = S[0].astype(np.int64) - 1
    cols = S[1].astype(np.int64) - 1
    vals = S[2]
    if cols.max() > n:
        raise ValueError(f"linearization has {cols.max()} columns, key map expects {n}: keys differ")
    m = int(rows.max()) + 1
    is_rhs = cols == n
    J = sp.csr_matrix((vals[~is_rhs], (rows[~is_rhs], cols[~is_rhs])), shape=(m, n))
    b = np.bincount(rows[is_rhs], weights=vals[is_rhs], minlength=m)
    Jt = J.T.tocsr()
    H = (Jt @ J).tocsr()
    H.sum_duplicates()
    H.sort_indices()
    g = -(Jt @ b)
    return LinearSystem(H=H, g=g, J=J, b=b)


def _expand_uniform(blocks: sp.csr_matrix, d: int) -> tuple[np.ndarray, np.ndarray]:
    """CSR (indptr, indices) of the dof pattern of a vertex pattern whose vertices all have d dofs."""
    nv = blocks.shape[0]
    cnt = np.diff(blocks.indptr)
    expanded = (blocks.indices[:, None].astype(np.int64) * d + np.arange(d)).ravel()  # per vertex row
    row_len = np.repeat(cnt * d, d)  # each of the d dof rows of vertex v repeats its expanded segment
    starts = np.repeat(blocks.indptr[:-1].astype(np.int64) * d, d)
    indptr = np.zeros(nv * d + 1, dtype=np.int64)
    np.cumsum(row_len, out=indptr[1:])
    gather = np.repeat(starts - indptr[:-1], row_len) + np.arange(indptr[-1])
    index_type = np.int32 if nv * d < 2**31 and indptr[-1] < 2**31 else np.int64
    return indptr.astype(index_type), expanded[gather].astype(index_type)


class HessianPattern:
    """The full block sparsity of H: every entry of every block (u, v) of coupled variables.

    ``sparseJacobian_`` drops entries below 1e-12 and scipy's products drop exact zeros, so the
    pattern of JᵀJ can change between linearization points (e.g. at the zero-residual dead-reckoning
    start). Placing H into this fixed pattern lets everything symbolic downstream (subdomain
    gathers, orderings, harmonic-extension plans) be computed once per graph.
    """

    def __init__(self, H: sp.csr_matrix, offsets: np.ndarray):
        offsets = np.asarray(offsets, dtype=np.int64)
        nv, n = len(offsets) - 1, int(offsets[-1])
        owner = np.repeat(np.arange(nv), np.diff(offsets))
        C = sp.coo_matrix(H)
        blocks = sp.csr_matrix((np.ones(C.nnz + nv), (np.concatenate([owner[C.row], np.arange(nv)]),
                                                      np.concatenate([owner[C.col], np.arange(nv)]))),
                               shape=(nv, nv))
        blocks.sum_duplicates()
        blocks.sort_indices()
        dims = np.diff(offsets)
        if nv and np.all(dims == dims[0]):  # every variable d dofs: expand the block pattern directly
            self.indptr, self.indices = _expand_uniform(blocks, int(dims[0]))
        else:
            E = sp.csr_matrix((np.ones(n), (np.arange(n), owner)), shape=(n, nv))
            F = (E @ blocks @ E.T).tocsr()
            F.sort_indices()
            self.indptr, self.indices = F.indptr, F.indices
        self.shape = (n, n)
        rows = np.repeat(np.arange(n, dtype=np.int64), np.diff(self.indptr))
        self.diagonal = np.flatnonzero(rows == self.indices)

        self._last = None  # (indptr, indices, positions) of the last pattern placed into this one

    def fit(self, H: sp.csr_matrix) -> sp.csr_matrix | None:
        """H with the fixed pattern (explicit zeros where needed); None if H has entries outside it.

        The positions of H's entries are found by a search once per pattern of H (JᵀJ keeps one
        pattern after the first step), afterwards by comparing two arrays."""
        H = sp.csr_matrix(H)
        H.sort_indices()
        last = self._last
        if last is None or not (np.array_equal(H.indptr, last[0]) and np.array_equal(H.indices, last[1])):
            # position of each entry of H in the fixed pattern: the elementwise product of H's
            # pattern with a matrix holding 1-based positions (scipy keeps canonical order)
            pos = sp.csr_matrix((np.arange(1, len(self.indices) + 1, dtype=float), self.indices, self.indptr),
                                shape=self.shape)
            ones = sp.csr_matrix((np.ones(H.nnz), H.indices, H.indptr), shape=self.shape)
            hit = sp.csr_matrix(ones.multiply(pos))
            hit.sort_indices()
            if hit.nnz != H.nnz or not np.array_equal(hit.indices, H.indices):
                return None
            self._last = last = (H.indptr.copy(), H.indices.copy(), hit.data.astype(np.int64) - 1)
        data = np.zeros(len(self.indices))
        data[last[2]] = H.data
        return sp.csr_matrix((data, self.indices, self.indptr), shape=self.shape)

    def damped(self, H: sp.csr_matrix, d: np.ndarray) -> sp.csr_matrix:
        """H + diag(d) without changing the pattern (scipy's sum would drop explicit zeros)."""
        data = H.data.copy()
        data[self.diagonal] += d
        return sp.csr_matrix((data, self.indices, self.indptr), shape=self.shape)
