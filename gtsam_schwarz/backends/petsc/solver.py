"""The nonlinear loop's linear solve on PETSc over MPI: KSPCG with the same two-level Schwarz
preconditioner as the serial solver.

Rows are owned by subdomain (``layout.rank_layout``: rank r owns the dofs of the nonoverlapping
vertex sets of its subdomains, renumbered to be contiguous). Two entries: ``solve(H, …)`` takes the
same whole H on every rank (each ran the serial linearization), copies its own rows into an MPIAIJ
matrix and returns the full step on every rank; ``solve_distributed(H, damping, b, …)`` takes H and b
already assembled in PETSc by the ranks (``distributed.DistributedOptimizer``) and leaves the step
distributed. The preconditioner is

    M⁻¹ = Σ_i R_iᵀ A_i⁻¹ R_i + Φ (ΦᵀAΦ)⁻¹ Φᵀ

with PCMG (two levels, additive, Galerkin coarse matrix) whose interpolation is our GDSW/RGDSW
basis Φ (each rank computes and contributes its own rows, ``coarse.LocalCoarseBasis``), whose
fine-level smoother is PCASM (basic, i.e. the symmetric additive Schwarz sum, on our overlapping
subdomains with overlap 0 on top; local Cholesky by CHOLMOD when this PETSc has it, else PETSc's
own with nested dissection) applied once (preonly), and whose coarse solve is redundant LU.
CG stops on the unpreconditioned residual ‖r‖ ≤ tol·‖b‖, as ``krylov.pcg``; λ estimates come
from KSP's Lanczos matrix. ``solve`` gathers the solution onto every rank (``VecScatter.toAll``), so
the nonlinear loop takes identical decisions on all ranks.

The lagging policy is :class:`~gtsam_schwarz.nonlinear.linear_solver.PreconditionedCG`'s (same
parameters, same decisions): a lagged solve keeps the PC (KSPSetReusePreconditioner) while the
operator gets the new numbers.
"""

from __future__ import annotations

import itertools
import time

import numpy as np
import scipy.sparse as sp

from ...dd.interface import find_interface
from ...nonlinear.linear_solver import PreconditionedCG
from ...nonlinear.params import LinearSolverParams
from ...nonlinear.records import SolveResult
from ...schwarz import REGISTRY
from ...schwarz.one_level import AdditiveSchwarz, BlockJacobi
from ...schwarz.pointwise import Identity, Jacobi
from ...schwarz.two_level import TwoLevelSchwarz
from ...solvers import EntryChange, Gather
from ...util.gathered import stored
from .coarse import LocalCoarseBasis
from .layout import RankLayout, rank_layout

_ids = itertools.count()
HISTORY_MAX = 100_000  # residual norms kept per solve
DIVERGENCE = 1e300  # no divergence test: krylov.pcg has none either
# A₀ = ΦᵀAΦ by PCMG's Galerkin product (PtAP), or as the serial code computes it: since Φ is discrete
# harmonic, (AΦ)_I = 0 and A₀ = Φ_Γᵀ(AΦ)_Γ = (A Φ_Γ)ᵀ Φ, two products with the few interface rows of Φ
COARSE_MATRICES = ("galerkin", "harmonic")


def petsc():
    """petsc4py's PETSc module (initialized on first use)."""
    from petsc4py import PETSc

    return PETSc


_CHOLMOD = None


