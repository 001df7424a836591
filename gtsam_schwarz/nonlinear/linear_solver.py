"""The linear-solve strategy of the nonlinear loop: H δ = −g by a direct factorization or by
preconditioned CG, with the preconditioner kept across linearizations (lagging) and inexact-Newton
forcing. The optimizer asks a :class:`LinearSolver` for a step and knows no preconditioner by name.
"""

from __future__ import annotations

import importlib
import time
from dataclasses import replace
from typing import Callable

import numpy as np
import scipy.sparse as sp

from ..dd.decomposition import decompose
from ..dd.geometry import VertexGeometry
from ..dd.partition import default_subdomains
from ..dd.structure import GraphStructure
from ..krylov import pcg
from ..schwarz import create_preconditioner
from ..dd.index_sets import IndexSets
from ..solvers import EntryChange, SparseCholesky, SparsityPattern, block_diagonal, cholesky_cost, pattern_cholesky_cost, vertex_pattern
from ..solvers import block_cholesky
from ..solvers.block_diagonal import BlockDiagonalSolver, vertex_block_order
from ..schwarz.memory import estimate_two_level, fit_memory
from ..util.threads import side_thread
from ..solvers.memory import FACTOR_BYTES, MATRIX_BYTES, InsufficientMemoryError, available_memory, gib
from ..util.gathered import stored
from ..util.sparse import as_csr
from .params import LinearSolverParams
from .records import SolveResult

Geometry = Callable[[], VertexGeometry | None]


class LinearSolver:
    """Solves H x = rhs for successive matrices of one graph (same pattern, new numbers)."""

    decomposition = None
    choice = ""  # the solver that runs (for "auto": the one it chose)
    # whether H may come as a GatheredCSR (values in the linearizer's source array): the solver reads
    # it only by products and gathers, never factorizes it whole
    takes_gathered = False
    reason = ""  # why (for "auto": the predicted costs)

    def fresh_saved_per_entry(self, nnz: int) -> int:
        """Bytes per entry of an H of ``nnz`` entries that a run with this solver touches fewer than the
        optimizer's prefault assumes (FRESH_BYTES_PER_ENTRY)."""
        return 0

    def solve(self, H: sp.csr_matrix, rhs: np.ndarray, tol: float, geometry: Geometry,
              decrement_tol: float | None = None, decrement_left: float | None = None) -> SolveResult:
        """H x = rhs to relative residual ``tol``. An iterative solver may stop earlier once the exact
        x would lower the quadratic model ½xᵀHx − rhsᵀx by at most ``decrement_tol`` and x is within
        ``decrement_left`` of that (then ``decrement_stop``); a direct one ignores both."""
        raise NotImplementedError

    def moved(self, step_max: float) -> None:
        """The linearization point moved by an accepted step of max-norm ``step_max``."""

    def refinable(self) -> bool:
        """Whether this solver bounds what CG left (``bound_left``) and :meth:`refine` continues its solves."""
        return False

    def refine(self, H, rhs, tol, previous: SolveResult, decrement_tol=None, decrement_left=None) -> SolveResult:
        """The last solve of H (``previous``, to a looser tolerance) continued to ``tol`` with the same
        preconditioner, counts merged."""
        raise NotImplementedError

    def release(self) -> None:
        """Drop the numbers held between solves (factorizations, coarse basis; the symbolic work is
        kept): the next solve computes them anew. For the end of a run, whose result is built next."""


