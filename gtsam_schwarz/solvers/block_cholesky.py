"""Sparse block Cholesky K = L Lᵀ of an SPD matrix made of dense d×d vertex blocks, in its own order.

The Hessian of a pose graph and every matrix gathered from it by whole poses (the one-level blocks
diag(A_1, …, A_N), paper Sec. 3.1) is made of dense d×d blocks (d = 3 for Pose2, 6 for Pose3). Its
Cholesky factor, in an order of whole vertices, is too: every block of L is dense, so L needs one row
index per block instead of one per entry. The factor's blocks are stored in ``dtype`` (single
precision by default): the preconditioner applies the exact inverse of L̃ L̃ᵀ, with L̃ the factor
rounded as it is computed, an SPD matrix whatever the rounding (its diagonal blocks are the Cholesky
factors of the updated blocks, checked positive definite). At 1M 2D poses the one-level factors take
4.4 bytes per entry of L instead of CHOLMOD's simplicial 12 (docs/survey.md, forty-second pass).

The symbolic analysis (elimination tree, the block pattern of L) is done once per pattern; the
numbers by a left-looking block factorization. Kernels compiled by numba (:mod:`..util.compiled`);
they hold no GIL, so two factors are factorized and solved side by side on the local threads.
"""

from __future__ import annotations

import os
import threading

import numpy as np
import scipy.sparse as sp

from ..util.compiled import AVAILABLE, jit
from ..util.threads import WORKERS, run_all
from .base import SingularLocalMatrixError, check_finite


def _precision():
    """The block factors' default precision: env GTSAM_SCHWARZ_BLOCK_FACTOR = float32 (the default),
    float64, or none (CHOLMOD's simplicial factors instead); None where numba is missing."""
    choice = os.environ.get("GTSAM_SCHWARZ_BLOCK_FACTOR", "float32").strip().lower()
    if not AVAILABLE or choice in ("none", "0", "cholmod"):
        return None
    if choice not in ("float32", "float64"):
        raise ValueError(f"GTSAM_SCHWARZ_BLOCK_FACTOR: {choice!r} is none of float32, float64, none")
    return np.dtype(choice)


PRECISION = _precision()


def vertex_block(offsets: np.ndarray | None) -> int | None:
    """d where every vertex of ``offsets`` (dof offsets) has d dofs, else None."""
    if offsets is None or len(offsets) < 2:
        return None
    dims = np.diff(offsets)
    return int(dims[0]) if np.all(dims == dims[0]) else None


def warm_up(d: int, dtype) -> None:
    """Import numba and compile (or load from its cache) the kernels for d×d blocks in ``dtype`` with
    the argument types of the real calls (32-bit indices), on a tiny matrix: for a background thread,
    so that the first factorization does not wait for them."""
    K = sp.csr_matrix(np.eye(2 * d) + 0.1)
    K.indptr, K.indices = K.indptr.astype(np.int32), K.indices.astype(np.int32)
    F = BlockCholesky(K, d, "a warm-up matrix", dtype=dtype)
    F.solve(np.ones(2 * d))
    F.solve(np.ones((2 * d, 2)))


def warm_up_later(d: int | None, dtype) -> threading.Thread | None:
    """:func:`warm_up` on a thread of its own (None: nothing to do for ``d`` / ``dtype``)."""
    if not d or dtype is None or not AVAILABLE:
        return None
    thread = threading.Thread(target=warm_up, args=(d, dtype), name="gtsam-schwarz-block-kernels", daemon=True)
    thread.start()
    return thread


def bytes_per_entry(d: int, dtype) -> float:
    """Bytes a :class:`BlockCholesky` holds per entry of L: its number, and one row index per d×d block."""
    return np.dtype(dtype).itemsize + 4.0 / (d * d)


def applies(K: sp.spmatrix, d: int | None) -> bool:
    """Whether K (CSR, sorted indices) is made of whole dense d×d blocks that :class:`BlockCholesky` takes."""
    n = K.shape[0]
    if not AVAILABLE or not d or n % d or K.shape[1] != n or not sp.isspmatrix_csr(K) or not K.has_sorted_indices:
        return False
    return bool(_whole_blocks(K.indptr, K.indices, d))


