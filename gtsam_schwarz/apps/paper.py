"""Reproduce the paper's tables (tab:laplace_scalability, tab:numerical_performance, tab:weak_numerical,
tab:weak_null) and its figures, plus weak scaling beyond its largest case (``gtsam-schwarz paper``)."""

from __future__ import annotations

import signal
import time
from dataclasses import asdict, dataclass

import numpy as np

from ..problems import bar_chain
from ..krylov import pcg
from ..io.jsonout import json_safe
from ..nonlinear import SchwarzOptimizer, SchwarzParams
from ..schwarz import make_preconditioner
from ..problems import square_loops
from .report import DEFAULT_SIGMA


# -- the paper's numbers -------------------------------------------------------------------------
def _rows(text: str) -> list[list[float]]:
    return [[float(v) for v in line.split()] for line in text.strip().splitlines()]


# tab:laplace_scalability: subdomains, bars | one-level CG, λmin, λmax | GDSW CG, λmin, λmax
PAPER_BARS1D = _rows("""
4   254  7   1.82e-2 1.98 6 1.00 2.10
8   506  16  4.79e-3 1.99 6 1.00 2.10
16  1010 32  1.22e-3 2.00 6 1.00 2.10
32  2018 65  3.05e-4 2.00 6 1.00 2.10
64  4034 132 7.64e-5 2.00 6 1.00 2.10
128 8066 262 1.91e-5 2.00 6 1.00 2.10
""")

# tab:numerical_performance: loops, points/side | none GN, CG | one-level GN, CG | GDSW GN, CG
PAPER_NUMERICAL = _rows("""
4 4 5 153.0 5 16.0 5 13.0
4 8 5 273.6 5 15.8 5 12.4
4 16 6 510.8 6 16.0 6 12.3
4 32 5 1036.2 5 15.8 5 12.4
4 64 6 2115.7 6 15.8 6 12.5
4 128 8 3750.0 8 14.6 8 11.6
8 4 5 206.0 5 25.2 5 14.8
8 8 6 385.3 6 24.7 6 14.5
8 16 6 705.5 6 24.0 6 14.5
8 32 5 1342.2 5 24.6 5 14.6
8 64 7 3000.4 7 23.9 7 14.4
8 128 8 5441.2 8 22.0 8 13.4
16 4 6 329.3 6 41.5 6 15.8
16 8 5 551.8 5 40.6 5 16.0
16 16 6 993.2 6 40.0 6 15.3
16 32 6 2031.7 6 37.2 6 15.3
16 64 7 3694.0 7 38.1 7 15.3
16 128 9 9158.8 9 40.7 9 15.1
32 4 6 549.2 6 73.2 6 16.7
32 8 6 898.7 6 73.0 6 16.7
32 16 7 1557.3 7 65.7 7 16.7
32 32 6 2567.3 6 66.8 6 16.2
32 64 8 8014.6 8 75.0 8 16.2
32 128 16 12549.7 16 61.8 16 15.1
""")

# tab:weak_numerical (16 points per side): loops | none GN, CG | one-level GN, CG | GDSW GN, CG
PAPER_WEAK = _rows("""
4 6 510.8 6 16.0 6 12.3
8 6 705.5 6 24.0 6 14.5
16 6 993.2 6 40.0 6 15.3
32 7 1557.3 7 65.7 7 16.7
64 6 2370.7 6 121.5 6 16.7
128 9 6633.2 9 264.3 9 16.8
""")

# tab:weak_null (16 points per side): loops | without rotation GN, CG | with rotation GN, CG
PAPER_NULL = _rows("""
4 6 14.7 6 12.3
8 6 20.8 6 14.5
16 6 28.7 6 15.3
32 7 43.3 7 16.7
64 6 69.2 6 16.7
128 9 135.9 9 16.8
""")

ONE_LEVEL_PCS = ("none", "one-level", "gdsw")
TABLES = {
    "tab:numerical_performance": "loops 4-32 x points per side 4-128",
    "tab:weak_numerical": "weak scaling, 16 points per side",
    "tab:weak_null": "GDSW with and without the rotational coarse mode",
    "beyond": "beyond the paper: up to 1024 loops, overlap 2 and 3",
}