def cholmod_available() -> bool:
    """Whether this PETSc factors a SEQAIJ matrix with CHOLMOD (tried once on a 2 × 2 matrix)."""
    global _CHOLMOD
    if _CHOLMOD is None:
        PETSc = petsc()
        ok = False
        try:
            if PETSc.Sys.hasExternalPackage("suitesparse"):
                M = PETSc.Mat().createAIJ(size=(2, 2), csr=(np.array([0, 1, 2], dtype=PETSc.IntType),
                                                            np.array([0, 1], dtype=PETSc.IntType),
                                                            np.array([2.0, 3.0])), comm=PETSc.COMM_SELF)
                ksp = PETSc.KSP().create(PETSc.COMM_SELF)
                ksp.setOperators(M)
                ksp.setType("preonly")
                pc = ksp.getPC()
                pc.setType("cholesky")
                pc.setFactorSolverType("cholmod")
                ksp.setUp()
                b, x = M.createVecs()
                b.set(1.0)
                ksp.solve(b, x)
                ok = bool(abs(x.getArray()[1] - 1.0 / 3.0) < 1e-12)
                for o in (ksp, M, b, x):
                    o.destroy()
        except Exception:  # noqa: BLE001 — any failure means: use PETSc's own Cholesky
            ok = False
        _CHOLMOD = ok
    return _CHOLMOD


def _kind(name: str, grouping: str = "components"):
    """("two-level", kind, rotation, interface grouping) | ("one-level",) | ("jacobi",) | ("pbjacobi",) |
    ("none",) | ("direct",) for a registered preconditioner name (``grouping``: the params' default)."""
    if name == "direct":
        return ("direct",)
    if name == "auto":  # the serial cost model's choice is per graph; over MPI the Schwarz solver is the point
        return ("two-level", "gdsw", True, grouping)
    try:
        cls, fixed = REGISTRY[name]
    except KeyError:
        raise ValueError(f"unknown preconditioner {name!r}") from None
    if issubclass(cls, TwoLevelSchwarz):
        return ("two-level", fixed.get("kind", "gdsw"), fixed.get("rotation", True),
                fixed.get("interface_grouping", grouping))
    if issubclass(cls, BlockJacobi):
        return ("pbjacobi",)
    if issubclass(cls, AdditiveSchwarz):
        return ("one-level",)
    if issubclass(cls, Jacobi):
        return ("jacobi",)
    if issubclass(cls, Identity):
        return ("none",)
    raise ValueError(f"preconditioner {name!r} has no PETSc counterpart (supported: two-level Schwarz "
                     f"(gdsw, rgdsw, …), one-level, block-jacobi, jacobi, none, direct)")


class _Operator:
    """What the lagging policy of PreconditionedCG looks at (``operator is None``, ``coarse_size``)."""

    def __init__(self, coarse_size: int = 0):
        self.coarse_size = coarse_size
        self.uses_geometry = False