class BlockCholesky:
    """K = L Lᵀ for a symmetric positive definite K of dense d×d blocks (both triangles stored, CSR with
    sorted indices), in K's own order (already fill-reducing); L's blocks in ``dtype``. The pattern is
    analysed once; :meth:`refactor` takes new numbers of the same pattern."""

    releases_gil = True   # factorizations and solves run side by side on the local threads

    def __init__(self, K: sp.spmatrix, d: int, what: str = "local matrix", dtype=np.float32, factor: bool = True):
        K = sp.csr_matrix(K) if not sp.isspmatrix_csr(K) else K
        if not applies(K, d):
            raise ValueError(f"{what} is not made of whole sorted {d}×{d} blocks")
        self.what, self.d, self.dtype = what, d, np.dtype(dtype)
        self.n, self.nnz_K = K.shape[0], K.nnz
        self.nv = self.n // d
        parent = _elimination_tree(K.indptr, K.indices, d, self.nv)
        self.Lp, self.Li = _block_pattern(K.indptr, K.indices, d, self.nv, parent)   # blocks below the diagonal
        self._Lx = self._Ld = None
        if factor:
            self.refactor(K)

    @property
    def nnz_blocks(self) -> int:
        """Blocks of L, its diagonal blocks included."""
        return int(self.Lp[-1]) + self.nv

    @property
    def nnz(self) -> int:
        """Entries of L as a scalar factor would hold them (the diagonal blocks' lower triangles)."""
        d = self.d
        return int(self.Lp[-1]) * d * d + self.nv * d * (d + 1) // 2

    @property
    def nbytes(self) -> int:
        """Bytes the factor holds with its numbers."""
        return int(self.Lp.nbytes + self.Li.nbytes) + self.nnz_blocks * self.d * self.d * self.dtype.itemsize

    @property
    def has_numeric(self) -> bool:
        return self._Lx is not None

    def refactor(self, K: sp.spmatrix) -> "BlockCholesky":
        """Factorize new numbers of the analysed pattern."""
        K = sp.csr_matrix(K) if not sp.isspmatrix_csr(K) else K
        check_finite(K, self.what)
        d, nv = self.d, self.nv
        if K.shape[0] != self.n or K.nnz != self.nnz_K:
            raise ValueError(f"{self.what}: {K.shape[0]} rows and {K.nnz} entries, the analysis had {self.n} and {self.nnz_K}")
        self._Lx = self._Ld = None   # the old numbers go before the new ones are made
        Lx = np.empty((int(self.Lp[-1]), d, d), dtype=self.dtype)
        Ld = np.empty((nv, d, d), dtype=self.dtype)
        failed = _factorize(K.indptr, K.indices, K.data, d, self.Lp, self.Li, Lx, Ld)
        if failed:
            raise SingularLocalMatrixError(f"{self.what} is not positive definite (block {failed - 1})")
        self._Lx, self._Ld = Lx, Ld
        return self

    def solve(self, b: np.ndarray, pool=None) -> np.ndarray:
        """x with L Lᵀ x = b (b: (n,) or (n, k)); ``pool`` (:func:`~gtsam_schwarz.util.threads.local_threads`):
        the columns of b in as many blocks as it has workers, solved side by side (the same numbers)."""
        if self._Lx is None:
            raise RuntimeError(f"{self.what}: the factor's numbers were released")
        b = np.asarray(b, dtype=np.float64)
        B = b.reshape(self.n, -1)
        k = B.shape[1]
        parts = min(k, WORKERS) if pool is not None else 1
        if parts == 1:
            x = np.array(B, order="C", copy=True)
            self._solve_into(x)
            return x.reshape(b.shape)
        out = np.empty(B.shape)
        cuts = np.linspace(0, k, parts + 1).astype(int)

        def part(c0, c1):   # each block of columns solved in a C-ordered copy of its own
            x = np.array(B[:, c0:c1], order="C", copy=True)
            self._solve_into(x)
            out[:, c0:c1] = x

        run_all(pool, [lambda c0=c0, c1=c1: part(c0, c1) for c0, c1 in zip(cuts[:-1], cuts[1:])])
        return out.reshape(b.shape)

    def _solve_into(self, x: np.ndarray) -> None:
        """x ← (L Lᵀ)⁻¹ x for a C-ordered (n, k) x."""
        one = _ONE_COLUMN.get(self.d)
        if one is not None and x.shape[1] == 1:
            one(self.Lp, self.Li, self._Lx, self._Ld, x.reshape(-1))
        else:
            _solve(self.Lp, self.Li, self._Lx, self._Ld, x)

    __call__ = solve

    def release_numeric(self) -> None:
        """Free the factor's numbers and keep its analysis (the next :meth:`refactor` fills it again)."""
        self._Lx = self._Ld = None


