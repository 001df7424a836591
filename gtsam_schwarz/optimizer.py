"""Gauss–Newton over ``gtsam.Values`` with Schwarz-preconditioned CG as the linear solver.

Per iteration: linearize (gtsam) → export H, g → build the preconditioner → PCG → retract.
What depends only on the graph (key map, decomposition, index sets) is built once.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import gtsam
import numpy as np
import scipy.sparse as sp

from .decomposition import GraphStructure, segments
from .krylov import pcg
from .linear_system import KeyMap, export_linear_system
from .local_solvers import factorize
from .preconditioners import PRECONDITIONERS, make_preconditioner

LINEAR_SOLVERS = PRECONDITIONERS + ("direct",)


@dataclass
class SchwarzParams:
    """Parameters, named like GTSAM's where they mean the same thing.

    Stopping: the paper's (‖g‖ ≤ ``gradient_tol`` or ‖g‖ ≤ ``relative_gradient_tol``·‖g₀‖), GTSAM's
    error decrease (relative ``relative_error_tol``, absolute ``absolute_error_tol``, ``error_tol``),
    and ``max_iterations``. A step that increases the error is rejected and ends the loop.
    """

    preconditioner: str = "gdsw"  # none | jacobi | block-jacobi | one-level | gdsw | gdsw-norot | direct
    subdomains: int | None = None  # None: one per `subdomain_size` poses
    subdomain_size: int = 500
    overlap: int = 1
    grow_along: str = "odometry"  # or "all"
    cg_tol: float = 1e-8
    cg_max_iterations: int | None = None  # None: 10 × the system dimension
    max_iterations: int = 100
    gradient_tol: float = 1e-8
    relative_gradient_tol: float = 1e-6
    relative_error_tol: float = 1e-5
    absolute_error_tol: float = 1e-5
    error_tol: float = 0.0
    verbose: bool = False

    def __post_init__(self):
        if self.preconditioner not in LINEAR_SOLVERS:
            raise ValueError(f"unknown preconditioner {self.preconditioner!r}; "
                             f"choose one of {', '.join(LINEAR_SOLVERS)}")
        if self.subdomains is not None and self.subdomains < 1:
            raise ValueError(f"subdomains must be >= 1, got {self.subdomains}")
        if self.overlap < 0:
            raise ValueError(f"overlap must be >= 0, got {self.overlap}")
        if not self.cg_tol > 0:
            raise ValueError(f"cg_tol must be > 0, got {self.cg_tol}")


@dataclass
class SolveResult:
    x: np.ndarray
    iterations: int = 0
    converged: bool = True
    lambda_min: float = float("nan")
    lambda_max: float = float("nan")
    residuals: list = field(default_factory=list)


class SchwarzOptimizer:
    """``SchwarzOptimizer(graph, initial, params).optimize()`` → ``gtsam.Values``, like GTSAM's."""

    def __init__(self, graph: gtsam.NonlinearFactorGraph, initial: gtsam.Values,
                 params: SchwarzParams | None = None):
        self.graph = graph
        self.params = params or SchwarzParams()
        self.keymap = KeyMap.from_graph(graph, initial)
        self._values = gtsam.Values(initial)
        self._error = float(graph.error(self._values))
        self.initial_error = self._error
        self.history: list[dict] = []
        self.decomposition = None
        self.converged = False
        self.stop_reason = ""
        self.final_gradient_norm = float("nan")
        self._g0 = None

    # -- GTSAM-like accessors ------------------------------------------------------------
    def values(self) -> gtsam.Values:
        return self._values

    def error(self) -> float:
        return self._error

    def iterations(self) -> int:
        return len(self.history)

    # -- pieces ----------------------------------------------------------------------------
    def n_subdomains(self) -> int:
        p = self.params
        if p.subdomains is not None:
            return p.subdomains
        return max(1, int(round(self.keymap.size / p.subdomain_size)))

    def _decompose(self, H):
        if self.decomposition is None:
            structure = GraphStructure.from_matrix(H, self.keymap.offsets)
            self.decomposition = segments(structure, self.n_subdomains(), self.params.overlap,
                                          self.params.grow_along)
            self._translation_mask = self.keymap.translation_mask()
        return self.decomposition

    def solve_linear(self, H, rhs) -> tuple[SolveResult, float]:
        """Solve H x = rhs with the configured method; returns (result, setup seconds)."""
        p = self.params
        t0 = time.perf_counter()
        if p.preconditioner == "direct":
            solve = factorize(sp.csc_matrix(H), "the Gauss-Newton matrix")
            t1 = time.perf_counter()
            return SolveResult(x=solve(rhs)), t1 - t0
        M = make_preconditioner(p.preconditioner, H, self._decompose(H), self._translation_mask)
        t1 = time.perf_counter()
        x, info = pcg(H, rhs, None if p.preconditioner == "none" else M, tol=p.cg_tol,
                      maxiter=p.cg_max_iterations)
        return SolveResult(x=x, iterations=info.iterations, converged=info.converged,
                           lambda_min=info.lambda_min, lambda_max=info.lambda_max,
                           residuals=info.residuals), t1 - t0

    # -- the loop -------------------------------------------------------------------------
    def iterate(self) -> dict | None:
        """One Gauss–Newton step. Returns its history record, or None if a gradient test stopped."""
        p = self.params
        t0 = time.perf_counter()
        lin = self.graph.linearize(self._values)
        t1 = time.perf_counter()
        system = export_linear_system(lin, self.keymap)
        t2 = time.perf_counter()
        gnorm = float(np.linalg.norm(system.g))
        if self._g0 is None:
            self._g0 = gnorm
        self.final_gradient_norm = gnorm
        if gnorm <= p.gradient_tol:
            self.converged, self.stop_reason = True, f"gradient norm {gnorm:.3e} <= {p.gradient_tol:g}"
            return None
        if gnorm <= p.relative_gradient_tol * self._g0:
            self.converged, self.stop_reason = True, (
                f"gradient norm decreased by {gnorm / self._g0:.3e} <= {p.relative_gradient_tol:g}")
            return None
        if not p.preconditioner == "direct":
            self._decompose(system.H)
        t3 = time.perf_counter()
        result, setup = self.solve_linear(system.H, system.rhs)
        t4 = time.perf_counter()
        new_values = self.keymap.retract(self._values, result.x)
        new_error = float(self.graph.error(new_values))
        t5 = time.perf_counter()
        record = {
            "iteration": len(self.history) + 1,
            "error_before": self._error,
            "error": new_error,
            "gradient_norm": gnorm,
            "step_norm": float(np.linalg.norm(result.x)),
            "cg_iterations": result.iterations,
            "cg_converged": result.converged,
            "lambda_min": result.lambda_min,
            "lambda_max": result.lambda_max,
            "cg_residuals": result.residuals,
            "accepted": bool(np.isfinite(new_error) and new_error <= self._error),
            "seconds": {"linearize": t1 - t0, "export": t2 - t1, "setup": setup + (t3 - t2),
                        "cg": t4 - t3 - setup, "update": t5 - t4},
        }
        self.history.append(record)
        if p.verbose:
            print(f"iter {record['iteration']:3d}  error {new_error:.6e}  |g| {gnorm:.3e}  "
                  f"cg {result.iterations:5d}  {sum(record['seconds'].values()):.2f}s", flush=True)
        if record["accepted"]:
            self._values, self._error = new_values, new_error
        return record

    def optimize(self) -> gtsam.Values:
        """Iterate until a stopping rule fires; returns the optimized ``gtsam.Values``."""
        p = self.params
        while len(self.history) < p.max_iterations:
            before = self._error
            record = self.iterate()
            if record is None:
                break
            if not record["accepted"]:
                self.converged = abs(record["error"] - before) <= max(p.absolute_error_tol,
                                                                       p.relative_error_tol * before)
                self.stop_reason = "step increased the error: rejected"
                break
            decrease = before - self._error
            if self._error <= p.error_tol:
                self.converged, self.stop_reason = True, f"error {self._error:.3e} <= {p.error_tol:g}"
                break
            if decrease <= p.absolute_error_tol:
                self.converged, self.stop_reason = True, f"absolute error decrease {decrease:.3e}"
                break
            if before > 0 and decrease / before <= p.relative_error_tol:
                self.converged, self.stop_reason = True, f"relative error decrease {decrease / before:.3e}"
                break
        else:
            self.stop_reason = f"maximum of {p.max_iterations} iterations reached"
        return self._values

    def summary(self) -> dict:
        cg = [h["cg_iterations"] for h in self.history]
        return {
            "iterations": len(self.history),
            "initial_error": self.initial_error,
            "final_error": self._error,
            "converged": self.converged,
            "stop_reason": self.stop_reason,
            "cg_iterations": cg,
            "cg_mean": float(np.mean(cg)) if cg else 0.0,
            "subdomains": self.decomposition.n_subdomains if self.decomposition else None,
        }
