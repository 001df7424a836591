"""H·x from the native linearizer's source array, without H's CSR values (compiled by numba).

The source array S holds, per pose kind, the diagonal blocks' upper triangles summed per pose and one
d×d off-diagonal block per factor (or per repeated pair): all of H = Σ_f J_fᵀ J_f (paper Eq. hgn) in
~half the memory of its CSR values. The product walks the poses once and the factors once, adding
H_ij x_j and H_ijᵀ x_i: at 1M 2D poses one thread takes about as long as scipy's CSR product on two
(34-36 ms, docs/survey.md, thirty-ninth pass), and H's values, 343 MiB, are never made.
"""

from __future__ import annotations

import numpy as np

from ..util.threads import local_threads, on_local_thread

try:   # compiled kernels; without numba the linearizer keeps H's CSR values
    import numba
except ImportError:  # pragma: no cover - numba is a dependency; a build without it still runs
    numba = None

AVAILABLE = numba is not None


def _jit(f):
    return numba.njit(cache=True, nogil=True)(f) if AVAILABLE else f


@_jit
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


@_jit
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


@_jit
def _block_product(B, ends_i, ends_j, dof, x, y, lo, hi):
    """y += H_ij x_j and H_ijᵀ x_i for every block f: H_ij[a, b] = B[a·d + b, f] between the poses
    ends_i[f] and ends_j[f], whose dofs start at dof[·]."""
    d = 6 if B.shape[0] == 36 else 3
    for f in range(lo, hi):
        i = dof[ends_i[f]]
        j = dof[ends_j[f]]
        for a in range(d):
            s = 0.0
            t = 0.0
            for b in range(d):
                s += B[a * d + b, f] * x[j + b]
                t += B[b * d + a, f] * x[i + b]
            y[i + a] += s
            y[j + a] += t


@_jit
def _block_product3(B, ends_i, ends_j, dof, x, y, lo, hi):
    """:func:`_block_product` for 3×3 blocks, unrolled (at 1M 2D poses 2.5× faster than the loops)."""
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


class FactorProduct:
    """x ↦ H x from one source array: per kind the diagonal sums and the off-diagonal blocks (views),
    with each pose's first dof (an empty table: Pose2 dofs 0..3n−1). From ``THREADED_FROM`` blocks the
    blocks are split between the local threads (the kernels release the GIL), the second half summed
    into its own vector."""

    THREADED_FROM = 500_000

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
            _block_product(B, ei, ej, dof, x, y, lo, hi)

    def __call__(self, x: np.ndarray) -> np.ndarray:
        y = np.empty(self.n)
        self._diagonals(x, y)
        m = sum(block[0].shape[1] for block in self.blocks)
        if m < self.THREADED_FROM or on_local_thread():
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
