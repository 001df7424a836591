"""``gtsam-schwarz demo``, the main job: why and when to use this solver, measured in under a minute.

Three parts, each printed as a table and drawn as one panel of ``demo.png``:

1. *Same answer, less time*: the paper's model problem at 65k poses, solved by ours (the automatic
   choice), GTSAM's LM and g2o's Gauss–Newton (when installed).
2. *Bounded CG* (the paper's point): one Gauss–Newton system per model-problem size, one subdomain
   per loop; CG iterations with block-Jacobi and one-level Schwarz grow with the graph, with the
   GDSW coarse space they stay flat.
3. *Where fill explodes*: lawnmower surveys (2D rows with closures to the previous row) and 3D
   surveys (stacked floors): the direct factor's fill grows with the graph while CG with the
   ``rgdsw-linear`` coarse space stays near 30–50 iterations. One linear solve each, at the chordal
   initialization (where the optimizer starts), direct (CHOLMOD) against Schwarz-preconditioned CG,
   setup included, and what ``auto`` picks from its cost model. On the 32 768-pose 3D survey Schwarz
   is the faster one and keeps less memory.
"""

from __future__ import annotations

import time
import warnings

import numpy as np

from .commands import _accuracy, _add_quiet, _progress, make_out_dir, positive_int

SOLVE_CASE = (256, 64)  # loops x points per side: 65 537 poses
SCALING_LOOPS = (4, 16, 64, 256)  # x 16 points per side: 257 … 16 385 poses
SCALING_PRECONDITIONERS = ("block-jacobi", "one-level", "gdsw")
# lawnmower rows x cols; 3D floors x rows x cols
FILL_SURVEYS = ((50, 50), (100, 100), (150, 150), (4, 16, 16), (8, 24, 24), (32, 32, 32))
FILL_SCHWARZ = "rgdsw-linear"
QUICK = {"solve": (8, 16), "loops": (2, 4, 8), "surveys": ((12, 12), (2, 6, 6))}
CG_CAP = 5000


def _solver_row(name: str, final_error: float, seconds: float, truth_accuracy: dict | None, **extra) -> dict:
    row = {"solver": name, "final_error": float(final_error), "seconds": float(seconds), **extra}
    if truth_accuracy:
        row["ate_rmse"], row["rpe_rmse"] = truth_accuracy["ate_rmse"], truth_accuracy["rpe_rmse"]
    return row


def solve_part(loops: int, pps: int, progress) -> dict:
    """Part 1: the model problem by ours (auto and gdsw), GTSAM LM and g2o GN (if installed)."""
    from ..nonlinear import SchwarzParams
    from ..problems import square_loops
    from . import peers
    from .compare import run_gtsam, run_ours

    prob = square_loops(loops, pps, sigma=0.01, seed=0)
    rows = []
    progress.start("ours (auto)")
    r = run_ours(prob.graph, prob.initial, SchwarzParams(), prob.arrays)
    rows.append(_solver_row("ours (auto)", r["final_error"], r["seconds"], _accuracy(r["values"], prob.ground_truth),
                            iterations=r["iterations"], cg_mean=r["cg_mean"],
                            linear_solver=r["linear_solver"]["used"], converged=r["converged"]))
    progress.done()
    progress.start("gtsam-lm")
    g = run_gtsam(prob.graph, prob.initial, "gtsam-lm")
    rows.append(_solver_row("GTSAM LM", g["final_error"], g["seconds"], _accuracy(g["values"], prob.ground_truth),
                            iterations=g["iterations"], failed=g.get("failed")))
    progress.done()
    if peers.available():
        progress.start("g2o-gn")
        try:
            p = peers.solve_g2o(prob.graph, prob.initial, "gn")
            err = prob.graph.error(p["values"]) if p.get("values") is not None else float("nan")
            rows.append(_solver_row("g2o GN", err, p["seconds"], _accuracy(p.get("values"), prob.ground_truth),
                                    iterations=p["iterations"], failed=p.get("failed")))
        finally:
            progress.done()
    else:
        rows.append({"solver": "g2o GN", "not_installed": "pip install -e '.[peers]'"})
    ref = next(r["seconds"] for r in rows if r["solver"] == "GTSAM LM")
    for r in rows:
        if "seconds" in r:
            r["x_gtsam_lm"] = r["seconds"] / ref if ref > 0 else float("nan")
    return {"problem": f"model problem {loops} loops x {pps} points per side", "poses": prob.poses,
            "rows": rows, "initial": _accuracy(prob.initial, prob.ground_truth)}


