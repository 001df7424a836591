"""The ``solve``, ``compare`` and ``synth`` commands (``demo``: demo.py) of the ``gtsam-schwarz`` script.

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

from .compare import GTSAM_SOLVERS, run_gtsam, run_ours
from ..io.jsonout import json_safe
from ..nonlinear.hooks import verbose_printer
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


def _size(text: str) -> float:
    """argparse type: a positive size such as 512M or 2.5G, in bytes."""
    from ..solvers.memory import parse_bytes

    try:
        value = parse_bytes(text)
    except ValueError:
        value = float("nan")
    if not value > 0:
        raise argparse.ArgumentTypeError(f"expected a size such as 512M or 2G, got {text!r}")
    return value


def _load(path: str, strict: bool = False):
    """The graph of a file; the loader's warnings (skipped records, repaired information matrices) on
    stderr, or — with ``strict`` — a usage error for either."""
    from ..io import GraphFileError, load_graph

    p = pathlib.Path(path)
    if not p.exists():
        raise UsageError(f"{path}: no such file")
    if p.is_dir():
        raise UsageError(f"{path}: is a directory, expected a g2o or TORO file")
    try:
        loaded = load_graph(p, strict=strict)
        for warning in loaded.warnings:
            print(f"warning: {warning}", file=sys.stderr)
        return loaded
    except GraphFileError as exc:
        raise UsageError(str(exc)) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise UsageError(f"{path}: cannot read: {exc}") from None


# -- checks on output paths, before any work ------------------------------------------------------
GRAPH_FORMATS = {".g2o": "g2o", ".tum": "tum"}  # -o: by extension
TRUTH_FORMATS = {".g2o": "g2o", ".tum": "tum"}  # synth --ground-truth: by extension


def check_output(option: str, path: str, formats: dict | None = None) -> str | None:
    """Refuse, as a :class:`UsageError`, an output path whose folder does not exist (we never create
    it), is not a folder or is not writable, a path that is a folder, or (``formats``: extension →
    format) an unknown extension. Returns the format."""
    p = pathlib.Path(path)
    folder = p.parent
    shown = str(folder) if str(folder) not in ("", ".") else "the current folder"
    if not folder.exists():
        raise UsageError(f"{option} {path}: folder {shown} does not exist (create it first)")
    if not folder.is_dir():
        raise UsageError(f"{option} {path}: {shown} is not a folder")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise UsageError(f"{option} {path}: folder {shown} is not writable")
    if p.is_dir():
        raise UsageError(f"{option} {path}: is a directory, expected a file name")
    if formats is None:
        return None
    fmt = formats.get(p.suffix.lower())
    if fmt is None:
        choices = ", ".join(formats)
        raise UsageError(f"{option} {path}: unknown extension {p.suffix or '(none)'!s}; use {choices}")
    return fmt


def check_plot(option: str, path: str) -> str:
    """:func:`check_output` for a figure: png, pdf or svg by the extension."""
    from .plots import PLOT_FORMATS

    return check_output(option, path, {f".{f}": f for f in PLOT_FORMATS})


def _load_truth(path: str):
    from .trajectory import TrajectoryError, read_trajectory

    try:
        return read_trajectory(path)
    except TrajectoryError as exc:
        raise UsageError(str(exc)) from None


def _check_truth_matches(truth, values) -> None:
    from .trajectory import Trajectory, TrajectoryError, associate

    try:
        associate(Trajectory.from_values(values), truth)
    except TrajectoryError as exc:
        raise UsageError(f"--ground-truth: {exc}") from None


def _accuracy(values, truth) -> dict | None:
    from .trajectory import evaluate

    return evaluate(values, truth) if values is not None else None


def _progress(args, label: str, total: int | None = None, show: bool = True):
    from .progress import Progress

    return Progress(label, total, enabled=show and not getattr(args, "quiet", False))


def _landmarks(loaded) -> str:
    return f", {loaded.landmarks} landmarks ({loaded.landmark_edges} observations)" if loaded.landmarks else ""


def _add_strict(p) -> None:
    p.add_argument("--strict", action="store_true",
                   help="refuse a file with records we do not understand or information matrices that are not "
                        "positive definite (default: skip / repair them, with a warning)")


def _add_quiet(p) -> None:
    p.add_argument("-q", "--quiet", action="store_true",
                   help="no progress display on stderr (a live bar on a terminal, a line every few seconds "
                        "otherwise); errors are still printed")


def _progress_hook(progress):
    """Our optimizer's iteration hook that notes the iteration on ``progress``."""
    def hook(record):
        progress.note(f"iteration {record['iteration']}, error {record['error']:.6g}, cg {record['cg_iterations']}")
    return hook