class PetscSchwarzSolver(PreconditionedCG):
    """``LinearSolver`` on PETSc: ``solve(H, rhs, tol, geometry) → SolveResult`` with the full step on
    every rank. ``comm``: a petsc4py communicator (default COMM_WORLD). ``local_solver``: "auto"
    (CHOLMOD if this PETSc has it, else "petsc"), "cholmod", "petsc" or "mumps" for the subdomain
    factorizations. ``options``: extra PETSc options (without the solver's prefix, e.g.
    ``{"ksp_monitor": ""}``). ``coarse_matrix``: "harmonic" (A₀ = (AΦ_Γ)ᵀΦ, as the serial code; default,
    about 20× cheaper on M3500) or "galerkin" (PCMG's PtAP, PCMGSetGalerkin)."""

    takes_gathered = False   # H is copied into PETSc's matrix whole
    own_factors = False   # the subdomain factors are PETSc's

    def __init__(self, params: LinearSolverParams, offsets: np.ndarray, translation_mask: np.ndarray,
                 comm=None, local_solver: str = "auto", options: dict | None = None,
                 coarse_matrix: str = "harmonic"):
        super().__init__(params, offsets, translation_mask)
        self.PETSc = PETSc = petsc()
        self.comm = comm if comm is not None else PETSc.COMM_WORLD
        self.rank, self.size = self.comm.getRank(), self.comm.getSize()
        self.kind = _kind(params.preconditioner, params.interface_grouping)
        if local_solver == "auto":
            local_solver = "cholmod" if cholmod_available() else "petsc"
        if local_solver not in ("cholmod", "petsc", "mumps"):
            raise ValueError(f"local_solver must be auto, cholmod, petsc or mumps, got {local_solver!r}")
        self.local_solver = local_solver
        if coarse_matrix not in COARSE_MATRICES:
            raise ValueError(f"coarse_matrix must be one of {', '.join(COARSE_MATRICES)}, got {coarse_matrix!r}")
        self.coarse_matrix = coarse_matrix
        self.extra_options = dict(options or {})
        self.prefix = f"gs{next(_ids)}_"
        self.layout: RankLayout | None = None
        self.ksp = self.A = self.P = self.A0 = None
        self._gamma = None  # bool over the original dofs: interface dofs
        self._rows = None  # Gather of the rank's rows of H, permuted
        self._basis = None  # LocalCoarseBasis
        self._P_pattern = None
        self._coarse_size = 0
        self._scatter = self._xall = self._b = self._x = self._d = None
        self._b_external = False  # _b is the caller's Vec (solve_distributed): not ours to destroy
        self._orig_rows = None  # (permutation, indices, indptr): this rank's rows of A, original numbering
        self.timings = {"assemble": 0.0, "coarse_basis": 0.0, "pc_setup": 0.0, "ksp_solve": 0.0, "gather": 0.0}

    # -- layout and assembly --------------------------------------------------------------------
    def _layout(self, H, geometry=None) -> RankLayout:
        if self.layout is None:
            if self.kind[0] in ("two-level", "one-level"):
                self.layout = rank_layout(self._decompose(H, geometry), self.size)
            else:  # no subdomains needed: contiguous blocks of vertices
                self.layout = _vertex_layout(self.offsets, self.size)
        return self.layout

    def _assemble(self, H: sp.csr_matrix) -> bool:
        """The rank's rows of H (new numbering) into ``self.A``; True when A was (re)created."""
        PETSc = self.PETSc
        lay = self._layout(H)
        lo, hi = lay.rows(self.rank)
        if self._rows is None:
            rows, order = lay.order[lo:hi], lay.order
            self._rows = Gather(lambda M: M[rows][:, order])
        pattern = self._rows.pattern
        L = self._rows(H)
        if self.A is not None and self._rows.pattern is pattern:
            self.A.setValuesCSR(L.indptr.astype(PETSc.IntType), L.indices.astype(PETSc.IntType), L.data)
            self.A.assemble()
            return False
        for o in (self.A, self.ksp):
            if o is not None:
                o.destroy()
        self.ksp = None
        n = lay.n
        bsize = None
        if self.kind[0] == "pbjacobi":  # point-block Jacobi: one block per variable
            dims = np.diff(self.offsets)
            if len(dims) == 0 or np.any(dims != dims[0]):
                raise ValueError("block-jacobi on PETSc needs variables of one dimension")
            bsize = int(dims[0])
        self.A = PETSc.Mat().createAIJ(size=((hi - lo, n), (hi - lo, n)), bsize=bsize,
                                       csr=(L.indptr.astype(PETSc.IntType), L.indices.astype(PETSc.IntType),
                                            L.data), comm=self.comm)
        self.A.setOption(PETSc.Mat.Option.NEW_NONZERO_ALLOCATION_ERR, True)
        self.A.assemble()
        if self.A.getOwnershipRange() != (lo, hi):
            raise AssertionError(f"PETSc rows {self.A.getOwnershipRange()} != layout rows {(lo, hi)}")
        self._b, self._x = self.A.createVecs()[::-1]
        self._scatter, self._xall = PETSc.Scatter.toAll(self._x)
        return True

    # -- coarse basis ---------------------------------------------------------------------------
    def _coarse(self, H, geometry):
        """The rank's rows of Φ into ``self.P``; True when P was (re)created (new pattern)."""
        PETSc = self.PETSc
        lay = self.layout
        lo, hi = lay.rows(self.rank)
        if self._basis is None:
            _, kind, rotation, grouping = self.kind
            interface = find_interface(self.decomposition, grouping)
            self._basis = LocalCoarseBasis(self.decomposition, interface, lay.subdomains(self.rank),
                                           lay.dof_rank == self.rank, kind, rotation, self.translation_mask)
        rigid = self.params.coarse_modes == "rigid"
        rows, cols, vals, nc = self._basis(H, geometry() if rigid else None)
        L = sp.csr_matrix((vals, (lay.position[rows] - lo, cols)), shape=(hi - lo, nc))
        L.sort_indices()
        nc_all = self.comm.tompi4py().allreduce(nc, op=_mpi().MAX) if self.size > 1 else nc
        if nc_all != nc:
            raise AssertionError("ranks disagree on the coarse dimension")
        self._coarse_size = nc
        if self.coarse_matrix == "harmonic":
            if self._gamma is None:
                itf = self._basis.interface
                self._gamma = np.repeat(itf.interior_subdomain < 0, np.diff(self.offsets))
            g = self._gamma[rows]
            LG = sp.csr_matrix((vals[g], (lay.position[rows[g]] - lo, cols[g])), shape=(hi - lo, nc))
            LG.sort_indices()
            PG = PETSc.Mat().createAIJ(size=((hi - lo, lay.n), (None, nc)),
                                       csr=(LG.indptr.astype(PETSc.IntType), LG.indices.astype(PETSc.IntType),
                                            LG.data), comm=self.comm)
            PG.assemble()
            self._PG = PG
        indptr, indices = L.indptr.astype(PETSc.IntType), L.indices.astype(PETSc.IntType)
        same = (self.P is not None and self._P_pattern is not None and self._P_pattern[0] == L.shape
                and np.array_equal(self._P_pattern[1], indptr) and np.array_equal(self._P_pattern[2], indices))
        same = self._all(same)
        if same:
            self.P.setValuesCSR(indptr, indices, L.data)
            self.P.assemble()
            return False
        if self.P is not None:
            self.P.destroy()
        self.P = PETSc.Mat().createAIJ(size=((hi - lo, lay.n), (None, nc)), csr=(indptr, indices, L.data),
                                       comm=self.comm)
        self.P.assemble()
        self._P_pattern = (L.shape, indptr, indices)
        return True

    def _harmonic_coarse_matrix(self, new: bool) -> None:
        """A₀ = (A Φ_Γ)ᵀ Φ into ``self.A0`` (values copied into the old A₀ when its pattern stays)."""
        PETSc = self.PETSc
        AP = self.A.matMult(self._PG)
        A0 = AP.transposeMatMult(self.P)
        AP.destroy()
        self._PG.destroy()
        if new or self.A0 is None:
            if self.A0 is not None:
                self.A0.destroy()
            self.A0 = A0
            return
        A0.copy(self.A0, structure=PETSc.Mat.Structure.SAME_NONZERO_PATTERN)
        A0.destroy()

    def _all(self, flag: bool) -> bool:
        """Logical and over the ranks (so that all take the same collective branch)."""
        if self.size == 1:
            return bool(flag)
        return bool(self.comm.tompi4py().allreduce(bool(flag), op=_mpi().LAND))

    # -- the KSP ----------------------------------------------------------------------------------
    def _options(self) -> dict:
        """The options database entries (without the prefix) that petsc4py 3.18 has no setter for."""
        sub = {"ksp_type": "preonly", "pc_type": "cholesky"}
        if self.local_solver == "cholmod":
            sub["pc_factor_mat_solver_type"] = "cholmod"
        elif self.local_solver == "mumps":
            sub["pc_factor_mat_solver_type"] = "mumps"
        else:
            sub["pc_factor_mat_ordering_type"] = "nd"
        opts = {}
        kind = self.kind[0]
        if kind == "two-level":
            opts["pc_mg_galerkin"] = "both" if self.coarse_matrix == "galerkin" else "none"
            opts.update({f"mg_levels_1_sub_{k}": v for k, v in sub.items()})
            opts["mg_coarse_redundant_pc_type"] = "lu"
            opts["mg_coarse_redundant_pc_factor_mat_ordering_type"] = "nd"
        elif kind == "one-level":
            opts.update({f"sub_{k}": v for k, v in sub.items()})
        elif kind == "direct":
            opts["pc_factor_mat_solver_type"] = "mumps" if self.size > 1 or self.local_solver == "mumps" else \
                ("cholmod" if self.local_solver == "cholmod" else "petsc")
        opts.update(self.extra_options)
        return opts

    def _subdomain_sets(self):
        PETSc = self.PETSc
        sets = self.decomposition.index_sets(overlapping=True)
        return [PETSc.IS().createGeneral(idx.astype(PETSc.IntType), comm=PETSc.COMM_SELF)
                for idx in self.layout.index_sets(sets, self.rank)]

    def _asm(self, pc):
        pc.setType("asm")
        pc.setASMType(self.PETSc.PC.ASMType.BASIC)  # Σ R_iᵀ A_i⁻¹ R_i, symmetric (not restricted)
        subsets = self._subdomain_sets()
        pc.setASMLocalSubdomains(len(subsets), subsets)
        pc.setASMOverlap(0)  # after the subdomains: setting them resets the overlap; ours already overlap

    def _create_ksp(self):
        PETSc = self.PETSc
        db = PETSc.Options(self.prefix)
        for k, v in self._options().items():
            db[k] = v
        ksp = PETSc.KSP().create(self.comm)
        ksp.setOptionsPrefix(self.prefix)
        ksp.setOperators(self.A)
        pc = ksp.getPC()
        kind = self.kind[0]
        if kind == "direct":
            ksp.setType("preonly")
            pc.setType("cholesky")
        else:
            ksp.setType("cg")
            ksp.setNormType(PETSc.KSP.NormType.UNPRECONDITIONED)  # ‖b − Ax‖, as krylov.pcg
            ksp.setComputeSingularValues(True)  # Lanczos λ estimates
            if kind == "two-level":
                pc.setType("mg")
                pc.setMGLevels(2)
                pc.setMGType(PETSc.PC.MGType.ADDITIVE)  # ASM(r) + Φ A₀⁻¹ Φᵀ r
                pc.setMGInterpolation(1, self.P)
                smoother = pc.getMGSmoother(1)
                smoother.setType("preonly")
                self._asm(smoother.getPC())
                coarse = pc.getMGCoarseSolve()
                if self.coarse_matrix == "harmonic":
                    coarse.setOperators(self.A0)
                coarse.setType("preonly")
                coarse.getPC().setType("redundant")
            elif kind == "one-level":
                self._asm(pc)
            elif kind == "jacobi":
                pc.setType("jacobi")
            elif kind == "pbjacobi":
                pc.setType("pbjacobi")
            else:
                pc.setType("none")
        ksp.setFromOptions()
        self.ksp = ksp

    def _build(self, H_rows, geometry):
        """New numbers into the preconditioner (rebuilt: factorizations, Φ, A₀); ``H_rows()`` gives H's
        rows of this rank in the original numbering (for the coarse basis)."""
        t0 = time.perf_counter()
        recreate = self.ksp is None
        if self.kind[0] == "two-level":
            recreate |= self._coarse(H_rows(), geometry)
        t1 = time.perf_counter()
        if self.kind[0] == "two-level" and self.coarse_matrix == "harmonic":
            self._harmonic_coarse_matrix(new=recreate)
        if recreate:
            if self.ksp is not None:
                self.ksp.destroy()
            self._create_ksp()
        pc = self.ksp.getPC()
        pc.setReusePreconditioner(False)
        self.ksp.setUp()
        pc.setUp()  # KSPSetUp sets the PC up only the first time; the numeric rebuild belongs to setup
        pc.setUpOnBlocks()
        if self.kind[0] == "two-level":  # PCMG leaves its levels' factorizations to their first solve
            for level in (pc.getMGSmoother(1), pc.getMGCoarseSolve()):
                level.setUp()
                level.getPC().setUpOnBlocks()
        self.timings["coarse_basis"] += t1 - t0
        self.timings["pc_setup"] += time.perf_counter() - t1
        self.operator = _Operator(self._coarse_size)

    def _rebuild(self, H_rows, geometry, H) -> None:
        """:meth:`_build`, and the reference for H's change since this build: from the whole H where
        every rank has it, else from this rank's rows of the assembled matrix."""
        self._build(H_rows, geometry)
        self._change = None
        if self.params.lagged_preconditioner:
            self._change = EntryChange(H) if H is not None else self._own_change()

    def _own_rows(self) -> sp.csr_matrix:
        """This rank's rows of the assembled matrix as a (rows × n) CSR, layout numbering."""
        lo, hi = self.layout.rows(self.rank)
        indptr, indices, data = self.A.getValuesCSR()
        return sp.csr_matrix((data, indices, indptr), shape=(hi - lo, self.layout.n))

    def _own_change(self) -> EntryChange:
        """A distributed :class:`EntryChange` of this rank's rows, scaled by the whole diagonal."""
        diagonal = self.A.getDiagonal()
        if self._scatter is None:  # (solve_distributed: no gathered solution so far)
            self._scatter, self._xall = self.PETSc.Scatter.toAll(diagonal)
        self._scatter.scatter(diagonal, self._xall, addv=self.PETSc.InsertMode.INSERT,
                              mode=self.PETSc.ScatterMode.FORWARD)
        diagonal.destroy()
        d = self._xall.getArray(readonly=True).copy()
        return EntryChange(self._own_rows(), seed=self.rank, diagonal=d, first_row=self.layout.rows(self.rank)[0])

    def _matrix_change(self, H) -> float | None:
        """Serial :class:`EntryChange` where H is the whole scipy matrix; for the assembled PETSc
        matrix (distributed), the sums over every rank's own rows."""
        if self._change is None or sp.issparse(H):
            return super()._matrix_change(H)
        total, count = self._change.sums(self._own_rows())
        if self.size > 1:
            comm = self.comm.tompi4py()
            total, count = comm.allreduce(total, op=_mpi().SUM), comm.allreduce(count, op=_mpi().SUM)
        return float(np.sqrt(total / count)) if count else 0.0

    def _ksp_solve(self, tol: float, maxiter: int, warm: bool):
        """KSP solve to relative residual ``tol`` within ``maxiter`` iterations."""
        ksp = self.ksp
        ksp.setTolerances(rtol=tol, atol=0.0, divtol=DIVERGENCE, max_it=maxiter)
        ksp.setInitialGuessNonzero(warm)
        ksp.setConvergenceHistory(length=min(maxiter + 1, HISTORY_MAX), reset=True)
        t0 = time.perf_counter()
        ksp.solve(self._b, self._x)
        self.timings["ksp_solve"] += time.perf_counter() - t0
        its = int(ksp.getIterationNumber()) if self.kind[0] != "direct" else 0
        reason = int(ksp.getConvergedReason())
        history = np.asarray(ksp.getConvergenceHistory(), dtype=float)
        lmin = lmax = float("nan")
        if self.kind[0] != "direct" and its > 0:
            try:
                lmax, lmin = (float(v) for v in ksp.computeExtremeSingularValues())
            except Exception:  # noqa: BLE001 — estimates are informative only
                pass
        return its, reason, history, lmin, lmax

    # -- LinearSolver ------------------------------------------------------------------------------
    def refinable(self) -> bool:
        return False   # KSP solves to tol: no bound of what it left, no continuation

    def solve(self, H, rhs, tol, geometry, decrement_tol=None, decrement_left=None):  # decrement_*: not used (KSP solves to tol)
        """CG to relative residual ``tol`` (same lagging decisions as PreconditionedCG); the step x
        in the original numbering, complete on every rank."""
        t0 = time.perf_counter()
        H = stored(H)
        self._layout(H, geometry)   # the serial solver's subdomains (its partition sees the poses too)
        created = self._assemble(H)
        lay = self.layout
        lo, hi = lay.rows(self.rank)
        self.timings["assemble"] += time.perf_counter() - t0
        rhs = np.asarray(rhs, dtype=float)
        self._b.setArray(rhs[lay.order[lo:hi]])
        result = self._solve_assembled(created, tol, geometry, lambda: H, float(np.linalg.norm(rhs)), t0, H)
        t3 = time.perf_counter()
        self._scatter.scatter(self._x, self._xall, addv=self.PETSc.InsertMode.INSERT,
                              mode=self.PETSc.ScatterMode.FORWARD)
        result.x = lay.unpermute(self._xall.getArray(readonly=True).copy())
        self.timings["gather"] += time.perf_counter() - t3
        return result

    def set_layout(self, structure_matrix: sp.spmatrix, geometry=None) -> RankLayout:
        """Decompose (once) from a matrix with H's block pattern and fix the rows of every rank
        (``geometry``: the poses, for the geometric partition, as the serial solver's first solve has)."""
        return self._layout(sp.csr_matrix(structure_matrix), geometry)

    def solve_distributed(self, H, damping: np.ndarray | None, b, tol, geometry):
        """(H + diag(damping)) x = b, H, b and damping already distributed (layout numbering); ``result.x``
        is the solver's own distributed Vec, valid until the next solve."""
        PETSc = self.PETSc
        t0 = time.perf_counter()
        lay = self.layout
        lo, hi = lay.rows(self.rank)
        created = self.A is None
        if created:
            self.A = H.duplicate(copy=True)
            self.A.setOption(PETSc.Mat.Option.NEW_NONZERO_ALLOCATION_ERR, True)
            self._x, self._d = self.A.createVecs()
            self._orig_rows = None
        else:
            H.copy(self.A, structure=PETSc.Mat.Structure.SAME_NONZERO_PATTERN)
        if damping is not None:
            self._d.setArray(np.asarray(damping, dtype=float))
            self.A.setDiagonal(self._d, addv=PETSc.InsertMode.ADD_VALUES)
        self._b, self._b_external = b, True
        self.timings["assemble"] += time.perf_counter() - t0
        return self._solve_assembled(created, tol, geometry, self._local_rows, float(b.norm()), t0)

    def _local_rows(self) -> sp.csr_matrix:
        """This rank's rows of A in the original numbering as an n × n CSR (the coarse basis reads them)."""
        lay = self.layout
        lo, hi = lay.rows(self.rank)
        indptr, indices, data = self.A.getValuesCSR()
        if self._orig_rows is None or len(self._orig_rows[0]) != len(data):
            r = lay.order[lo + np.repeat(np.arange(hi - lo), np.diff(indptr))]
            C = sp.csr_matrix((np.arange(1, len(data) + 1, dtype=float), (r, lay.order[indices])), shape=(lay.n, lay.n))
            C.sort_indices()
            self._orig_rows = (C.data.astype(np.int64) - 1, C.indices, C.indptr)
        perm, cols, ptr = self._orig_rows
        return sp.csr_matrix((data[perm], cols, ptr), shape=(lay.n, lay.n))

    def _solve_assembled(self, created: bool, tol: float, geometry, H_rows, bnorm: float, t0: float,
                         H: sp.csr_matrix | None = None) -> SolveResult:
        """KSP solve of ``self.A`` x = ``self._b`` with the lagging policy; ``H_rows()``: this rank's rows
        of H, original numbering (for the coarse basis). ``H``: the whole matrix where every rank has
        it (:meth:`solve`), whose change since the build is checked as in the serial solver; None
        (:meth:`solve_distributed`): the change of the assembled matrix, summed over the ranks."""
        p = self.params
        cap = None if created else self._lag_cap(H if H is not None else self.A)
        lagged = cap is not None
        self._rebuilt = not lagged
        if lagged:
            self.ksp.getPC().setReusePreconditioner(True)
        else:
            self._rebuild(H_rows, geometry, H)
        setup = time.perf_counter() - t0
        n = self.layout.n
        maxiter = cap if lagged else (p.cg_max_iterations or 10 * n)
        its, reason, history, lmin, lmax = self._ksp_solve(tol, maxiter, warm=False)
        residuals = list(history / bnorm) if bnorm > 0 else [0.0]
        converged = reason > 0
        if lagged and not converged:  # stale: rebuild for H, continue from x
            t2 = time.perf_counter()
            self._rebuilt = True
            self._rebuild(H_rows, geometry, H)
            setup += time.perf_counter() - t2
            more, reason, history, lmin, lmax = self._ksp_solve(tol, p.cg_max_iterations or 10 * n, warm=True)
            its += more
            residuals += list(history[1:] / bnorm) if bnorm > 0 else []
            converged = reason > 0
            self._moved = 0.0  # the warm-started count is no reference: keep the previous one
        elif self._rebuilt:
            self._cg_after_build, self._moved = its, 0.0
        return SolveResult(x=self._x, iterations=its, converged=converged, lambda_min=lmin, lambda_max=lmax,
                           residuals=residuals, tolerance=tol if self.kind[0] != "direct" else 0.0,
                           setup_seconds=setup, coarse_size=self._coarse_size, rebuilt=self._rebuilt,
                           lagged=lagged)

    # -- checks -------------------------------------------------------------------------------------
    def apply_preconditioner(self, r: np.ndarray) -> np.ndarray:
        """M⁻¹ r (original numbering, full vector on every rank) with the current PC: for tests."""
        lay = self.layout
        lo, hi = lay.rows(self.rank)
        self._b.setArray(np.asarray(r, dtype=float)[lay.order[lo:hi]])
        self.ksp.getPC().apply(self._b, self._x)
        self._scatter.scatter(self._x, self._xall, addv=self.PETSc.InsertMode.INSERT,
                              mode=self.PETSc.ScatterMode.FORWARD)
        return lay.unpermute(self._xall.getArray(readonly=True).copy())

    def destroy(self) -> None:
        for o in (self.ksp, self.A, self.P, self.A0, None if self._b_external else self._b, self._x, self._xall,
                  self._scatter, self._d):
            if o is not None:
                o.destroy()
        self.ksp = self.A = self.P = self.A0 = None


