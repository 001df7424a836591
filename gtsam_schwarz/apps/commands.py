"""The ``solve``, ``compare``, ``synth`` and ``demo`` commands of the ``gtsam-schwarz`` script.

Each ``add_*`` registers a subcommand on an argparse subparsers object; each ``run_*`` takes the
parsed arguments and returns an exit code. Bad input raises :class:`UsageError` (exit code 2).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import pathlib
import sys
import time

import numpy as np

from .compare import GTSAM_SOLVERS, run_gtsam, run_ours
from .jsonout import json_safe
from ..dd import PARTITIONS
from ..nonlinear import LINEAR_SOLVERS, METHODS, SchwarzParams


class UsageError(Exception):
    """A problem with the user's input: printed as one line, exit code 2."""


def _number(kind, minimum, strict: bool):
    """argparse type: a finite ``kind`` (int/float) ≥ ``minimum`` (> if ``strict``), with a clear message."""
    word = "an integer" if kind is int else "a number"
    bound = f"{'>' if strict else '>='} {minimum}"

    def parse(text: str):
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {word}, got {text!r}") from None
        if not math.isfinite(value) or value < minimum or (strict and value == minimum):
            raise argparse.ArgumentTypeError(f"expected {word} {bound}, got {text!r}")
        return value

    return parse


positive_int = _number(int, 1, strict=False)
nonnegative_int = _number(int, 0, strict=False)
positive_float = _number(float, 0.0, strict=True)
nonnegative_float = _number(float, 0.0, strict=False)


def _tty() -> bool:
    return sys.stderr.isatty()


def _load(path: str):
    from ..io import GraphFileError, load_graph

    p = pathlib.Path(path)
    if not p.exists():
        raise UsageError(f"{path}: no such file")
    if p.is_dir():
        raise UsageError(f"{path}: is a directory, expected a g2o or TORO file")
    try:
        return load_graph(p)
    except GraphFileError as exc:
        raise UsageError(str(exc)) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise UsageError(f"{path}: cannot read: {exc}") from None


def _iteration_printer(stream):
    def hook(record):
        flag = "" if record["accepted"] else "  rejected"
        print(f"  iter {record['iteration']:3d}  error {record['error']:14.8g}  |grad| {record['gradient_norm']:10.3e}"
              f"  cg {record['cg_iterations']:5d}  lambda {record['lambda']:8.1e}  "
              f"{sum(record['seconds'].values()):6.2f} s{flag}", file=stream, flush=True)
    return hook


# -- solve --------------------------------------------------------------------------------------
def add_solve(sub) -> None:
    p = sub.add_parser("solve", help="optimize a g2o/TORO pose graph",
                       description="Optimize a g2o or TORO pose graph with Schwarz-preconditioned CG.")
    p.add_argument("file", help="g2o (VERTEX_SE2/EDGE_SE2, SE3:QUAT) or TORO (VERTEX2/EDGE2) file")
    p.add_argument("--method", choices=METHODS, default="lm", help="lm (default) or gn")
    p.add_argument("--preconditioner", choices=LINEAR_SOLVERS, default="gdsw")
    p.add_argument("--subdomains", type=positive_int, default=None, help="default: about 500 poses each")
    p.add_argument("--partition", choices=PARTITIONS, default="auto")
    p.add_argument("--overlap", type=nonnegative_int, default=1)
    p.add_argument("--cg-tol", type=positive_float, default=1e-8)
    p.add_argument("--max-iterations", type=nonnegative_int, default=100)
    p.add_argument("--inexact", action="store_true", help="Eisenstat-Walker forcing of the CG tolerance")
    p.add_argument("-o", "--output", help="write the optimized graph as g2o (atomically)")
    p.add_argument("--force", action="store_true", help="allow -o to overwrite the input file")
    p.add_argument("--plot", help="write trajectory and convergence plots to this PNG")
    p.add_argument("--json", action="store_true", help="print exactly one JSON object on stdout")
    p.set_defaults(run=run_solve)


