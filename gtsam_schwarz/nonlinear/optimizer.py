"""Gauss–Newton and Levenberg–Marquardt with Schwarz-preconditioned CG, GTSAM's optimizer API.

Per iteration: the linearizer gives H, g → the linear solver (direct or preconditioned CG) gives
the step → the linearizer retracts and evaluates → the loop decides. What depends only on the graph
(pattern, decomposition, index sets, symbolic factorizations) is built once.
"""

from __future__ import annotations

import os
import time
import warnings
from contextlib import nullcontext

import numpy as np

from ..dd.index_sets import vertex_dofs
from ..util.blas import blas_limits
from ..linearization.base import Linearizer, LinearSystem
from ..util import with_small_pages
from ..util.gathered import entries
from ..solvers.memory import available_memory
from ..util.heap import populate_ahead
from .gauge import free_components
from .hooks import verbose_printer
from .initialize import chordal_state, prepare_chordal
from .linear_solver import Forcing, LinearSolver, make_linear_solver
from .params import (DampingParams, LevenbergMarquardtParams, LinearSolverParams, SchwarzParams, as_nonlinear,
                     linear_solver_names)
from .records import IterationRecord

LINEAR_SOLVERS = linear_solver_names()
# fresh memory a run touches per entry of H, at least (bench children after loading: 72-156 bytes;
# model problems 72-77, city10000 91, sphere2500 96, lawnmowers 88 (Schwarz) and 126-156 (direct))
FRESH_BYTES_PER_ENTRY = 64
# H in the factor form (a GatheredCSR: no CSR values) from this many entries on, where the linear solver
# takes it (CG). numba's import and the kernels' loading cost ~1 s of Python work beside the start: below,
# that is not worth the memory (3D 32x32x32, 8M entries: 12.2 against 11.2-11.6 s without it, for 92 MiB;
# lawnmower 600x600, 16M: 16.21 s in a bench against 15.38-15.63 s in earlier sessions'); the 3D 45x45x45
# survey (22.5M entries) and the 1M lawnmower (45M) take it
FACTOR_FORM_FROM = int(os.environ.get("GTSAM_SCHWARZ_FACTOR_FORM_FROM", 20_000_000))
# what the factor form does not hold per entry: H's values (8 bytes) and the gather index (4); its prefault
# is that much smaller (1M 2D lawnmower: the peak 3 917 → 3 516-3 606 MiB, the run's own ~3 650 without one)
FACTOR_FORM_SAVES_PER_ENTRY = 12


