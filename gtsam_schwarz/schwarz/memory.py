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
from ..coarse.extension import column_groups
from ..dd.index_sets import IndexSets
from ..solvers import block_cholesky, block_diagonal, pattern_cholesky_cost, vertex_pattern
from ..solvers.memory import FACTOR_BYTES, MATRIX_BYTES, InsufficientMemoryError, available_memory, gib
from ..util import as_csr

EXTENSION_BYTES = 20  # per entry of one column block: right-hand side, solution, its selected part, mask (measured 18)
OVERHEAD = 1.4  # allocator slack and temporaries not counted above (measured/estimated 0.7-1.1: docs/survey.md, memory)
LOW_MEMORY_FROM = 2**30  # estimated peak (bytes) beyond which the factorizations are not kept between phases
LOW_MEMORY_SLACK = 1.0  # one factorization at a time, 3D 36 864 poses: 2171 MiB estimated, 2162 measured (2511 both kept)


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

    low_memory: bool = False  # factorizations not kept between the extension and the one-level level

    def persistent(self) -> float:
        return OVERHEAD * sum(self.parts.values())

    def peak(self, block_columns: int | None = None, low_memory: bool | None = None) -> float:
        """Bytes at the worst moment of an update. ``low_memory``: the interior factors live only
        during the extension and the subdomain factors only after it, so only the larger phase counts."""
        width = self.K if block_columns is None else min(self.K, block_columns)
        extension = self.extension_column * width
        if not (self.low_memory if low_memory is None else low_memory):
            return OVERHEAD * (sum(self.parts.values()) + extension)
        p = self.parts
        shared = sum(v for k, v in p.items() if k not in ("subdomain factors", "interior factors"))
        return LOW_MEMORY_SLACK * OVERHEAD * (shared + max(p["subdomain factors"], p["interior factors"] + extension))

    def describe(self) -> str:
        return ", ".join(f"{k} {gib(OVERHEAD * v)}" for k, v in self.parts.items())


def _factor_bytes(offsets: np.ndarray, dtype) -> float:
    """Bytes per predicted entry of a subdomain or interior factor: by vertex blocks in ``dtype`` where
    every vertex has the same dofs (:mod:`..solvers.block_cholesky`), else CHOLMOD's."""
    d = block_cholesky.vertex_block(offsets)
    return block_cholesky.bytes_per_entry(d, dtype) if d and dtype is not None else FACTOR_BYTES