def _gtsam_progress_hook(progress):
    """GTSAM's ``iterationHook`` (iteration, error before, error after) that notes on ``progress``."""
    def hook(iteration, before, after):
        progress.note(f"iteration {iteration}, error {after:.6g}")
    return hook


def _chain(*hooks):
    hooks = [h for h in hooks if h is not None]
    if not hooks:
        return None
    if len(hooks) == 1:
        return hooks[0]

    def hook(record):
        for h in hooks:
            h(record)
    return hook


ACCURACY_NOTE = ("ATE: position RMSE after rigid Umeyama alignment, no scale (evo_ape -a); "
                 "RPE: relative translation RMSE, consecutive poses (evo_rpe)")


# -- solve --------------------------------------------------------------------------------------
def add_solve(sub) -> None:
    p = sub.add_parser("solve", help="optimize a g2o/TORO pose graph",
                       description="Optimize a g2o or TORO pose graph with Schwarz-preconditioned CG. Prints a line "
                                   "per iteration and a summary on stdout (or one JSON object with --json); "
                                   "progress goes to stderr.")
    p.add_argument("file", help="g2o (VERTEX_SE2/EDGE_SE2, SE3:QUAT) or TORO (VERTEX2/EDGE2) file")
    p.add_argument("--method", choices=METHODS, default="lm",
                   help="nonlinear method: lm (Levenberg-Marquardt, default) or gn (Gauss-Newton)")
    p.add_argument("--preconditioner", choices=LINEAR_SOLVERS, default="auto",
                   help="linear solver: 'auto' (default: a sparse Cholesky or GDSW-preconditioned CG, whichever "
                        "a cost model from the symbolic analysis predicts faster for this graph), 'direct', or a "
                        "CG preconditioner (gdsw: two-level Schwarz with the GDSW coarse space, …)")
    p.add_argument("--subdomains", type=positive_int, default=None, metavar="N",
                   help="number of subdomains (default: about 100 poses each in 2D (250 with exact steps), 32 in 3D (64 under 16 384 poses))")
    p.add_argument("--partition", choices=PARTITIONS, default="auto",
                   help="how to cut the graph: trajectory segments, cells of the poses' positions "
                        "(geometric), METIS, or auto (whichever gives the fewest interface poses; default)")
    p.add_argument("--overlap", type=nonnegative_int, default=None, metavar="K",
                   help="layers of overlap grown around each subdomain (default: 0 for rgdsw-linear, "
                        "gdsw-linear and auto, 1 for the others)")
    p.add_argument("--cg-tol", type=positive_float, default=1e-8, metavar="T",
                   help="CG stopping tolerance, relative residual (default 1e-8)")
    p.add_argument("--max-iterations", type=nonnegative_int, default=100, metavar="N",
                   help="most nonlinear iterations (default 100)")
    p.add_argument("--inexact", action="store_true",
                   help="Eisenstat-Walker forcing (a loose CG tolerance far from the solution) whatever the linear "
                        "solver (default: for Schwarz-preconditioned CG only, not for the direct factorization)")
    p.add_argument("-o", "--output", metavar="OUT.g2o|OUT.tum",
                   help="write the optimized poses, atomically, in the format of the extension: .g2o (the graph "
                        "with optimized vertices) or .tum (trajectory: key tx ty tz qx qy qz qw); the folder "
                        "must exist")
    p.add_argument("--force", action="store_true", help="allow -o to overwrite the input file")
    _add_strict(p)
    p.add_argument("--backend", choices=("serial", "petsc"), default="serial",
                   help="where the linear solves run: this process (serial, default) or PETSc over MPI (petsc: "
                        "needs petsc4py and mpi4py; see docs/distributed.md)")
    p.add_argument("--ranks", type=positive_int, default=None, metavar="K",
                   help="with --backend petsc: run under mpiexec -n K (default: in this process, i.e. one rank, "
                        "or one of the ranks of your own mpiexec)")
    p.add_argument("--plot", metavar="OUT.png|OUT.pdf|OUT.svg",
                   help="write trajectory and convergence plots, in the format of the extension; the folder "
                        "must exist")
    p.add_argument("--ground-truth", metavar="FILE.g2o|FILE.tum",
                   help="reference poses (g2o VERTEX lines or a TUM file whose timestamps are the pose keys): "
                        "report ATE and RPE (RMSE, evo's definitions) of the initial guess and the result")
    p.add_argument("--memory-limit", type=_size, default=None, metavar="SIZE",
                   help="memory the linear solver may use, e.g. 2G (default: $GTSAM_SCHWARZ_MEMORY_LIMIT or "
                        "what is available); a configuration predicted not to fit adapts or stops with exit 2")
    p.add_argument("--json", action="store_true", help="print exactly one JSON object on stdout")
    _add_quiet(p)
    p.set_defaults(run=run_solve)


