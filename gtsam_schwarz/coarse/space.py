"""GDSW-type coarse spaces: interface modes extended harmonically, Φ and A_0 = ΦᵀAΦ (paper Sec. 3.3)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from ..dd.decomposition import Decomposition
from ..dd.geometry import VertexGeometry
from ..dd.interface import Interface
from .extension import CoarseBasis, HarmonicExtension
from .modes import COMPONENT_SPACES, column_subdomains, interface_values


@dataclass(frozen=True)
class CoarseSpace:
    basis: CoarseBasis  # n × n_c coarse basis Φ (rows stored interior first)
    A0: sp.csr_matrix  # Φᵀ A Φ
    column_component: np.ndarray  # interface component (coarse node) of each column

    def __post_init__(self):
        if sp.issparse(self.basis):  # a plain sparse Φ (global row order)
            object.__setattr__(self, "basis", CoarseBasis(sp.csr_matrix(self.basis), np.arange(self.basis.shape[0])))

    @property
    def size(self) -> int:
        return self.basis.shape[1]

    @property
    def Phi(self) -> sp.csr_matrix:
        """Φ as a CSR matrix in global row order (a copy; the preconditioner applies ``basis``)."""
        return self.basis.tocsr()


def gdsw_coarse_space(A: sp.spmatrix, decomposition: Decomposition, interface: Interface,
                      kind: str = "gdsw", geometry: VertexGeometry | None = None,
                      rotation: bool = True, translation_mask: np.ndarray | None = None,
                      extension: HarmonicExtension | None = None, recycle=None) -> CoarseSpace:
    """GDSW (``kind="gdsw"``), RGDSW (``"rgdsw"``) or any space in :data:`COARSE_SPACES`
    (``"gdsw-linear"``, ``"rgdsw-linear"``: hat functions along interface entities, which need an
    interface from ``find_interface(..., group="two-hop")``), with or without rotations.

    Pass the same ``extension`` for successive matrices to reuse its symbolic work, and a previous
    basis of it that is no longer used as ``recycle`` to reuse its storage."""
    rows, cols, vals, column_component, col_subdomains = coarse_columns(
        decomposition, interface, kind, geometry, rotation, translation_mask)
    extension = extension or HarmonicExtension(decomposition, interface)
    Phi, A0 = extension(A, rows, cols, vals, col_subdomains, recycle)
    return CoarseSpace(basis=Phi, A0=A0, column_component=column_component)


def coarse_columns(decomposition: Decomposition, interface: Interface, kind: str = "gdsw",
                   geometry: VertexGeometry | None = None, rotation: bool = True,
                   translation_mask: np.ndarray | None = None, keep: bool = False):
    """Φ_Γ as triplets (global dof, column, value), the component of each column and the
    (columns × subdomains) incidence of the subdomains each column's extension reaches.

    ``keep=True`` (the memory estimate before a build) leaves the result on the interface for the
    next call with the same arguments and poses, which takes it (the build itself): computed once."""
    key = (kind, rotation, id(translation_mask), id(decomposition))
    kept = interface.__dict__.pop("_kept_coarse_columns", None)
    if kept is not None and kept[0] == key and _same_geometry(kept[1], geometry):
        return kept[2]
    offsets = decomposition.structure.offsets
    rows, cols, vals, column_component = interface_values(
        interface, offsets, kind, geometry, rotation, translation_mask)
    if not len(column_component):
        col_subdomains = sp.csr_matrix((0, decomposition.n_subdomains))
    elif kind in COMPONENT_SPACES:
        col_subdomains = sp.csr_matrix(interface.component_subdomains()[column_component])
    else:
        last = interface.__dict__.get("_column_subdomains")  # the same (cached) triplet pattern: reused
        if last is not None and last[0] is rows and last[1] is cols:
            col_subdomains = last[2]
        else:
            col_subdomains = column_subdomains(interface, offsets, rows, cols, len(column_component))
            if not (rows.flags.writeable or cols.flags.writeable):  # a cached pattern: so is this
                col_subdomains.indptr.flags.writeable = col_subdomains.indices.flags.writeable = False
                interface.__dict__["_column_subdomains"] = (rows, cols, col_subdomains)
    result = rows, cols, vals, column_component, col_subdomains
    if keep:  # (a frozen dataclass's own dict, as the partitions of unity)
        interface.__dict__["_kept_coarse_columns"] = (key, geometry, result)
    return result


def _same_geometry(a: VertexGeometry | None, b: VertexGeometry | None) -> bool:
    if a is None or b is None:
        return a is b
    return (a is b or (np.array_equal(a.positions, b.positions) and np.array_equal(a.rotations, b.rotations)))
