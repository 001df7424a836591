"""Preconditioners M⁻¹ ≈ A⁻¹ for CG, each built once per linear system.

Like pyamg, every preconditioner offers ``aspreconditioner()`` → scipy ``LinearOperator``; like
FROSch, Schwarz operators add up: two-level = one-level overlapping operator + coarse operator.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import LinearOperator

from .coarse import CoarseSpace, HarmonicExtension, gdsw_coarse_space
from .decomposition import Decomposition
from .interface import find_interface
from .linear_system import VertexGeometry
from .local_solvers import BlockDiagonalSolver, IndexSets, SingularLocalMatrixError, factorize

PRECONDITIONERS = ("none", "jacobi", "block-jacobi", "one-level", "gdsw", "gdsw-norot", "rgdsw")


class Preconditioner:
    """Base: an SPD operator x ↦ M⁻¹x of dimension n."""

    n: int

    def matvec(self, x: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def __call__(self, x):
        return self.matvec(x)

    def __add__(self, other: "Preconditioner") -> "Preconditioner":
        return SumOperator([self, other])

    def update(self, A, geometry: VertexGeometry | None = None) -> "Preconditioner":
        """New numbers in A (same pattern), and new poses for a rigid coarse space; symbolic work
        is kept."""
        raise NotImplementedError

    def aspreconditioner(self) -> LinearOperator:
        return LinearOperator((self.n, self.n), matvec=self.matvec, rmatvec=self.matvec, dtype=float)

    def todense(self) -> np.ndarray:
        """M⁻¹ as a dense matrix (for tests on small problems)."""
        return np.column_stack([self.matvec(e) for e in np.eye(self.n)])


class SumOperator(Preconditioner):
    """Additive combination Σ_k M_k⁻¹."""

    def __init__(self, parts):
        self.parts = list(parts)
        self.n = self.parts[0].n

    def update(self, A, geometry=None):
        for p in self.parts:
            p.update(A, geometry)
        return self

    def matvec(self, x):
        y = self.parts[0].matvec(x)
        for p in self.parts[1:]:
            y += p.matvec(x)
        return y


class Identity(Preconditioner):
    def __init__(self, A):
        self.n = A.shape[0]

    def update(self, A, geometry=None):
        return self

    def matvec(self, x):
        return np.array(x, dtype=float, copy=True)


class Jacobi(Preconditioner):
    """Point Jacobi: diag(A)⁻¹."""

    def __init__(self, A):
        self.n = A.shape[0]
        self.update(A)

    def update(self, A, geometry=None):
        d = np.asarray(sp.csr_matrix(A).diagonal(), dtype=float)
        if np.any(d <= 0) or not np.all(np.isfinite(d)):
            raise SingularLocalMatrixError("Jacobi: the matrix has a non-positive diagonal entry")
        self.inv_diag = 1.0 / d
        return self

    def matvec(self, x):
        return self.inv_diag * x


class AdditiveSchwarz(Preconditioner):
    """One-level additive Schwarz Σ_i R_iᵀ A_i⁻¹ R_i, A_i = R_i A R_iᵀ (paper Eq. OS-preconditioner)."""

    def __init__(self, A, sets: IndexSets):
        self.n = A.shape[0]
        self.sets = sets
        self.solver = BlockDiagonalSolver(A, sets)

    def update(self, A, geometry=None):
        """Same subdomains, new numbers: numeric refactorization only."""
        self.solver.update(A)
        return self

    def matvec(self, x):
        return self.solver.matvec(x)


class BlockJacobi(AdditiveSchwarz):
    """One block per variable (pose): Schwarz with nonoverlapping single-pose subdomains."""

    def __init__(self, A, offsets: np.ndarray):
        super().__init__(A, IndexSets(indices=np.arange(int(offsets[-1])), ptr=np.asarray(offsets), n=A.shape[0]))


class CoarseCorrection(Preconditioner):
    """R_0ᵀ A_0⁻¹ R_0 with R_0 = Φᵀ and A_0 = Φᵀ A Φ.

    A rank-deficient Φ (dependent coarse vectors) makes A_0 singular: then the dependent
    directions are dropped (pseudo-inverse on the range of the diagonally scaled A_0), which
    gives the same coarse space without them. ``dropped`` counts them.
    """

    DROP_TOL = 1e-10

    def __init__(self, coarse: CoarseSpace):
        self.coarse = coarse
        self.n = coarse.Phi.shape[0]
        self.PhiT = coarse.Phi.T.tocsr()
        self.dropped = 0
        try:
            self._solve = factorize(coarse.A0, "the coarse matrix A_0")
        except SingularLocalMatrixError:
            self._solve = self._range_solver(coarse.A0)

    def _range_solver(self, A0):
        nc = A0.shape[0]
        if nc > 8000:
            raise SingularLocalMatrixError(f"the coarse matrix A_0 ({nc} × {nc}) is singular")
        D = A0.diagonal()
        s = np.where(D > 0, 1.0 / np.sqrt(np.where(D > 0, D, 1.0)), 0.0)
        w, V = np.linalg.eigh(s[:, None] * A0.toarray() * s[None, :])
        keep = w > self.DROP_TOL * max(w.max(), 0.0)
        self.dropped = int(nc - keep.sum())
        W = s[:, None] * V[:, keep]
        inv = 1.0 / w[keep]
        return lambda r: W @ (inv * (W.T @ r))

    def matvec(self, x):
        if self.coarse.size == 0:
            return np.zeros(self.n)
        return self.coarse.Phi @ self._solve(self.PhiT @ x)


class TwoLevelSchwarz(SumOperator):
    """Two-level additive Schwarz: one-level operator + GDSW/RGDSW coarse correction (Sec. 3.3)."""

    def __init__(self, A, decomposition: Decomposition, kind: str = "gdsw", rotation: bool = True,
                 geometry: VertexGeometry | None = None, translation_mask: np.ndarray | None = None,
                 interface_grouping: str = "components"):
        self.decomposition = decomposition
        self.kind, self.rotation, self.translation_mask = kind, rotation, translation_mask
        self.interface = find_interface(decomposition, interface_grouping)
        self.extension = HarmonicExtension(decomposition, self.interface)
        self.one_level = AdditiveSchwarz(A, decomposition.index_sets(overlapping=True))
        self._build_coarse(A, geometry)

    def _build_coarse(self, A, geometry):
        self.coarse_space = gdsw_coarse_space(A, self.decomposition, self.interface, self.kind, geometry,
                                              self.rotation, self.translation_mask, self.extension)
        self.coarse = CoarseCorrection(self.coarse_space)
        super().__init__([self.one_level, self.coarse])

    def update(self, A, geometry: VertexGeometry | None = None):
        """New numbers in A (and poses in ``geometry``): interface, index sets, submatrix patterns
        and symbolic factorizations are kept; numbers, Φ and A_0 are recomputed."""
        self.one_level.update(A)
        self._build_coarse(A, geometry)
        return self


def make_preconditioner(name: str, A, decomposition: Decomposition | None = None,
                        translation_mask: np.ndarray | None = None,
                        geometry: VertexGeometry | None = None,
                        interface_grouping: str = "components") -> Preconditioner:
    """Build the preconditioner called ``name`` (one of :data:`PRECONDITIONERS`) for matrix A.

    ``geometry`` (poses at the linearization point) gives the coarse spaces rigid-body modes;
    without it they use unit vectors per interface dof.
    """
    if name == "none":
        return Identity(A)
    if name == "jacobi":
        return Jacobi(A)
    if name == "block-jacobi":
        if decomposition is None:
            raise ValueError("block-jacobi needs the variables' dof ranges (a decomposition)")
        return BlockJacobi(A, decomposition.structure.offsets)
    if name in ("one-level", "gdsw", "gdsw-norot", "rgdsw"):
        if decomposition is None:
            raise ValueError(f"{name} needs a decomposition")
        if name == "one-level":
            return AdditiveSchwarz(A, decomposition.index_sets(overlapping=True))
        mask = translation_mask if translation_mask is not None else np.ones(A.shape[0], dtype=bool)
        return TwoLevelSchwarz(A, decomposition, kind="rgdsw" if name == "rgdsw" else "gdsw",
                               rotation=name != "gdsw-norot", geometry=geometry,
                               translation_mask=mask, interface_grouping=interface_grouping)
    raise ValueError(f"unknown preconditioner {name!r}; choose one of {', '.join(PRECONDITIONERS)}")