class DirectSolver(LinearSolver):
    """Sparse Cholesky of H (CHOLMOD with one symbolic analysis, or SuperLU): the reference.

    Given the block ``offsets``, its first factorization is preceded by the predicted size of the
    factor (``solvers.cost``): one that would not fit ``memory_limit`` (None: what is available)
    stops with :class:`InsufficientMemoryError` instead of being killed by the operating system.

    ``lagged``: a new matrix is first solved by CG preconditioned with the last factor (the exact
    inverse of the last H + λD, close to one for the next), allowed at most ``LAG_MAX_ITERATIONS``
    and ``LAG_BUDGET`` × the measured time of refactorizing and solving; CG that falls behind the
    convergence rate this needs is given up and H refactorized. The solve that only confirms
    convergence then costs a few triangular solves instead of a factorization."""

    choice = "direct"
    LAG_BUDGET = 0.7  # share of a refactorization + solve that a lagged CG solve may spend
    LAG_MIN_ITERATIONS = 6  # a smaller cap (a factorization as cheap as a few solves) is not worth trying
    LAG_RATE_FROM = 3  # from this iteration on, CG must keep the rate that reaches tol within the cap
    # a lagged solve that converges does so in 4-12 iterations (the solve confirming convergence);
    # one that does not (the solve after a large first step, H far from the factor's) shows it by the
    # third: residual 5e-2-2e-1 against 1e-4-2e-3 (2D and 3D surveys, city10000, sphere2500)
    LAG_MAX_ITERATIONS = 12

    def __init__(self, offsets: np.ndarray | None = None, memory_limit=None, lagged: bool = True):
        self._pattern = self._factor = None
        self.offsets, self.memory_limit, self.lagged = offsets, memory_limit, lagged
        self._refactor_seconds = self._iteration_seconds = None  # measured: refactor + solve; SpMV + solve
        self.predicted_seconds = None  # the cost model's factorization + solve (check_memory's or the auto choice's)
        self.ordering = None  # "natural" where H's own order fills in as little as CHOLMOD's (set with the prediction)
        self._released = False  # the factor's numbers were dropped (release): refactorize, no lagged solve

    def check_memory(self, H) -> None:
        cost = cholesky_cost(H, self.offsets, natural=True)
        self.predicted_seconds = CostModel().direct(cost)
        self.ordering = "natural" if cost.natural_suffices else None
        need = FACTOR_BYTES * cost.nnz_L + MATRIX_BYTES * H.nnz
        available = available_memory(self.memory_limit)
        if need > available:
            raise InsufficientMemoryError(
                f"the direct factorization needs about {gib(need)} (nnz(L) {cost.nnz_L:.3g}, {cost.fill:.0f}x "
                f"nnz(H)) but {gib(available)} is available: use preconditioner='auto' or 'rgdsw-linear' "
                f"(Schwarz-CG) or more memory")

    def lag_cap(self) -> int:
        """CG iterations a lagged solve may take: LAG_BUDGET × (refactor + solve) / (SpMV + solve)."""
        if not (self.lagged and self._refactor_seconds and self._iteration_seconds):
            return 0
        return int(self.LAG_BUDGET * self._refactor_seconds / self._iteration_seconds)

    def _lagged_solve(self, H, rhs, tol) -> tuple[SolveResult | None, int]:
        """CG on H preconditioned by the previous factor; (None, iterations) when given up."""
        cap = self.lag_cap()
        if cap < self.LAG_MIN_ITERATIONS:
            return None, 0
        cap = min(cap, self.LAG_MAX_ITERATIONS)
        k = np.arange(cap + 1)  # ρ_k ≤ tol^(k/cap): behind the rate that converges within the cap, give up
        bounds = np.where(k >= self.LAG_RATE_FROM, tol ** (k / cap), np.inf)
        t0 = time.perf_counter()
        # to the tolerance, no Newton-decrement stop: its bound needs the Ritz estimate of λmin(M⁻¹H),
        # which a few iterations with a factor of a far matrix overestimate (3D 32x32x32 after a large
        # first step: λ̂min 0.46, λ̂max 70; the stop left the error 4.7e-7 relative above the minimum)
        x, info = pcg(H, rhs, self._factor, tol=tol, maxiter=cap, bounds=bounds)
        if info.iterations:
            self._iteration_seconds = (time.perf_counter() - t0) / info.iterations
        if not info.converged:
            return None, info.iterations
        return SolveResult(x=x, iterations=info.iterations, converged=True, lambda_min=info.lambda_min,
                           lambda_max=info.lambda_max, residuals=list(info.residuals), tolerance=tol,
                           rebuilt=False, lagged=True), info.iterations

    def solve(self, H, rhs, tol, geometry, decrement_tol=None, decrement_left=None):
        t0 = time.perf_counter()
        H = stored(H)
        fresh = self._factor is None or not self._pattern.matches(H)
        tried = 0
        if not fresh and not self._released:
            result, tried = self._lagged_solve(H, rhs, tol)
            if result is not None:
                return result
        t1 = time.perf_counter()
        if fresh:
            if self._factor is None and self.offsets is not None:
                self.check_memory(H)
            self._pattern, self._factor = SparsityPattern(H), SparseCholesky(H, "the Gauss-Newton matrix",
                                                                             ordering=self.ordering)
        else:
            self._factor.refactor(H)
        self._released = False
        t2 = time.perf_counter()
        x = self._factor.solve(rhs)
        t3 = time.perf_counter()
        if self.lagged:  # what a lagged solve saves, and (first time) what one of its iterations costs
            self._refactor_seconds = self._factor.factor_seconds + (t3 - t2)
            if fresh and self.predicted_seconds is not None:
                # a first factorization also allocates (and page-faults) the factor: at 1M 2D poses
                # 3.4 s against 0.4-0.5 s for a refactorization; the cost model's figure bounds it
                self._refactor_seconds = min(self._refactor_seconds, self.predicted_seconds)
            if self._iteration_seconds is None:  # one SpMV and one more (warm) solve
                self._factor.solve(H @ x)
                self._iteration_seconds = time.perf_counter() - t3
        return SolveResult(x=x, iterations=tried, setup_seconds=t3 - t1, tolerance=0.0, lagged=tried > 0,
                           exact=True)

    def release(self) -> None:
        if self._factor is not None:
            self._factor.release_numeric()
            self._released = True