def _write_poses(path: str, fmt: str, loaded, values, args) -> None:
    from ..io import GraphFileError, write_g2o
    from ..io.tum import write_tum

    try:
        if fmt == "tum":
            write_tum(path, values)
        else:
            write_g2o(path, loaded.graph, values, force=args.force, input_path=args.file)
    except GraphFileError as exc:
        raise UsageError(str(exc)) from None
    except OSError as exc:
        raise UsageError(f"{path}: cannot write: {exc.strerror or exc}") from None


def _solve_on_petsc(args) -> int:
    """``solve --backend petsc [--ranks K]``: the MPI driver (backends/petsc/run.py) in this process,
    or under ``mpiexec -n K`` (with Open MPI's --allow-run-as-root / --oversubscribe where needed)."""
    from ..backends import available

    for option, value in (("--plot", args.plot), ("--ground-truth", args.ground_truth)):
        if value:
            raise UsageError(f"{option} is not available with --backend petsc")
    ok, why = available("petsc")
    if not ok:
        raise UsageError(f"--backend petsc: {why}")
    argv = [args.file, "--method", args.method, "--preconditioner", args.preconditioner, "--partition", args.partition,
            "--cg-tol", repr(args.cg_tol), "--max-iterations", str(args.max_iterations)]
    argv += ["--subdomains", str(args.subdomains)] if args.subdomains else []
    argv += ["--overlap", str(args.overlap)] if args.overlap is not None else []
    argv += [flag for flag, on in (("--inexact", args.inexact), ("--force", args.force), ("--json", args.json)) if on]
    argv += ["-o", args.output] if args.output else []
    if args.ranks is None:
        from ..backends.petsc.run import main as run_mpi

        return run_mpi(argv)
    import subprocess

    from ..backends.petsc.env import launch_command, mpi_environment, mpiexec_path

    if mpiexec_path() is None:
        raise UsageError("--ranks: mpiexec/mpirun not found on PATH (Debian: apt-get install openmpi-bin)")
    return subprocess.run(launch_command(args.ranks, argv), env=mpi_environment()).returncode