def _one_solve(H, rhs, offsets, mask, geometry, preconditioner: str, **options) -> dict:
    """One linear solve H x = rhs: seconds (setup + solve), CG iterations, coarse size, residual."""
    from ..nonlinear.linear_solver import make_linear_solver
    from ..nonlinear.params import LinearSolverParams
    from ..util.blas import blas_limits

    params = LinearSolverParams(preconditioner=preconditioner, cg_max_iterations=CG_CAP, **options)
    solver = make_linear_solver(params, offsets, mask)
    t0 = time.perf_counter()
    with blas_limits(1):   # as our optimizer solves (its blas_threads): OpenBLAS's threads beside CHOLMOD cost
        result = solver.solve(H, rhs, 1e-8, lambda: geometry)   # 2-4x in setup here (3D 8x24x24: 1.37 → 0.67 s)
    seconds = time.perf_counter() - t0
    residual = float(np.linalg.norm(H @ result.x - rhs) / np.linalg.norm(rhs))
    memory = _schwarz_memory(getattr(solver, "operator", None), H)
    return {"memory_bytes": memory, "seconds": seconds, "cg": int(result.iterations), "converged": bool(result.converged or
                                                                              preconditioner == "direct"),
            "coarse_size": int(result.coarse_size), "residual": residual,
            "choice": getattr(solver, "choice", preconditioner), "reason": getattr(solver, "reason", "")}


def _schwarz_memory(M, H) -> float | None:
    """Predicted bytes a two-level operator keeps (factors, gathered blocks, Φ, A₀; schwarz.memory's
    parts without its allocator slack, to compare with the direct factor's bytes)."""
    if M is None or not hasattr(M, "extension"):
        return None
    from ..schwarz.memory import estimate_two_level

    return float(sum(estimate_two_level(M, H).parts.values()))


def _system(problem):
    """The Gauss–Newton system at the problem's initial guess, from the native linearizer."""
    from ..linearization.native import NativeLinearizer

    lin = NativeLinearizer.from_arrays(**problem.arrays)
    state = lin.initial_state()
    system = lin.linearize(state)
    return system.H.tocsr(), system.rhs, lin.offsets, lin.translation_mask(), lin.geometry(state)


def scaling_part(loop_counts, progress) -> list[dict]:
    """Part 2: CG iterations of one Gauss–Newton system per size, one subdomain per loop (paper)."""
    from ..problems import square_loops

    rows = []
    for loops in loop_counts:
        prob = square_loops(loops, 16, sigma=0.01, seed=0)
        H, rhs, offsets, mask, geometry = _system(prob)
        row = {"loops": loops, "poses": prob.poses}
        for name in SCALING_PRECONDITIONERS:
            progress.start(f"CG scaling: {loops} loops, {name}")
            r = _one_solve(H, rhs, offsets, mask, geometry, name, subdomains=loops, partition="segments")
            row[name] = r["cg"] if r["converged"] else None  # None: not converged within CG_CAP
            progress.done()
        rows.append(row)
    return rows


def _survey(dims):
    from ..problems import lawnmower, survey3d

    if len(dims) == 2:
        return f"2D {dims[0]}x{dims[1]}", lawnmower(*dims, sigma=0.01, seed=0)
    return f"3D {dims[0]}x{dims[1]}x{dims[2]}", survey3d(*dims, sigma=0.01, seed=0)


def fill_part(surveys, progress) -> list[dict]:
    """Part 3: one linear solve per survey, at its chordal initialization, direct against Schwarz-CG."""
    from ..linearization.native import NativeLinearizer
    from ..nonlinear.initialize import chordal_state
    from ..nonlinear.linear_solver import AutoSolver
    from ..nonlinear.params import LinearSolverParams
    from ..solvers import cholesky_cost
    from ..solvers.memory import FACTOR_BYTES

    rows = []
    for dims in surveys:
        name, prob = _survey(dims)
        lin = NativeLinearizer.from_arrays(**prob.arrays)
        state, _ = chordal_state(lin, lin.initial_state())
        system = lin.linearize(state)
        H, rhs, offsets, mask, geometry = (system.H.tocsr(), system.rhs, lin.offsets, lin.translation_mask(),
                                           lin.geometry(state))
        cost = cholesky_cost(H, offsets)
        row = {"survey": name, "poses": prob.poses, "nnz_H": int(H.nnz),
               "nnz_L": float(cost.nnz_L), "fill": float(cost.fill), "flops": float(cost.flops),
               "direct_factor_bytes": float(FACTOR_BYTES * cost.nnz_L)}
        for solver in ("direct", FILL_SCHWARZ):
            progress.start(f"fill: {name}, {solver}")
            # a solve to 1e-8 is an exact step: the exact steps' subdomain size (forcing "none")
            row[solver] = _one_solve(H, rhs, offsets, mask, geometry, solver, forcing="none")
            progress.done()
        progress.start(f"fill: {name}, auto's choice")
        # what `auto` would run for a solve to 1e-8, as both were just measured (exact steps: forcing "none")
        auto = AutoSolver(LinearSolverParams(forcing="none"), offsets, mask)
        auto.choose(H)
        progress.done()
        row["auto_choice"], row["auto_reason"] = auto.choice, auto.reason
        row["schwarz_over_direct"] = row[FILL_SCHWARZ]["seconds"] / row["direct"]["seconds"]
        faster = FILL_SCHWARZ if row["schwarz_over_direct"] < 1.0 else "direct"
        row["auto_picks_faster"] = auto.choice == faster
        rows.append(row)
    return rows