class PreconditionedCG(LinearSolver):
    """CG preconditioned by the registered operator ``params.preconditioner``.

    The decomposition and the operator's symbolic setup are done on the first solve; afterwards
    each solve updates the operator's numbers, or keeps them (lagged) while H's entries have changed
    by less than ``lag_change`` (:class:`EntryChange`) and the poses have moved less than
    ``lag_distance`` since the build.
    """

    takes_gathered = True
    own_factors = True   # the subdomain factors are this package's (BlockDiagonalSolver), not a backend's

    def fresh_saved_per_entry(self, nnz: int) -> int:
        return self.block_factor_saving(nnz) if self.own_factors else 0

    @staticmethod
    def block_factor_saving(nnz: int) -> int:
        """The subdomain factors by blocks in single precision (from BlockDiagonalSolver.BLOCK_FROM
        entries) hold ~4.4 bytes per entry of L against CHOLMOD's 12: at 1M 2D lawnmower poses
        (nnz(L) ≈ 1.3·nnz(H)) the one-level factors 684 → 272 MiB and the interior factors 427 → ~160
        MiB, the run's own peak ~12 bytes per entry of H lower."""
        single = BlockDiagonalSolver.factor_dtype == np.float32 and nnz >= BlockDiagonalSolver.BLOCK_FROM
        return 12 if single else 0

    def __init__(self, params: LinearSolverParams, offsets: np.ndarray, translation_mask: np.ndarray):
        self.params = params
        self.choice = params.preconditioner
        self.offsets = np.asarray(offsets, dtype=np.int64)
        self.translation_mask = translation_mask
        self.operator = None
        self._cg_after_build = None  # CG iterations of the first solve after the last numeric build
        self._moved = float("inf")  # max-norm of the accepted steps since the preconditioner's build
        self._rebuilt = True  # the last solve recomputed the preconditioner's numbers
        self._change = None  # EntryChange from the matrix of the last build (None: unknown)
        self._subdomain_change = None  # EntryChange from the matrix the subdomains were last factorized for
        self._subdomains_kept = False  # the last build kept earlier subdomain factorizations
        self._transported = False  # the last build carried the coarse level to new poses (TwoLevelSchwarz.transport)
        self._decomposing = None  # the decomposition started by :meth:`prepare` (a Future), until taken
        self._block_order = None  # its subdomain blocks' order, started after it (a Future), until taken

    def n_subdomains(self) -> int:
        p = self.params
        nv = len(self.offsets) - 1
        if p.subdomains is not None:
            return p.subdomains
        dims = np.diff(self.offsets)
        return default_subdomains(nv, p.subdomain_size, int(np.bincount(dims).argmax()) if nv else 3, p.inexact_krylov)

    # graphs from this many vertices start their decomposition ahead of the first solve (:meth:`prepare`)
    AHEAD_FROM = 20_000

    def prepare(self, vertices: sp.csr_matrix, nnz: int, geometry=None) -> None:
        """Start the decomposition on the side thread before the first linearization, from H's vertex
        pattern ``vertices`` (the linearizer's fixed pattern, ``nnz`` entries of H) and the poses: it then runs beside the
        linearization and the automatic choice's analysis instead of after them (graphs from
        ``AHEAD_FROM`` vertices; :meth:`_decompose` takes the result)."""
        if self.decomposition is not None or self._decomposing is not None or vertices.shape[0] < self.AHEAD_FROM:
            return
        if self.own_factors and nnz >= BlockDiagonalSolver.BLOCK_FROM and self.choice not in ("none", "jacobi", "block-jacobi"):
            # the subdomain factors' kernels, loaded on a thread of their own before the first build
            block_cholesky.warm_up_later(block_cholesky.vertex_block(self.offsets), BlockDiagonalSolver.factor_dtype)
        structure = GraphStructure.from_vertex_pattern(vertices, self.offsets)
        coordinates = self._coordinates(geometry)   # read here: the poses may move once the loop runs
        self._decomposing = side_thread().submit(self._decompose_structure, structure, coordinates)
        # then, on the same thread, the subdomain blocks' fill-reducing order (CHOLMOD's, no GIL; 1M 2D
        # poses ~0.9 s), which the operator's setup would otherwise start after the first linearization
        # and wait for; an operator that orders no blocks does not take it
        self._block_order = side_thread().submit(self._order_blocks, self._decomposing, vertices)

    @staticmethod
    def _order_blocks(decomposing, vertices: sp.csr_matrix):
        sets = decomposing.result().index_sets(overlapping=True)
        return vertex_block_order(vertices, sets) if sets.vertices is not None and sets.count else None

    def _coordinates(self, geometry):
        """The poses' positions for the geometric partition (None where it is not asked for)."""
        if geometry is None or self.params.partition not in ("auto", "geometric"):
            return None
        g = geometry() if callable(geometry) else geometry
        return None if g is None else g.positions

    def _decompose_structure(self, structure: GraphStructure, coordinates):
        p = self.params
        return decompose(structure, self.n_subdomains(), p.partition, p.overlap_layers(), p.grow_along, coordinates)

    def _decompose(self, H, geometry=None):
        """The decomposition (made on the first call, or started by :meth:`prepare`): ``geometry`` (a
        :class:`VertexGeometry` or a callable giving one) lends the poses' positions to the geometric
        partition."""
        if self.decomposition is None and self._decomposing is not None:
            job, self._decomposing = self._decomposing, None
            self.decomposition = job.result()
        if self.decomposition is None:
            self.decomposition = self._decompose_structure(GraphStructure.from_matrix(H, self.offsets),
                                                           self._coordinates(geometry))
        return self.decomposition

    def _new_operator(self, p: LinearSolverParams, H, geometry):
        """The operator ``p.preconditioner`` on the decomposition, set up for H's pattern (with the
        subdomain blocks' order found ahead, where :meth:`prepare` started one)."""
        M = create_preconditioner(p.preconditioner, H.shape[0], self._decompose(H, geometry), self.translation_mask,
                                  interface_grouping=p.interface_grouping, coarse_modes=p.coarse_modes,
                                  memory_limit=p.memory_limit)
        order, self._block_order = self._block_order, None
        if order is not None and hasattr(M, "block_order"):
            M.block_order = order
        M.setup(H)
        return M

    def moved(self, step_max: float) -> None:
        self._moved += step_max
        release = getattr(self.operator, "release", None)
        if release is not None and self._lag_cap() is None and not self._may_transport():
            release()  # the next solve rebuilds: drop what it replaces now

    def ahead(self, geometry) -> None:
        """The poses moved (an accepted step) and the next linearization comes: where the next solve
        may carry the coarse level to them (:meth:`_may_transport`) and cannot keep M lagged (the
        poses moved at least ``lag_distance``), Φ's multiplication starts now on the side thread
        (``TwoLevelSchwarz.transport_ahead``); ``geometry``: a callable giving the poses."""
        M = self.operator
        if self._may_transport() and self._lag_cap() is None and hasattr(M, "transport_ahead"):
            M.transport_ahead(geometry())

    def _may_transport(self) -> bool:
        """Whether the next solve may carry the coarse level to the new poses (and keep the subdomain
        factorizations): then they are kept until that solve's test of H's change."""
        M = self.operator
        return (hasattr(M, "transport") and self.params.transport_coarse and self.params.lagged_preconditioner
                and self._subdomain_change is not None and M.subdomains_factored and M.coarse is not None)

    def release(self) -> None:
        release = getattr(self.operator, "release", None)
        if release is not None:
            release(factors=True)
            self._cg_after_build = self._change = self._subdomain_change = None   # the next solve rebuilds

    def _lag_cap(self, H=None) -> int | None:
        """Lagged preconditioner: keep the previous M while H's entries have changed by less than
        ``lag_change`` since M was built (diagonally scaled RMS, :class:`EntryChange`; not checked
        without ``H``) and the linearization point has moved less than ``lag_distance`` (sum of the
        steps' max-norms; a rejected LM step moves nothing, only λ changes). CG may then use it for
        at most ``lag_growth`` × its count right after the build; None: build M anew.

        Measured change of H after LM's first step from the chordal start: 1.7e-4 (3D survey
        32x32x32; a lagged M took 55 CG iterations against 10 fresh), 2.0e-4 (3D 8x24x24: 36
        against 18), 3.0e-4-3.2e-4 (lawnmower 100x100 to 600x600), 5.2e-4 (city10000), 1.2e-3
        (M3500, sphere2500). After the second step: 4.7e-6-4.4e-5 on the surveys and city10000
        (lawnmower 600x600: a lagged M took 5 iterations to the fresh one's 5, same residuals)."""
        p = self.params
        if (not p.lagged_preconditioner or self.operator is None or self._cg_after_build is None
                or self._moved >= p.lag_distance):
            return None
        if H is not None:
            change = self._matrix_change(H)
            if change is None or change > p.lag_change:
                return None
        return int(p.lag_growth * self._cg_after_build) + 2

    def _matrix_change(self, H) -> float | None:
        """:class:`EntryChange` of H since the last build (None: no build to compare with)."""
        return None if self._change is None else self._change(H)

    def preconditioner(self, H, geometry: Geometry, lag: bool = False, subdomains: bool = False):
        """The operator for H: created and set up on the first call, afterwards updated in place
        (same subdomains, interface, submatrix patterns and symbolic factorizations; new numbers).
        ``lag=True`` returns the previous one unchanged. A two-level operator keeps its subdomain
        factorizations while H has changed by at most ``subdomain_lag_change`` since them, unless
        ``subdomains`` (refactorize them)."""
        p = self.params
        M = self.operator
        self._rebuilt = not (lag and M is not None)
        if M is None or (not lag and not p.reuse_symbolic):
            if M is not None and hasattr(M, "settle_transport"):
                M.settle_transport(undo=False)   # replaced: its multiplication under way only finishes
            M = self._new_operator(p, H, geometry)
            self.operator = M
            self._subdomain_change = None
        elif lag:
            settle = getattr(M, "settle_transport", None)
            if settle is not None:
                settle()   # Φ as it was built: a multiplication started ahead is undone
            return M
        keep = (not subdomains and p.lagged_preconditioner and self._subdomain_change is not None
                and getattr(M, "subdomains_factored", False) and self._subdomain_change(H) <= p.subdomain_lag_change)
        geometry = geometry() if M.uses_geometry else None
        transport = keep and p.transport_coarse and getattr(M, "can_transport", lambda g: False)(geometry)
        if transport:
            M = M.transport(H, geometry)
        else:
            M = M.update_coarse(H, geometry) if keep else M.update(H, geometry)
        self._subdomains_kept, self._transported = keep, transport
        if p.lagged_preconditioner:
            self._change = EntryChange(H)
            if not keep and hasattr(M, "update_coarse"):
                self._subdomain_change = self._change
        return M

    def solve(self, H, rhs, tol, geometry, decrement_tol=None, decrement_left=None, bound_left=False):
        """Preconditioned CG to relative residual ``tol`` (or until the step's whole model decrease is
        bounded by ``decrement_tol``). A lagged preconditioner that lets CG exceed its iteration cap
        is rebuilt for H and CG continues from where it stopped. ``bound_left``: bound the model
        decrease left beyond the result (:func:`~gtsam_schwarz.krylov.pcg`'s ``left_bound``)."""
        p = self.params
        t0 = time.perf_counter()
        H = as_csr(H)   # (a gathered H stays one: CG multiplies by it from its source)
        cap = self._lag_cap(H)
        lagged = cap is not None
        reference = self._cg_after_build
        M = self.preconditioner(H, geometry, lag=lagged)
        kept = self._subdomains_kept and not lagged
        transported = self._transported and not lagged
        if kept and reference is not None:  # earlier subdomain factors: the lagged M's cap
            cap = int(p.lag_growth * reference) + 2
        setup = time.perf_counter() - t0
        decrement = {"decrement_tol": decrement_tol, "decrement_left": decrement_left, "bound_left": bound_left}
        x, info = pcg(H, rhs, M, tol=tol, maxiter=cap if cap is not None else p.cg_max_iterations, **decrement)
        iterations, residuals = info.iterations, list(info.residuals)
        if cap is not None and not (info.converged or info.decrement_stop):  # stale: rebuild for H, continue from x
            t2 = time.perf_counter()
            if kept and not transported:  # the coarse level is H's already: refactorize the subdomains
                M = M.refactor_subdomains(H)
                self._subdomain_change = self._change
            else:
                M = self.preconditioner(H, geometry, subdomains=True)
            kept = self._subdomains_kept = transported = self._transported = False
            setup += time.perf_counter() - t2
            x, info = pcg(H, rhs, M, tol=tol, maxiter=p.cg_max_iterations, x0=x, **decrement)
            iterations += info.iterations
            residuals += info.residuals[1:]
            self._moved = 0.0  # the warm-started count is no reference: keep the previous one
        elif self._rebuilt and not info.decrement_stop:  # (a solve stopped on its decrement is no reference count)
            self._cg_after_build, self._moved = info.iterations, 0.0
        return SolveResult(x=x, iterations=iterations, converged=info.converged,
                           decrement_stop=info.decrement_stop, decrement_bound=info.decrement_bound,
                           left_bound=info.left_bound, lambda_min=info.lambda_min, lambda_max=info.lambda_max,
                           residuals=residuals, tolerance=tol, setup_seconds=setup,
                           coarse_size=M.coarse_size, rebuilt=self._rebuilt, lagged=lagged, subdomains_kept=kept,
                           coarse_transported=transported)

    def refinable(self) -> bool:
        return True

    def refine(self, H, rhs, tol, previous, decrement_tol=None, decrement_left=None):
        """CG from ``previous.x`` to ``tol`` with the preconditioner of the last solve (a restart: the
        Krylov space is built anew, at one product with H and one application of M more)."""
        x, info = pcg(H, rhs, self.operator, tol=tol, maxiter=self.params.cg_max_iterations, x0=previous.x,
                      decrement_tol=decrement_tol, decrement_left=decrement_left)
        iterations = previous.iterations + info.iterations
        if previous.rebuilt and not previous.lagged and not info.decrement_stop:  # the build's reference count
            self._cg_after_build = iterations
        return replace(previous, x=x, iterations=iterations, converged=info.converged,
                       decrement_stop=info.decrement_stop, decrement_bound=info.decrement_bound,
                       left_bound=float("nan"), residuals=list(previous.residuals) + list(info.residuals[1:]),
                       tolerance=tol, lambda_min=info.lambda_min, lambda_max=info.lambda_max)