def _mpi():
    from mpi4py import MPI

    return MPI


def _vertex_layout(offsets: np.ndarray, ranks: int) -> RankLayout:
    """Contiguous blocks of vertices (no subdomains): for point Jacobi, block Jacobi, none, direct."""
    from .layout import _balanced_runs

    dims = np.diff(offsets)
    nv = len(dims)
    if nv < ranks:
        raise ValueError(f"{nv} variables for {ranks} ranks")
    vrank = _balanced_runs(dims.astype(float), ranks)
    dof_rank = np.repeat(vrank, dims)
    order = np.arange(len(dof_rank))
    ranges = np.zeros(ranks + 1, dtype=np.int64)
    np.cumsum(np.bincount(dof_rank, minlength=ranks), out=ranges[1:])
    return RankLayout(ranks=ranks, subdomain_rank=np.zeros(0, np.int64), vertex_subdomain=vrank,
                      dof_rank=dof_rank, order=order, position=order.copy(), ranges=ranges)


def make_petsc_solver(params: LinearSolverParams, offsets: np.ndarray, translation_mask: np.ndarray,
                      **options) -> PetscSchwarzSolver:
    """The PETSc linear solver for ``params`` (``make_linear_solver``'s counterpart for
    ``backend="petsc"``); ``options``: ``comm``, ``local_solver``, ``options``."""
    return PetscSchwarzSolver(params, offsets, translation_mask, **options)
