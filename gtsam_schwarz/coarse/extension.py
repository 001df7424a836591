"""Discrete harmonic extension of interface values into subdomain interiors (paper Sec. 3.3).

Interior values solve A_II φ_I = −A_IΓ φ_Γ; A_II is block diagonal over subdomain interiors (every
edge lies in one subdomain), so one factorization and one multi-column solve extend every basis
function at once.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from ..dd.decomposition import Decomposition
from ..dd.interface import Interface
from ..solvers import Gather, SparseCholesky, factorize


class CoarseBasis:
    """Φ stored with its rows permuted: ``local`` = [Φ_I; Φ_Γ] (interior rows, then interface rows),
    Φ = P·local with ``order`` = the global row of each local row. Applying Φ or Φᵀ costs one
    permutation of a vector; the interior rows are written straight from the extension's solve
    (no merge with the interface rows, no transposed copy)."""

    def __init__(self, local: sp.csr_matrix, order: np.ndarray):
        self.local, self.order = local, order
        self.shape = local.shape

    @property
    def nnz(self) -> int:
        return self.local.nnz

    @property
    def nbytes(self) -> int:
        L = self.local
        return L.data.nbytes + L.indices.nbytes + L.indptr.nbytes + self.order.nbytes

    def matvec(self, z: np.ndarray) -> np.ndarray:
        """Φ z."""
        y = np.empty(self.shape[0])
        y[self.order] = self.local @ z
        return y

    def rmatvec(self, x: np.ndarray) -> np.ndarray:
        """Φᵀ x (through the CSC view of the local rows)."""
        return self.local.T @ x[self.order]

    def tocsr(self) -> sp.csr_matrix:
        """Φ in global row order (a copy: for tests, plots and other back-ends)."""
        inverse = np.empty_like(self.order)
        inverse[self.order] = np.arange(len(self.order))
        return sp.csr_matrix(self.local[inverse])


class HarmonicExtension:
    """Φ = [Φ_Γ; −A_II⁻¹ A_IΓ Φ_Γ] and A_0 = Φᵀ A Φ for one decomposition and interface.

    Interior and interface dofs, the patterns of A_II, A_IΓ and A_Γ·, the symbolic factorization
    of A_II and the pattern of Φ are computed once and reused for every new matrix with the same
    pattern. The right-hand sides are compressed: subdomain i only sees the K_i coarse columns whose
    subdomain set contains i, so all subdomains share K = max K_i columns of the solve with A_II,
    done in blocks of at most ``block_columns`` columns (None: all at once) to bound its memory.
    """

    def __init__(self, decomposition: Decomposition, interface: Interface, block_columns: int | None = None):
        offsets = decomposition.structure.offsets
        self.n = decomposition.structure.n_dofs
        owner_dof = np.repeat(interface.interior_subdomain, np.diff(offsets))  # −1 on Γ
        self.interior = np.flatnonzero(owner_dof >= 0)
        self.gamma = np.flatnonzero(owner_dof < 0)
        self.sub = owner_dof[self.interior]
        self.order = np.r_[self.interior, self.gamma]  # rows of Φ's local storage
        self.block_columns = block_columns
        I, G, order = self.interior, self.gamma, self.order
        self._A_II = Gather(lambda M: M[I][:, I])
        self._A_IG = Gather(lambda M: M[I][:, G])
        self._A_G = Gather(lambda M: M[G][:, order])
        self._factor = None
        self._cached = None  # (signature of the interface values, plan)

    def _refactor(self, A):
        pattern = self._A_II.pattern
        A_II = self._A_II(A)
        if isinstance(self._factor, SparseCholesky) and self._A_II.pattern is pattern:
            self._factor.refactor(A_II)  # same pattern: numbers only
        else:
            self._factor = factorize(A_II, "the interior matrix A_II")

    def _plan(self, A_IG: sp.csr_matrix, gamma_rows, gamma_cols, col_subdomains) -> dict:
        """Symbolic part of one extension: which products of A_IΓ and Φ_Γ entries add up to which
        entry of the compressed right-hand side, and the pattern of Φ's local rows."""
        nc, nI = col_subdomains.shape[0], len(self.interior)
        P = sp.csr_matrix(col_subdomains.T)  # subdomain × column
        P.sort_indices()
        counts = np.diff(P.indptr)
        K = int(counts.max())
        pair_sub = np.repeat(np.arange(P.shape[0]), counts)
        pair_key = pair_sub * np.int64(nc) + P.indices  # sorted
        local_k = np.arange(len(P.indices)) - P.indptr[pair_sub]
        # Φ_Γ triplets grouped by interface dof; every A_IΓ entry (i, g) meets each triplet of row g
        gpos = np.searchsorted(self.gamma, gamma_rows)
        by_g = np.argsort(gpos, kind="stable")
        g_ptr = np.searchsorted(gpos[by_g], np.arange(len(self.gamma) + 1))
        C = A_IG.tocoo()
        deg = g_ptr[C.col + 1] - g_ptr[C.col]
        term_a = np.repeat(np.arange(C.nnz), deg)
        first = np.repeat(g_ptr[C.col] - np.cumsum(deg) + deg, deg)
        term_phi = by_g[first + np.arange(len(term_a))]
        rows = C.row[term_a]
        key = self.sub[rows] * np.int64(nc) + gamma_cols[term_phi]
        at = np.minimum(np.searchsorted(pair_key, key), len(pair_key) - 1)
        if np.any(pair_key[at] != key):
            raise AssertionError("interface coupling outside its subdomain: decomposition is inconsistent")
        # right-hand-side terms sorted by local column, so a block of columns is a contiguous range
        k_of_term = local_k[at]
        by_k = np.argsort(k_of_term, kind="stable")
        term_k = k_of_term[by_k]
        # Φ_I: row r holds the K_i columns of its subdomain i (sorted), values X[r, :K_i]
        k_row = counts[self.sub]
        idx = np.int32 if max(nc, self.n) < 2**31 - 1 else np.int64
        table = np.zeros((P.shape[0], K), dtype=idx)
        table[pair_sub, local_k] = P.indices
        prefix = np.arange(K)[None, :] < k_row[:, None]
        indices_I = table[self.sub][prefix]
        del table, prefix
        g_order = np.lexsort((gamma_cols, gpos))
        ptr_G = np.searchsorted(gpos[g_order], np.arange(len(self.gamma) + 1))
        indptr = np.r_[0, np.cumsum(k_row), len(indices_I) + ptr_G[1:]].astype(np.int64)
        indices = np.r_[indices_I, gamma_cols[g_order].astype(idx)]
        if indptr[-1] < 2**31 - 1:
            indptr = indptr.astype(np.int32)
        return {"K": K, "nI": nI, "term_a": term_a[by_k], "term_phi": term_phi[by_k],
                "target": term_k * np.int64(nI) + rows[by_k],  # column-major: F-ordered blocks
                "term_k_ptr": np.searchsorted(term_k, np.arange(K + 1)), "k_row": k_row,
                "row_start": indptr[:nI + 1].astype(np.int64), "nnz_I": len(indices_I),
                "g_order": g_order, "gpos": gpos, "indices": indices, "indptr": indptr}

    def columns_per_block(self, K: int) -> int:
        return K if self.block_columns is None else max(1, min(K, int(self.block_columns)))

    def _extend(self, A_IG: sp.csr_matrix, gamma_vals: np.ndarray, plan: dict, data: np.ndarray) -> None:
        """Φ_I = −A_II⁻¹ A_IΓ Φ_Γ into data[:nnz_I] (row-major Φ_I), column blocks of the compressed
        right-hand side at a time."""
        K, nI = plan["K"], plan["nI"]
        weights = -A_IG.data[plan["term_a"]] * gamma_vals[plan["term_phi"]]
        k_ptr, k_row, start = plan["term_k_ptr"], plan["k_row"], plan["row_start"]
        width = self.columns_per_block(K)
        for k0 in range(0, K, width):  # a loop over blocks of coarse columns (one when memory allows)
            k1 = min(K, k0 + width)
            lo, hi = k_ptr[k0], k_ptr[k1]
            B = np.bincount(plan["target"][lo:hi] - k0 * nI, weights=weights[lo:hi],
                            minlength=nI * (k1 - k0)).reshape(k1 - k0, nI).T  # F-ordered nI × (k1 − k0)
            X = self._factor(B)
            del B
            sel = np.arange(k0, k1)[None, :] < k_row[:, None]
            if k0 == 0 and k1 == K:
                data[:plan["nnz_I"]] = X[sel]  # row-major prefix of every row: Φ_I's CSR order
            else:
                data[(start[:-1, None] + np.arange(k0, k1)[None, :])[sel]] = X[sel]
            del X, sel

    def __call__(self, A: sp.spmatrix, gamma_rows: np.ndarray, gamma_cols: np.ndarray,
                 gamma_vals: np.ndarray, col_subdomains: sp.csr_matrix) -> tuple[CoarseBasis, sp.csr_matrix]:
        """(Φ, A_0) for interface values given as triplets (global dof, column, value)."""
        n, nc = self.n, col_subdomains.shape[0]
        A = sp.csr_matrix(A)
        if nc == 0 or len(self.interior) == 0:
            Phi_G = sp.csr_matrix((gamma_vals, (gamma_rows, gamma_cols)), shape=(n, nc))
            return CoarseBasis(Phi_G, np.arange(n)), (Phi_G.T @ A @ Phi_G).tocsr()
        pattern = self._A_IG.pattern
        A_IG = self._A_IG(A)
        col_subdomains = sp.csr_matrix(col_subdomains)
        signature = (gamma_rows, gamma_cols, col_subdomains.indptr, col_subdomains.indices)
        cached = self._cached
        if (cached is None or self._A_IG.pattern is not pattern
                or not all(np.array_equal(a, b) for a, b in zip(cached[0], signature))):
            self._cached = None
            self._cached = cached = (tuple(np.array(a, copy=True) for a in signature),
                                     self._plan(A_IG, gamma_rows, gamma_cols, col_subdomains))
        plan = cached[1]
        self._refactor(A)
        data = np.empty(len(plan["indices"]))
        self._extend(A_IG, gamma_vals, plan, data)
        data[plan["nnz_I"]:] = gamma_vals[plan["g_order"]]
        local = sp.csr_matrix((data, plan["indices"], plan["indptr"]), shape=(n, nc))
        # (AΦ)_I = A_II Φ_I + A_IΓ Φ_Γ = 0 for the harmonic extension, so Φᵀ A Φ = Φ_Γᵀ (AΦ)_Γ:
        # only the interface rows of A enter (Φ is dense on subdomain interiors; A Φ would not be)
        Phi_GG = local[plan["nI"]:]
        A0 = (Phi_GG.T @ (self._A_G(A) @ local)).tocsr()
        return CoarseBasis(local, self.order), ((A0 + A0.T) * 0.5).tocsr()