def run_solve(args) -> int:
    if args.ranks is not None and args.backend != "petsc":
        raise UsageError("--ranks K needs --backend petsc")
    if args.backend == "petsc":
        return _solve_on_petsc(args)
    out_format = check_output("-o", args.output, GRAPH_FORMATS) if args.output else None
    if args.plot:
        check_plot("--plot", args.plot)
    if args.output and not args.force and pathlib.Path(args.output).exists() \
            and os.path.samefile(args.output, args.file):
        raise UsageError(f"{args.output}: refusing to overwrite the input file (use --force)")
    loaded = _load(args.file, args.strict)
    truth = None
    if args.ground_truth:
        truth = _load_truth(args.ground_truth)
        _check_truth_matches(truth, loaded.initial)
    human = not args.json
    # progress on stderr, unless the iteration lines on a terminal's stdout already show it
    progress = _progress(args, "solve", show=not (human and sys.stdout.isatty()))
    if human:
        print(f"{args.file}: {loaded.poses} poses, {loaded.edges} edges{_landmarks(loaded)}, {loaded.dimension}D "
              f"({loaded.format}, initial guess from {loaded.initial_guess})", flush=True)
    hook = _chain(verbose_printer(sys.stdout) if human else None, _progress_hook(progress))
    params = SchwarzParams(method=args.method, preconditioner=args.preconditioner, subdomains=args.subdomains,
                           partition=args.partition, overlap=args.overlap, cg_tol=args.cg_tol,
                           max_iterations=args.max_iterations, iteration_hook=hook,
                           forcing="eisenstat-walker" if args.inexact else "auto", memory_limit=args.memory_limit)
    with progress:
        progress.start(f"{pathlib.Path(args.file).name} ({loaded.poses} poses, {args.method} + {args.preconditioner})")
        row = run_ours(loaded.graph, loaded.initial, params, loaded.arrays, release_arrays=True)
        progress.done(f"{row['iterations']} iterations, error {row['final_error']:.8g}")
    if args.output:
        _write_poses(args.output, out_format, loaded, row["values"], args)
    if args.plot:
        from .solve_plots import solve_figure
        try:
            solve_figure(args.plot, loaded, row, truth=truth)
        except OSError as exc:
            raise UsageError(f"{args.plot}: cannot write: {exc.strerror or exc}") from None
    split = row["split"]
    report = {
        "file": str(args.file), "poses": loaded.poses, "edges": loaded.edges, "dimension": loaded.dimension,
        "method": args.method, "preconditioner": args.preconditioner, "partition": args.partition,
        "partition_used": row.get("partition"), "subdomains": row["subdomains"], "overlap": params.overlap_layers(), "coarse_size": row["coarse_size"],
        "iterations": row["iterations"], "linear_solves": row["linear_solves"],
        "cg_iterations": row["cg_iterations"], "cg_mean": row["cg_mean"],
        "initial_error": row["initial_error"], "final_error": row["final_error"],
        "converged": row["converged"], "stop_reason": row["stop_reason"],
        "linear_solver": row["linear_solver"], "anchored": row["anchored"],
        "seconds": {"total": row["seconds"], "linearize": split["linearize"] + split["export"],
                    "setup": split["setup"], "cg": split["cg"], "update": split["update"]},
        "output": args.output, "plot": args.plot,
    }
    if truth is not None:
        final, initial = _accuracy(row["values"], truth), _accuracy(loaded.initial, truth)
        report["ground_truth"] = {
            "file": str(args.ground_truth), "poses": final["poses"], "alignment": final["alignment"],
            "ate_rmse": final["ate_rmse"], "rpe_rmse": final["rpe_rmse"],
            "initial_ate_rmse": initial["ate_rmse"], "initial_rpe_rmse": initial["rpe_rmse"],
            "definition": ACCURACY_NOTE}
    if args.json:
        print(json.dumps(json_safe(report), allow_nan=False))
    else:
        ls = row["linear_solver"]
        if row["linear_solves"]:
            print(f"linear solver: {ls['used']}" + (f" (auto: {ls['reason']})" if ls["requested"] == "auto" else ""))
        if row["anchored"]:
            print(f"gauge: no prior on the component(s) of pose(s) {', '.join(map(str, row['anchored']))}: "
                  f"its first pose anchored")
        print(f"{'converged' if row['converged'] else 'stopped'} after {row['iterations']} iterations "
              f"({row['stop_reason']}): error {row['initial_error']:.8g} -> {row['final_error']:.8g}; "
              + ("no linear solve; " if not row["linear_solves"] else
                 "sparse Cholesky; " if row["linear_solver"]["used"] == "direct" else
                 f"{row['subdomains']} subdomains ({row.get('partition') or args.partition}), coarse space {row['coarse_size']}, "
                 f"{row['cg_mean']:.1f} CG iterations per solve; ") + f"{row['seconds']:.2f} s "
              f"(linearize {report['seconds']['linearize']:.2f}, setup {split['setup']:.2f}, cg {split['cg']:.2f})")
        if truth is not None:
            g = report["ground_truth"]
            print(f"against {args.ground_truth} ({g['poses']} poses): ATE {g['ate_rmse']:.6g} m, "
                  f"RPE {g['rpe_rmse']:.6g} m (initial guess: ATE {g['initial_ate_rmse']:.6g} m, "
                  f"RPE {g['initial_rpe_rmse']:.6g} m); ATE after rigid {g['alignment']} Umeyama alignment, "
                  f"RPE over consecutive poses")
        for what, path in (("optimized poses", args.output), ("plot", args.plot)):
            if path:
                print(f"wrote {what} to {path}")
    return 0


# -- compare -------------------------------------------------------------------------------------
OURS = ("gdsw", "one-level", "block-jacobi")


