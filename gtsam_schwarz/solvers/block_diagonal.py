"""All subdomain solves at once: one factorization of diag(A_1, …, A_N), A_i = R_i A R_iᵀ.

Subdomain i is an index set I_i (paper Sec. 3.1); R_i extracts its dofs. Stacking the R_i gives
one gather ``x[indices]``; the block-diagonal matrix of all local matrices is factorized once and
every application of Σ R_iᵀ A_i⁻¹ R_i is one gather, one solve and one scatter-add — no Python
loop over subdomains. Blocks never couple, so each could equally be factorized on its own process.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from ..util import as_csr, vertex_dofs
from ..util.gathered import entries
from ..util.threads import WORKERS, local_threads, on_local_thread, run_all
from . import block_cholesky
from .base import SingularLocalMatrixError
from .cost import pattern_ordering, vertex_pattern
from .factory import KEEPS_ANALYSIS, factorize_local
from .gather import Gather, block_positions, vertex_level, sharing_vertex_level


def block_diagonal(A: sp.spmatrix, sets) -> sp.csr_matrix:
    """diag(R_1 A R_1ᵀ, …, R_N A R_Nᵀ) as one sparse matrix (couplings between blocks dropped);
    ``sets`` is an :class:`~gtsam_schwarz.dd.IndexSets`."""
    A = as_csr(A)
    m = len(sets.indices)
    blk = sets.block_of_entry()
    position = np.full(sets.n, -1, dtype=np.int64)
    position[sets.indices] = np.arange(m)
    if np.count_nonzero(position >= 0) == m:  # disjoint sets (no overlap): select A's entries, no product
        block = np.full(sets.n, -1, dtype=np.int64)
        block[sets.indices] = blk
        rows = np.repeat(np.arange(A.shape[0]), np.diff(A.indptr))
        keep = (block[rows] >= 0) & (block[rows] == block[A.indices])
        return sp.csr_matrix((A.data[keep], (position[rows[keep]], position[A.indices[keep]])), shape=(m, m))
    if sets.vertices is not None:
        B = _block_diagonal_by_vertices(A, sets)
        if B is not None:
            return B
    R = sets.restriction()
    C = (R @ A @ R.T).tocoo()
    keep = blk[C.row] == blk[C.col]
    return sp.csr_matrix((C.data[keep], (C.row[keep], C.col[keep])), shape=(m, m))


def block_diagonal_positions(A: sp.csr_matrix, sets) -> sp.csr_matrix | None:
    """The pattern of :func:`block_diagonal` (A, sets) with, as its numbers, the position in A.data of
    every entry, for sets of whole vertices and one d×d block size (H of a pose graph): no matrix of
    positions as large as A is formed per chunk, and the entries' positions come from a BSR pattern
    (lawnmower 600x600, the one-level blocks' three chunks of 17.5M entries: 1.39 against 2.27 s in
    a run). None where that does not apply."""
    if sets.vertices is None:
        return None
    dims = np.diff(sets.offsets)
    if not (len(dims) and np.all(dims == dims[0])):
        return None
    return _block_diagonal_by_vertices(as_csr(A), sets, positions=True)


def _block_diagonal_by_vertices(A: sp.csr_matrix, sets, positions: bool = False) -> sp.csr_matrix | None:
    """:func:`block_diagonal` for sets of whole vertices and a matrix made of whole dense vertex
    blocks (H is): the product R A Rᵀ is formed on the vertex pattern (a 9th or 36th of the entries
    for Pose2 / Pose3 blocks) and every kept vertex block is expanded to its dof entries, rows in
    order (CSR with sorted indices, no sort). None when A is not block-dense. ``positions`` (one
    block size): the entries' positions in A.data instead of their numbers."""
    offsets = sets.offsets
    dims = np.diff(offsets)
    nv = len(dims)
    level = vertex_level(A, offsets)
    if level is None:
        return None  # not whole blocks: the dof-level product
    V, col_start = level
    Bv = block_diagonal(V, type(sets)(indices=sets.vertices, ptr=sets.vertex_ptr, n=nv))  # vertex-level sets
    Bv.sort_indices()
    entry = Bv.data.astype(np.int64) - 1
    vert = sets.vertices
    if nv and np.all(dims == dims[0]):   # one block size: B is the BSR matrix of A's blocks (u, v) kept in Bv
        P = block_positions(A, Bv, entry, vert, offsets, col_start, int(dims[0]))
        if positions:
            return P
        B = sp.csr_matrix((entries(A, P.data), P.indices, P.indptr), shape=P.shape, copy=False)
        B.has_sorted_indices = True
        return B
    dpos = np.cumsum(dims[vert]) - dims[vert]  # dof position of every vertex position
    # 1) each vertex row's entries expanded by the column block's width: dof columns and the
    #    offset of each in the dof rows of A (same for every dof row of the vertex)
    dv = dims[vert[Bv.indices]]
    first = np.cumsum(dv) - dv
    c = np.arange(int(dv.sum())) - np.repeat(first, dv)
    seg_cols = np.repeat(dpos[Bv.indices], dv) + c
    seg_src = np.repeat(col_start[entry], dv) + c
    seg_ptr = np.r_[0, np.cumsum(np.add.reduceat(dv, Bv.indptr[:-1]) * (np.diff(Bv.indptr) > 0))] \
        if Bv.nnz else np.zeros(Bv.shape[0] + 1, dtype=np.int64)
    # 2) dof row a of vertex position P repeats P's segment, reading A's row offsets[u] + a
    #    (entry-sized arrays in int32 where they fit and dropped as soon as used: they are the
    #    peak of a 3D build, nnz(B) ≈ 1.4·nnz(H))
    du = dims[vert]
    row_vertex_pos = np.repeat(np.arange(len(vert)), du)
    a = np.arange(len(row_vertex_pos)) - np.repeat(dpos, du)
    lengths = (seg_ptr[1:] - seg_ptr[:-1])[row_vertex_pos]
    indptr = np.r_[0, np.cumsum(lengths)]
    nnz = int(indptr[-1])
    m = len(sets.indices)
    small = max(nnz, A.nnz, len(seg_cols), m) < 2**31 - 1
    itype = np.int32 if small else np.int64
    base = np.repeat((seg_ptr[:-1][row_vertex_pos] - indptr[:-1]).astype(itype), lengths)
    base += np.arange(nnz, dtype=itype)  # the entry's place in its vertex row's segment
    src = np.repeat((A.indptr[offsets[vert[row_vertex_pos]] + a]).astype(itype), lengths)
    src += seg_src.astype(itype, copy=False)[base]
    data = entries(A, src)
    del src
    cols = seg_cols.astype(itype, copy=False)[base]
    del base
    B = sp.csr_matrix((data, cols, indptr.astype(itype)), shape=(m, m), copy=False)
    B.has_sorted_indices = True
    return B


