"""H·x from the native linearizer's source array, without H's CSR values (compiled by numba).

The source array S holds, per pose kind, the diagonal blocks' upper triangles summed per pose and one
d×d off-diagonal block per factor (or per repeated pair): all of H = Σ_f J_fᵀ J_f (paper Eq. hgn) in
~half the memory of its CSR values. The product walks the poses once and the factors once, adding
H_ij x_j and H_ijᵀ x_i: at 1M 2D poses one thread takes about as long as scipy's CSR product on two
(34-36 ms, docs/survey.md, thirty-ninth pass), and H's values, 343 MiB, are never made.
"""

from __future__ import annotations

import numpy as np

from ..util.compiled import AVAILABLE, jit  # noqa: F401 (AVAILABLE: the optimizer's test)
from ..util.threads import local_threads, on_local_thread


def warm_up(dims: tuple = (3, 6)) -> None:
    """Import numba and compile (or load from its cache: ~0.1 s each) the kernels of the block sizes
    ``dims`` on tiny arrays, with the argument types of the real calls: for a background thread, so
    that the first product does not wait for them (its Python work holds the GIL: no more than needed)."""
    x, y, ends, none, dof = np.zeros(18), np.zeros(18), np.zeros(1, np.int64), np.zeros(0, np.int64), np.zeros(1, np.int64)
    if 3 in dims:
        _diagonal_product3(np.zeros((6, 1)), np.zeros((3, 3), np.int64), x, y)            # Pose2
        _block_product3(np.zeros((9, 1)), ends, ends, none, x, y, 0, 1)
    if 6 in dims:
        _diagonal_product(np.zeros((21, 1)), np.zeros((6, 6), np.int64), dof, x, y)        # Pose3
        _block_product6(np.zeros((2, 36)).T, ends, ends, dof, x, y, 0, 1)   # (its blocks: a transposed, F-ordered view)
    bptr, one = np.array([0, 1], np.int64), np.ones(1, np.int64)
    for positions in (np.zeros(1, np.int32), np.zeros(1, np.int64)):   # (gathers' positions: either width)
        _compose_blocks(positions, np.zeros(1, np.int32), bptr, one, 3, np.zeros(1, np.int32), np.zeros(1, np.uint8),
                        np.zeros((1, 3, 3), np.int64))


@jit
def _diagonal_product(D, symk, dof, x, y):
    """y[dofs of p] = D_p x[dofs of p] for every pose p, its dofs from dof[p] on (D_p: its upper
    triangle's sums, (nsym, n))."""
    d = symk.shape[0]
    for p in range(D.shape[1]):
        o = dof[p]
        for a in range(d):
            s = 0.0
            for b in range(d):
                s += D[symk[a, b], p] * x[o + b]
            y[o + a] = s


@jit
def _diagonal_product3(D, symk, x, y):
    """:func:`_diagonal_product` for Pose2s whose dofs are 0..3n−1, unrolled (1M poses: 20 → ~5 ms)."""
    s00, s01, s02, s11, s12, s22 = symk[0, 0], symk[0, 1], symk[0, 2], symk[1, 1], symk[1, 2], symk[2, 2]
    for p in range(D.shape[1]):
        o = 3 * p
        x0, x1, x2 = x[o], x[o + 1], x[o + 2]
        h00, h01, h02, h11, h12, h22 = D[s00, p], D[s01, p], D[s02, p], D[s11, p], D[s12, p], D[s22, p]
        y[o] = h00 * x0 + h01 * x1 + h02 * x2
        y[o + 1] = h01 * x0 + h11 * x1 + h12 * x2
        y[o + 2] = h02 * x0 + h12 * x1 + h22 * x2


@jit
def _block_product6(B, ends_i, ends_j, dof, x, y, lo, hi):
    """y += H_ij x_j and H_ijᵀ x_i for the 6×6 blocks f in lo..hi−1: H_ij[a, b] = B[a·6 + b, f] between
    the poses ends_i[f] and ends_j[f], whose dofs start at dof[·] (the loops' bounds are constants, so
    the compiler unrolls them)."""
    for f in range(lo, hi):
        i = dof[ends_i[f]]
        j = dof[ends_j[f]]
        for a in range(6):
            s = 0.0
            t = 0.0
            for b in range(6):
                s += B[a * 6 + b, f] * x[j + b]
                t += B[b * 6 + a, f] * x[i + b]
            y[i + a] += s
            y[j + a] += t


@jit
def _block_product3(B, ends_i, ends_j, dof, x, y, lo, hi):
    """:func:`_block_product6` for 3×3 blocks, unrolled (at 1M 2D poses 2.5× faster than the loops)."""
    step = dof.shape[0] == 0   # no table: pose p's dofs start at 3p
    for f in range(lo, hi):
        if step:
            i = 3 * ends_i[f]
            j = 3 * ends_j[f]
        else:
            i = dof[ends_i[f]]
            j = dof[ends_j[f]]
        xi0, xi1, xi2 = x[i], x[i + 1], x[i + 2]
        xj0, xj1, xj2 = x[j], x[j + 1], x[j + 2]
        b0, b1, b2, b3, b4, b5, b6, b7, b8 = B[0, f], B[1, f], B[2, f], B[3, f], B[4, f], B[5, f], B[6, f], B[7, f], B[8, f]
        y[i] += b0 * xj0 + b1 * xj1 + b2 * xj2
        y[i + 1] += b3 * xj0 + b4 * xj1 + b5 * xj2
        y[i + 2] += b6 * xj0 + b7 * xj1 + b8 * xj2
        y[j] += b0 * xi0 + b3 * xi1 + b6 * xi2
        y[j + 1] += b1 * xi0 + b4 * xi1 + b7 * xi2
        y[j + 2] += b2 * xi0 + b5 * xi1 + b8 * xi2