def run_solve(args) -> int:
    from ..io import GraphFileError, write_g2o

    if args.output and not args.force and pathlib.Path(args.output).exists() \
            and os.path.samefile(args.output, args.file):
        raise UsageError(f"{args.output}: refusing to overwrite the input file (use --force)")
    loaded = _load(args.file)
    human = not args.json
    out = sys.stdout if human else sys.stderr
    hook = _iteration_printer(out) if (human or _tty()) else None
    if human:
        print(f"{args.file}: {loaded.poses} poses, {loaded.edges} edges, {loaded.dimension}D "
              f"({loaded.format}, initial guess from {loaded.initial_guess})", flush=True)
    params = SchwarzParams(method=args.method, preconditioner=args.preconditioner, subdomains=args.subdomains,
                           partition=args.partition, overlap=args.overlap, cg_tol=args.cg_tol,
                           max_iterations=args.max_iterations, iteration_hook=hook,
                           forcing="eisenstat-walker" if args.inexact else "none")
    row = run_ours(loaded.graph, loaded.initial, params)
    if args.output:
        try:
            write_g2o(args.output, loaded.graph, row["values"], force=args.force, input_path=args.file)
        except GraphFileError as exc:
            raise UsageError(str(exc)) from None
    if args.plot:
        from .solve_plots import solve_figure
        solve_figure(args.plot, loaded, row)
    split = row["split"]
    report = {
        "file": str(args.file), "poses": loaded.poses, "edges": loaded.edges, "dimension": loaded.dimension,
        "method": args.method, "preconditioner": args.preconditioner, "partition": args.partition,
        "subdomains": row["subdomains"], "overlap": args.overlap, "coarse_size": row["coarse_size"],
        "iterations": row["iterations"], "linear_solves": row["linear_solves"],
        "cg_iterations": row["cg_iterations"], "cg_mean": row["cg_mean"],
        "initial_error": row["initial_error"], "final_error": row["final_error"],
        "converged": row["converged"], "stop_reason": row["stop_reason"],
        "seconds": {"total": row["seconds"], "linearize": split["linearize"] + split["export"],
                    "setup": split["setup"], "cg": split["cg"], "update": split["update"]},
        "output": args.output, "plot": args.plot,
    }
    if args.json:
        print(json.dumps(report))
    else:
        print(f"{'converged' if row['converged'] else 'stopped'} after {row['iterations']} iterations "
              f"({row['stop_reason']}): error {row['initial_error']:.8g} -> {row['final_error']:.8g}; "
              f"{row['subdomains']} subdomains, coarse space {row['coarse_size']}, "
              f"{row['cg_mean']:.1f} CG iterations per solve; {row['seconds']:.2f} s "
              f"(linearize {report['seconds']['linearize']:.2f}, setup {split['setup']:.2f}, cg {split['cg']:.2f})")
        for what, path in (("optimized graph", args.output), ("plot", args.plot)):
            if path:
                print(f"wrote {what} to {path}")
    return 0


# -- compare -------------------------------------------------------------------------------------
OURS = ("gdsw", "one-level", "block-jacobi")


def compare_rows(graph, initial, ours=OURS, gtsam_solvers=GTSAM_SOLVERS, method="lm", partition="auto",
                 subdomains=None, progress=None) -> list[dict]:
    """Our solver with each preconditioner and GTSAM's optimizers on the same graph."""
    rows = []
    for name in gtsam_solvers:
        if progress:
            progress(name)
        rows.append(run_gtsam(graph, initial, name))
    for name in ours:
        if progress:
            progress(name)
        r = run_ours(graph, initial, SchwarzParams(method=method, preconditioner=name, partition=partition,
                                                   subdomains=subdomains))
        r["solver"] = f"schwarz-{method}-{name}"
        rows.append(r)
    ref = next((r for r in rows if r["solver"] == "gtsam-lm" and "failed" not in r), None)
    for r in rows:
        r["ratio_to_gtsam_lm"] = r["seconds"] / ref["seconds"] if ref and ref["seconds"] > 0 else float("nan")
    return rows


def print_table(rows, stream=sys.stdout) -> None:
    print(f"{'solver':<26}{'final error':>18}{'its':>6}{'CG/solve':>10}{'seconds':>10}{'x GTSAM LM':>12}", file=stream)
    print("-" * 82, file=stream)
    for r in rows:
        err = f"{r['final_error']:.10g}" if math.isfinite(r["final_error"]) else "failed"
        cg = f"{r['cg_mean']:.1f}" if "cg_mean" in r else "-"
        print(f"{r['solver']:<26}{err:>18}{r['iterations']:>6}{cg:>10}{r['seconds']:>10.3f}"
              f"{r['ratio_to_gtsam_lm']:>12.2f}", file=stream)
        if r.get("failed"):
            print(f"{'':<26}  ({r['failed']})", file=stream)