@jit
def _whole_blocks(indptr, indices, d):
    """Whether every row's columns come in whole aligned blocks of d in ascending order, the d rows of a
    block row alike, the diagonal block present (the flag ``has_sorted_indices`` is not trusted)."""
    n = indptr.shape[0] - 1
    for I in range(n // d):
        r0 = indptr[d * I]
        length = indptr[d * I + 1] - r0
        if length % d != 0:
            return False
        diagonal = False
        for k in range(length):
            c = indices[r0 + k]
            if k % d == 0:
                if c % d != 0 or (k > 0 and c <= indices[r0 + k - 1]):   # aligned, the blocks ascending
                    return False
                if c // d == I:
                    diagonal = True
            elif c != indices[r0 + k - 1] + 1:
                return False
            for r in range(1, d):
                s = indptr[d * I + r]
                if indptr[d * I + r + 1] - s != length or indices[s + k] != c:
                    return False
        if not diagonal:
            return False
    return True


@jit
def _elimination_tree(indptr, indices, d, nv):
    """parent[J] in the elimination tree of the block pattern (−1 at roots), from each block row's
    blocks left of the diagonal (Liu's algorithm with path compression)."""
    parent = np.full(nv, -1, np.int64)
    ancestor = np.full(nv, -1, np.int64)
    for I in range(nv):
        for k in range(indptr[d * I], indptr[d * I + 1], d):
            K = indices[k] // d
            if K >= I:
                break
            while K != -1 and K < I:
                nxt = ancestor[K]
                ancestor[K] = I
                if nxt == -1:
                    parent[K] = I
                K = nxt
    return parent


@jit
def _block_pattern(indptr, indices, d, nv, parent):
    """(Lp, Li): L's blocks below the diagonal by block column, rows ascending. Row I of L holds the
    vertices on the tree paths from each K < I with K_IK ≠ 0 up to I (the row subtree), counted, then
    filled in increasing I."""
    mark = np.full(nv, -1, np.int64)
    count = np.zeros(nv + 1, np.int64)
    for sweep in range(2):
        if sweep == 1:
            Lp = np.zeros(nv + 1, np.int64)
            for J in range(nv):
                Lp[J + 1] = Lp[J] + count[J]
            Li = np.empty(Lp[nv], np.int32)
            fill = Lp[:nv].copy()
            mark[:] = -1
        for I in range(nv):
            mark[I] = I
            for k in range(indptr[d * I], indptr[d * I + 1], d):
                K = indices[k] // d
                if K >= I:
                    break
                while mark[K] != I:
                    mark[K] = I
                    if sweep == 0:
                        count[K] += 1
                    else:
                        Li[fill[K]] = I
                        fill[K] += 1
                    K = parent[K]
    return Lp, Li


@jit
def _factorize(indptr, indices, data, d, Lp, Li, Lx, Ld):
    """Left-looking block Cholesky: for each block column J, K's blocks (rows ≥ J) less Σ_K L_·K L_JKᵀ
    over the columns K with a block in row J (linked lists by next row, as in CSparse's cs_chol), the
    diagonal block's Cholesky factor C_J, then L_IJ = W_I C_J⁻ᵀ. Returns 0, or J + 1 where C_J fails."""
    nv = Lp.shape[0] - 1
    W = np.zeros((nv, d, d))
    head = np.full(nv, -1, np.int64)
    nxt = np.full(nv, -1, np.int64)
    pos = np.zeros(nv, np.int64)
    C = np.zeros((d, d))
    for J in range(nv):
        r0 = indptr[d * J]
        for k in range(r0, indptr[d * J + 1], d):   # K's column J below the diagonal: row J's blocks, transposed
            I = indices[k] // d
            if I < J:
                continue
            off = k - r0
            for b in range(d):
                rb = indptr[d * J + b] + off
                for a in range(d):
                    W[I, a, b] = data[rb + a]
        K = head[J]
        while K != -1:   # the columns K with L_JK ≠ 0
            after = nxt[K]
            p = pos[K]
            for q in range(p + 1, Lp[K + 1]):   # the blocks below row J: L_IK L_JKᵀ
                I = Li[q]
                for a in range(d):
                    for b in range(d):
                        s = 0.0
                        for c in range(d):
                            s += Lx[q, a, c] * Lx[p, b, c]
                        W[I, a, b] -= s
            for a in range(d):   # the diagonal block: L_JK L_JKᵀ
                for b in range(a + 1):
                    s = 0.0
                    for c in range(d):
                        s += Lx[p, a, c] * Lx[p, b, c]
                    W[J, a, b] -= s
            pos[K] = p + 1
            if p + 1 < Lp[K + 1]:
                I = Li[p + 1]
                nxt[K] = head[I]
                head[I] = K
            K = after
        for a in range(d):   # C_J: the Cholesky factor of the updated diagonal block (lower triangle)
            for b in range(a + 1):
                s = W[J, a, b]
                for c in range(b):
                    s -= C[a, c] * C[b, c]
                if a == b:
                    if not s > 0.0:
                        return J + 1
                    C[a, a] = np.sqrt(s)
                else:
                    C[a, b] = s / C[b, b]
        for a in range(d):
            for b in range(d):
                Ld[J, a, b] = C[a, b] if b <= a else 0.0
                W[J, a, b] = 0.0
        for q in range(Lp[J], Lp[J + 1]):   # L_IJ = W_I C_J⁻ᵀ: each row x of it solves x C_Jᵀ = w
            I = Li[q]
            for a in range(d):
                for b in range(d):
                    s = W[I, a, b]
                    for c in range(b):
                        s -= Lx[q, a, c] * C[b, c]
                    Lx[q, a, b] = s / C[b, b]
                    W[I, a, b] = 0.0
        pos[J] = Lp[J]
        if Lp[J] < Lp[J + 1]:
            I = Li[Lp[J]]
            nxt[J] = head[I]
            head[I] = J
    return 0


@jit
def _solve(Lp, Li, Lx, Ld, X):
    """X ← (L Lᵀ)⁻¹ X in place (X: (n, k), C order): forward by columns of L, backward by its rows."""
    nv, d, k = Ld.shape[0], Ld.shape[1], X.shape[1]
    y = np.zeros((d, k))
    for J in range(nv):
        o = d * J
        for a in range(d):   # y = C_J⁻¹ x_J
            for c in range(k):
                s = X[o + a, c]
                for b in range(a):
                    s -= Ld[J, a, b] * y[b, c]
                y[a, c] = s / Ld[J, a, a]
        for a in range(d):
            for c in range(k):
                X[o + a, c] = y[a, c]
        for q in range(Lp[J], Lp[J + 1]):
            oi = d * Li[q]
            for a in range(d):
                for c in range(k):
                    s = 0.0
                    for b in range(d):
                        s += Lx[q, a, b] * y[b, c]
                    X[oi + a, c] -= s
    for J in range(nv - 1, -1, -1):
        o = d * J
        for b in range(d):
            for c in range(k):
                y[b, c] = X[o + b, c]
        for q in range(Lp[J], Lp[J + 1]):   # x_J −= Σ_I L_IJᵀ x_I
            oi = d * Li[q]
            for a in range(d):
                for b in range(d):
                    w = Lx[q, a, b]
                    for c in range(k):
                        y[b, c] -= w * X[oi + a, c]
        for a in range(d - 1, -1, -1):   # x_J = C_J⁻ᵀ y
            for c in range(k):
                s = y[a, c]
                for b in range(a + 1, d):
                    s -= Ld[J, b, a] * X[o + b, c]
                X[o + a, c] = s / Ld[J, a, a]


def _one_column(D: int):
    """:func:`_solve` for D×D blocks and one column, D a constant of the compiled code (its loops
    unrolled: 3D survey 32³, a one-level chunk of nnz(L) 5.8M, 15 against 32 ms; a 300x300 grid of
    3×3 blocks as one, nnz(L) 34M, 68 ms against 194 ms, CHOLMOD's simplicial solve 94 ms)."""
    def solve(Lp, Li, Lx, Ld, x):
        y = np.empty(D)
        for J in range(Ld.shape[0]):
            o = D * J
            for a in range(D):   # y = C_J⁻¹ x_J
                s = x[o + a]
                for b in range(a):
                    s -= Ld[J, a, b] * y[b]
                y[a] = s / Ld[J, a, a]
            for a in range(D):
                x[o + a] = y[a]
            for q in range(Lp[J], Lp[J + 1]):
                i = D * Li[q]
                for a in range(D):
                    s = 0.0
                    for b in range(D):
                        s += Lx[q, a, b] * y[b]
                    x[i + a] -= s
        for J in range(Ld.shape[0] - 1, -1, -1):
            o = D * J
            for b in range(D):
                y[b] = x[o + b]
            for q in range(Lp[J], Lp[J + 1]):   # x_J −= Σ_I L_IJᵀ x_I
                i = D * Li[q]
                for a in range(D):
                    xa = x[i + a]
                    for b in range(D):
                        y[b] -= Lx[q, a, b] * xa
            for a in range(D - 1, -1, -1):   # x_J = C_J⁻ᵀ y
                s = y[a]
                for b in range(a + 1, D):
                    s -= Ld[J, b, a] * x[o + b]
                x[o + a] = s / Ld[J, a, a]
    return jit(solve)


_ONE_COLUMN = {D: _one_column(D) for D in (3, 6)}   # Pose2 and Pose3
