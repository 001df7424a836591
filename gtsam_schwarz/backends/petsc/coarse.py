"""The rows of the GDSW / RGDSW coarse basis Φ that one rank owns, computed by that rank alone.

Φ = [Φ_Γ; −A_II⁻¹ A_IΓ Φ_Γ] (``coarse.HarmonicExtension``): Φ_Γ comes from
``coarse.interface_values`` (the same rigid or unit modes and partition of unity), and since A_II
is block diagonal over the subdomain interiors, the interior rows of subdomain i only need A's rows
on I_i: the rank extends into the interiors of its own subdomains only (one factorization of its
block of A_II, one solve with the compressed right-hand sides: subdomain i sees only the K_i coarse
columns whose subdomain set contains i, as in the serial extension). Plain numpy/scipy: no PETSc here.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from ...coarse import interface_values
from ...coarse.modes import COMPONENT_SPACES, column_subdomains
from ...dd.decomposition import Decomposition
from ...dd.geometry import VertexGeometry
from ...dd.interface import Interface
from ...solvers import SparseCholesky, SparsityPattern, factorize
from ...util import sorted_unique


class _Rows:
    """Rows I of A (the interiors of the rank's subdomains, sorted): where A[I, I] and A[I, J] (J: the
    interface dofs they touch) sit in ``A.data``, found once per pattern of A (index arrays, never
    a copy of A). Interiors of different subdomains never couple, so A[I, I] is block diagonal."""

    def __init__(self, I: np.ndarray, A: sp.csr_matrix, gamma: np.ndarray):
        self.I = I
        n = A.shape[0]
        starts, ends = A.indptr[I], A.indptr[I + 1]
        lens = ends - starts
        pos = np.repeat(starts - np.cumsum(lens) + lens, lens) + np.arange(int(lens.sum()))
        row = np.repeat(np.arange(len(I)), lens)
        cols = A.indices[pos]
        local = np.full(n, -1, dtype=np.int64)
        local[I] = np.arange(len(I))
        inner = local[cols] >= 0
        on_gamma = gamma[cols]
        # CSR in A's (sorted) column order: the local numbers are monotone in the global ones
        self.src_II = pos[inner]
        self.indices_II = local[cols[inner]]
        self.indptr_II = np.r_[0, np.cumsum(np.bincount(row[inner], minlength=len(I)))]
        self.J = sorted_unique(cols[on_gamma])
        self.src_IJ = pos[on_gamma]
        self.indices_IJ = np.searchsorted(self.J, cols[on_gamma])
        self.indptr_IJ = np.r_[0, np.cumsum(np.bincount(row[on_gamma], minlength=len(I)))]

    def A_II(self, A) -> sp.csr_matrix:
        n = len(self.I)
        return sp.csr_matrix((A.data[self.src_II], self.indices_II, self.indptr_II), shape=(n, n))

    def A_IJ(self, A) -> sp.csr_matrix:
        return sp.csr_matrix((A.data[self.src_IJ], self.indices_IJ, self.indptr_IJ), shape=(len(self.I), len(self.J)))


class LocalCoarseBasis:
    """Φ's rows on the dofs ``owned`` (a bool mask over the original dofs), for the subdomains
    ``subdomains`` whose interiors those dofs contain.

    ``__call__(A, geometry)`` → (rows, cols, vals, n_columns): triplets in the original dof
    numbering. As in ``coarse.HarmonicExtension``, one factorization of the (block diagonal) A_II of
    the rank's interiors and one solve with K = max_i K_i compressed right-hand sides extend every
    column at once; the positions in A, the compression plan and CHOLMOD's symbolic analysis are
    kept across calls with the same pattern of A and the same interface values' pattern."""

    def __init__(self, decomposition: Decomposition, interface: Interface, subdomains: np.ndarray,
                 owned: np.ndarray, kind: str = "gdsw", rotation: bool = True,
                 translation_mask: np.ndarray | None = None):
        self.decomposition, self.interface = decomposition, interface
        self.kind, self.rotation, self.translation_mask = kind, rotation, translation_mask
        self.offsets = decomposition.structure.offsets
        self.n = decomposition.structure.n_dofs
        self.owned = np.asarray(owned, dtype=bool)
        owner_dof = np.repeat(interface.interior_subdomain, np.diff(self.offsets))  # −1 on Γ
        self.gamma = owner_dof < 0
        mine = np.isin(owner_dof, subdomains)
        if np.any(mine & ~self.owned):
            raise AssertionError("an interior dof of this rank's subdomains is owned by another rank")
        self.interior = np.flatnonzero(mine)
        self.sub = owner_dof[self.interior]
        self._pattern = None  # SparsityPattern of A that ``_rows`` was found for
        self._rows: _Rows | None = None
        self._factor = None
        self._plan = None  # (signature of the coarse columns' subdomain sets, plan)

    def interface_basis(self, geometry: VertexGeometry | None):
        """Φ_Γ triplets (global dof, column, value) and the interface component of each column."""
        return interface_values(self.interface, self.offsets, self.kind, geometry, self.rotation,
                                self.translation_mask)

    def column_subdomains(self, rows, cols, column_component) -> sp.csr_matrix:
        """Column × subdomain incidence: the subdomains whose interiors each column's extension
        reaches (its component's set for gdsw/rgdsw, the union over its support for the linear spaces)."""
        if self.kind in COMPONENT_SPACES:
            return sp.csr_matrix(self.interface.component_subdomains()[column_component])
        return column_subdomains(self.interface, self.offsets, rows, cols, len(column_component))

    def _compression(self, C: sp.csr_matrix) -> dict:
        """Subdomain i sees only the K_i columns whose subdomain set contains i (``C``: column ×
        subdomain): column c of subdomain i goes to slot k of the compressed right-hand side."""
        C = sp.csr_matrix(C)
        C.sort_indices()
        signature = (C.shape, C.indptr.copy(), C.indices.copy())
        if self._plan is not None and self._plan[0][0] == C.shape and all(
                np.array_equal(a, b) for a, b in zip(self._plan[0][1:], signature[1:])):
            return self._plan[1]
        P = sp.csr_matrix(C.T)  # subdomain × column
        P.sort_indices()
        counts = np.diff(P.indptr)
        K = int(counts[sorted_unique(self.sub)].max()) if len(self.sub) else 0
        pair_sub = np.repeat(np.arange(P.shape[0]), counts)
        nc = C.shape[0]
        plan = {"K": K, "nc": nc, "pair_key": pair_sub * np.int64(max(nc, 1)) + P.indices,
                "local_k": np.arange(len(P.indices)) - P.indptr[pair_sub], "P": P}
        # the Φ entries: interior row r, slot k < K_sub(r), column table[sub(r), k]
        table = np.full((P.shape[0], max(K, 1)), -1, dtype=np.int64)
        keep = plan["local_k"] < max(K, 1)
        table[pair_sub[keep], plan["local_k"][keep]] = P.indices[keep]
        cols = table[self.sub]
        r, k = np.nonzero(cols >= 0)
        plan.update(entry_row=r, entry_k=k, entry_col=cols[r, k])
        self._plan = (signature, plan)
        return plan

    def __call__(self, A: sp.spmatrix, geometry: VertexGeometry | None = None):
        rows, cols, vals, column_component = self.interface_basis(geometry)
        nc = len(column_component)
        keep = self.owned[rows]
        out_r, out_c, out_v = [rows[keep]], [cols[keep]], [vals[keep]]
        if nc and len(self.interior):
            A = sp.csr_matrix(A)
            if not A.has_sorted_indices:
                A = A.sorted_indices()
            if self._pattern is None or not self._pattern.matches(A):
                self._rows, self._pattern, self._factor = _Rows(self.interior, A, self.gamma), SparsityPattern(A), None
            R = self._rows
            plan = self._compression(self.column_subdomains(rows, cols, column_component))
            Phi_J = sp.csr_matrix((vals, (rows, cols)), shape=(self.n, nc))[R.J]
            S = (R.A_IJ(A) @ Phi_J).tocoo()  # A_IΓ Φ_Γ: nonzero only in columns of the row's subdomain
            key = self.sub[S.row] * np.int64(nc) + S.col
            at = np.minimum(np.searchsorted(plan["pair_key"], key), len(plan["pair_key"]) - 1)
            if np.any(plan["pair_key"][at] != key):
                raise AssertionError("interface coupling outside its subdomain: decomposition is inconsistent")
            B = np.zeros((len(self.interior), plan["K"]))
            B[S.row, plan["local_k"][at]] = -S.data
            K_II = R.A_II(A)
            if isinstance(self._factor, SparseCholesky):
                self._factor.refactor(K_II)
            else:
                self._factor = factorize(K_II, "the interior matrix A_II of this rank's subdomains")
            X = np.asarray(self._factor(B)).reshape(len(self.interior), plan["K"])
            # every (row, column of its subdomain) entry, zeros too: Φ's pattern stays fixed across updates
            out_r.append(self.interior[plan["entry_row"]])
            out_c.append(plan["entry_col"])
            out_v.append(X[plan["entry_row"], plan["entry_k"]])
        return (*(np.concatenate(a) for a in (out_r, out_c, out_v)), nc)