def paper_values(loops: int, pps: int, preconditioner: str, overlap: int = 1):
    """The paper's (GN iterations, average CG per GN step) for a model case, and its tables."""
    if overlap != 1:
        return None, []
    found, tables = None, []
    if preconditioner in ONE_LEVEL_PCS:
        k = ONE_LEVEL_PCS.index(preconditioner)
        for row in PAPER_NUMERICAL:
            if row[0] == loops and row[1] == pps:
                found = (int(row[2 + 2 * k]), row[3 + 2 * k])
                tables.append("tab:numerical_performance")
        for row in PAPER_WEAK:
            if row[0] == loops and pps == 16:
                found = (int(row[1 + 2 * k]), row[2 + 2 * k])
                tables.append("tab:weak_numerical")
    if preconditioner in ("gdsw-norot", "gdsw"):
        k = ("gdsw-norot", "gdsw").index(preconditioner)
        for row in PAPER_NULL:
            if row[0] == loops and pps == 16:
                found = found or (int(row[1 + 2 * k]), row[2 + 2 * k])
                tables.append("tab:weak_null")
    return found, tables


# -- settings and case lists ---------------------------------------------------------------------
@dataclass(frozen=True)
class Settings:
    """Noise, stopping rules and per-case budgets of one reproduction run."""

    sigma: float = DEFAULT_SIGMA  # GN (with step rejection) converges at every size up to 1024 loops
    seed: int = 0
    cg_tol: float = 1e-8
    gradient_tol: float = 1e-8
    relative_gradient_tol: float = 1e-6
    max_gn: int = 30
    cg_cap: int = 100_000  # CG iterations per linear solve
    case_seconds: float = 600.0  # wall-clock budget per model case
    quick: bool = False


FIGURE_SIGMA = 0.01  # Fig. optimized_results only: enough noise to see the odometry drift
BARS_SIZES = (4, 8, 16, 32, 64, 128)
WEAK_LOOPS = (4, 8, 16, 32, 64, 128)
BEYOND_LOOPS = (256, 512, 1024)


def model_cases(quick: bool) -> list[tuple[int, int, str, int]]:
    """(loops, points per side, preconditioner, overlap) of every model case, smallest first."""
    cases = []
    if quick:
        cases += [(4, p, pc, 1) for p in (4, 8) for pc in ONE_LEVEL_PCS]
        cases += [(L, 16, pc, 1) for L in (4, 8, 16, 32) for pc in ONE_LEVEL_PCS + ("gdsw-norot",)]
        cases += [(L, 16, pc, ov) for L in (8, 32) for pc in ("one-level", "gdsw") for ov in (2, 3)]
    else:
        cases += [(int(r[0]), int(r[1]), pc, 1) for r in PAPER_NUMERICAL for pc in ONE_LEVEL_PCS]
        cases += [(L, 16, pc, 1) for L in WEAK_LOOPS + BEYOND_LOOPS for pc in ONE_LEVEL_PCS + ("gdsw-norot",)]
        cases += [(L, 16, pc, ov) for L in WEAK_LOOPS + BEYOND_LOOPS for pc in ("one-level", "gdsw") for ov in (2, 3)]
    seen, out = set(), []
    for c in cases:
        if c not in seen:
            seen.add(c)
            out.append(c)
    return sorted(out, key=lambda c: (c[0] * c[1], c[0], c[3], c[2]))


# -- the 1D bar chain (appendix) -----------------------------------------------------------------
def bars1d(sizes=BARS_SIZES, tol: float = 1e-8) -> list[dict]:
    """tab:laplace_scalability: CG iterations and Lanczos λmin/λmax of M⁻¹K, overlap 1.

    CG stops on the natural norm √(rᵀM⁻¹r) ≤ tol·√(r₀ᵀM⁻¹r₀), which reproduces the paper's counts;
    ``cg_residual_norm`` is the count with the default ‖r‖ ≤ tol·‖b‖ rule, for comparison.
    """
    paper = {int(r[0]): r for r in PAPER_BARS1D}
    rows = []
    for N in sizes:
        chain = bar_chain(N)
        dec = chain.decomposition(overlap=1)
        row = {"subdomains": N, "bars": chain.bars, "stopping": "natural"}
        for key, name, k in (("one_level", "one-level", 2), ("gdsw", "gdsw", 5)):
            M = make_preconditioner(name, chain.K, dec)
            x, info = pcg(chain.K, chain.b, M, tol=tol, norm="natural")
            _, plain = pcg(chain.K, chain.b, M, tol=tol)
            entry = {"cg": info.iterations, "lambda_min": info.lambda_min, "lambda_max": info.lambda_max,
                     "converged": info.converged, "cg_residual_norm": plain.iterations,
                     "max_error": float(np.max(np.abs(x - chain.solution)))}
            if N in paper:
                p = paper[N]
                entry["paper"] = {"cg": int(p[k]), "lambda_min": p[k + 1], "lambda_max": p[k + 2]}
            row[key] = entry
        rows.append(row)
    return rows


# -- the 2D model problem ------------------------------------------------------------------------
class _Budget(Exception):
    pass