# -- output ---------------------------------------------------------------------------------------
def _fmt(v, spec: str, missing: str = "-") -> str:
    return missing if v is None or (isinstance(v, float) and not np.isfinite(v)) else format(v, spec)


def print_report(report: dict) -> None:
    s = report["solve"]
    print(f"1. Same answer, less time: {s['problem']} = {s['poses']} poses (sigma 0.01, seed 0)")
    print(f"   {'solver':<14}{'final error':>16}{'its':>5}{'seconds':>9}{'x GTSAM LM':>12}{'ATE [m]':>10}  note")
    for r in s["rows"]:
        if "not_installed" in r:
            print(f"   {r['solver']:<14}{'not installed':>16}  ({r['not_installed']})")
            continue
        note = r.get("failed") or (f"{r['linear_solver']}" + (f", CG {r['cg_mean']:.1f}/solve" if r.get("cg_mean")
                                                              else "") if "linear_solver" in r else "")
        print(f"   {r['solver']:<14}{_fmt(r['final_error'], '.10g'):>16}{r.get('iterations', 0):>5}"
              f"{r['seconds']:>9.3f}{_fmt(r.get('x_gtsam_lm'), '.2f'):>12}{_fmt(r.get('ate_rmse'), '.4f'):>10}  {note}")
    print("   (g2o's time excludes building its graph and copying its estimate back)")
    print()
    print("2. Bounded CG: iterations for one Gauss-Newton system, one subdomain per loop, 16 points per side")
    names = SCALING_PRECONDITIONERS
    print(f"   {'loops':>6}{'poses':>8}" + "".join(f"{n:>14}" for n in names))
    for r in report["scaling"]:
        print(f"   {r['loops']:>6}{r['poses']:>8}" + "".join(f"{_fmt(r[n], 'd', f'>{CG_CAP}'):>14}" for n in names))
    print()
    print(f"3. Where fill explodes: surveys, one linear solve each; direct (CHOLMOD) vs {FILL_SCHWARZ} CG")
    print(f"   {'survey':>12}{'poses':>7}{'nnz(L)/nnz(H)':>15}{'direct s':>10}{'schwarz s':>11}{'CG':>5}"
          f"{'ratio':>7}{'direct MiB':>12}{'schwarz MiB':>13}  auto picks")
    for r in report["fill"]:
        sch = r[FILL_SCHWARZ]
        print(f"   {r['survey']:>12}{r['poses']:>7}{r['fill']:>15.1f}{r['direct']['seconds']:>10.3f}"
              f"{sch['seconds']:>11.3f}{sch['cg']:>5}{r['schwarz_over_direct']:>7.2f}"
              f"{r['direct_factor_bytes'] / 2**20:>12.0f}{_fmt(_mib(sch['memory_bytes']), '.0f'):>13}  {r['auto_choice']}"
              + ("" if r["auto_picks_faster"] else " (the slower one here)"))
    print("   ratio = Schwarz seconds / direct seconds; MiB: the direct factor and what the Schwarz "
          "operator keeps (predicted from the symbolic analyses); larger graphs: docs/survey.md and "
          "`gtsam-schwarz bench --size large`")


def _mib(nbytes):
    return None if nbytes is None else nbytes / 2**20