class CostModel:
    """Seconds per linear solve, predicted from the symbolic analysis (``solvers.cost``).

    Calibrated on this project's 2-core machine (CHOLMOD, one BLAS thread) from the factor, solve and
    SpMV times of M3500, city10000, sphere2500, the model problems, lawnmower and 3D surveys
    (docs/survey.md, "Ninth pass"): a numeric factorization costs :meth:`factor_seconds`, a
    triangular solve pair ``SOLVE``·nnz(L), an SpMV ``SPMV``·nnz(H). Schwarz: the subdomain
    factorization twice (overlapping blocks and interiors), harmonic extension with
    ``COARSE_COLUMNS`` right-hand sides, ``CG_ITERATIONS`` iterations.
    """

    # since CHOLMOD's OpenMP runs one thread (solvers/openmp.py; thirteenth session, its four threads
    # had made the supernodal factorizations 2-2.5x slower): measured 0.041 s sphere2500, 0.037 s
    # city10000, 0.051 s lawn100x100, 0.315 s survey8x24x24 (0.38-0.51 of the old rates' prediction)
    FLOP_SIMPLICIAL = 7e-10  # flops / nnz(L) below CHOLMOD's supernodal switch (40): no OpenMP there
    SUPERNODAL_FROM = 40
    FLOP = 3e-10  # small supernodes (flops / nnz(L) below ~70: city10000 and sparser)
    SUPERNODE = 2.2e-8  # per entry of L where the supernodes grow with the fill (flops / nnz(L) 70 to 4000)
    FLOP_LARGE = 1.5e-11  # the rate of the largest supernodes (3D 32x32x32 and 45x45x45: 1.5e-11, 1.9e-11)
    ENTRY = 1e-8
    SOLVE = 2e-9
    SPMV = 3e-9
    CG_ITERATIONS = 30
    # the screen before the two-level estimate (which costs 40-60 ms on the small graphs): Schwarz solves
    # measured 55-110 SpMVs' time each (sphere2500 55, lawn100x100 69, city10000 84, survey8x24x24 110,
    # counted as SPMV·nnz(H)); a direct solve predicted below SCHWARZ_OVERHEAD·SCREEN_ITERATIONS = 84 of
    # them goes direct unestimated
    SCREEN_ITERATIONS = 14
    COARSE_COLUMNS = 20
    SCHWARZ_OVERHEAD = 6.0  # gathers, interface values, Φ and A₀ assembly, Python: measured 2–10× the counted work

    def __init__(self, inexact: bool = False):
        """``inexact``: Schwarz's steps are solved to Eisenstat–Walker tolerances (fewer CG iterations)."""
        self.inexact = inexact
        self.two_level_iterations = self.TWO_LEVEL_ITERATIONS_INEXACT if inexact else self.TWO_LEVEL_ITERATIONS

    def factor_seconds(self, flops: float, nnz_L: float) -> float:
        """A numeric factorization. The rate per flop grows with the supernodes, whose size follows
        c = flops / nnz(L), about as c itself (before the OpenMP limit; the rates since: see ``FLOP``):
        measured 7.3e-10 s per flop at c = 85 (city10000), 1.4e-10 at 450 (lawnmower 300x300),
        1.5e-11 at 4400 (3D survey 32x32x32). So from c ≈ 90 the
        time is about ``SUPERNODE``·nnz(L) (2D and 3D, H and the chordal rotation system alike),
        below at ``FLOP`` per flop, never faster than ``FLOP_LARGE`` per flop; ``ENTRY``·nnz(L) on top.
        A simplicial factor (c below CHOLMOD's switch, 40) costs ``FLOP_SIMPLICIAL`` per flop."""
        if flops < self.SUPERNODAL_FROM * nnz_L:
            return self.ENTRY * nnz_L + self.FLOP_SIMPLICIAL * flops
        return self.ENTRY * nnz_L + max(self.FLOP_LARGE * flops, min(self.FLOP * flops, self.SUPERNODE * nnz_L))

    def direct(self, cost) -> float:
        return self.factor_seconds(cost.flops, cost.nnz_L) + self.SOLVE * cost.nnz_L

    def schwarz_floor(self, nnz_H: int) -> float:
        """The screen for "Schwarz cannot win": a solve costs about this many SpMVs at least."""
        return self.SCHWARZ_OVERHEAD * self.SCREEN_ITERATIONS * self.SPMV * nnz_H

    def schwarz(self, local, nnz_H: int) -> float:
        setup = 2 * self.factor_seconds(local.flops, local.nnz_L) + self.COARSE_COLUMNS * self.SOLVE * local.nnz_L
        cg = self.CG_ITERATIONS * (self.SPMV * nnz_H + self.SOLVE * local.nnz_L)
        return self.SCHWARZ_OVERHEAD * (setup + cg)

    # two-level Schwarz from its own symbolic estimate (schwarz.memory.MemoryEstimate): K columns of
    # the extension, Φ's entries; fitted on rgdsw-linear runs of the survey graphs (docs/survey.md)
    SOLVE_COLUMN = 1.6e-9  # per factor entry and right-hand-side column of the extension's solve
    PHI_ENTRY = 3e-8  # assembly per entry of Φ (right-hand side, selection, A₀ products)
    PHI_APPLY = 1.3e-9  # per entry of Φ and product (Φ z, Φᵀ x)
    TWO_LEVEL_ITERATIONS = 40  # rgdsw-linear: 36–46 per fresh solve on the surveys
    TWO_LEVEL_ITERATIONS_INEXACT = 14  # with the forcing term: 12–14 per solve in 3D, 9 in 2D
    # measured per solve / the counted work, LM with inexact steps: 0.59-0.65 (city10000, lawn100x100,
    # sphere2500), 0.96 (survey8x24x24), 1.0 (M3500); the counted iterations cost 0.6-0.9 of their
    # prediction, the setup 0.8-1.5
    TWO_LEVEL_OVERHEAD = 0.75
    # exact steps (forcing "none"): one fresh solve to 1e-8 carries the first build's symbolic work
    # (decomposition, analyses) that LM's inexact solves share: 1.44 on survey8x24x24 (the demo's solve)
    TWO_LEVEL_OVERHEAD_EXACT = 1.3

    def two_level(self, est, nnz_H: int) -> float:
        """Seconds per solve of CG with a two-level preconditioner: subdomain and interior
        factorizations, the K-column extension, Φ's assembly, and per iteration an SpMV, the local
        solves and Φ, Φᵀ."""
        L, s = est.local, est.interior_share
        setup = (self.factor_seconds(L.flops, L.nnz_L) + self.factor_seconds(L.flops * s * s, L.nnz_L * s)
                 + self.SOLVE_COLUMN * est.K * s * L.nnz_L + self.PHI_ENTRY * est.nnz_phi)
        iteration = self.SPMV * nnz_H + self.SOLVE * L.nnz_L + 2 * self.PHI_APPLY * est.nnz_phi
        overhead = self.TWO_LEVEL_OVERHEAD if self.inexact else self.TWO_LEVEL_OVERHEAD_EXACT
        return overhead * (setup + self.two_level_iterations * iteration)