class _BlockDiagonalGather(Gather):
    """:func:`block_diagonal` (A, sets) as a gather, its positions found directly where
    :func:`block_diagonal_positions` applies."""

    def __init__(self, sets):
        super().__init__(lambda M: block_diagonal(M, sets))
        self.sets = sets

    def _positions(self, A: sp.csr_matrix):
        P = block_diagonal_positions(A, self.sets)
        if P is None:
            return super()._positions(A)
        return P.data, P.indices, P.indptr, P.shape


def vertex_block_order(vertices: sp.spmatrix, sets) -> tuple | None:
    """(B, perm): the vertex pattern B of diag(A_1, …, A_N) for index sets of whole vertices (``vertices``:
    A's vertex pattern) and CHOLMOD's fill-reducing permutation of it, or None where its symbolic
    interface is not usable. Symbolic only: it may be found before A has numbers."""
    nv = len(sets.offsets) - 1
    blocks = block_diagonal(vertices, type(sets)(indices=sets.vertices, ptr=sets.vertex_ptr, n=nv))
    perm = pattern_ordering(blocks)
    return None if perm is None else (blocks, perm)


class BlockDiagonalSolver:
    """Applies Σ_i R_iᵀ A_i⁻¹ R_i for the index sets ``sets`` (one-level additive Schwarz).

    Blocks that are all the same small size (block-Jacobi: one pose each) are inverted as a dense
    batch; anything else is sparse Cholesky of the block-diagonal matrix, in chunks of consecutive
    subdomains of about ``CHUNK_ENTRIES`` entries each (one factor per chunk: only the gathered
    matrices of the two chunks being factorized, one per local thread, exist beside the factors; one
    block of all chunks held 250 MB more at the peak at 91 125 3D poses). The
    symbolic work (gather positions, ordering) is done on the first :meth:`update`; later ones with
    a matrix of the same pattern only refactor numerically. Sets of whole vertices are first put in
    a fill-reducing order (:meth:`order_vertices`) and factorized in it.
    """

    DENSE_MAX = 12
    threaded = True  # simplicial chunks solved on the local threads (util.threads)
    # False: each chunk's gather positions (B's pattern and where its entries sit in A, 8 bytes per
    # entry: 383 MiB at 1M 2D poses) are dropped once its B is gathered, the factor's analysis kept;
    # the next update finds them again. For a caller short of memory whose factors are seldom renewed.
    keep_positions = True
    CHUNK_ENTRIES = 8_000_000  # entries of A in the rows of one chunk (an upper bound of its block's)
    # for a matrix of BLOCK_FROM entries or more, the chunks' factors by vertex blocks, their numbers in
    # factor_dtype (env GTSAM_SCHWARZ_BLOCK_FACTOR = float32 / float64 / none); CHOLMOD's simplicial
    # factors (12 bytes per entry of L) below, or with None. At 1M 2D lawnmower poses the one-level
    # factors 684 → 272 MiB in single precision, the same CG counts. Below, numba's import (~130 MiB,
    # ~1 s) is not worth it, and single precision changes CG's counts where they are few and exact: the
    # paper's bar chain, 4 subdomains, 7 → 9 one-level iterations (a local solve's forward error 6e-6)
    factor_dtype = block_cholesky.PRECISION
    BLOCK_FROM = 4_000_000

    def __init__(self, sets, A: sp.spmatrix | None = None):
        self.sets = sets
        self.n = sets.n
        sizes = sets.sizes
        self._dense = None
        self._chunks = None  # [(lo, hi, Gather, factor)]: local rows lo:hi, their blocks and factor
        self._dense_blocks = bool(sets.count and sizes.min() == sizes.max() and sizes[0] <= self.DENSE_MAX)
        self.ordered = None  # None: not decided; True: the sets are in a fill-reducing order (factorized in it)
        self._vertex_blocks = None  # the vertex pattern of diag(A_i) that order_vertices analysed, until taken
        if A is not None:
            self.update(A)

    def _plan_chunks(self, A: sp.csr_matrix) -> list:
        """Consecutive subdomains grouped into equal shares of A's rows' entries, at most about
        CHUNK_ENTRIES each, as many as a multiple of the local threads (each thread then factorizes
        and solves the same amount; shares cut at CHUNK_ENTRIES left the last chunk a fraction of
        the others for one thread alone)."""
        sets = self.sets
        row_nnz = np.diff(A.indptr)
        per_set = np.bincount(sets.block_of_entry(), weights=row_nnz[sets.indices], minlength=sets.count)
        total = float(per_set.sum())
        count = int(np.ceil(total / self.CHUNK_ENTRIES)) if total > 0 else 1
        if count > 1:
            count = -(-count // WORKERS) * WORKERS
        middle = np.cumsum(per_set) - 0.5 * per_set   # a subdomain goes where its middle entry falls
        chunk = np.minimum((middle * (count / max(total, 1.0))).astype(np.int64), count - 1)
        cuts = np.r_[0, np.flatnonzero(np.diff(chunk)) + 1, sets.count]
        cuts = np.unique(cuts)
        chunks = []
        for j0, j1 in zip(cuts[:-1], cuts[1:]):
            part = sets.subsets(int(j0), int(j1))
            chunks.append([int(sets.ptr[j0]), int(sets.ptr[j1]), _BlockDiagonalGather(part), None])
        return chunks

    def order_vertices(self, A: sp.spmatrix, ahead=None) -> bool:
        """Put every set's vertices in the fill-reducing order of CHOLMOD's analysis of the vertex
        pattern of diag(A_1, …, A_N) (before the first :meth:`update`); the blocks are then factorized
        in their own order. The vertex level has a d²-th of the entries: lawnmower 600x600, the
        one-level blocks' analyses 0.13 against 0.7 s, the same nnz(L), solves 26 against 34 ms (the
        factor's rows in the gathered order). ``ahead``: :func:`vertex_block_order` of these sets and
        A's vertex pattern, found earlier (or a Future of it). Returns whether the sets were reordered
        (sets of whole vertices, sparse blocks, CHOLMOD's symbolic interface usable)."""
        if self.ordered is not None:
            return self.ordered
        sets = self.sets
        self.ordered = False
        if self._dense_blocks or sets.vertices is None or self._chunks is not None or not sets.count:
            return False
        if ahead is None:
            found = vertex_block_order(vertex_pattern(as_csr(A), sets.offsets), sets)
        else:
            found = ahead.result() if hasattr(ahead, "result") else ahead
        if found is None:
            return False
        blocks, perm = found
        if blocks.shape[0] != len(sets.vertices):
            raise ValueError(f"the blocks' order found ahead has {blocks.shape[0]} vertices, the sets {len(sets.vertices)}")
        self._vertex_blocks = blocks
        rank = np.empty_like(perm)
        rank[perm] = np.arange(len(perm))
        # the blocks never couple, so the permutation keeps every set's positions together: sort within sets
        block = np.repeat(np.arange(sets.count), np.diff(sets.vertex_ptr))
        vertices = sets.vertices[np.lexsort((rank, block))]
        self.sets = type(sets)(indices=vertex_dofs(vertices, sets.offsets), ptr=sets.ptr, n=sets.n, vertices=vertices,
                               vertex_ptr=sets.vertex_ptr, offsets=sets.offsets)
        self.ordered = True
        return True

    def take_vertex_blocks(self):
        """The vertex pattern of diag(A_1, …, A_N) in the sets' original order, as :meth:`order_vertices`
        analysed it (None if it did not), handed over once: the memory estimate of the same blocks
        needs it (1M 2D poses: 0.5 s to form again)."""
        blocks, self._vertex_blocks = self._vertex_blocks, None
        return blocks

    def prepare(self, A: sp.spmatrix) -> None:
        """The symbolic work of :meth:`update` for A's pattern (chunks and their gather positions),
        without numbers: a caller may run it on another thread ahead of the update."""
        A = as_csr(A)
        if not self._dense_blocks:
            self._prepare(A)

    def _prepare(self, A: sp.csr_matrix) -> tuple:
        """(A as the chunks' gathers read it, whether each chunk needs a fresh analysis)."""
        if self._chunks is None:
            self.order_vertices(A)
            self._chunks = self._plan_chunks(A)
        fresh = []
        with sharing_vertex_level():   # the chunks share A's vertex level while finding positions
            for chunk in self._chunks:   # the positions (symbolic) one chunk after the other
                A, same = chunk[2].renew(A)
                fresh.append(chunk[3] is None or not same)
                if fresh[-1]:
                    chunk[3] = None
        return A, fresh

    def update(self, A: sp.spmatrix) -> "BlockDiagonalSolver":
        """Refactor for new numbers in A (symbolic work is reused while A's pattern is unchanged)."""
        A = as_csr(A)
        if self._dense_blocks:
            s = int(self.sets.sizes[0])
            idx = self.sets.indices.reshape(-1, s)
            blocks = np.asarray(A[idx[:, :, None].repeat(s, 2).ravel(),
                                  idx[:, None, :].repeat(s, 1).ravel()]).reshape(-1, s, s)
            try:
                self._dense = np.linalg.inv(blocks)
            except np.linalg.LinAlgError:
                raise SingularLocalMatrixError("a diagonal block is singular") from None
            if not np.all(np.isfinite(self._dense)):
                raise SingularLocalMatrixError("a diagonal block is singular")
            return self
        A, fresh = self._prepare(A)

        def job(chunk, new):   # gathered, then factorized: one chunk's matrix per thread at a time
            B = chunk[2](A)
            if not self.keep_positions:
                chunk[2].forget()
            self._factorize(chunk, B, new, A.nnz)

        jobs = [lambda c=c, f=f: job(c, f) for c, f in zip(self._chunks, fresh)]
        if self.threaded and len(jobs) > 1 and not on_local_thread():
            run_all(local_threads(), jobs)   # two chunks factorized side by side (CHOLMOD holds no GIL)
        else:
            for j in jobs:
                j()
        return self

    def _factorize(self, chunk: list, B: sp.csr_matrix, fresh: bool, nnz: int) -> None:
        """Chunk's factor of B: refactorized, or (``fresh``) analysed first. Simplicial factors (CHOLMOD's
        choice for such blocks) go through :mod:`.cholmod_native` where it works, so that
        :meth:`matvec` can solve the chunks on the local threads; the others through scikit-sparse.
        :meth:`update` runs this on the local threads, two chunks at a time (1M 2D poses, the seven
        chunks' refactorization 1.27 s one after the other, 0.8 s two at a time)."""
        if fresh:
            chunk[3] = self._local_factor(B, nnz)
        else:
            chunk[3].refactor(B)

    def block_dtype(self, nnz: int):
        """The block factors' precision for a matrix of ``nnz`` entries (None: not by blocks)."""
        return self.factor_dtype if nnz >= self.BLOCK_FROM else None

    def _local_factor(self, B: sp.csr_matrix, nnz: int):
        """A chunk's factor: by dense vertex blocks where the sets are whole vertices of one size in a
        fill-reducing order (:func:`.factorize_local`, in :meth:`block_dtype` of A's ``nnz``)."""
        return factorize_local(B, "a subdomain matrix", natural=bool(self.ordered), dense=False,
                               block=block_cholesky.vertex_block(self.sets.offsets) if self.sets.vertices is not None else None,
                               block_dtype=self.block_dtype(nnz))

    def release(self) -> None:
        """Drop the numeric factorizations (to bound the memory); the next :meth:`update` refactorizes
        with the symbolic analyses kept."""
        for chunk in self._chunks or ():
            if isinstance(chunk[3], KEEPS_ANALYSIS):
                chunk[3].release_numeric()
            else:
                chunk[3] = None
        self._dense = None

    def matvec(self, x: np.ndarray) -> np.ndarray:
        indices = self.sets.indices
        if self._dense is not None:
            s = self._dense.shape[1]
            yl = np.einsum("bij,bj->bi", self._dense, x[indices].reshape(-1, s)).ravel()
        elif len(self._chunks) == 1:
            yl = self._chunks[0][3].solve(x[indices])
        else:
            yl = np.empty(len(indices), dtype=x.dtype)

            def solve(lo, hi, factor):   # each chunk gathers its own rows of x (beside the other's solve)
                yl[lo:hi] = factor.solve(x[indices[lo:hi]])

            jobs = [lambda c=c: solve(c[0], c[1], c[3]) for c in self._chunks]
            if self.threaded and all(getattr(c[3], "releases_gil", False) for c in self._chunks):
                run_all(local_threads(), jobs)   # the chunks' solves side by side (no GIL held)
            else:
                for job in jobs:
                    job()
        return np.bincount(indices, weights=yl, minlength=self.n)
