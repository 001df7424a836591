"""The nonlinear loop: GN and LM params, the optimizer (GTSAM's API), the linear-solve strategy,
typed iteration records and progress hooks."""

from .linear_solver import DirectSolver, Forcing, LinearSolver, PreconditionedCG, make_linear_solver
from .optimizer import LINEAR_SOLVERS, SchwarzOptimizer
from .params import (FORCING, METHODS, GaussNewtonParams, LevenbergMarquardtParams, LinearSolverParams,
                     SchwarzParams, linear_solver_names)
from .records import PHASES, IterationRecord, SolveResult

__all__ = ["DirectSolver", "FORCING", "Forcing", "GaussNewtonParams", "IterationRecord", "LINEAR_SOLVERS",
           "LevenbergMarquardtParams", "LinearSolver", "LinearSolverParams", "METHODS", "PHASES",
           "PreconditionedCG", "SchwarzOptimizer", "SchwarzParams", "SolveResult", "linear_solver_names",
           "make_linear_solver"]
