"""Peak memory of a two-level Schwarz preconditioner, predicted before its numeric setup.

From the symbolic analysis only: the fill of the overlapping subdomain blocks (a CHOLMOD-style
analysis of their vertex pattern, ``solvers.cost``), the interior blocks A_II (scaled from it by
their share of the dofs), the gathered submatrices, Φ (Σ_i |I_i|·K_i interior entries: every
interior dof of subdomain i carries the K_i coarse columns that reach i) and the right-hand sides
of the harmonic extension (|I| × K per block of columns, with its solution and selection).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from ..coarse import coarse_columns
from ..dd.index_sets import IndexSets
from ..solvers import block_diagonal, pattern_cholesky_cost, vertex_pattern
from ..solvers.memory import FACTOR_BYTES, MATRIX_BYTES, InsufficientMemoryError, available_memory, gib

EXTENSION_BYTES = 20  # per entry of one column block: right-hand side, solution, its selected part, mask (measured 18)
OVERHEAD = 1.25  # allocator slack and temporaries not counted above (fitted: docs/survey.md, memory)


@dataclass
class MemoryEstimate:
    """Bytes by part; ``extension_column`` is per column of the extension's right-hand side."""

    parts: dict = field(default_factory=dict)
    extension_column: float = 0.0
    K: int = 0
    block_columns: int | None = None
    limit: float = float("inf")
    local: object = None  # CholeskyCost of the overlapping subdomain blocks (predicted)
    nnz_phi: float = 0.0  # entries of Φ
    interior_share: float = 0.0  # interior dofs / dofs of the overlapping blocks

    def persistent(self) -> float:
        return OVERHEAD * sum(self.parts.values())

    def peak(self, block_columns: int | None = None) -> float:
        width = self.K if block_columns is None else min(self.K, block_columns)
        return self.persistent() + OVERHEAD * self.extension_column * width

    def describe(self) -> str:
        return ", ".join(f"{k} {gib(OVERHEAD * v)}" for k, v in self.parts.items())


def estimate_two_level(M, A) -> MemoryEstimate:
    """The parts of a :class:`~gtsam_schwarz.schwarz.TwoLevelSchwarz`'s memory for matrix A (after
    its ``setup``: interface and extension plan known, nothing numeric yet)."""
    dec, ext = M.decomposition, M.extension
    offsets = dec.structure.offsets
    A = sp.csr_matrix(A)
    S = sp.csc_matrix(dec.overlapping)
    S.sort_indices()
    vsets = IndexSets(indices=S.indices.astype(np.int64), ptr=S.indptr.astype(np.int64), n=S.shape[0])
    blocks = block_diagonal(vertex_pattern(A, offsets), vsets)
    local = pattern_cholesky_cost(blocks, np.diff(offsets)[vsets.indices])
    n_block = int(np.diff(offsets)[vsets.indices].sum())
    nI = len(ext.interior)
    rows, cols, _, column_component, col_subdomains = coarse_columns(
        dec, M.interface, M.kind, None, M.rotation, M.translation_mask)
    nc = len(column_component)
    K_sub = np.diff(sp.csr_matrix(col_subdomains.T).indptr) if nc else np.zeros(dec.n_subdomains, np.int64)
    nnz_phi = float(np.sum(K_sub[ext.sub])) + len(rows)
    K = int(K_sub.max()) if nc else 0
    nnz_A0 = min(float(nc) ** 2, float(np.sum(K_sub.astype(float) ** 2)))  # columns that share a subdomain couple
    dense_coarse = nc <= 4000 and nnz_A0 >= 0.1 * nc * nc  # as solvers.factorize decides
    est = MemoryEstimate(K=K, local=local, nnz_phi=nnz_phi, interior_share=nI / max(n_block, 1))
    est.parts = {
        "subdomain factors": FACTOR_BYTES * local.nnz_L + MATRIX_BYTES * local.nnz_A,
        "interior factors": FACTOR_BYTES * local.nnz_L * nI / max(n_block, 1) + MATRIX_BYTES * A.nnz,
        "coarse basis": 12.0 * nnz_phi,
        "patterns": 16.0 * A.nnz,  # the gathers' copies of A's pattern and their source positions
        "coarse matrix": 16.0 * nc * nc if dense_coarse else 48.0 * nnz_A0,
    }
    est.extension_column = EXTENSION_BYTES * nI
    return est


def fit_memory(M, A, limit=None, name: str = "Schwarz", est: MemoryEstimate | None = None) -> MemoryEstimate:
    """Estimate M's peak (or take ``est``) and make it fit ``limit`` (bytes; None: the memory
    available now): extend in blocks of columns when the full right-hand side would not fit, and
    raise :class:`InsufficientMemoryError` when even one column at a time would not."""
    est = est if est is not None else estimate_two_level(M, A)
    est.limit = available_memory(limit)
    if est.peak() <= est.limit:
        return est
    room = est.limit - est.persistent()
    width = int(room // (OVERHEAD * est.extension_column)) if est.extension_column else 0
    if width >= 1:
        est.block_columns = min(width, est.K)
        return est
    parts = est.parts
    biggest = max(parts, key=parts.get)
    advice = {"subdomain factors": "smaller subdomains (subdomain_size) or more memory",
              "interior factors": "smaller subdomains (subdomain_size) or more memory",
              "patterns": "preconditioner='direct' or more memory",
              "coarse basis": "larger subdomains (subdomain_size), a smaller coarse space (rgdsw-linear) or more memory",
              "coarse matrix": "larger subdomains (subdomain_size), a smaller coarse space (rgdsw-linear) or more memory"}[biggest]
    raise InsufficientMemoryError(
        f"{name} needs about {gib(est.peak(1))} ({est.describe()}) but {gib(est.limit)} is available: "
        f"use {advice}")