def _json_rows(rows):
    keep = ("solver", "final_error", "iterations", "seconds", "ratio_to_gtsam_lm", "cg_mean", "linear_solves",
            "subdomains", "coarse_size", "converged", "failed")
    return [json_safe({k: r[k] for k in keep if k in r}) for r in rows]


def add_compare(sub) -> None:
    p = sub.add_parser("compare", help="our solver next to GTSAM's optimizers on one file")
    p.add_argument("file")
    p.add_argument("--subdomains", type=positive_int, default=None)
    p.add_argument("--partition", choices=PARTITIONS, default="auto")
    p.add_argument("--json", action="store_true", help='print {"rows": [...]} as one JSON object')
    p.set_defaults(run=run_compare)


def run_compare(args) -> int:
    loaded = _load(args.file)
    progress = (lambda name: print(f"running {name} ...", file=sys.stderr, flush=True)) if _tty() else None
    rows = compare_rows(loaded.graph, loaded.initial, partition=args.partition, subdomains=args.subdomains,
                        progress=progress)
    if args.json:
        print(json.dumps({"file": str(args.file), "poses": loaded.poses, "edges": loaded.edges,
                          "rows": _json_rows(rows)}))
    else:
        print(f"{args.file}: {loaded.poses} poses, {loaded.edges} edges, {loaded.dimension}D")
        print_table(rows)
    return 0


# -- synth ---------------------------------------------------------------------------------------
def add_synth(sub) -> None:
    p = sub.add_parser("synth", help="write the paper's model problem as a g2o file")
    p.add_argument("--loops", type=positive_int, required=True)
    p.add_argument("--points-per-side", type=positive_int, required=True)
    p.add_argument("--sigma", type=nonnegative_float, default=0.01)
    p.add_argument("--seed", type=nonnegative_int, default=0)
    p.add_argument("--3d", dest="three_d", action="store_true", help="the helix (Pose3) variant")
    p.add_argument("-o", "--output", required=True)
    p.add_argument("--force", action="store_true", help="overwrite an existing file")
    p.set_defaults(run=run_synth)


def run_synth(args) -> int:
    from ..io import GraphFileError, write_g2o
    from ..problems import helix_loops, square_loops

    out = pathlib.Path(args.output)
    if out.exists() and not args.force:
        raise UsageError(f"{out}: exists (use --force to overwrite)")
    make = helix_loops if args.three_d else square_loops
    prob = make(args.loops, args.points_per_side, sigma=args.sigma, seed=args.seed)
    try:
        write_g2o(out, prob.graph, prob.initial, force=True)
    except GraphFileError as exc:
        raise UsageError(str(exc)) from None
    print(f"wrote {out}: {prob.poses} poses, {prob.graph.size() - 1} edges "
          f"({args.loops} loops x {args.points_per_side} points per side, sigma {args.sigma}, seed {args.seed})")
    return 0


# -- demo ----------------------------------------------------------------------------------------
def add_demo(sub) -> None:
    p = sub.add_parser("demo", help="the main job: the model problem solved with GDSW next to GTSAM")
    p.add_argument("--loops", type=positive_int, default=16)
    p.add_argument("--points-per-side", type=positive_int, default=16)
    p.add_argument("--out", default=".", help="folder for the plots (default: current folder)")
    p.set_defaults(run=run_demo)


def run_demo(args) -> int:
    from .solve_plots import convergence_figure, trajectory_figure
    from ..problems import square_loops

    prob = square_loops(args.loops, args.points_per_side, sigma=0.01, seed=0)
    print(f"model problem: {args.loops} loops x {args.points_per_side} points per side = {prob.poses} poses "
          f"(sigma 0.01, seed 0), one subdomain per loop", flush=True)
    progress = (lambda name: print(f"running {name} ...", file=sys.stderr, flush=True)) if _tty() else None
    rows = compare_rows(prob.graph, prob.initial, ours=("gdsw", "one-level", "block-jacobi", "none"),
                        gtsam_solvers=("gtsam-lm", "gtsam-gn"), method="gn", partition="segments",
                        subdomains=args.loops, progress=progress)
    print_table(rows)
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    gdsw = next(r for r in rows if r["solver"].endswith("-gdsw"))
    traj = trajectory_figure(out / "demo_trajectory.png", prob, gdsw["values"], subdomains=args.loops)
    conv = convergence_figure(out / "demo_convergence.png", prob, subdomains=args.loops)
    print(f"wrote {traj} and {conv}")
    return 0


def add_all(sub) -> None:
    for add in (add_solve, add_compare, add_synth, add_demo):
        add(sub)
