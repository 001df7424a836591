"""GDSW-type coarse space: interface modes extended by discrete harmonic extension (paper Sec. 3.3).

For every interface pose the interface values are unit vectors on its dofs (all of them, or the
translations only for the variant without rotation). Interior values solve
A_II φ_I = −A_IΓ φ_Γ; A_II is block diagonal over the subdomain interiors (every edge lies in one
subdomain), so one factorization and one multi-column solve extend all basis functions at once.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from .decomposition import Decomposition
from .interface import Interface
from .local_solvers import factorize


@dataclass(frozen=True)
class CoarseSpace:
    Phi: sp.csr_matrix  # n × n_c coarse basis
    A0: sp.csr_matrix  # Φᵀ A Φ
    column_vertex: np.ndarray  # interface vertex of each coarse column

    @property
    def size(self) -> int:
        return self.Phi.shape[1]


def interface_values(interface: Interface, offsets: np.ndarray, dof_mask: np.ndarray | None):
    """Φ_Γ as (global dof, column) pairs: a unit vector per selected dof of each interface vertex."""
    starts = offsets[interface.vertices]
    dims = offsets[interface.vertices + 1] - starts
    owner = np.repeat(np.arange(interface.size), dims)
    dofs = np.repeat(starts, dims) + np.arange(int(dims.sum())) - np.repeat(np.cumsum(dims) - dims, dims)
    if dof_mask is not None:
        keep = dof_mask[dofs]
        dofs, owner = dofs[keep], owner[keep]
    return dofs, owner  # column c is dof dofs[c], belonging to interface vertex owner[c]


def harmonic_extension(A: sp.spmatrix, decomposition: Decomposition, interface: Interface,
                       gamma_rows: np.ndarray, gamma_cols: np.ndarray, gamma_vals: np.ndarray,
                       col_vertex: np.ndarray) -> sp.csr_matrix:
    """Φ with Φ_Γ given as triplets and Φ_I = −A_II⁻¹ A_IΓ Φ_Γ, restricted subdomain by subdomain.

    The right-hand sides are compressed: subdomain i only sees the K_i coarse columns of its own
    interface vertices, so all subdomains share K = max K_i columns of one solve with A_II.
    """
    offsets = decomposition.structure.offsets
    n = decomposition.structure.n_dofs
    nc = len(col_vertex)
    A = sp.csr_matrix(A)
    owner_dof = np.repeat(interface.interior_subdomain, np.diff(offsets))  # −1 on Γ
    interior = np.flatnonzero(owner_dof >= 0)
    gamma = np.flatnonzero(owner_dof < 0)
    Phi_G = sp.csr_matrix((gamma_vals, (gamma_rows, gamma_cols)), shape=(n, nc))
    if nc == 0 or len(interior) == 0:
        return Phi_G
    sub = owner_dof[interior]
    # (subdomain, column) pairs: column c lives on subdomain i if its vertex is in V_i
    inc = sp.csr_matrix(interface.subdomains)  # interface-vertex × subdomain
    pos = np.searchsorted(interface.vertices, col_vertex)
    P = sp.csr_matrix(inc[pos].T)  # subdomain × column
    P.sort_indices()
    counts = np.diff(P.indptr)
    K = int(counts.max())
    pair_sub = np.repeat(np.arange(P.shape[0]), counts)
    pair_key = pair_sub * np.int64(nc) + P.indices  # sorted
    local_k = np.arange(len(P.indices)) - P.indptr[pair_sub]
    # right-hand sides −A_IΓ Φ_Γ, columns renumbered locally per subdomain
    B = sp.coo_matrix(-(A[interior][:, gamma] @ Phi_G[gamma]))
    key = sub[B.row] * np.int64(nc) + B.col
    at = np.searchsorted(pair_key, key)
    if np.any(at >= len(pair_key)) or np.any(pair_key[np.minimum(at, len(pair_key) - 1)] != key):
        raise AssertionError("interface coupling outside its subdomain: decomposition is inconsistent")
    Bc = np.zeros((len(interior), K))
    np.add.at(Bc, (B.row, local_k[at]), B.data)
    solve = factorize(A[interior][:, interior], "the interior matrix A_II")
    X = solve(Bc)
    # scatter back: interior row r, local column k < counts[sub[r]] → global column
    table = np.full((P.shape[0], K), -1, dtype=np.int64)
    table[pair_sub, local_k] = P.indices
    cols = table[sub]
    r, k = np.nonzero(cols >= 0)
    Phi_I = sp.csr_matrix((X[r, k], (interior[r], cols[r, k])), shape=(n, nc))
    return (Phi_G + Phi_I).tocsr()


def gdsw_coarse_space(A: sp.spmatrix, decomposition: Decomposition, interface: Interface,
                      dof_mask: np.ndarray | None = None) -> CoarseSpace:
    """GDSW coarse space; ``dof_mask`` selects the interface dofs that get a mode
    (None: all dofs, "with rotation"; translation mask: "without rotation")."""
    offsets = decomposition.structure.offsets
    dofs, owner = interface_values(interface, offsets, dof_mask)
    nc = len(dofs)
    col_vertex = interface.vertices[owner]
    Phi = harmonic_extension(A, decomposition, interface, dofs, np.arange(nc), np.ones(nc), col_vertex)
    A0 = (Phi.T @ sp.csr_matrix(A) @ Phi).tocsr()
    return CoarseSpace(Phi=Phi, A0=A0, column_vertex=col_vertex)
