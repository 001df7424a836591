"""The GTSAM linearizer: ``graph.linearize`` exported to scipy (H = JᵀJ, gradient), steps retracted by gtsam.

GTSAM whitens every factor, so ``GaussianFactorGraph.sparseJacobian_()`` gives the whitened
Jacobian J and right-hand side b (= minus the whitened residual) of ½‖J δ − b‖². The Gauss–Newton
matrix is A = JᵀJ and the gradient of the objective is g = −Jᵀb (paper Sec. 2, Eq. hgn).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import gtsam
import numpy as np
import scipy.sparse as sp

from ..dd.geometry import VertexGeometry
from .base import LinearSystem
from .pattern import HessianPattern

# Tangent coordinates that are translations, per gtsam value type (GTSAM's own order:
# Pose2 = (x, y, θ), Pose3 = (ω, v): rotation first, then translation).
_TRANSLATION_DOFS = {3: (0, 1), 6: (3, 4, 5)}


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
class JacobianSystem(LinearSystem):
    """A linear system that keeps the whitened Jacobian J and right-hand side b (tests, plots)."""

    J: sp.csr_matrix | None = None
    b: np.ndarray | None = None


def export_linear_system(lin: gtsam.GaussianFactorGraph, keymap: KeyMap) -> JacobianSystem:
    """``GaussianFactorGraph`` → scipy (J, b, H, g) from one ``sparseJacobian_`` call, no per-factor loop.

    ``sparseJacobian_`` returns 1-based (row, col, value) triplets in GTSAM's natural key order;
    column ``n+1`` holds the right-hand side b.
    """
    n = keymap.dim
    S = lin.sparseJacobian_()
    if S.size == 0:
        return JacobianSystem(sp.csr_matrix((n, n)), np.zeros(n), 0.0, sp.csr_matrix((0, n)), np.zeros(0))
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
    return JacobianSystem(H=H, g=g, error=0.5 * float(b @ b), J=J, b=b)




class GtsamLinearizer:
    """:class:`~gtsam_schwarz.linearization.base.Linearizer` through GTSAM: works for any factor.

    Per linearization: ``graph.linearize`` → ``sparseJacobian_`` → H, g (J is not kept), H placed
    in the graph's fixed block pattern; the state is a ``gtsam.Values``.
    """

    def __init__(self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values):
        self.graph = graph
        self.keymap = KeyMap.from_graph(graph, values)
        self.keys, self.offsets = self.keymap.keys, self.keymap.offsets
        self.pattern: HessianPattern | None = None
        self.seconds = {"linearize": 0.0, "export": 0.0}  # of the last linearize call

    def state(self, values: gtsam.Values) -> gtsam.Values:
        return gtsam.Values(values)

    def linearize(self, state: gtsam.Values) -> LinearSystem:
        t0 = time.perf_counter()
        lin = self.graph.linearize(state)
        t1 = time.perf_counter()
        system = export_linear_system(lin, self.keymap)
        H = self._fixed_pattern(system.H)
        self.seconds = {"linearize": t1 - t0, "export": time.perf_counter() - t1}
        return LinearSystem(H=H, g=system.g, error=system.error, diagonal=self.pattern.diagonal,
                            seconds=self.seconds)

    def _fixed_pattern(self, H):
        """H in the graph's full block pattern, so symbolic work is reused (see HessianPattern)."""
        fitted = self.pattern.fit(H) if self.pattern is not None else None
        if fitted is None:
            self.pattern = HessianPattern(H, self.offsets)
            fitted = self.pattern.fit(H)
        return fitted

    def retract(self, state: gtsam.Values, x: np.ndarray) -> gtsam.Values:
        return self.keymap.retract(state, x)

    def error(self, state: gtsam.Values) -> float:
        return float(self.graph.error(state))

    def geometry(self, state: gtsam.Values) -> VertexGeometry | None:
        return self.keymap.geometry(state)

    def values(self, state: gtsam.Values) -> gtsam.Values:
        return state

    def translation_mask(self) -> np.ndarray:
        return self.keymap.translation_mask()
