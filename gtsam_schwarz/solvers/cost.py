"""Predicted cost of a sparse Cholesky factorization from the block pattern alone.

A pose graph's Hessian has dense d×d blocks (d = 3 in 2D, 6 in 3D) on the pattern of its vertex
graph. The column counts c_j of the factor of that vertex pattern (a d-times smaller surrogate, a
diagonally dominant Laplacian, same fill-reducing ordering) give the real factor's size: about
d²·Σc_j entries and d³·Σc_j² flops. CHOLMOD's symbolic analysis gives the counts directly
(:mod:`.cholmod_symbolic`); without it the surrogate is factorized, 1/d³ of the real work. Nothing
of it depends on the numbers.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from . import cholmod_symbolic
from .sparse import SPARSE_BACKEND
from ..util import as_csr, vertex_pattern  # noqa: F401 (vertex_pattern re-exported: solvers.vertex_pattern)


NATURAL_SLACK = 1.02  # a matrix's own order is used where its factor has at most this many times AMD's entries


@dataclass(frozen=True)
class CholeskyCost:
    """Predicted size and work of the Cholesky factor of a block matrix."""

    nnz_A: int  # entries of the matrix (both triangles)
    nnz_L: float  # entries of its Cholesky factor (one triangle)
    flops: float  # multiply-adds of the numeric factorization
    n_dofs: int = 0
    nnz_L_natural: float | None = None  # the same in the matrix's own order (when asked for and known)
    flops_natural: float | None = None

    @property
    def natural_suffices(self) -> bool:
        """Whether the matrix's own order costs at most ``NATURAL_SLACK`` × the fill-reducing
        ordering's nnz(L) and flops: the factorization can then skip the ordering, the largest part
        of its analysis (1M-pose model problem, keys along the trajectory: 0.29 against 0.89 s for
        AMD on H's 28M entries, the same factor)."""
        return (self.nnz_L_natural is not None and self.nnz_L_natural <= NATURAL_SLACK * self.nnz_L
                and self.flops_natural <= NATURAL_SLACK * self.flops)

    @property
    def fill(self) -> float:
        """nnz(L) / nnz(tril(A)): 1 means no fill."""
        return self.nnz_L / max((self.nnz_A + self.n_dofs) / 2, 1)


def cholesky_cost(A: sp.spmatrix, offsets: np.ndarray, natural: bool = False) -> CholeskyCost:
    """Predicted nnz(L) and flops of factorizing A (block pattern given by ``offsets``); with
    ``natural``, also nnz(L) in A's own order (:attr:`CholeskyCost.natural_suffices`)."""
    offsets = np.asarray(offsets, dtype=np.int64)
    return pattern_cholesky_cost(vertex_pattern(A, offsets), np.diff(offsets), int(as_csr(A).nnz), natural)


def pattern_cholesky_cost(B: sp.spmatrix, dims: np.ndarray, nnz_A: int | None = None,
                          natural: bool = False) -> CholeskyCost:
    """Predicted nnz(L) and flops of a block matrix given by its vertex pattern B and block sizes
    (and, with ``natural``, nnz(L) without a fill-reducing ordering: elimination tree only, O(nnz))."""
    nv = B.shape[0]
    dims = np.asarray(dims, dtype=np.int64)
    if nv == 0:
        return CholeskyCost(0, 0.0, 0.0, 0)
    d = float(np.mean(dims))
    B = sp.csr_matrix(B)
    S = _surrogate(B)  # SPD, the same pattern
    counts = _factor_column_counts(S)
    nnz_L = d * d * counts.sum() - nv * d * (d - 1) / 2
    flops = d ** 3 * float(np.sum(counts.astype(float) ** 2))
    if nnz_A is None:
        nnz_A = int(d * d * sp.csr_matrix(B).nnz)
    nnz_natural = flops_natural = None
    own = cholmod_symbolic.natural_column_counts(S) if natural and SPARSE_BACKEND == "cholmod" else None
    if own is not None:
        nnz_natural = float(d * d * own.sum() - nv * d * (d - 1) / 2)
        flops_natural = d ** 3 * float(np.sum(own.astype(float) ** 2))
    return CholeskyCost(nnz_A=nnz_A, nnz_L=float(nnz_L), flops=flops, n_dofs=int(dims.sum()),
                        nnz_L_natural=nnz_natural, flops_natural=flops_natural)


def _surrogate(B: sp.csr_matrix) -> sp.csc_matrix:
    """The diagonally dominant Laplacian with the symmetrized pattern of B and its diagonal:
    −1 off the diagonal, deg + ε_v on it (deg counts the row's entries, diagonal included).

    A structurally symmetric B with every diagonal entry and sorted indices (a vertex pattern of
    H) is used as it is: its CSR arrays are the CSC arrays of S (no sum with Bᵀ, no diagonal sum)."""
    nv = B.shape[0]
    eps = 1e-3 * np.arange(nv) / max(nv, 1)
    if B.has_sorted_indices:
        indptr, indices = B.indptr, B.indices
        deg = np.diff(indptr)
        rows = np.repeat(np.arange(nv, dtype=indices.dtype), deg)
        on_diagonal = indices == rows
        if np.count_nonzero(on_diagonal) == nv:
            T = B.T.tocsr()  # the transpose's pattern: symmetric iff it equals B's
            T.sort_indices()
            if np.array_equal(T.indptr, indptr) and np.array_equal(T.indices, indices):
                data = np.full(len(indices), -1.0)
                data[on_diagonal] = -1.0 + (deg + 1.0 + eps)
                S = sp.csc_matrix((data, indices, indptr), shape=(nv, nv))
                S.has_sorted_indices = True
                return S
    B = B + B.T
    B.data[:] = -1.0
    deg = -np.asarray(B.sum(axis=1)).ravel()
    return (B + sp.diags(deg + 1.0 + eps)).tocsc()


SUPERNODAL_DEGREE = 4.5  # mean entries per column of the surrogate from which it is factorized supernodally


_LAST_COUNTS: list = []  # [((shape, indptr, indices), counts)] of the last pattern analysed: a run's chordal start and its
# automatic linear solver both ask for the pose graph's vertex pattern (the analysis, not the answer, is kept)


def _same_pattern(S: sp.spmatrix, key: tuple) -> bool:
    shape, indptr, indices = key
    return S.shape == shape and np.array_equal(S.indptr, indptr) and np.array_equal(S.indices, indices)


def _pattern_key(S: sp.spmatrix) -> tuple:
    """S's pattern: its arrays, referenced if read-only, else copied (comparing them costs less than a
    digest: 262 145 poses 1 against 14 ms)."""
    return (S.shape, *(a if not a.flags.writeable else a.copy() for a in (S.indptr, S.indices)))


def counted_simplicially(S: sp.spmatrix) -> bool:
    """Whether :func:`_counts` takes a symmetric pattern's counts from a simplicial factor (a sparse one)."""
    return S.nnz < SUPERNODAL_DEGREE * S.shape[0]


def record_column_counts(S: sp.spmatrix, factor) -> None:
    """Remember the column counts of ``factor``, a simplicial factor (``SparseCholesky(..., mode=
    "simplicial")``) of a matrix with S's symmetric pattern under CHOLMOD's own ordering: the 2D chordal
    start factorizes the vertex pattern of H before the automatic linear solver asks for its counts
    (262 145 poses: 70 ms saved; 1M: 0.3-0.9 s). Ignored where :func:`_counts` would not count simplicially."""
    if SPARSE_BACKEND == "cholmod" and counted_simplicially(S):
        _LAST_COUNTS[:] = [(_pattern_key(S), factor.column_counts())]


def pattern_ordering(B: sp.spmatrix) -> np.ndarray | None:
    """CHOLMOD's fill-reducing permutation of the symmetric pattern B (the ordering its analysis
    picks, postordered), or None where its symbolic interface is not usable here. The column counts
    of that analysis are remembered for :func:`pattern_cholesky_cost` of the same pattern."""
    if SPARSE_BACKEND != "cholmod":
        return None
    S = _surrogate(sp.csr_matrix(B))
    found = cholmod_symbolic.ordering(S)
    if found is None:
        return None
    _LAST_COUNTS[:] = [(_pattern_key(S), found[0])]
    return found[1]


def _factor_column_counts(S: sp.csc_matrix) -> np.ndarray:
    """Column counts of the Cholesky factor of S (see :func:`_counts`), remembered for the last pattern."""
    if _LAST_COUNTS and _same_pattern(S, _LAST_COUNTS[0][0]):
        return _LAST_COUNTS[0][1]
    key = _pattern_key(S)
    counts = _counts(S)
    _LAST_COUNTS[:] = [(key, counts)]
    return counts


def _counts(S: sp.csc_matrix) -> np.ndarray:
    """Column counts of the Cholesky factor of S under the solver's own fill-reducing ordering.

    With CHOLMOD, from its symbolic analysis (:mod:`.cholmod_symbolic`: 3D survey 45x45x45 0.76 s
    against 5.4 s for the numeric surrogate below, the same counts). Where that interface is not
    usable, a numeric factorization of the surrogate: graphs with dense neighbourhoods (surveys:
    ≥ ``SUPERNODAL_DEGREE`` entries per column; 2D lawnmowers have 5, 3D surveys 7) fill in heavily,
    and CHOLMOD's supernodal factorization (BLAS-3) is faster there than the simplicial one (3D survey 32x32x32: 0.8 vs 3.7 s; 45x45x45 ~25 s
    simplicial; 2D lawnmower 600x600: 1.9 vs 2.3 s); its padding is
    left out by counting the numerically nonzero entries (S's values are generic, so fill does not
    cancel; far from the diagonal it can underflow, though: on the 1M-pose lawnmower 0.8 % fewer
    entries and 5 % fewer flops than the exact simplicial counts, in 7.2 s instead of 17 s). Sparse
    graphs stay simplicial, which is faster for them (262k-pose model problem: 0.05 vs 0.16 s)."""
    if SPARSE_BACKEND == "cholmod":
        counts = cholmod_symbolic.column_counts(S)
        if counts is not None:
            return counts
        from sksparse.cholmod import cholesky
        if not counted_simplicially(S):
            L = sp.csc_matrix(cholesky(S, mode="supernodal").L())
            col = np.repeat(np.arange(L.shape[1]), np.diff(L.indptr))
            return np.bincount(col[L.data != 0], minlength=L.shape[1])
        L = sp.csc_matrix(cholesky(S, mode="simplicial").LD())  # the pattern of L (D on its diagonal)
        return np.diff(L.indptr)
    lu = spla.splu(S, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True})
    return np.diff(sp.csc_matrix(lu.L).indptr)
