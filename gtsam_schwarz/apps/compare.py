"""Side-by-side runs on one graph: our optimizer and GTSAM's own optimizers, timed the same way."""

from __future__ import annotations

import time
import warnings

import gtsam

from ..nonlinear import SchwarzOptimizer, SchwarzParams

GTSAM_SOLVERS = ("gtsam-lm", "gtsam-gn", "gtsam-lm-pcg", "gtsam-lm-subgraph")


ITERATIVE_TOL = 1e-8  # our CG tolerance: GTSAM's default (1e-3) stops LM early at a worse error,
ITERATIVE_MAX = 20_000  # e.g. M3500 at 75.2 instead of 68.96; block-Jacobi needs ~2400 CG iterations
#                         per M3500 solve at 1e-8


def _gtsam_params(name: str, iterative_tol: float | None = None):
    def tight(cg_params):
        if iterative_tol is not None:  # relative tolerance, no absolute floor, a high cap
            cg_params.epsilon_rel, cg_params.epsilon_abs = iterative_tol, 0.0
            cg_params.maxIterations = ITERATIVE_MAX
        return cg_params

    if name == "gtsam-gn":
        return gtsam.GaussNewtonParams(), gtsam.GaussNewtonOptimizer
    params = gtsam.LevenbergMarquardtParams()
    if name == "gtsam-lm-pcg":
        pcg = tight(gtsam.PCGSolverParameters())
        pcg.preconditioner = gtsam.BlockJacobiPreconditionerParameters()
        params.setIterativeParams(pcg)
        params.setLinearSolverType("ITERATIVE")
    elif name == "gtsam-lm-subgraph":
        params.setIterativeParams(tight(gtsam.SubgraphSolverParameters()))
        params.setLinearSolverType("ITERATIVE")
    elif name != "gtsam-lm":
        raise ValueError(f"unknown GTSAM solver {name!r}; choose one of {', '.join(GTSAM_SOLVERS)}")
    return params, gtsam.LevenbergMarquardtOptimizer


def run_gtsam(graph, initial, name: str = "gtsam-lm", max_iterations: int = 100,
              iterative_tol: float | None = None, iteration_hook=None) -> dict:
    """GTSAM's optimizer ``name`` with its default parameters (multifrontal Cholesky; PCG with
    block-Jacobi; SubgraphSolver); ``iterative_tol`` sets the iterative solvers' CG tolerance
    (e.g. :data:`ITERATIVE_TOL`, ours, for a comparison at equal final error); ``iteration_hook``
    is GTSAM's ``iterationHook`` (called with iteration, error before, error after).

    A failure (GTSAM's exceptions are RuntimeErrors) is a row with ``failed`` (its first line, for
    one-line table cells) and ``failed_message`` (the whole message)."""
    params, cls = _gtsam_params(name, iterative_tol)
    params.setMaxIterations(max_iterations)
    if iteration_hook is not None:
        params.iterationHook = iteration_hook
    t = time.perf_counter()
    opt = cls(graph, initial, params)
    try:
        values = opt.optimize()
    except RuntimeError as exc:  # e.g. GTSAM's IndeterminantLinearSystemException
        message = str(exc).strip() or type(exc).__name__
        first = next(line.strip() for line in message.splitlines() if line.strip())
        return {"solver": name, "final_error": float("nan"), "iterations": int(opt.iterations()),
                "seconds": time.perf_counter() - t, "values": None, "failed": first, "failed_message": message}
    seconds = time.perf_counter() - t
    return {"solver": name, "final_error": float(graph.error(values)), "iterations": int(opt.iterations()),
            "seconds": seconds, "values": values}


def run_ours(graph, initial, params: SchwarzParams, arrays: dict | None = None, release_arrays: bool = False) -> dict:
    """Our optimizer with ``params``; the row carries the summary and the time split.

    ``arrays``: the loader's parsed numbers (``LoadedGraph.arrays``): the native linearizer is built
    from them instead of reading the gtsam graph factor by factor (its construction is timed).
    ``release_arrays``: empty that dict (the caller's too) once the linearizer holds its own copies,
    for callers that do not read it again: the loader's arrays are no longer held through the solve
    (1M 2D poses: 244 MiB, ~220 of them freed), nor the start's poses once the optimizer holds its state
    (the last 31 MiB: the linearizer's view of them)."""
    t = time.perf_counter()
    linearizer = None
    if arrays and params.linearization != "gtsam":
        from ..linearization.native import NativeLinearizer
        linearizer = NativeLinearizer.from_arrays(**arrays)
        if release_arrays:
            arrays.clear()
    opt = SchwarzOptimizer(graph, initial, params, linearizer=linearizer)
    if release_arrays and linearizer is not None:
        linearizer.release_initial()
    with warnings.catch_warnings():  # the row reports converged / stop_reason itself
        warnings.simplefilter("ignore", RuntimeWarning)
        values = opt.optimize()
    seconds = time.perf_counter() - t
    s = opt.summary()
    split = {k: sum(h["seconds"][k] for h in opt.history) for k in ("linearize", "export", "setup", "cg", "update")}
    return {"solver": params.preconditioner, "method": params.method, "final_error": s["final_error"],
            "iterations": s["iterations"], "linear_solves": s["linear_solves"], "cg_mean": s["cg_mean"],
            "cg_iterations": s["cg_iterations"], "subdomains": s["subdomains"], "partition": s.get("partition"), "coarse_size": s["coarse_size"],
            "converged": s["converged"], "stop_reason": s["stop_reason"], "initial_error": s["initial_error"],
            "seconds": seconds, "split": split, "values": values, "history": opt.history,
            "decomposition": opt.decomposition, "linear_solver": s["linear_solver"], "anchored": s["anchored"]}
