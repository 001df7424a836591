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


class HarmonicExtension:
    """Φ = [Φ_Γ; −A_II⁻¹ A_IΓ Φ_Γ] and A_0 = Φᵀ A Φ for one decomposition and interface.

    Interior and interface dofs, the patterns of A_II, A_IΓ and A_Γ·, and the symbolic
    factorization of A_II are computed once and reused for every new matrix with the same pattern.
    The right-hand sides are compressed: subdomain i only sees the K_i coarse columns whose
    subdomain set contains i, so all subdomains share K = max K_i columns of one solve with A_II.
    """

    def __init__(self, decomposition: Decomposition, interface: Interface):
        offsets = decomposition.structure.offsets
        self.n = decomposition.structure.n_dofs
        owner_dof = np.repeat(interface.interior_subdomain, np.diff(offsets))  # −1 on Γ
        self.interior = np.flatnonzero(owner_dof >= 0)
        self.gamma = np.flatnonzero(owner_dof < 0)
        self.sub = owner_dof[self.interior]
        I, G = self.interior, self.gamma
        self._A_II = Gather(lambda M: M[I][:, I])
        self._A_IG = Gather(lambda M: M[I][:, G])
        self._A_G = Gather(lambda M: M[G])
        self._factor = None
        self._cached = None  # (signature of the interface values, plan)

    def _solve_interior(self, A, B):
        pattern = self._A_II.pattern
        A_II = self._A_II(A)
        if isinstance(self._factor, SparseCholesky) and self._A_II.pattern is pattern:
            self._factor.refactor(A_II)  # same pattern: numbers only
        else:
            self._factor = factorize(A_II, "the interior matrix A_II")
        return self._factor(B)

    def _plan(self, A_IG: sp.csr_matrix, gamma_rows, gamma_cols, col_subdomains) -> dict:
        """Symbolic part of one extension: which products of A_IΓ and Φ_Γ entries add up to which
        entry of the compressed right-hand side, and where Φ's entries go in its CSR arrays."""
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
        # A_IG entry order in C equals A_IG.data order (CSR → COO keeps it)
        table = np.full((P.shape[0], K), -1, dtype=np.int64)
        table[pair_sub, local_k] = P.indices
        cols = table[self.sub]
        r, k = np.nonzero(cols >= 0)  # row-major: already grouped by (sorted) interior row
        # Φ's CSR layout without a sort: Γ triplets (sorted by row) and interior entries are two
        # row-sorted lists with disjoint rows, merged by counting how many of the other come first
        g_order = np.argsort(gamma_rows, kind="stable")
        g_rows = gamma_rows[g_order]
        i_rows = self.interior[r]
        slot = np.empty(len(g_rows) + len(i_rows), dtype=np.int64)
        slot[:len(g_rows)] = np.arange(len(g_rows)) + np.searchsorted(i_rows, g_rows)
        slot[len(g_rows):] = np.arange(len(i_rows)) + np.searchsorted(g_rows, i_rows, side="right")
        indices = np.empty(len(slot), dtype=np.int64)
        indices[slot[:len(g_rows)]] = gamma_cols[g_order]
        indices[slot[len(g_rows):]] = cols[r, k]
        indptr = np.zeros(self.n + 1, dtype=np.int64)
        np.cumsum(np.bincount(np.concatenate([g_rows, i_rows]), minlength=self.n), out=indptr[1:])
        return {"K": K, "term_a": term_a, "term_phi": term_phi, "target": rows * K + local_k[at],
                "x_entries": r * K + k, "g_order": g_order, "slot": slot,
                "indices": indices, "indptr": indptr, "gpos": gpos, "nI": nI}

    def __call__(self, A: sp.spmatrix, gamma_rows: np.ndarray, gamma_cols: np.ndarray,
                 gamma_vals: np.ndarray, col_subdomains: sp.csr_matrix) -> tuple[sp.csr_matrix, sp.csr_matrix]:
        """(Φ, A_0) for interface values given as triplets (global dof, column, value)."""
        n, nc = self.n, col_subdomains.shape[0]
        A = sp.csr_matrix(A)
        if nc == 0 or len(self.interior) == 0:
            Phi_G = sp.csr_matrix((gamma_vals, (gamma_rows, gamma_cols)), shape=(n, nc))
            return Phi_G, (Phi_G.T @ A @ Phi_G).tocsr()
        pattern = self._A_IG.pattern
        A_IG = self._A_IG(A)
        col_subdomains = sp.csr_matrix(col_subdomains)
        signature = (gamma_rows, gamma_cols, col_subdomains.indptr, col_subdomains.indices)
        cached = self._cached
        if (cached is None or self._A_IG.pattern is not pattern
                or not all(np.array_equal(a, b) for a, b in zip(cached[0], signature))):
            self._cached = cached = (tuple(np.array(a, copy=True) for a in signature),
                                     self._plan(A_IG, gamma_rows, gamma_cols, col_subdomains))
        plan = cached[1]
        K, nI = plan["K"], plan["nI"]
        weights = -A_IG.data[plan["term_a"]] * gamma_vals[plan["term_phi"]]
        Bc = np.bincount(plan["target"], weights=weights, minlength=nI * K).reshape(nI, K)
        X = self._solve_interior(A, Bc)
        data = np.empty(len(plan["slot"]))
        data[plan["slot"]] = np.concatenate([gamma_vals[plan["g_order"]], X.ravel()[plan["x_entries"]]])
        Phi = sp.csr_matrix((data, plan["indices"], plan["indptr"]), shape=(n, nc))
        # (AΦ)_I = A_II Φ_I + A_IΓ Φ_Γ = 0 for the harmonic extension, so Φᵀ A Φ = Φ_Γᵀ (AΦ)_Γ:
        # only the interface rows of A enter (Φ is dense on subdomain interiors; A Φ would not be)
        Phi_GG = sp.csr_matrix((gamma_vals, (plan["gpos"], gamma_cols)), shape=(len(self.gamma), nc))
        A0 = (Phi_GG.T @ (self._A_G(A) @ Phi)).tocsr()
        return Phi, ((A0 + A0.T) * 0.5).tocsr()