def compare_rows(graph, initial, ours=OURS, gtsam_solvers=GTSAM_SOLVERS, method="lm", partition="auto",
                 subdomains=None, progress=None) -> list[dict]:
    """Our solver with each preconditioner and GTSAM's optimizers on the same graph.

    ``progress``: a :class:`~gtsam_schwarz.apps.progress.Progress` told each solver's start, its
    iterations and its end."""
    rows = []
    for name in gtsam_solvers:
        if progress is not None:
            progress.start(name)
        rows.append(run_gtsam(graph, initial, name,
                              iteration_hook=_gtsam_progress_hook(progress) if progress is not None else None))
        if progress is not None:
            progress.done("failed" if rows[-1].get("failed") else f"error {rows[-1]['final_error']:.8g}")
    for name in ours:
        label = f"schwarz-{method}-{name}"
        if progress is not None:
            progress.start(label)
        r = run_ours(graph, initial, SchwarzParams(method=method, preconditioner=name, partition=partition,
                                                   subdomains=subdomains,
                                                   iteration_hook=_progress_hook(progress) if progress else None))
        r["solver"] = label
        rows.append(r)
        if progress is not None:
            progress.done(f"error {r['final_error']:.8g}")
    ref = next((r for r in rows if r["solver"] == "gtsam-lm" and "failed" not in r), None)
    for r in rows:
        r["ratio_to_gtsam_lm"] = r["seconds"] / ref["seconds"] if ref and ref["seconds"] > 0 else float("nan")
    return rows


def _failure_message(row) -> str:
    return row.get("failed_message") or row.get("failed") or ""


def print_table(rows, stream=None) -> None:
    """The comparison table; ATE and RPE columns when the rows carry them; a failure's whole message
    on indented lines below its row."""
    stream = stream or sys.stdout
    accuracy = any("ate_rmse" in r for r in rows)
    extra = f"{'ATE [m]':>11}{'RPE [m]':>11}" if accuracy else ""
    header = f"{'solver':<26}{'final error':>18}{'its':>6}{'CG/solve':>10}{'seconds':>10}{'x GTSAM LM':>12}{extra}"
    print(header, file=stream)
    print("-" * len(header), file=stream)
    for r in rows:
        err = f"{r['final_error']:.10g}" if math.isfinite(r["final_error"]) else "failed"
        cg = f"{r['cg_mean']:.1f}" if "cg_mean" in r else "-"
        acc = ""
        if accuracy:
            acc = "".join(f"{r[k]:>11.4g}" if r.get(k) is not None and math.isfinite(r[k]) else f"{'-':>11}"
                          for k in ("ate_rmse", "rpe_rmse"))
        print(f"{r['solver']:<26}{err:>18}{r['iterations']:>6}{cg:>10}{r['seconds']:>10.3f}"
              f"{r['ratio_to_gtsam_lm']:>12.2f}{acc}", file=stream)
        if r.get("failed"):
            for line in _failure_message(r).splitlines():
                if line.strip():
                    print(f"{'':<28}{line.rstrip()}", file=stream)


def _json_rows(rows):
    keep = ("solver", "final_error", "iterations", "seconds", "ratio_to_gtsam_lm", "cg_mean", "linear_solves",
            "subdomains", "coarse_size", "converged", "failed", "ate_rmse", "rpe_rmse")
    out = []
    for r in rows:
        row = {k: r[k] for k in keep if k in r}
        if r.get("failed"):
            row["failed"] = _failure_message(r)
        out.append(json_safe(row))
    return out


def _add_accuracy(rows, truth) -> None:
    for r in rows:
        acc = _accuracy(r.get("values"), truth)
        r["ate_rmse"] = acc["ate_rmse"] if acc else None
        r["rpe_rmse"] = acc["rpe_rmse"] if acc else None


def add_compare(sub) -> None:
    p = sub.add_parser("compare", help="our solver next to GTSAM's optimizers on one file",
                       description="Run GTSAM's LM and GN (Cholesky), LM with PCG (block-Jacobi) and with "
                                   "SubgraphSolver, and ours with GDSW, one-level Schwarz and block-Jacobi on the "
                                   "same file; print final errors, iterations and time ratios to GTSAM's LM. "
                                   "Progress goes to stderr.")
    p.add_argument("file", help="g2o (VERTEX_SE2/EDGE_SE2, SE3:QUAT) or TORO (VERTEX2/EDGE2) file")
    _add_strict(p)
    p.add_argument("--subdomains", type=positive_int, default=None, metavar="N",
                   help="number of subdomains for ours (default: about 100 poses each in 2D (250 with exact steps), 32 in 3D (64 under 16 384 poses))")
    p.add_argument("--partition", choices=PARTITIONS, default="auto",
                   help="how ours cuts the graph (default auto)")
    p.add_argument("--ground-truth", metavar="FILE.g2o|FILE.tum",
                   help="reference poses: add ATE and RPE (RMSE, evo's definitions) per solver")
    p.add_argument("--json", action="store_true", help='print {"rows": [...]} as one JSON object on stdout')
    _add_quiet(p)
    p.set_defaults(run=run_compare)