class SchwarzOptimizer:
    """``SchwarzOptimizer(graph, initial, params).optimize()`` → ``gtsam.Values``, like GTSAM's.

    ``params``: :class:`SchwarzParams` (flat; default Levenberg–Marquardt), :class:`GaussNewtonParams`,
    :class:`LevenbergMarquardtParams`, or GTSAM's ``LevenbergMarquardtParams`` / ``GaussNewtonParams``
    (with ``linear_solver=LinearSolverParams(...)`` for our settings beside them). ``linearizer``: any
    :class:`Linearizer` (default: GTSAM's linearization, which handles every factor). ``history``
    holds one :class:`IterationRecord` per linear solve. Silent unless ``verbose`` or a hook is set;
    a run that stops without converging warns (``warnings.warn``) with the reason.
    """

    chordal_ahead = True  # the chordal start's solver choice analysed while the start is read

    @with_small_pages
    def __init__(self, graph, initial, params=None, linearizer: Linearizer | None = None,
                 linear_solver: LinearSolverParams | None = None):
        self.graph = graph
        self.params = params if params is not None else SchwarzParams()
        self.nonlinear_params = as_nonlinear(self.params, linear_solver)
        if linearizer is None:
            linearizer = make_linearizer(graph, initial, self.nonlinear_params.linearization)
        self.linearizer = linearizer
        p = self.nonlinear_params
        self.linear_solver: LinearSolver = make_linear_solver(p.linear_solver, linearizer.offsets,
                                                              linearizer.translation_mask())
        # faulted in on a helper thread while the start is computed (tuned heap only); the native
        # linearizer's estimate, not its pattern, which may still be in the making
        nnz = getattr(linearizer, "nnz_estimate", None)
        if nnz is None and getattr(linearizer, "pattern", None) is not None:
            nnz = linearizer.pattern.nnz
        if nnz is not None:   # at most a share of what the linear solver may use (its memory limit)
            limit = available_memory(self.nonlinear_params.linear_solver.memory_limit)
            # (with the automatic choice still open, what its Schwarz candidate would touch)
            fresh = (FRESH_BYTES_PER_ENTRY - (FACTOR_FORM_SAVES_PER_ENTRY if self._factor_form(expected=True) else 0)
                     - self.linear_solver.fresh_saved_per_entry(nnz))
            populate_ahead(fresh * nnz, ceiling=limit)
        if self._factor_form(expected=True) and hasattr(linearizer, "prepare_factor_form"):
            linearizer.prepare_factor_form()   # numba's kernels loaded beside the start
        method = self.nonlinear_params.initialization
        # the chordal start's solver choice is analysed on the side thread while the start is read
        prepared = prepare_chordal(linearizer, self._chordal_solver()) if method != "file" and self.chordal_ahead else None
        self._state = linearizer.state(initial) if initial is not None else linearizer.initial_state()
        self._error = linearizer.error(self._state)
        self.initial_error = self._error
        self.initialization = self._initialize(method, prepared)
        self.history: list[IterationRecord] = []
        self.converged = False
        self.stop_reason = ""
        self.final_gradient_norm = float("nan")
        self._g0 = None
        self._last_decrease: float | None = None  # the previous accepted step's error decrease
        self.method = "lm" if isinstance(p, LevenbergMarquardtParams) else "gn"
        self._lambda = p.lambda_initial if self.method == "lm" else 0.0
        self.anchors: np.ndarray | None = None  # first vertex of each component without a prior
        self._anchor_dofs = None
        if hasattr(self.linear_solver, "on_choice"):  # auto: decided on the first solve
            self.linear_solver.on_choice = lambda choice: choice != "direct" and self._release_scratch()
        # inexact Newton steps where CG with a Schwarz preconditioner solves them ("" = the automatic
        # choice is still open: the first solve's tolerance matters only to CG)
        self.forcing = Forcing(p.linear_solver, krylov=lambda: getattr(self.linear_solver, "choice", "") != "direct")
        self._hooks = [h for h in (p.iteration_hook, verbose_printer() if p.verbose else None) if h is not None]

    # -- GTSAM-like accessors ------------------------------------------------------------
    @with_small_pages
    def values(self):
        """The current estimate as ``gtsam.Values``."""
        return self.linearizer.values(self._state)

    def error(self) -> float:
        return self._error

    def iterations(self) -> int:
        """Nonlinear iterations (linearization points from which a step was tried)."""
        return len({h.iteration for h in self.history})

    def lambda_(self) -> float:
        """The current Levenberg–Marquardt damping λ (GTSAM's ``lambda_()``; 0 for Gauss–Newton)."""
        return self._lambda

    @property
    def keymap(self):
        """The GTSAM linearizer's key map (dof ranges of the graph's keys)."""
        return self.linearizer.keymap

    @property
    def decomposition(self):
        return self.linear_solver.decomposition

    def _chordal_solver(self) -> str:
        # its two systems are Laplacians with one (2D, complex) or three (3D) unknowns per pose: on sparse
        # graphs they are factorized (262k-pose model problem: 0.17 s, CG 0.9 s); they go to CG where the
        # factor fills in (91 125-pose 3D survey: 24 s direct, 6.6 s CG, 1/3 of the memory; 360 000-pose 2D
        # lawnmower: 3.9 s direct, 2.1 s CG)
        schwarz = self.nonlinear_params.linear_solver.preconditioner not in ("auto", "direct")
        return "cg-3d" if schwarz else "auto"

    def _initialize(self, method: str, prepared=None) -> dict:
        """Replace the given start by a global initialization when that lowers the error
        (``prepared``: :func:`~.initialize.prepare_chordal`'s result)."""
        record = {"method": method, "used": False, "error_given": self._error, "error": float("nan"),
                  "seconds": 0.0, "note": ""}
        if method == "file":
            return record
        t0 = time.perf_counter()
        state, note = chordal_state(self.linearizer, self._state, solver=self._chordal_solver(), prepared=prepared)
        record["note"] = note
        if state is not None:
            error = self.linearizer.error(state)
            record["error"] = error
            if np.isfinite(error) and error < self._error:
                self._state, self._error, record["used"] = state, error, True
        record["seconds"] = time.perf_counter() - t0
        return record

    # -- pieces ----------------------------------------------------------------------------
    def _linearize(self) -> LinearSystem:
        if self.anchors is None:   # the first linearization: the linear solver's pattern work goes first
            self._prepare_linear_solver()
        elif hasattr(self.linear_solver, "ahead"):   # later ones: its work on the new poses alone
            state = self._state
            self.linear_solver.ahead(lambda: self.linearizer.geometry(state))
        if hasattr(self.linearizer, "factor_form"):
            self.linearizer.factor_form = self._factor_form()
        t0 = time.perf_counter()
        system = self.linearizer.linearize(self._state)
        total = time.perf_counter() - t0  # phases: GTSAM's path splits off its export to scipy
        export = system.seconds.get("export", 0.0)
        system.seconds = {**system.seconds, "linearize": total - export, "export": export}
        if self.linear_solver.choice not in ("direct", ""):  # a Schwarz build's peak comes next
            self._release_scratch()
        if self.anchors is None:
            self.anchors = free_components(system.H, self.linearizer.offsets, self.linearizer.geometry(self._state),
                                           system.diagonal, getattr(self.linearizer, "prior_vertices", None))
            self._anchor_dofs = vertex_dofs(self.anchors, self.linearizer.offsets) if len(self.anchors) else None
        return system

    def _factor_form(self, expected: bool = False) -> bool:
        """Whether H comes without its CSR values (:class:`~gtsam_schwarz.util.gathered.GatheredCSR`):
        a large H, for a linear solver that only multiplies by it and gathers from it (``expected``: or
        one whose automatic choice is still open)."""
        nnz = getattr(self.linearizer, "nnz_estimate", 0) or 0
        open_choice = expected and self.linear_solver.choice == ""
        possible = getattr(self.linearizer, "factor_form_possible", None)
        return ((self.linear_solver.takes_gathered or open_choice) and nnz >= FACTOR_FORM_FROM
                and possible is not None and possible())

    def _prepare_linear_solver(self) -> None:
        """Hand the linear solver H's vertex pattern (the native linearizer's fixed pattern) and the
        poses before the first linearization: its decomposition starts on the side thread and runs
        beside that linearization (lawnmower 600x600: ~0.4 s of one core's symbolic work)."""
        prepare = getattr(self.linear_solver, "prepare", None)
        pattern = getattr(self.linearizer, "pattern", None)
        if prepare is not None and hasattr(pattern, "vertex_pattern"):
            state = self._state
            prepare(pattern.vertex_pattern(), pattern.nnz, lambda: self.linearizer.geometry(state))

    def _release_scratch(self) -> None:
        """Let the linearizer drop its scratch arrays before a Schwarz build (its memory peak), and keep
        no residuals from an evaluation to the next linearization (beside the peak of the next build or
        transport). Not for the direct path, nor before the automatic choice is made: at 1M 2D poses,
        scratch dropped in the first iteration and allocated again in the second cost 1.2-1.6 s of page faults."""
        release = getattr(self.linearizer, "release_scratch", None)
        if release is not None:
            release()
        if hasattr(self.linearizer, "keep_residuals"):
            self.linearizer.keep_residuals = False

    def _gradient_converged(self, gnorm: float) -> bool:
        p = self.nonlinear_params
        if self._g0 is None:
            self._g0 = gnorm
        self.final_gradient_norm = gnorm
        if gnorm <= p.gradient_tol:
            self.converged, self.stop_reason = True, f"gradient norm {gnorm:.3e} <= {p.gradient_tol:g}"
            return True
        if gnorm <= p.relative_gradient_tol * self._g0:
            self.converged, self.stop_reason = True, (
                f"gradient norm decreased by {gnorm / self._g0:.3e} <= {p.relative_gradient_tol:g}")
            return True
        return False

    def _damping(self, system: LinearSystem, lam: float) -> tuple:
        """(d, H's diagonal) of the damped matrix H + diag(d) (see :meth:`_damping_diagonal`);
        (None, None) where nothing is added."""
        if lam == 0.0 and self._anchor_dofs is None:
            return None, None
        # the linearizer's known diagonal positions: a gather, not a search of every row
        diag = entries(system.H, system.diagonal_positions())
        return self._damping_diagonal(diag, lam, self._anchor_dofs), diag

    def _damped(self, system: LinearSystem, lam: float, damping: tuple | None = None):
        """H + λD for a ``with`` block (H's diagonal raised in place, restored after it):
        D = I, or diag(H) clipped to [1e-6, 1e32] with ``diagonal_damping`` (GTSAM's).
        ``damping``: :meth:`_damping`'s result when the caller has it."""
        d, diag = damping if damping is not None else self._damping(system, lam)
        return nullcontext(system.H) if d is None else system.damped(d, diag)

    def _damping_diagonal(self, diag: np.ndarray, lam: float, anchors) -> np.ndarray:
        """λD (D = I, or diag(H) clipped to [1e-6, 1e32] with ``diagonal_damping``) plus, for gauge,
        the anchors' own diagonal once more (see gauge.py); ``anchors`` index ``diag`` (or None)."""
        d = np.zeros(len(diag))
        if lam != 0.0:
            diagonal = getattr(self.nonlinear_params, "diagonal_damping", False)
            d = lam * (np.clip(diag, 1e-6, 1e32) if diagonal else np.ones(len(diag)))
        if anchors is not None:
            d[anchors] += diag[anchors]
        return d

    def _try_step(self, system: LinearSystem, gnorm: float, lam: float, iteration: int,
                  seconds: dict) -> tuple[IterationRecord, object]:
        """Solve (H + λD) δ = −g, retract, evaluate; returns the record and the new state. The run's
        first inexact solve may go to a looser tolerance first (:meth:`Forcing.probe`)."""
        tol = self.forcing.tolerance(gnorm)
        probe = self.forcing.probe(tol) if self.linear_solver.refinable() else None
        total, left = self._decrement_tols()
        geometry = lambda: self.linearizer.geometry(self._state)  # noqa: E731
        extra = {"bound_left": True} if probe is not None else {}
        t0 = time.perf_counter()
        damping = self._damping(system, lam)
        with self._damped(system, lam, damping) as H:
            result = self.linear_solver.solve(H, system.rhs, probe or tol, geometry,
                                              decrement_tol=total, decrement_left=left, **extra)
        t1 = time.perf_counter()
        new_state, new_error, predicted = self._evaluate(system, result.x, damping if result.exact else None)
        cg, update = t1 - t0 - result.setup_seconds, time.perf_counter() - t1
        probed = ""
        if probe is not None and result.tolerance == probe and result.converged and not result.decrement_stop:
            # kept where the step's model error exceeds the bound on CG's left-over model decrease: solving
            # further would change the outcome less than the nonlinearity does (a failed step is kept: LM
            # retries it exactly)
            model_error = abs(self._error - new_error + predicted)
            if not np.isfinite(new_error) or model_error >= result.left_bound:
                probed, tol = "kept", probe
            else:
                probed = "refined"
                t2 = time.perf_counter()
                with self._damped(system, lam) as H:
                    result = self.linear_solver.refine(H, system.rhs, tol, result, decrement_tol=total,
                                                       decrement_left=left)
                t3 = time.perf_counter()
                new_state, new_error, predicted = self._evaluate(system, result.x)
                cg, update = cg + t3 - t2, update + time.perf_counter() - t3
        self.forcing.solved(gnorm, tol)
        dx = result.x
        record = self._record(iteration, gnorm, lam, new_error, predicted, float(np.linalg.norm(dx)),
                              float(np.abs(dx).max()) if len(dx) else 0.0, result, seconds, cg, update)
        record.probe = probed
        return record, new_state

    def _evaluate(self, system: LinearSystem, dx: np.ndarray, exact_damping: tuple | None = None
                  ) -> tuple[object, float, float]:
        """The state retracted by ``dx``, its error, and the undamped model's change gᵀδ + ½δᵀHδ.
        ``exact_damping``: the (d, diagonal) of :meth:`_damping` when δ solves (H + diag(d))δ = −g to
        rounding (a direct factorization): then Hδ = −g − d∘δ and the change is ½gᵀδ − ½δᵀdiag(d)δ,
        without a product by H (262k-pose model problem: ~10 ms of an LM iteration)."""
        new_state = self.linearizer.retract(self._state, dx)
        new_error = self.linearizer.error(new_state)
        if exact_damping is None:
            return new_state, new_error, float(system.g @ dx + 0.5 * dx @ (system.H @ dx))
        d = exact_damping[0]
        change = 0.5 * float(system.g @ dx) - (0.5 * float(d @ (dx * dx)) if d is not None else 0.0)
        return new_state, new_error, change

    def _record(self, iteration: int, gnorm: float, lam: float, new_error: float, predicted: float,
                step_norm: float, step_max: float, result, seconds: dict, cg: float, update: float) -> IterationRecord:
        """The record of one tried step; ``predicted`` = gᵀδ + ½δᵀHδ, ``cg`` and ``update`` the seconds of
        the solve (without its setup) and of the evaluation."""
        return IterationRecord(
            iteration=iteration, error_before=self._error, error=new_error, gradient_norm=gnorm,
            step_norm=step_norm, step_max=step_max, lambda_=lam,
            model_fidelity=(self._error - new_error) / -predicted if predicted < 0 else float("nan"),
            predicted_decrease=-predicted, cg_iterations=result.iterations, cg_converged=result.converged,
            cg_tolerance=result.tolerance, lambda_min=result.lambda_min, lambda_max=result.lambda_max,
            coarse_size=result.coarse_size, preconditioner_rebuilt=result.rebuilt,
            preconditioner_lagged=result.lagged, cg_residuals=result.residuals,
            subdomains_kept=bool(getattr(result, "subdomains_kept", False)),
            coarse_transported=bool(getattr(result, "coarse_transported", False)),
            decrement_stop=bool(getattr(result, "decrement_stop", False)),
            decrement_bound=float(getattr(result, "decrement_bound", float("nan"))),
            seconds={"linearize": seconds.get("linearize", 0.0), "export": seconds.get("export", 0.0),
                     "setup": result.setup_seconds, "cg": cg, "update": update})

    def _decrement_tols(self) -> tuple[float | None, float | None]:
        """The Newton-decrement rule's (total, left): CG may stop once the exact (damped) step is bounded
        to lower the model by at most ``total`` — a decrease after which GTSAM's error rule, with the
        remaining-decrease check, would stop — and CG has reached all of it but ``left`` =
        ``remaining_decrease_tol`` × error. The loop then stops after that step. (None, None): off."""
        p = self.nonlinear_params
        error_rules = p.relative_error_tol > 0 or p.absolute_error_tol >= 0  # off: stop on the gradient only (the paper)
        E = self._error
        if not (p.newton_decrement and error_rules and p.remaining_decrease_tol > 0 and np.isfinite(E) and E > p.error_tol):
            return None, None
        left = p.remaining_decrease_tol * E
        previous = self._last_decrease
        if previous is None or not previous > 0:
            return left, left  # no rate to judge the decreases still to come by: the step itself must be negligible
        rule = max(p.absolute_error_tol, p.relative_error_tol * E)  # GTSAM: a decrease this small stops
        # remaining_decrease(d, previous) = d²/(previous − d) ≤ left  ⇔  d ≤ (−left + √(left² + 4·left·previous))/2
        rate = 0.5 * (-left + np.sqrt(left * left + 4.0 * left * previous))
        return max(left, min(rule, rate, 0.99 * previous)), left

    def _decrement_converged(self, record: IterationRecord, before: float, new_state) -> bool:
        """After a step whose CG stopped on the decrement rule: keep it if it lowered the error, then
        stop (converged). Returns False (the loop stops)."""
        if np.isfinite(record.error) and record.error <= before:
            record.accepted = True
            self._accept(new_state, record)
        self.converged = True
        self.stop_reason = (f"Newton decrement: the exact step would lower the error by at most "
                            f"{record.decrement_bound:.3e}, after which the error rule stops (CG stopped "
                            f"after {record.cg_iterations} iterations, within "
                            f"{self.nonlinear_params.remaining_decrease_tol:g} x error of it): converged")
        return False

    def _accept(self, new_state, record: IterationRecord):
        self._state, self._error = new_state, record.error
        self.linear_solver.moved(record.step_max)

    def _log(self, record: IterationRecord):
        self.history.append(record)
        for hook in self._hooks:
            hook(record)

    def _error_converged(self, before: float, step_tolerance: float) -> bool:
        """GTSAM's checkConvergence on an accepted step, confirmed by the remaining-decrease estimate.

        With inexact Newton, a small decrease after an inexact step only means the step was
        truncated: the next step is solved to ``cg_tol`` and the test is repeated after it. A small
        decrease on a linearly converging run is not the minimum either: the run goes on until the
        decreases still to come, d_k·r/(1−r) with r = d_k/d_{k−1} (≤ 0.99), are below
        ``remaining_decrease_tol`` × error.
        """
        p = self.nonlinear_params
        decrease = before - self._error
        previous, self._last_decrease = self._last_decrease, decrease
        reason = ""
        if self._error <= p.error_tol:
            reason = f"error {self._error:.3e} <= {p.error_tol:g}"
        elif decrease <= p.absolute_error_tol:
            reason = f"absolute error decrease {decrease:.3e}"
        elif before > 0 and decrease / before <= p.relative_error_tol:
            reason = f"relative error decrease {decrease / before:.3e}"
        if not reason:
            self.forcing.exact_next = False
            return False
        if step_tolerance > p.linear_solver.cg_tol and self._error > p.error_tol:
            self.forcing.exact_next = True
            return False
        if p.remaining_decrease_tol > 0 and self._error > p.error_tol:
            remaining = remaining_decrease(decrease, previous)
            if remaining > p.remaining_decrease_tol * self._error:
                return False
            reason += f", remaining decrease ~{remaining:.1e}"
        self.converged, self.stop_reason = True, reason
        return True

    # -- the loops ------------------------------------------------------------------------
    @with_small_pages
    def iterate(self) -> bool:
        """One nonlinear iteration (GN step, or LM until a step is accepted or λ is too large).

        Returns False when the loop must stop (a stopping rule fired or no step was accepted).
        BLAS runs single-threaded meanwhile: our dense operations are small, and idle OpenBLAS
        threads spinning beside CHOLMOD's OpenMP threads slowed setup and CG by up to 20× (measured).
        """
        if self.nonlinear_params.blas_threads is None:
            return self._iterate()
        with blas_limits(self.nonlinear_params.blas_threads):  # one cached controller: no library rescan
            return self._iterate()

    def _iterate(self) -> bool:
        iteration = self.iterations() + 1
        system = self._linearize()
        gnorm = float(np.linalg.norm(system.g))
        if self._gradient_converged(gnorm):
            return False
        if self.method == "gn":
            return self._gauss_newton(system, gnorm, iteration)
        return self._levenberg_marquardt(system, gnorm, iteration)

    def _gauss_newton(self, system: LinearSystem, gnorm: float, iteration: int) -> bool:
        before = self._error
        record, new_state = self._try_step(system, gnorm, 0.0, iteration, system.seconds)
        if record.decrement_stop:
            stop = self._decrement_converged(record, before, new_state)
            self._log(record)
            return stop
        record.accepted = bool(np.isfinite(record.error) and record.error <= before)
        self._log(record)
        if not record.accepted:
            # never stop at a worse or unchanged point: fall back to damped steps (λ from LM's defaults)
            self._lambda = DampingParams().lambda_initial
            return self._levenberg_marquardt(system, gnorm, iteration, DampingParams(), {})
        self._accept(new_state, record)
        return not self._error_converged(before, record.cg_tolerance)

    def _levenberg_marquardt(self, system: LinearSystem, gnorm: float, iteration: int,
                             damping: DampingParams | None = None, seconds: dict | None = None) -> bool:
        p = self.nonlinear_params
        d = damping or p
        before = self._error
        seconds = system.seconds if seconds is None else seconds
        while True:
            record, new_state = self._try_step(system, gnorm, self._lambda, iteration, seconds)
            seconds = {}
            if record.decrement_stop:
                stop = self._decrement_converged(record, before, new_state)
                self._log(record)
                return stop
            ok = (np.isfinite(record.error) and record.error < before
                  and record.model_fidelity >= d.min_model_fidelity)
            record.accepted = bool(ok)
            self._log(record)
            if ok:
                self._accept(new_state, record)
                self._lambda = max(self._lambda / d.lambda_factor, d.lambda_lower_bound)
                return not self._error_converged(before, record.cg_tolerance)
            floor = (p.remaining_decrease_tol * before if p.remaining_decrease_tol > 0
                     else max(p.absolute_error_tol, p.relative_error_tol * before))
            if record.cg_tolerance <= p.linear_solver.cg_tol and record.predicted_decrease <= floor:
                # the quadratic model promises less than the error tolerances: nothing left to gain
                # (GTSAM would raise λ to its bound here, wasting solves on Jacobian round-off)
                self.converged = True
                self.stop_reason = (f"predicted decrease {record.predicted_decrease:.3e} below the "
                                    f"error tolerance: converged")
                return False
            self.forcing.exact_next = True  # retry the rejected step with an exact solve
            self._lambda *= d.lambda_factor
            if self._lambda > d.lambda_upper_bound:
                self.converged = True
                self.stop_reason = f"lambda {self._lambda:.1e} above {d.lambda_upper_bound:g}: no further decrease"
                return False

    @with_small_pages
    def optimize(self):
        """Iterate until a stopping rule fires; returns the optimized ``gtsam.Values``.

        A run that ends without converging (iteration cap, no acceptable step) warns with the reason."""
        p = self.nonlinear_params
        while self.iterations() < p.max_iterations:
            if not self.iterate():
                break
        else:
            self.stop_reason = f"maximum of {p.max_iterations} iterations reached"
        if not self.converged:
            warnings.warn(f"SchwarzOptimizer did not converge: {self.stop_reason} "
                          f"(error {self.initial_error:.6g} -> {self._error:.6g})", RuntimeWarning, stacklevel=2)
        self._release_run_memory()
        return self.values()

    def _release_run_memory(self) -> None:
        """Before the result is built: the linear solver's numbers (factorizations, coarse basis) and
        the linearizer's buffers go back to the heap, where the result's ``gtsam.Values`` finds room,
        and a caller that keeps the optimizer does not keep them. A later :meth:`iterate` computes
        them anew (a fresh factorization or preconditioner, no lagged solve)."""
        release = getattr(self.linear_solver, "release", None)
        if release is not None:
            release()
        release = getattr(self.linearizer, "release_scratch", None)
        if release is not None:
            release(values=True)

    def optimizeSafely(self):
        """GTSAM's ``optimizeSafely``: ``optimize``, but on an exception return the best values so far."""
        try:
            return self.optimize()
        except Exception as exc:  # noqa: BLE001 — GTSAM's contract: never raise, return what we have
            self.stop_reason = f"stopped by {type(exc).__name__}: {exc}"
            warnings.warn(f"SchwarzOptimizer.optimizeSafely: {self.stop_reason}", RuntimeWarning, stacklevel=2)
            return self.values()

    def summary(self) -> dict:
        cg = [h.cg_iterations for h in self.history]
        return {
            "method": self.method,
            "preconditioner": self.nonlinear_params.linear_solver.preconditioner,
            "iterations": self.iterations(),
            "linear_solves": len(self.history),
            "initial_error": self.initial_error,
            "final_error": self._error,
            "converged": self.converged,
            "stop_reason": self.stop_reason,
            "cg_iterations": cg,
            "cg_total": int(sum(cg)),
            "cg_mean": float(np.mean(cg)) if cg else 0.0,
            "subdomains": self.decomposition.n_subdomains if self.decomposition else None,
            "partition": (self.decomposition.partition or None) if self.decomposition else None,
            "coarse_size": self.history[-1].coarse_size if self.history else 0,
            "anchored": [int(k) for k in self._anchor_keys()],
            "linear_solver": self.linear_solver_choice(),
            "initialization": self.initialization,
        }

    def linear_solver_choice(self) -> dict:
        """Which linear solver ran and why (the automatic choice records its prediction)."""
        return {"requested": self.nonlinear_params.linear_solver.preconditioner,
                "used": self.linear_solver.choice, "reason": self.linear_solver.reason}

    def _anchor_keys(self):
        """Keys of the poses anchored for gauge freedom (components without a prior)."""
        if self.anchors is None or not len(self.anchors):
            return []
        return np.asarray(self.linearizer.keys)[self.anchors].tolist()


def remaining_decrease(decrease: float, previous: float | None) -> float:
    """The decreases still to come if they shrink geometrically: d·r/(1−r), r = d/d_prev clipped to
    [0, 0.99]; unknown (inf) without a previous decrease."""
    if decrease <= 0:
        return 0.0
    if previous is None or previous <= 0:
        return float("inf")
    r = min(decrease / previous, 0.99)
    return decrease * r / (1.0 - r)


def make_linearizer(graph, initial, name: str = "auto") -> Linearizer:
    """"gtsam": GTSAM's linearize for every factor; "native": vectorized kernels for Pose2/Pose3 between
    and prior factors (GTSAM for any other factor, added into the same H, g); "auto": native."""
    if name == "gtsam":
        from ..linearization.gtsam_export import GtsamLinearizer
        return GtsamLinearizer(graph, initial)
    from ..linearization.native import NativeLinearizer
    return NativeLinearizer(graph, initial)