@jit
def _compose_blocks(positions, out, bptr, rowlen, d, bsrc, btype, coef):
    """out[t] = the source position of H's CSR entry positions[t], for d×d blocks everywhere: block row v
    holds entries [bptr[v]·d², bptr[v+1]·d²), dof row a of it rowlen[v]·d of them, block k's entry (a, b)
    reads bsrc[k] + coef[btype[k], a, b]. The block row is searched only when a position leaves the last
    one (positions mostly come row after row)."""
    nv = bptr.shape[0] - 1
    dd = d * d
    v = 0
    for t in range(positions.shape[0]):
        p = positions[t]
        if p < bptr[v] * dd or p >= bptr[v + 1] * dd:
            lo, hi = 0, nv
            while hi - lo > 1:
                mid = (lo + hi) // 2
                if bptr[mid] * dd <= p:
                    lo = mid
                else:
                    hi = mid
            v = lo
        q = p - bptr[v] * dd
        width = rowlen[v] * d
        a = q // width
        r = q - a * width
        kk = r // d
        k = bptr[v] + kk
        out[t] = bsrc[k] + coef[btype[k], a, r - kk * d]


class BlockSourceMap:
    """Where each of H's CSR entries sits in the source array, from one number per block instead of one
    per entry (uniform d×d blocks: 1M 2D poses, 25 MB for 172 MB): block k of the pattern reads
    ``bsrc[k] + coef[btype[k]]``. Used as a GatheredCSR's index (:meth:`compose`)."""

    def __init__(self, bptr: np.ndarray, rowlen: np.ndarray, d: int, bsrc: np.ndarray, btype: np.ndarray,
                 coef: np.ndarray, nnz: int):
        self.bptr, self.rowlen, self.d = bptr, rowlen, d
        self.bsrc, self.btype, self.coef, self.nnz = bsrc, btype, coef, nnz
        self.dtype = bsrc.dtype

    def compose(self, positions: np.ndarray) -> np.ndarray:
        """Source positions of the entries at ``positions`` (any order; fastest row after row)."""
        positions = np.ascontiguousarray(positions)
        out = np.empty(len(positions), dtype=self.dtype)
        if len(positions):
            _compose_blocks(positions, out, self.bptr, self.rowlen, self.d, self.bsrc, self.btype, self.coef)
        return out

    def entries(self, lo: int, hi: int) -> np.ndarray:
        """Source positions of the entries lo..hi−1."""
        return self.compose(np.arange(lo, hi, dtype=np.int64))

    @property
    def nbytes(self) -> int:
        return self.bsrc.nbytes + self.btype.nbytes + self.coef.nbytes


class FactorProduct:
    """x ↦ H x from one source array: per kind the diagonal sums and the off-diagonal blocks (views),
    with each pose's first dof (an empty table: Pose2 dofs 0..3n−1). From ``THREADED_FROM`` blocks' entries the
    blocks are split between the local threads (the kernels release the GIL), the second half summed
    into its own vector."""

    THREADED_FROM = 2_000_000   # entries of the off-diagonal blocks (as scipy's threaded product, spmv.py)

    def __init__(self, n: int, diagonals: list, blocks: list):
        self.n, self.diagonals, self.blocks = n, diagonals, blocks

    def _diagonals(self, x, y):
        for D, symk, dof in self.diagonals:
            if len(dof) == 0:
                _diagonal_product3(D, symk, x, y)
            else:
                _diagonal_product(D, symk, dof, x, y)

    @staticmethod
    def _blocks(block, x, y, lo, hi):
        B, ei, ej, dof = block
        if B.shape[0] == 9:
            _block_product3(B, ei, ej, dof, x, y, lo, hi)
        else:
            _block_product6(B, ei, ej, dof, x, y, lo, hi)

    def __call__(self, x: np.ndarray) -> np.ndarray:
        y = np.empty(self.n)
        self._diagonals(x, y)
        entries = sum(block[0].shape[0] * block[0].shape[1] for block in self.blocks)
        if entries < self.THREADED_FROM or on_local_thread():
            for block in self.blocks:
                self._blocks(block, x, y, 0, block[0].shape[1])
            return y
        z = np.zeros(self.n)

        def half(second: bool):
            out = z if second else y
            for block in self.blocks:
                cut = block[0].shape[1] // 2
                self._blocks(block, x, out, cut if second else 0, block[0].shape[1] if second else cut)

        job = local_threads().submit(half, True)
        try:
            half(False)
        finally:
            job.result()
        y += z
        return y