def run_compare(args) -> int:
    loaded = _load(args.file, args.strict)
    truth = None
    if args.ground_truth:
        truth = _load_truth(args.ground_truth)
        _check_truth_matches(truth, loaded.initial)
    with _progress(args, "compare", total=len(GTSAM_SOLVERS) + len(OURS)) as progress:
        rows = compare_rows(loaded.graph, loaded.initial, partition=args.partition, subdomains=args.subdomains,
                            progress=progress)
    if truth is not None:
        _add_accuracy(rows, truth)
    if args.json:
        print(json.dumps({"file": str(args.file), "poses": loaded.poses, "edges": loaded.edges,
                          "rows": _json_rows(rows)}))
    else:
        print(f"{args.file}: {loaded.poses} poses, {loaded.edges} edges{_landmarks(loaded)}, {loaded.dimension}D")
        print_table(rows)
        if truth is not None:
            print(ACCURACY_NOTE)
    return 0


# -- synth ---------------------------------------------------------------------------------------
def grid_size(names: str):
    """argparse type: sizes like ``ROWSxCOLS`` (``names`` = "ROWSxCOLS"), each an integer >= 1."""
    count = len(names.split("x"))

    def parse(text: str) -> tuple[int, ...]:
        parts = text.lower().split("x")
        try:
            sizes = tuple(int(p) for p in parts)
        except ValueError:
            sizes = ()
        if len(sizes) != count or min(sizes) < 1:
            raise argparse.ArgumentTypeError(f"expected {names} with integers >= 1 (e.g. "
                                             f"{'x'.join(['20'] * count)}), got {text!r}")
        return sizes

    return parse


def add_synth(sub) -> None:
    p = sub.add_parser("synth", help="write a model problem (loops, lawnmower survey, 3D survey) as a g2o file",
                       description="Write a model problem as g2o: the paper's unit-square multi-loop problem (or "
                                   "its 3D helix), a 2D lawnmower survey of a grid, or a 3D survey of stacked "
                                   "floors. VERTEX lines are the dead-reckoning initial guess, EDGE lines the noisy "
                                   "odometry and the loop closures, FIX the prior's pose. Give exactly one of "
                                   "--loops (with --points-per-side), --lawnmower or --survey3d.")
    p.add_argument("--loops", type=positive_int, metavar="L", help="number of loops (= subdomains "
                   "in the paper) of the paper's model problem; needs --points-per-side")
    p.add_argument("--points-per-side", type=positive_int, metavar="P",
                   help="poses per side of the unit square (4P poses per loop)")
    p.add_argument("--lawnmower", type=grid_size("ROWSxCOLS"), metavar="ROWSxCOLS",
                   help="a 2D lawnmower survey (Pose2) of a ROWS x COLS grid, row by row, closures to the "
                        "previous row: ROWS*COLS poses")
    p.add_argument("--survey3d", type=grid_size("FLOORSxROWSxCOLS"), metavar="FLOORSxROWSxCOLS",
                   help="a 3D survey (Pose3): FLOORS lawnmower grids stacked, closures to the previous row and to "
                        "the floor below: FLOORS*ROWS*COLS poses")
    p.add_argument("--sigma", type=nonnegative_float, default=0.01, metavar="S",
                   help="odometry noise standard deviation on every tangent coordinate (x, y, theta in 2D) "
                        "(default 0.01)")
    p.add_argument("--seed", type=nonnegative_int, default=0, metavar="K", help="noise seed (default 0)")
    p.add_argument("--3d", dest="three_d", action="store_true", help="with --loops: the helix (Pose3) variant")
    p.add_argument("-o", "--output", required=True, metavar="FILE.g2o", help="the g2o file to write (atomically)")
    p.add_argument("--ground-truth", metavar="FILE.g2o|FILE.tum",
                   help="also write the true poses (g2o: same edges, true vertices; tum: trajectory), for "
                        "solve --ground-truth")
    p.add_argument("--force", action="store_true", help="overwrite existing files")
    p.set_defaults(run=run_synth)