def estimate_two_level(M, A, geometry=None) -> MemoryEstimate:
    """The parts of a :class:`~gtsam_schwarz.schwarz.TwoLevelSchwarz`'s memory for matrix A (after
    its ``setup``: interface and extension plan known, nothing numeric yet). With the poses
    (``geometry``) of the coming build, its coarse columns are computed once, for both."""
    dec, ext = M.decomposition, M.extension
    offsets = dec.structure.offsets
    A = as_csr(A)
    S = sp.csc_matrix(dec.overlapping)
    S.sort_indices()
    vsets = IndexSets(indices=S.indices.astype(np.int64), ptr=S.indptr.astype(np.int64), n=S.shape[0])
    nI = len(ext.interior)
    # the coarse columns first: the subdomain blocks' order may still be in the making (TwoLevelSchwarz.setup)
    rows, cols, _, column_component, col_subdomains = coarse_columns(
        dec, M.interface, M.kind, geometry if M.uses_geometry else None, M.rotation, M.translation_mask,
        keep=geometry is not None)
    if hasattr(M, "ordered"):
        M.ordered()
    solver = getattr(getattr(M, "one_level", None), "solver", None)
    blocks = solver.take_vertex_blocks() if hasattr(solver, "take_vertex_blocks") else None
    if blocks is None or blocks.shape[0] != len(vsets.indices):   # not formed by the one-level setup
        blocks = block_diagonal(vertex_pattern(A, offsets), vsets)
    local = pattern_cholesky_cost(blocks, np.diff(offsets)[vsets.indices])
    n_block = int(np.diff(offsets)[vsets.indices].sum())
    nc = len(column_component)
    K_sub = np.diff(sp.csr_matrix(col_subdomains.T).indptr) if nc else np.zeros(dec.n_subdomains, np.int64)
    nnz_phi = float(np.sum(K_sub[ext.sub])) + len(rows)
    K = int(K_sub.max()) if nc else 0
    nnz_A0 = min(float(nc) ** 2, float(np.sum(K_sub.astype(float) ** 2)))  # columns that share a subdomain couple
    dense_coarse = nc <= 4000 and nnz_A0 >= 0.1 * nc * nc  # as solvers.factorize decides
    est = MemoryEstimate(K=K, local=local, nnz_phi=nnz_phi, interior_share=nI / max(n_block, 1))
    single = nnz_phi >= ext.SINGLE_FROM
    est.parts = {
        "subdomain factors": _factor_bytes(offsets, solver.block_dtype(A.nnz) if hasattr(solver, "block_dtype") else None)
        * local.nnz_L,
        "interior factors": _factor_bytes(offsets, ext.interior_factor_dtype(single)) * local.nnz_L * nI / max(n_block, 1),
        # the gathered blocks (overlapping, A_II, A_IΓ, A_Γ·) with their source positions and one
        # shared copy of A's pattern
        "gathered matrices": MATRIX_BYTES * (local.nnz_A + A.nnz) + 4.0 * A.nnz,
        # Φ's CSR entries (8 + 4 bytes, or 4 + 4 in single precision) and the extension's kept
        # positions of A_IΓΦ_Γ's entries in the compressed right-hand side (int32, at most one per
        # entry of Φ_I)
        "coarse basis": (12.0 if single else 16.0) * nnz_phi,
        # A₀ and, while it is assembled, A_Γ·Φ for one block of interface rows (K columns each at most)
        # with the rows of Φ that block reads, in double precision (~12 bytes per entry)
        "coarse matrix": (16.0 * nc * nc if dense_coarse else 48.0 * nnz_A0) + 24.0 * ext.a0_block_rows(len(ext.gamma)) * K,
    }
    # the extension solves group by group (coarse.extension.column_groups): its largest right-hand side
    nI_sub = np.bincount(ext.sub, minlength=len(K_sub))
    group = column_groups(K_sub, nI_sub, ext.max_groups) if nc else np.zeros(len(K_sub), np.int64)
    K_group = np.zeros(int(group.max()) + 1 if len(group) else 1)
    np.maximum.at(K_group, group, K_sub)
    largest = float(np.max(np.bincount(group, weights=nI_sub) * K_group)) if len(group) else 0.0
    est.extension_column = EXTENSION_BYTES * largest / max(K, 1)
    return est


def fit_memory(M, A, limit=None, name: str = "Schwarz", est: MemoryEstimate | None = None,
               geometry=None) -> MemoryEstimate:
    """Estimate M's peak (or take ``est``) and make it fit ``limit`` (bytes; None: the memory
    available now): extend in blocks of columns when the full right-hand side would not fit, and
    raise :class:`InsufficientMemoryError` when even one column at a time would not."""
    est = est if est is not None else estimate_two_level(M, A, geometry)
    est.limit = available_memory(limit)
    # keep the factorizations if they fit and are small; else one phase at a time (the factorizations
    # kept only save a symbolic analysis per rebuild: at 91 125 3D poses the process peak 2960 ->
    # 2600 MiB, LM 60.4 -> 61.5 s)
    modes = (True,) if est.peak(None, False) > LOW_MEMORY_FROM else (False, True)
    for low in modes:
        if est.peak(None, low) <= est.limit:
            est.low_memory = low
            return est
        fixed = est.peak(0, low)
        width = int((est.limit - fixed) // (OVERHEAD * est.extension_column)) if est.extension_column else 0
        if width >= 1 and est.peak(width, low) <= est.limit:
            est.block_columns, est.low_memory = min(width, est.K), low
            return est
    parts = est.parts
    biggest = max(parts, key=parts.get)
    advice = {"subdomain factors": "smaller subdomains (subdomain_size) or more memory",
              "interior factors": "smaller subdomains (subdomain_size) or more memory",
              "gathered matrices": "preconditioner='direct', overlap=0 or more memory",
              "coarse basis": "larger subdomains (subdomain_size), a smaller coarse space (rgdsw-linear) or more memory",
              "coarse matrix": "larger subdomains (subdomain_size), a smaller coarse space (rgdsw-linear) or more memory"}[biggest]
    raise InsufficientMemoryError(
        f"{name} needs about {gib(est.peak(1, True))} ({est.describe()}) but {gib(est.limit)} is available: "
        f"use {advice}")