def _alarm(signum, frame):
    raise _Budget()


def paper_params(preconditioner: str, loops: int, overlap: int, settings: Settings) -> SchwarzParams:
    """The paper's solver: plain Gauss–Newton, one subdomain per loop, unit (algebraic) coarse modes,
    stopping only on ‖g‖ ≤ 1e-8 or ‖g‖ ≤ 1e-6‖g₀‖ (GTSAM's error-decrease rules off)."""
    return SchwarzParams(method="gn", preconditioner=preconditioner, subdomains=loops, partition="segments",
                         overlap=overlap, coarse_modes="unit", interface_grouping="vertices",
                         cg_tol=settings.cg_tol, cg_max_iterations=settings.cg_cap, forcing="none",
                         max_iterations=settings.max_gn, gradient_tol=settings.gradient_tol,
                         relative_gradient_tol=settings.relative_gradient_tol,
                         relative_error_tol=0.0, absolute_error_tol=-1.0, error_tol=0.0)


def run_case(problem, preconditioner: str, overlap: int, settings: Settings) -> dict:
    """Optimize one model problem; a case that runs out of its budget is returned as capped."""
    opt = SchwarzOptimizer(problem.graph, problem.initial,
                           paper_params(preconditioner, problem.loops, overlap, settings))
    timed_out = False
    use_alarm = hasattr(signal, "setitimer")
    if use_alarm:
        try:
            previous = signal.signal(signal.SIGALRM, _alarm)
        except ValueError:  # not the main thread: no hard budget
            use_alarm = False
    t0 = time.perf_counter()
    try:
        if use_alarm:
            signal.setitimer(signal.ITIMER_REAL, settings.case_seconds)
        opt.optimize()
    except _Budget:
        timed_out = True
    finally:
        if use_alarm:
            signal.setitimer(signal.ITIMER_REAL, 0)
            signal.signal(signal.SIGALRM, previous)
    seconds = time.perf_counter() - t0
    cg = [int(h["cg_iterations"]) for h in opt.history]
    cg_capped = any(not h["cg_converged"] for h in opt.history)
    paper, tables = paper_values(problem.loops, problem.points_per_side, preconditioner, overlap)
    reason = f"budget of {settings.case_seconds:g} s per case exceeded" if timed_out else opt.stop_reason
    if cg_capped and not timed_out:
        reason = f"CG hit its cap of {settings.cg_cap} iterations; " + reason
    return {
        "loops": problem.loops, "points_per_side": problem.points_per_side,
        "preconditioner": preconditioner, "overlap": overlap, "poses": problem.poses,
        "gn_iterations": opt.iterations(),
        "cg_mean": float(np.mean(cg)) if cg else None,
        "cg_iterations": cg,
        "converged": bool(opt.converged and not timed_out),
        "capped": bool(timed_out or cg_capped),
        "stop_reason": reason,
        "final_error": float(opt.error()),
        "seconds": round(seconds, 3),
        "paper_gn": paper[0] if paper else None,
        "paper_cg": paper[1] if paper else None,
        "tables": tables or ["beyond"],
    }


def run_model(cases, settings: Settings, progress=None) -> list[dict]:
    """Run the model cases; each problem size is generated once and shared by its cases."""
    results, problem = [], None
    for i, (L, P, pc, ov) in enumerate(cases, 1):
        if problem is None or (problem.loops, problem.points_per_side) != (L, P):
            problem = square_loops(L, P, sigma=settings.sigma, seed=settings.seed)
        row = run_case(problem, pc, ov, settings)
        results.append(row)
        if progress:
            cg = "-" if row["cg_mean"] is None else f"{row['cg_mean']:.1f}"
            flag = " CAPPED" if row["capped"] else ("" if row["converged"] else " NOT CONVERGED")
            progress(f"[{i}/{len(cases)}] loops {L:4d} pps {P:3d} {pc:10s} overlap {ov}: "
                     f"GN {row['gn_iterations']}, CG/step {cg}, {row['seconds']:.1f} s{flag}")
    return results


# -- deviations ----------------------------------------------------------------------------------
DEVIATION_THRESHOLD = 0.20