def figure(path, report: dict) -> str:
    """demo.png: time per solver (1), CG iterations against poses (2), direct vs Schwarz time and memory (3)."""
    from .plots import save
    from .solve_plots import plt

    fig, axes = plt.subplots(1, 4, figsize=(21, 4.6))
    rows = [r for r in report["solve"]["rows"] if "seconds" in r]
    ax = axes[0]
    ax.barh([r["solver"] for r in rows][::-1], [r["seconds"] for r in rows][::-1],
            color=["tab:blue" if r["solver"].startswith("ours") else "0.6" for r in rows][::-1])
    ax.set_xlabel("seconds, end to end")
    ax.set_title(f"{report['solve']['poses']} poses: same final error")
    ax = axes[1]
    poses = [r["poses"] for r in report["scaling"]]
    for name, color in zip(SCALING_PRECONDITIONERS, ("0.5", "tab:orange", "tab:blue")):
        ax.plot(poses, [r[name] if r[name] is not None else np.nan for r in report["scaling"]], "o-",
                color=color, label=name)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("poses (one subdomain per loop)")
    ax.set_ylabel("CG iterations to 1e-8")
    ax.set_title("bounded CG with the coarse space")
    ax.legend()
    _survey_panel(axes[2], report["fill"], lambda r: r["direct"]["seconds"], lambda r: r[FILL_SCHWARZ]["seconds"],
                  ("direct", f"CG + {FILL_SCHWARZ}"), "seconds per linear solve", "heavy fill: direct vs Schwarz",
                  note=lambda r: f"{r[FILL_SCHWARZ]['cg']} CG")
    _survey_panel(axes[3], report["fill"], lambda r: r["direct_factor_bytes"] / 2**20,
                  lambda r: _mib(r[FILL_SCHWARZ]["memory_bytes"]) or np.nan,
                  ("direct factor", f"{FILL_SCHWARZ} operator"), "MiB (predicted from the symbolic analyses)",
                  "memory: direct vs Schwarz")
    fig.tight_layout()
    return save(fig, path)


def _survey_panel(ax, rows, direct, schwarz, labels, ylabel: str, title: str, note=None) -> None:
    """Direct against Schwarz over the surveys' poses, 2D solid and 3D dashed, log-log."""
    for dim, line in (("2D", "-"), ("3D", "--")):
        part = [r for r in rows if r["survey"].startswith(dim)]
        poses = [r["poses"] for r in part]
        if part:
            ax.plot(poses, [direct(r) for r in part], "s" + line, color="0.4", label=f"{dim} {labels[0]}")
            ax.plot(poses, [schwarz(r) for r in part], "o" + line, color="tab:blue", label=f"{dim} {labels[1]}")
        for r in part if note else ():
            ax.annotate(note(r), (r["poses"], schwarz(r)), textcoords="offset points", xytext=(4, 4), fontsize=8,
                        color="tab:blue")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("poses (survey)")
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.legend()


def add_demo(sub) -> None:
    p = sub.add_parser("demo", help="the main job: same answer as GTSAM, bounded CG, and where Schwarz pays off",
                       description=__doc__.split("\n\n", 1)[1].replace("``", ""),
                       formatter_class=__import__("argparse").RawDescriptionHelpFormatter)
    p.add_argument("--out", default=".", metavar="DIR",
                   help="folder for demo.png (default: current folder; created if its parent exists)")
    p.add_argument("--quick", action="store_true", help="small sizes only (seconds; for tests)")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of the tables")
    p.add_argument("--loops", type=positive_int, default=None, metavar="L",
                   help=f"part 1's model problem: loops (default {SOLVE_CASE[0]})")
    p.add_argument("--points-per-side", type=positive_int, default=None, metavar="P",
                   help=f"part 1's model problem: poses per side (default {SOLVE_CASE[1]})")
    _add_quiet(p)
    p.set_defaults(run=run_demo)


def run_demo(args) -> int:
    out = make_out_dir("--out", args.out)
    loops, pps = QUICK["solve"] if args.quick else SOLVE_CASE
    loops, pps = args.loops or loops, args.points_per_side or pps
    loop_counts = QUICK["loops"] if args.quick else SCALING_LOOPS
    surveys = QUICK["surveys"] if args.quick else FILL_SURVEYS
    steps = 3 + len(loop_counts) * len(SCALING_PRECONDITIONERS) + 3 * len(surveys)
    t0 = time.perf_counter()
    with warnings.catch_warnings(), _progress(args, "demo", total=steps) as progress:
        warnings.simplefilter("ignore", RuntimeWarning)  # rows report convergence themselves
        report = {"solve": solve_part(loops, pps, progress), "scaling": scaling_part(loop_counts, progress),
                  "fill": fill_part(surveys, progress)}
        report["seconds"] = time.perf_counter() - t0
        report["figure"] = figure(out / "demo.png", report)
    if args.json:
        from ..io.jsonout import json_safe
        import json

        print(json.dumps(json_safe(report)))
    else:
        print_report(report)
        print(f"wrote {report['figure']} ({report['seconds']:.0f} s in all)")
    return 0
