"""Gauss–Newton and Levenberg–Marquardt over ``gtsam.Values`` with Schwarz-preconditioned CG.

Per iteration: linearize (gtsam) → export H, g → build the preconditioner → PCG → retract.
What depends only on the graph (key map, decomposition, index sets) is built once.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import gtsam
import numpy as np
import scipy.sparse as sp
from threadpoolctl import threadpool_limits

from .decomposition import PARTITIONS, GraphStructure, decompose, default_subdomains
from .krylov import pcg
from .linear_system import HessianPattern, KeyMap, LinearSystem, export_linear_system
from .local_solvers import SparseCholesky, SparsityPattern
from .preconditioners import PRECONDITIONERS, make_preconditioner
from .runtime import tune_allocator

LINEAR_SOLVERS = PRECONDITIONERS + ("direct",)
METHODS = ("gn", "lm")
FORCING = ("none", "eisenstat-walker")
_TWO_LEVEL = ("gdsw", "gdsw-norot", "rgdsw")


def _choice(name, value, allowed):
    if value not in allowed:
        raise ValueError(f"unknown {name} {value!r}; choose one of {', '.join(allowed)}")


@dataclass
class SchwarzParams:
    """Parameters, named like GTSAM's where they mean the same thing.

    Stopping: the paper's (‖g‖ ≤ ``gradient_tol`` or ‖g‖ ≤ ``relative_gradient_tol``·‖g₀‖; the
    relative rule defaults to 1e-6 for Gauss–Newton, off for Levenberg–Marquardt, which starts
    from real files' poor initial guesses where ‖g₀‖ is huge), GTSAM's
    error decrease (relative ``relative_error_tol``, absolute ``absolute_error_tol``, ``error_tol``),
    and ``max_iterations``. Gauss–Newton rejects a step that increases the error and stops;
    Levenberg–Marquardt raises λ and retries, like GTSAM's (λ₀ = 1e-5, factor 10, λ ≤ 1e5).
    ``forcing="eisenstat-walker"`` makes the CG tolerance an inexact-Newton forcing term.
    """

    method: str = "gn"  # gn | lm
    preconditioner: str = "gdsw"  # none | jacobi | block-jacobi | one-level | gdsw | gdsw-norot | rgdsw | direct
    subdomains: int | None = None  # None: about `subdomain_size` poses each
    subdomain_size: int = 500
    partition: str = "auto"  # auto (segments or metis, the smaller interface) | segments | metis
    overlap: int = 1
    grow_along: str = "odometry"  # odometry | all
    interface_grouping: str = "components"  # components | vertices
    coarse_modes: str = "rigid"  # rigid (rigid-body modes about component centroids) | unit
    cg_tol: float = 1e-8
    cg_max_iterations: int | None = None  # None: 10 × the system dimension
    forcing: str = "none"  # none | eisenstat-walker
    forcing_max: float = 1e-3  # measured: 0.1 and 0.01 let LM drift to worse minima on M3500a
    reuse_symbolic: bool = True  # keep interface, patterns and symbolic factorizations across solves
    blas_threads: int | None = 1  # BLAS threads while iterating (None: leave the process setting)
    lagged_preconditioner: bool = True  # keep M (all its numbers) while the poses have hardly moved
    lag_distance: float = 0.1  # lagged: rebuild M once the steps since its build sum to this (max-norm)
    lag_growth: float = 1.5  # lagged: CG cap = this × the CG count right after the build; beyond it, rebuild
    max_iterations: int = 100
    gradient_tol: float = 1e-8
    relative_gradient_tol: float | None = None  # None: 1e-6 for gn, 0 (off) for lm
    relative_error_tol: float = 1e-5
    absolute_error_tol: float = 1e-5
    error_tol: float = 0.0
    lambda_initial: float = 1e-5
    lambda_factor: float = 10.0
    lambda_upper_bound: float = 1e5
    lambda_lower_bound: float = 0.0
    diagonal_damping: bool = False
    min_model_fidelity: float = 1e-3
    verbose: bool = False
    iteration_hook: object = None  # callable(record) after every linear solve, like GTSAM's iterationHook

    def __post_init__(self):
        _choice("method", self.method, METHODS)
        _choice("preconditioner", self.preconditioner, LINEAR_SOLVERS)
        _choice("partition", self.partition, PARTITIONS)
        _choice("forcing", self.forcing, FORCING)
        _choice("grow_along", self.grow_along, ("odometry", "all"))
        _choice("interface_grouping", self.interface_grouping, ("components", "vertices"))
        _choice("coarse_modes", self.coarse_modes, ("rigid", "unit"))
        if self.subdomains is not None and self.subdomains < 1:
            raise ValueError(f"subdomains must be >= 1, got {self.subdomains}")
        if self.overlap < 0:
            raise ValueError(f"overlap must be >= 0, got {self.overlap}")
        if not self.cg_tol > 0:
            raise ValueError(f"cg_tol must be > 0, got {self.cg_tol}")
        if self.max_iterations < 0:
            raise ValueError(f"max_iterations must be >= 0, got {self.max_iterations}")
        if self.relative_gradient_tol is None:
            self.relative_gradient_tol = 1e-6 if self.method == "gn" else 0.0
        if not self.lambda_factor > 1:
            raise ValueError(f"lambda_factor must be > 1, got {self.lambda_factor}")
        if not self.lag_distance >= 0:
            raise ValueError(f"lag_distance must be >= 0, got {self.lag_distance}")
        if not self.lag_growth >= 1:
            raise ValueError(f"lag_growth must be >= 1, got {self.lag_growth}")


@dataclass
class SolveResult:
    x: np.ndarray
    iterations: int = 0
    converged: bool = True
    lambda_min: float = float("nan")
    lambda_max: float = float("nan")
    residuals: list = field(default_factory=list)
    tolerance: float = float("nan")
    setup_seconds: float = 0.0
    coarse_size: int = 0
    rebuilt: bool = True  # the preconditioner's numbers were recomputed for this matrix
    lagged: bool = False  # CG started with the previous preconditioner (lagged)


class SchwarzOptimizer:
    """``SchwarzOptimizer(graph, initial, params).optimize()`` → ``gtsam.Values``, like GTSAM's.

    ``history`` holds one dict per linear solve (Levenberg–Marquardt may try several per
    iteration; ``accepted`` tells which step was kept).
    """

    def __init__(self, graph: gtsam.NonlinearFactorGraph, initial: gtsam.Values,
                 params: SchwarzParams | None = None):
        self.graph = graph
        self.params = params or SchwarzParams()
        tune_allocator()
        self.keymap = KeyMap.from_graph(graph, initial)
        self._values = gtsam.Values(initial)
        self._error = float(graph.error(self._values))
        self.initial_error = self._error
        self.history: list[dict] = []
        self.decomposition = None
        self.converged = False
        self.stop_reason = ""
        self.final_gradient_norm = float("nan")
        self._translation_mask = self.keymap.translation_mask()
        self._g0 = None
        self._forcing_prev = None  # (gradient norm, η) of the previous linear solve
        self._lambda = self.params.lambda_initial
        self._exact_next = False  # inexact Newton: the next solve must be exact (safeguard)
        self._preconditioner = None  # kept across linear solves: symbolic work is reused
        self._direct = None
        self._pattern = None  # HessianPattern of the graph
        self._cg_after_build = None  # CG iterations of the first solve after the last numeric build
        self._moved = float("inf")  # max-norm of the accepted steps since the preconditioner's build
        self._rebuilt = True  # the last solve recomputed the preconditioner's numbers

    # -- GTSAM-like accessors ------------------------------------------------------------
    def values(self) -> gtsam.Values:
        return self._values

    def error(self) -> float:
        return self._error

    def iterations(self) -> int:
        """Nonlinear iterations (linearization points from which a step was tried)."""
        return len({h["iteration"] for h in self.history})

    @property
    def lambda_(self) -> float:
        return self._lambda

    # -- pieces ----------------------------------------------------------------------------
    def n_subdomains(self) -> int:
        p = self.params
        return p.subdomains if p.subdomains is not None else default_subdomains(self.keymap.size, p.subdomain_size)

    def _decompose(self, H):
        if self.decomposition is None:
            p = self.params
            structure = GraphStructure.from_matrix(H, self.keymap.offsets)
            self.decomposition = decompose(structure, self.n_subdomains(), p.partition, p.overlap, p.grow_along)
        return self.decomposition

    def _tolerance(self, gnorm: float) -> float:
        """CG relative tolerance: fixed, or the Eisenstat–Walker (choice 2) forcing term."""
        p = self.params
        if p.forcing == "none" or self._exact_next:
            return p.cg_tol
        if self._forcing_prev is None:
            eta = p.forcing_max
        else:
            g_prev, eta_prev = self._forcing_prev
            eta = 0.9 * (gnorm / g_prev) ** 2
            safeguard = 0.9 * eta_prev ** 2
            if safeguard > 0.1:
                eta = max(eta, safeguard)
            eta = min(eta, p.forcing_max)
        return max(eta, p.cg_tol)

    def _direct_solve(self, H, rhs):
        H = sp.csr_matrix(H)
        if self._direct is None or not self._direct[0].matches(H):
            self._direct = (SparsityPattern(H), SparseCholesky(H, "the Gauss-Newton matrix"))
        else:
            self._direct[1].refactor(H)
        return self._direct[1].solve(rhs)

    def _lag_cap(self) -> int | None:
        """Lagged preconditioner: keep the previous M while the linearization point has moved less
        than ``lag_distance`` (sum of the steps' max-norms since M was built; a rejected LM step
        moves nothing, only λ changes). CG may then use it for at most ``lag_growth`` × its count
        right after the build; None: build M anew."""
        p = self.params
        if (not p.lagged_preconditioner or self._preconditioner is None or self._cg_after_build is None
                or self._moved >= p.lag_distance):
            return None
        return int(p.lag_growth * self._cg_after_build) + 2

    def preconditioner(self, H, lag: bool = False):
        """The preconditioner for H: built on the first call, afterwards updated in place (same
        subdomains, interface, submatrix patterns and symbolic factorizations; new numbers).
        ``lag=True`` returns the previous one unchanged."""
        p = self.params
        M = self._preconditioner
        rigid = p.preconditioner in _TWO_LEVEL and p.coarse_modes == "rigid"
        geometry = (lambda: self.keymap.geometry(self._values) if rigid else None)
        self._rebuilt = not (lag and M is not None)
        if M is None or (not lag and not p.reuse_symbolic):
            M = make_preconditioner(p.preconditioner, H, self._decompose(H), self._translation_mask,
                                    geometry(), p.interface_grouping)
            self._preconditioner = M
        elif not lag:
            M.update(H, geometry())
        return M

    def solve_linear(self, H, rhs, tol: float | None = None) -> SolveResult:
        """Solve H x = rhs with the configured preconditioned CG (or the direct reference).

        A lagged preconditioner that lets CG exceed its iteration cap is rebuilt for H and CG
        continues from where it stopped (warm start)."""
        p = self.params
        tol = p.cg_tol if tol is None else tol
        t0 = time.perf_counter()
        if p.preconditioner == "direct":
            x = self._direct_solve(H, rhs)
            return SolveResult(x=x, setup_seconds=time.perf_counter() - t0, tolerance=0.0)
        cap = self._lag_cap()
        M = self.preconditioner(H, lag=cap is not None)
        setup = time.perf_counter() - t0
        use = None if p.preconditioner == "none" else M
        x, info = pcg(H, rhs, use, tol=tol, maxiter=cap if cap is not None else p.cg_max_iterations)
        iterations, residuals = info.iterations, list(info.residuals)
        lagged = cap is not None
        if lagged and not info.converged:  # stale: rebuild for H, continue from x
            t2 = time.perf_counter()
            M = use = self.preconditioner(H) if use is not None else None
            setup += time.perf_counter() - t2
            x, info = pcg(H, rhs, use, tol=tol, maxiter=p.cg_max_iterations, x0=x)
            iterations += info.iterations
            residuals += info.residuals[1:]
            self._moved = 0.0  # the warm-started count is no reference: keep the previous one
        elif self._rebuilt:
            self._cg_after_build, self._moved = info.iterations, 0.0
        coarse = getattr(M, "coarse_space", None)
        return SolveResult(x=x, iterations=iterations, converged=info.converged,
                           lambda_min=info.lambda_min, lambda_max=info.lambda_max,
                           residuals=residuals, tolerance=tol, setup_seconds=setup,
                           coarse_size=coarse.size if coarse is not None else 0,
                           rebuilt=self._rebuilt, lagged=lagged)

    def _linearize(self) -> tuple[LinearSystem, dict]:
        t0 = time.perf_counter()
        lin = self.graph.linearize(self._values)
        t1 = time.perf_counter()
        system = export_linear_system(lin, self.keymap)
        system.H = self._fixed_pattern(system.H)
        t2 = time.perf_counter()
        return system, {"linearize": t1 - t0, "export": t2 - t1}

    def _gradient_converged(self, gnorm: float) -> bool:
        p = self.params
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

    def _fixed_pattern(self, H):
        """H in the graph's full block pattern, so symbolic work is reused (see HessianPattern)."""
        fitted = self._pattern.fit(H) if self._pattern is not None else None
        if fitted is None:
            self._pattern = HessianPattern(H, self.keymap.offsets)
            fitted = self._pattern.fit(H)
        return fitted

    def _damped(self, H, lam: float):
        if lam == 0.0:
            return H
        if self.params.diagonal_damping:
            d = np.clip(H.diagonal(), 1e-6, 1e32)
        else:
            d = np.ones(H.shape[0])
        return self._pattern.damped(H, lam * d)

    def _try_step(self, system: LinearSystem, gnorm: float, lam: float, iteration: int,
                  seconds: dict) -> tuple[dict, gtsam.Values]:
        """Solve (H + λD) δ = −g, retract, evaluate; returns the history record and new values."""
        tol = self._tolerance(gnorm)
        t0 = time.perf_counter()
        result = self.solve_linear(self._damped(system.H, lam), system.rhs, tol)
        t1 = time.perf_counter()
        new_values = self.keymap.retract(self._values, result.x)
        new_error = float(self.graph.error(new_values))
        t2 = time.perf_counter()
        self._forcing_prev = (gnorm, tol)
        dx = result.x
        predicted = float(system.g @ dx + 0.5 * dx @ (system.H @ dx))
        record = {
            "iteration": iteration,
            "error_before": self._error,
            "error": new_error,
            "gradient_norm": gnorm,
            "step_norm": float(np.linalg.norm(dx)),
            "step_max": float(np.abs(dx).max()) if len(dx) else 0.0,
            "lambda": lam,
            "model_fidelity": (self._error - new_error) / -predicted if predicted < 0 else float("nan"),
            "predicted_decrease": -predicted,
            "cg_iterations": result.iterations,
            "cg_converged": result.converged,
            "cg_tolerance": result.tolerance,
            "lambda_min": result.lambda_min,
            "lambda_max": result.lambda_max,
            "coarse_size": result.coarse_size,
            "preconditioner_rebuilt": result.rebuilt,
            "preconditioner_lagged": result.lagged,
            "cg_residuals": result.residuals,
            "accepted": False,
            "seconds": {"linearize": seconds.get("linearize", 0.0), "export": seconds.get("export", 0.0),
                        "setup": result.setup_seconds, "cg": t1 - t0 - result.setup_seconds,
                        "update": t2 - t1},
        }
        return record, new_values

    def _accept(self, new_values, record):
        self._values, self._error = new_values, record["error"]
        self._moved += record["step_max"]

    def _log(self, record):
        if self.params.iteration_hook is not None:
            self.params.iteration_hook(record)
        if self.params.verbose:
            flag = "" if record["accepted"] else "  (rejected)"
            print(f"iter {record['iteration']:3d}  error {record['error']:.6e}  |g| {record['gradient_norm']:.3e}"
                  f"  lambda {record['lambda']:.1e}  cg {record['cg_iterations']:5d}"
                  f"  {sum(record['seconds'].values()):.2f}s{flag}", flush=True)

    def _error_converged(self, before: float, step_tolerance: float) -> bool:
        """GTSAM's checkConvergence on an accepted step.

        With inexact Newton, a small decrease after an inexact step only means the step was
        truncated: the next step is solved to ``cg_tol`` and the test is repeated after it.
        """
        p = self.params
        decrease = before - self._error
        reason = ""
        if self._error <= p.error_tol:
            reason = f"error {self._error:.3e} <= {p.error_tol:g}"
        elif decrease <= p.absolute_error_tol:
            reason = f"absolute error decrease {decrease:.3e}"
        elif before > 0 and decrease / before <= p.relative_error_tol:
            reason = f"relative error decrease {decrease / before:.3e}"
        if not reason:
            self._exact_next = False
            return False
        if step_tolerance > p.cg_tol and self._error > p.error_tol:
            self._exact_next = True
            return False
        self.converged, self.stop_reason = True, reason
        return True

    # -- the loops ------------------------------------------------------------------------
    def iterate(self) -> bool:
        """One nonlinear iteration (GN step, or LM until a step is accepted or λ is too large).

        Returns False when the loop must stop (a stopping rule fired or no step was accepted).
        BLAS runs single-threaded meanwhile: our dense operations are small, and idle OpenBLAS
        threads spinning beside CHOLMOD's OpenMP threads slowed setup and CG by up to 20× (measured).
        """
        if self.params.blas_threads is None:
            return self._iterate()
        with threadpool_limits(limits=self.params.blas_threads, user_api="blas"):
            return self._iterate()

    def _iterate(self) -> bool:
        p = self.params
        iteration = self.iterations() + 1
        system, seconds = self._linearize()
        gnorm = float(np.linalg.norm(system.g))
        if self._gradient_converged(gnorm):
            return False
        before = self._error
        if p.method == "gn":
            record, new_values = self._try_step(system, gnorm, 0.0, iteration, seconds)
            record["accepted"] = bool(np.isfinite(record["error"]) and record["error"] <= before)
            self.history.append(record)
            self._log(record)
            if not record["accepted"]:
                self.converged = abs(record["error"] - before) <= max(p.absolute_error_tol,
                                                                       p.relative_error_tol * before)
                self.stop_reason = "step increased the error: rejected"
                return False
            self._accept(new_values, record)
            return not self._error_converged(before, record["cg_tolerance"])
        while True:  # Levenberg–Marquardt
            record, new_values = self._try_step(system, gnorm, self._lambda, iteration, seconds)
            seconds = {}
            fidelity = record["model_fidelity"]
            ok = np.isfinite(record["error"]) and record["error"] < before and fidelity >= p.min_model_fidelity
            record["accepted"] = bool(ok)
            self.history.append(record)
            self._log(record)
            if ok:
                self._accept(new_values, record)
                self._lambda = max(self._lambda / p.lambda_factor, p.lambda_lower_bound)
                return not self._error_converged(before, record["cg_tolerance"])
            if record["cg_tolerance"] <= p.cg_tol and record["predicted_decrease"] <= max(
                    p.absolute_error_tol, p.relative_error_tol * before):
                # the quadratic model promises less than the error tolerances: nothing left to gain
                # (GTSAM would raise λ to its bound here, wasting solves on Jacobian round-off)
                self.converged = True
                self.stop_reason = (f"predicted decrease {record['predicted_decrease']:.3e} below the "
                                    f"error tolerance: converged")
                return False
            self._exact_next = True  # retry the rejected step with an exact solve
            self._lambda *= p.lambda_factor
            if self._lambda > p.lambda_upper_bound:
                self.converged = True
                self.stop_reason = f"lambda {self._lambda:.1e} above {p.lambda_upper_bound:g}: no further decrease"
                return False

    def optimize(self) -> gtsam.Values:
        """Iterate until a stopping rule fires; returns the optimized ``gtsam.Values``."""
        p = self.params
        while self.iterations() < p.max_iterations:
            if not self.iterate():
                break
        else:
            self.stop_reason = f"maximum of {p.max_iterations} iterations reached"
        return self._values

    def summary(self) -> dict:
        cg = [h["cg_iterations"] for h in self.history]
        return {
            "method": self.params.method,
            "preconditioner": self.params.preconditioner,
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
            "coarse_size": self.history[-1]["coarse_size"] if self.history else 0,
        }