def _synth_problem(args):
    """(a function that builds the problem the synth options ask for, its description); a usage error
    for a wrong combination of options."""
    from ..problems import helix_loops, lawnmower, square_loops, survey3d

    given = [name for name, v in (("--loops", args.loops), ("--lawnmower", args.lawnmower),
                                  ("--survey3d", args.survey3d)) if v is not None]
    if len(given) != 1:
        if given:
            raise UsageError(f"give only one of --loops, --lawnmower and --survey3d (got {' and '.join(given)})")
        raise UsageError("one of --loops L --points-per-side P, --lawnmower ROWSxCOLS or "
                         "--survey3d FLOORSxROWSxCOLS is required")
    noise = f"sigma {args.sigma}, seed {args.seed}"
    if args.loops is not None:
        if args.points_per_side is None:
            raise UsageError("--points-per-side P is required with --loops")
        make = helix_loops if args.three_d else square_loops
        return (lambda: make(args.loops, args.points_per_side, sigma=args.sigma, seed=args.seed),
                f"{args.loops} loops x {args.points_per_side} points per side, {noise}")
    if args.points_per_side is not None:
        raise UsageError(f"--points-per-side goes with --loops, not with {given[0]}")
    if args.three_d:
        raise UsageError(f"--3d goes with --loops (the helix); {given[0]} sets the dimension itself")
    if args.lawnmower is not None:
        rows, cols = args.lawnmower
        return (lambda: lawnmower(rows, cols, sigma=args.sigma, seed=args.seed),
                f"2D lawnmower {rows} x {cols}, {noise}")
    floors, rows, cols = args.survey3d
    return (lambda: survey3d(floors, rows, cols, sigma=args.sigma, seed=args.seed),
            f"3D survey {floors} floors x {rows} x {cols}, {noise}")


def run_synth(args) -> int:
    from ..io import GraphFileError, write_g2o
    from ..io.tum import write_tum

    out = pathlib.Path(args.output)
    make, what = _synth_problem(args)  # the options first, then the files, then the work
    check_output("-o", args.output)
    truth_format = check_output("--ground-truth", args.ground_truth, TRUTH_FORMATS) if args.ground_truth else None
    for path in (args.output, args.ground_truth):
        if path and pathlib.Path(path).exists() and not args.force:
            raise UsageError(f"{path}: exists (use --force to overwrite)")
    if args.ground_truth and os.path.abspath(args.ground_truth) == os.path.abspath(args.output):
        raise UsageError(f"--ground-truth {args.ground_truth}: the same file as -o")
    prob = make()
    try:
        write_g2o(out, prob.graph, prob.initial, force=True)
        if truth_format == "g2o":
            write_g2o(args.ground_truth, prob.graph, prob.ground_truth, force=True)
        elif truth_format == "tum":
            write_tum(args.ground_truth, prob.ground_truth)
    except GraphFileError as exc:
        raise UsageError(str(exc)) from None
    except OSError as exc:
        raise UsageError(f"cannot write: {exc.strerror or exc}") from None
    also = f"; ground truth in {args.ground_truth}" if args.ground_truth else ""
    print(f"wrote {out}: {prob.poses} poses, {prob.graph.size() - 1} edges ({what}){also}")
    return 0


# -- shared by demo (demo.py) ---------------------------------------------------------------
def make_out_dir(option: str, path: str) -> pathlib.Path:
    """The output folder ``path``, created if missing; its parent must exist (no silent trees)."""
    out = pathlib.Path(path)
    if out.exists() and not out.is_dir():
        raise UsageError(f"{option} {path}: exists and is not a directory")
    if not out.exists():
        parent = out.parent
        if not parent.is_dir():
            raise UsageError(f"{option} {path}: folder {parent} does not exist (create it first)")
        try:
            out.mkdir()
        except OSError as exc:
            raise UsageError(f"{option} {path}: cannot create it: {exc.strerror or exc}") from None
    if not os.access(out, os.W_OK | os.X_OK):
        raise UsageError(f"{option} {path}: not writable")
    return out


def add_all(sub) -> None:
    for add in (add_solve, add_compare, add_synth):
        add(sub)