def deviations(bars: list[dict], model: list[dict], settings: Settings) -> list[dict]:
    """Every compared cell more than 20 % from the paper (bar chain: any CG mismatch), with a reason."""
    out = []
    for row in bars:
        for key in ("one_level", "gdsw"):
            e = row[key]
            if "paper" in e and e["cg"] != e["paper"]["cg"]:
                out.append({"table": "tab:laplace_scalability", "case": f"{row['subdomains']} subdomains",
                            "quantity": f"{key} CG", "ours": e["cg"], "paper": e["paper"]["cg"],
                            "reason": "finite-termination step of CG decided by rounding at the 1e-8 level"})
    for r in model:
        if r["paper_cg"] is None:
            continue
        case = f"{r['loops']} loops x {r['points_per_side']} pps, {r['preconditioner']}"
        for qty, ours, paper in (("GN", r["gn_iterations"], r["paper_gn"]), ("CG", r["cg_mean"], r["paper_cg"])):
            if ours is None or paper is None:
                continue
            rel = (ours - paper) / paper
            if abs(rel) > DEVIATION_THRESHOLD:
                out.append({"table": ", ".join(r["tables"]), "case": case, "quantity": qty,
                            "ours": ours, "paper": paper, "relative": rel,
                            "reason": deviation_reason(r, qty, rel, settings)})
    return out


def deviation_reason(r: dict, qty: str, rel: float, settings: Settings) -> str:
    if r["capped"]:
        return f"capped: {r['stop_reason']}"
    if qty == "GN":
        return (f"GN steps are set by the noise, which the paper does not state; σ = {settings.sigma:g} (chosen so "
                "that GN converges up to 1024 loops, see Setup) needs 2–3 steps where the paper needs 5–16")
    pc = r["preconditioner"]
    if pc == "none":
        return ("unpreconditioned counts in the thousands depend on the spectrum of H at the noisy linearization "
                "points and on finite-precision loss of orthogonality; the paper's own counts are erratic "
                "(2567 at 32x32, 8015 at 32x64) and its 8–16 GN steps at 128 points per side indicate a much "
                "noisier problem than ours")
    if pc == "one-level":
        return ("one-level counts are 10–30 % above the paper's throughout (5 % at 128 loops), with the same growth "
                "in the loops; not explained by the noise (σ = 0.05 gives the same counts), the CG stopping norm "
                "(the natural norm gives the same counts), overlap 0 or 2, or growing the overlap across loop "
                "closures (all measured separately): cause not identified")
    return "depends on the noise realization through H; the paper's σ and seed are unknown"


def settings_dict(settings: Settings) -> dict:
    return json_safe(asdict(settings))


# -- the whole reproduction ----------------------------------------------------------------------
FIGURES = {"scalability": "paper_scalability.png", "hat": "paper_hat_function.png",
           "sparsity": "paper_sparsity.png", "optimized_results": "paper_optimized_results.png"}
REPORT = "paper_results.md"


def reproduce(out_dir, settings: Settings, progress=None, command: str = "gtsam-schwarz paper") -> dict:
    """Compute every table and figure, write the figures and the Markdown report into ``out_dir``."""
    import pathlib

    from . import plots
    from ..io import atomic_write
    from .report import render

    out = pathlib.Path(out_dir)
    t0 = time.perf_counter()
    say = progress or (lambda msg: None)
    say("bar chain (tab:laplace_scalability)")
    bars = bars1d()
    files = {}
    say("figures hat, sparsity, optimized_results")
    files["hat"] = plots.hat_figure(out / FIGURES["hat"], square_loops(5, 8, settings.sigma, settings.seed))
    small = square_loops(8, 8, settings.sigma, settings.seed)
    files["sparsity"] = plots.sparsity_figure(out / FIGURES["sparsity"], small)
    fig_problem = square_loops(8, 8, FIGURE_SIGMA, settings.seed)
    opt = SchwarzOptimizer(fig_problem.graph, fig_problem.initial, paper_params("gdsw", 8, 1, settings))
    optimized = opt.optimize()
    files["optimized_results"] = plots.optimized_figure(out / FIGURES["optimized_results"], fig_problem, optimized)
    notes = [f"Fig. optimized_results uses σ = {FIGURE_SIGMA:g} (seed {settings.seed}) so that the odometry "
             f"drift is visible; GN + GDSW converged in {opt.iterations()} steps ({opt.stop_reason})."]
    model = run_model(model_cases(settings.quick), settings, progress)
    files["scalability"] = plots.scalability_figure(out / FIGURES["scalability"], model, PAPER_WEAK, PAPER_NULL)
    results = {
        "command": command,
        "settings": settings_dict(settings),
        "bars1d": bars,
        "model": model,
        "deviations": deviations(bars, model, settings),
        "figure_notes": notes,
        "seconds": round(time.perf_counter() - t0, 1),
    }
    report = out / REPORT
    atomic_write(report, render(results, {k: FIGURES[k] for k in ("scalability", "hat", "sparsity",
                                                                   "optimized_results")}), parents=True)
    results["files"] = {"report": str(report), **files}
    return results