class AutoSolver(LinearSolver):
    """Direct factorization or Schwarz-preconditioned CG, chosen per graph on the first solve by
    :class:`CostModel` from CHOLMOD-style symbolic analyses of H and of the subdomain blocks."""

    # the candidate's overlap is LinearSolverParams.overlap_layers("rgdsw-linear"): 0 unless asked
    # for; on the vertex sets V_i themselves (edge subdomains already share their interface poses) it
    # took fewer CG iterations and less time than one layer more on every survey (docs/survey.md:
    # LM 2D 90 000 poses 12.1 -> 9.8 s, 3D 18 772 27.6 -> 24.6 s, 3D 36 864 39.6 -> 35.3 s)

    # Schwarz is chosen only when predicted this much faster: within it the two are a tie for the
    # model (sphere2500: 0.144 vs 0.151 s predicted, 0.37 vs 0.36 s measured), and direct is exact
    SCHWARZ_MARGIN = 0.9

    def __init__(self, params: LinearSolverParams, offsets: np.ndarray, translation_mask: np.ndarray,
                 schwarz: str = "rgdsw-linear"):
        self.params, self.offsets, self.translation_mask, self.schwarz_name = params, offsets, translation_mask, schwarz
        self.chosen: LinearSolver | None = None
        self.choice = ""
        self.reason = ""
        self.model = CostModel(inexact=params.inexact_krylov)
        self.on_choice = None  # called with the choice once made (the optimizer frees memory for a build)
        self._ahead = None  # prepare()'s (nnz(H), direct's predicted cost, the Schwarz solver whose decomposition started)

    def prepare(self, vertices: sp.csr_matrix, nnz: int, geometry=None) -> None:
        """Before the first linearization, from H's vertex pattern (``nnz`` entries of H): direct's cost (the same analysis
        :meth:`choose` makes of H) and, where Schwarz passes the screen, its decomposition started on
        the side thread (:meth:`PreconditionedCG.prepare`). :meth:`choose` still decides, on H."""
        if self.chosen is not None or self._ahead is not None or vertices.shape[0] < PreconditionedCG.AHEAD_FROM:
            return
        direct = pattern_cholesky_cost(vertices, np.diff(np.asarray(self.offsets, dtype=np.int64)), nnz, natural=True)
        cg = None
        if not self._screened(direct, nnz):
            cg = PreconditionedCG(self._schwarz_params(), self.offsets, self.translation_mask)
            cg.prepare(vertices, nnz, geometry)
        self._ahead = (nnz, direct, cg)

    def _schwarz_params(self) -> LinearSolverParams:
        return LinearSolverParams(**{**vars(self.params), "preconditioner": self.schwarz_name})

    def _screened(self, direct, nnz: int) -> bool:
        """Whether direct wins without a Schwarz estimate: predicted faster than the floor of any
        Schwarz solve, and its factor fits."""
        direct_bytes = FACTOR_BYTES * direct.nnz_L + MATRIX_BYTES * nnz
        return self.model.direct(direct) <= self.model.schwarz_floor(nnz) and direct_bytes <= available_memory(self.params.memory_limit)

    @property
    def decomposition(self):
        return self.chosen.decomposition if self.chosen is not None else None

    @property
    def takes_gathered(self) -> bool:
        return self.chosen is not None and self.chosen.takes_gathered

    def fresh_saved_per_entry(self, nnz: int) -> int:
        """The chosen solver's; while the choice is open, the Schwarz candidate's: the prefault is then
        what the smaller run touches (prefaulting more costs memory, less only the first touch's time;
        1M 2D lawnmower poses, `auto` choosing Schwarz: peak 3 904 → 3 218 MiB, 43.18 → 41.51 s)."""
        if self.chosen is not None:
            return self.chosen.fresh_saved_per_entry(nnz)
        return PreconditionedCG.block_factor_saving(nnz)

    def choose(self, H, geometry: Geometry | None = None) -> LinearSolver:
        """Predict both costs and keep the cheaper solver (its name in ``choice``, why in ``reason``).
        ``geometry``: the poses of the first solve (its coarse columns are then computed once)."""
        ahead, self._ahead = self._ahead, None
        if ahead is not None and ahead[0] == H.nnz:   # prepare() analysed H's pattern: the same cost
            direct, cg = ahead[1], ahead[2]
        else:
            direct, cg = cholesky_cost(H, self.offsets, natural=True), None
        t_direct = self.model.direct(direct)
        params = self._schwarz_params()
        floor = self.model.schwarz_floor(H.nnz)
        direct_bytes = FACTOR_BYTES * direct.nnz_L + MATRIX_BYTES * H.nnz
        available = available_memory(self.params.memory_limit)
        if self._screened(direct, H.nnz):  # the screen: Schwarz cannot win, no estimate
            self.choice, self.chosen = "direct", self._direct(t_direct, direct)
            self.reason = (f"nnz(L) {direct.nnz_L:.3g} ({direct.fill:.1f}x nnz(H)), {direct.flops:.3g} flops: "
                           f"direct {t_direct:.3g} s per solve (predicted) < {floor:.3g} s, the time of "
                           f"{self.model.SCHWARZ_OVERHEAD * self.model.SCREEN_ITERATIONS:g} SpMVs (Schwarz cannot win)")
            return self._chose()
        if cg is None:
            cg = PreconditionedCG(params, self.offsets, self.translation_mask)
        dec = cg._decompose(H, geometry)
        M = cg._new_operator(params, H, geometry)
        fits, refusal = True, None
        if hasattr(M, "extension"):  # two-level: its own estimate (coarse columns, Φ, fill)
            est = estimate_two_level(M, H, geometry() if geometry is not None and M.uses_geometry else None)
            t_schwarz = self.model.two_level(est, H.nnz)
            try:
                M.memory = fit_memory(M, H, params.memory_limit, self.schwarz_name, est)
                M.extension.block_columns = M.memory.block_columns
            except InsufficientMemoryError as exc:
                fits, refusal = False, exc
        else:
            S = sp.csc_matrix(dec.overlapping)
            S.sort_indices()
            sets = IndexSets(indices=S.indices.astype(np.int64), ptr=S.indptr.astype(np.int64), n=S.shape[0])
            blocks = block_diagonal(vertex_pattern(H, self.offsets), sets)
            local = pattern_cholesky_cost(blocks, np.diff(self.offsets)[sets.indices])
            t_schwarz = self.model.schwarz(local, H.nnz)
        facts = (f"nnz(L) {direct.nnz_L:.3g} ({direct.fill:.1f}x nnz(H)), {direct.flops:.3g} flops: "
                 f"direct {t_direct:.3g} s vs {self.schwarz_name} {t_schwarz:.3g} s per solve (predicted)")
        if direct_bytes > available:  # the factor would not fit: Schwarz if it does
            if not fits:
                raise InsufficientMemoryError(f"neither fits: direct's factor needs ~{gib(direct_bytes)}; {refusal}")
            self.choice, self.chosen = self.schwarz_name, cg
            facts += f"; direct's factor needs ~{gib(direct_bytes)}, {gib(available)} available"
        elif not fits or t_direct <= t_schwarz / self.SCHWARZ_MARGIN:
            self.choice, self.chosen = "direct", self._direct(t_direct, direct)
            if not fits:
                facts += f"; {self.schwarz_name} would not fit in {gib(available)}"
        else:
            self.choice, self.chosen = self.schwarz_name, cg
        if self.chosen is cg:
            cg.operator = M  # set up already (interface, extension plan, memory fit): reused
        self.reason = facts
        return self._chose()

    def _direct(self, predicted: float, cost) -> DirectSolver:
        solver = DirectSolver(lagged=self.params.lagged_preconditioner)
        solver.predicted_seconds = predicted
        solver.ordering = "natural" if cost.natural_suffices else None
        return solver

    def _chose(self) -> LinearSolver:
        if self.on_choice is not None:
            self.on_choice(self.choice)
        return self.chosen

    def solve(self, H, rhs, tol, geometry, decrement_tol=None, decrement_left=None, bound_left=False):
        t0 = time.perf_counter()
        if self.chosen is None:
            self.choose(H, geometry)  # the analysis counts as setup of the first solve
        choosing = time.perf_counter() - t0
        extra = {"bound_left": True} if bound_left and self.chosen.refinable() else {}
        result = self.chosen.solve(H, rhs, tol, geometry, decrement_tol, decrement_left, **extra)
        result.setup_seconds += choosing
        return result

    def refinable(self) -> bool:
        return self.chosen is None or self.chosen.refinable()   # (if direct is chosen, its solves are exact)

    def refine(self, H, rhs, tol, previous, decrement_tol=None, decrement_left=None):
        return self.chosen.refine(H, rhs, tol, previous, decrement_tol, decrement_left)

    def moved(self, step_max: float) -> None:
        if self.chosen is not None:
            self.chosen.moved(step_max)

    def ahead(self, geometry) -> None:
        ahead = getattr(self.chosen, "ahead", None)
        if ahead is not None:
            ahead(geometry)

    def release(self) -> None:
        if self.chosen is not None:
            self.chosen.release()


# back-ends sit above this layer (they reuse the serial solver's pieces): loaded by name, no import cycle
BACKEND_FACTORIES = {"petsc": "gtsam_schwarz.backends.petsc.solver:make_petsc_solver"}


def make_linear_solver(params: LinearSolverParams, offsets: np.ndarray, translation_mask: np.ndarray) -> LinearSolver:
    """"auto" → :class:`AutoSolver`; "direct" → :class:`DirectSolver`; any registered preconditioner →
    :class:`PreconditionedCG`; ``backend="petsc"``: the same solve on PETSc over MPI."""
    if params.backend != "serial":
        module, _, factory = BACKEND_FACTORIES[params.backend].partition(":")
        return getattr(importlib.import_module(module), factory)(params, offsets, translation_mask)
    if params.preconditioner == "auto":
        return AutoSolver(params, offsets, translation_mask)
    if params.preconditioner == "direct":
        return DirectSolver(offsets, params.memory_limit, params.lagged_preconditioner)
    return PreconditionedCG(params, offsets, translation_mask)


class Forcing:
    """CG tolerance per Newton step: fixed ``cg_tol``, or Eisenstat–Walker's choice 2 forcing term
    η_k = 0.9 (‖g_k‖/‖g_{k−1}‖)², safeguarded by 0.9 η_{k−1}² and capped at ``forcing_max``;
    "auto": the forcing term while ``krylov()`` says the steps are solved by preconditioned CG, else
    ``cg_tol`` (a direct factorization, whose tolerance only its lagged CG sees).

    ``exact_next`` makes the next solve exact (after a small decrease from an inexact step, or to
    retry a rejected LM step)."""

    def __init__(self, params: LinearSolverParams, krylov=None):
        self.params = params
        self.krylov = krylov if krylov is not None else (lambda: True)
        self.previous = None  # (gradient norm, η) of the previous linear solve
        self.exact_next = False

    def probe(self, tol: float) -> float | None:
        """The looser tolerance ``forcing_probe`` for the run's first inexact solve (None: none). No
        forcing term exists before a first step shows how nonlinear the problem is: that step is
        solved to ``forcing_probe`` and kept where its model's error (predicted against actual
        decrease) exceeds the bound on what CG had left; otherwise CG continues to ``tol``."""
        p = self.params
        probe = p.forcing_probe
        if self.previous is not None or self.exact_next or not self.inexact() or not probe or probe <= tol:
            return None
        return probe

    def inexact(self) -> bool:
        p = self.params  # "auto" only while the steps are solved by preconditioned CG
        return p.inexact_krylov and (p.forcing != "auto" or bool(self.krylov()))

    def tolerance(self, gnorm: float) -> float:
        p = self.params
        if not self.inexact() or self.exact_next:
            return p.cg_tol
        if self.previous is None:
            eta = p.forcing_max
        else:
            g_prev, eta_prev = self.previous
            eta = 0.9 * (gnorm / g_prev) ** 2
            safeguard = 0.9 * eta_prev ** 2
            if safeguard > 0.1:
                eta = max(eta, safeguard)
            eta = min(eta, p.forcing_max)
        return max(eta, p.cg_tol)

    def solved(self, gnorm: float, tol: float) -> None:
        self.previous = (gnorm, tol)
