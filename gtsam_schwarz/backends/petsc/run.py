"""MPI entry point: ``mpiexec -n K python -m gtsam_schwarz.backends.petsc.run FILE [--json] [-o OUT]``.

Every rank reads the file; each rank linearizes only the factors it owns and assembles them into
PETSc (:class:`~gtsam_schwarz.backends.petsc.distributed.DistributedOptimizer`; ``--replicated``:
every rank linearizes the whole graph, as before); the linear solves run on PETSc across the K ranks
(:class:`~gtsam_schwarz.backends.petsc.solver.PetscSchwarzSolver`). See docs/distributed.md for what
changes at 100M poses. Only rank 0 prints (a line per
iteration and a summary, or one JSON object with ``--json``) and writes ``-o``. A usage error is one
line on stderr and exit code 2, as with ``gtsam-schwarz solve``.

``--square-loops L P`` solves the paper's model problem (``problems.square_loops(L, P)``),
``--lawnmower R C`` the survey ``problems.survey.lawnmower(R, C)``, instead of a file. ``--serial`` runs the serial linear solver in the same driver (for comparisons).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import pathlib
import sys
import time


from ...io.jsonout import json_safe
from ...nonlinear.hooks import verbose_printer

PHASES = ("linearize", "export", "setup", "cg", "update")


class UsageError(Exception):
    pass


class _Parser(argparse.ArgumentParser):
    def error(self, message):
        raise UsageError(message)


def _positive(kind):
    def parse(text):
        try:
            v = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
        if not (math.isfinite(v) and v > 0):
            raise argparse.ArgumentTypeError(f"expected a number > 0, got {text!r}")
        return v
    return parse


def _nonnegative_int(text):
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
    if v < 0:
        raise argparse.ArgumentTypeError(f"expected an integer >= 0, got {text!r}")
    return v


def build_parser() -> argparse.ArgumentParser:
    from ...dd import PARTITIONS
    from ...nonlinear import LINEAR_SOLVERS, METHODS

    p = _Parser(prog="python -m gtsam_schwarz.backends.petsc.run",
                description="Solve a pose graph with the Schwarz optimizer, linear solves on PETSc over MPI "
                            "(run under mpiexec -n K).")
    p.add_argument("file", nargs="?", help="g2o (SE2 / SE3:QUAT) or TORO file (or use --square-loops)")
    p.add_argument("--square-loops", nargs=2, type=_positive(int), metavar=("LOOPS", "POINTS"),
                   help="the paper's model problem instead of a file (sigma 0.01, seed 0)")
    p.add_argument("--lawnmower", nargs=2, type=_positive(int), metavar=("ROWS", "COLS"),
                   help="the lawnmower survey over a ROWS x COLS grid instead of a file")
    p.add_argument("--method", choices=METHODS, default="lm")
    p.add_argument("--preconditioner", choices=LINEAR_SOLVERS, default="gdsw")
    p.add_argument("--subdomains", type=_positive(int), default=None, metavar="N")
    p.add_argument("--partition", choices=PARTITIONS, default="auto")
    p.add_argument("--overlap", type=_nonnegative_int, default=None, metavar="K")
    p.add_argument("--cg-tol", type=_positive(float), default=1e-8, metavar="T")
    p.add_argument("--max-iterations", type=_nonnegative_int, default=100, metavar="N")
    p.add_argument("--inexact", action="store_true")
    p.add_argument("--local-solver", choices=("auto", "cholmod", "petsc", "mumps"), default="auto",
                   help="subdomain factorizations (default: CHOLMOD when this PETSc has it)")
    p.add_argument("--serial", action="store_true", help="the serial linear solver instead of PETSc (one rank)")
    p.add_argument("--replicated", action="store_true",
                   help="every rank linearizes the whole graph (default: each rank its own factors)")
    p.add_argument("-o", "--output", metavar="OUT.g2o|OUT.tum")
    p.add_argument("--force", action="store_true", help="allow -o to overwrite the input file")
    p.add_argument("--json", action="store_true", help="print exactly one JSON object on stdout (rank 0)")
    return p


def _load(args):
    """(graph, initial, description dict) on every rank."""
    if args.square_loops:
        from ...problems import square_loops

        loops, points = args.square_loops
        pb = square_loops(loops, points)
        poses = pb.initial.size()
        return pb.graph, pb.initial, {"file": f"square_loops({loops}, {points})", "poses": poses,
                                      "edges": pb.graph.size() - 1, "dimension": 2, "format": "model",
                                      "initial_guess": "dead reckoning"}, None
    if args.lawnmower:
        from ...problems.survey import lawnmower

        rows, cols = args.lawnmower
        pb = lawnmower(rows, cols)
        return pb.graph, pb.initial, {"file": f"lawnmower({rows}, {cols})", "poses": pb.initial.size(),
                                      "edges": pb.graph.size() - 1, "dimension": 2, "format": "model",
                                      "initial_guess": "dead reckoning"}, None
    if not args.file:
        raise UsageError("give a FILE, --square-loops LOOPS POINTS or --lawnmower ROWS COLS")
    from ...io import GraphFileError, load_graph

    path = pathlib.Path(args.file)
    if not path.exists():
        raise UsageError(f"{args.file}: no such file")
    if path.is_dir():
        raise UsageError(f"{args.file}: is a directory, expected a g2o or TORO file")
    try:
        loaded = load_graph(path)
    except GraphFileError as exc:
        raise UsageError(str(exc)) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise UsageError(f"{args.file}: cannot read: {exc}") from None
    return loaded.graph, loaded.initial, {"file": str(args.file), "poses": loaded.poses, "edges": loaded.edges,
                                          "dimension": loaded.dimension, "format": loaded.format,
                                          "initial_guess": loaded.initial_guess}, loaded


def _check_output(args):
    if not args.output:
        return None
    out = pathlib.Path(args.output)
    fmt = {".g2o": "g2o", ".tum": "tum"}.get(out.suffix.lower())
    if fmt is None:
        raise UsageError(f"-o {args.output}: unknown extension {out.suffix or '(none)'}; use .g2o, .tum")
    folder = out.parent if str(out.parent) else pathlib.Path(".")
    if not folder.is_dir():
        raise UsageError(f"-o {args.output}: folder {folder} does not exist (create it first)")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise UsageError(f"-o {args.output}: folder {folder} is not writable")
    if args.file and out.exists() and not args.force and os.path.samefile(out, args.file):
        raise UsageError(f"{args.output}: refusing to overwrite the input file (use --force)")
    return fmt


def solve(args, comm) -> dict:
    """Run the optimizer on every rank; returns the report (identical decisions on every rank)."""
    from ...nonlinear import SchwarzOptimizer, SchwarzParams
    from .distributed import DistributedOptimizer
    from .solver import PetscSchwarzSolver

    rank = comm.Get_rank()
    graph, initial, info, loaded = _load(args)
    human = not args.json and rank == 0
    if human:
        print(f"{info['file']}: {info['poses']} poses, {info['edges']} edges, {info['dimension']}D "
              f"({info['format']}, initial guess from {info['initial_guess']}); "
              f"{'serial' if args.serial else 'PETSc'} linear solves on {comm.Get_size()} rank(s)", flush=True)
    params = SchwarzParams(method=args.method, preconditioner=args.preconditioner, subdomains=args.subdomains,
                           partition=args.partition, overlap=args.overlap, cg_tol=args.cg_tol,
                           max_iterations=args.max_iterations, iteration_hook=verbose_printer(sys.stdout) if human else None,
                           forcing="eisenstat-walker" if args.inexact else "none")
    comm.Barrier()
    t0, cpu0 = time.perf_counter(), time.process_time()
    linear = None
    if args.serial:
        opt = SchwarzOptimizer(graph, initial, params)
    elif args.replicated:
        opt = SchwarzOptimizer(graph, initial, params)
        linear = PetscSchwarzSolver(opt.nonlinear_params.linear_solver, opt.linearizer.offsets,
                                    opt.linearizer.translation_mask(), local_solver=args.local_solver)
        opt.linear_solver = linear
    else:
        opt = DistributedOptimizer(graph, initial, params, local_solver=args.local_solver)
        linear = opt.linear_solver
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore" if rank else "default")
        values = opt.optimize()
    seconds = time.perf_counter() - t0
    s = opt.summary()
    split = {k: float(sum(h["seconds"].get(k, 0.0) for h in opt.history)) for k in PHASES}
    # the nonlinear loop must have taken the same decisions on every rank
    mine = (s["final_error"], s["iterations"], s["cg_total"], len(opt.history))
    agree = all(t == mine for t in comm.allgather(mine))
    per_rank = None
    if linear is not None and linear.layout is not None:
        lo, hi = linear.layout.rows(rank)
        from petsc4py import PETSc

        nnz = int(linear.A.getInfo(PETSc.Mat.InfoType.LOCAL)["nz_used"]) if linear.A is not None else 0
        import resource

        work = {"rows": hi - lo, "nnz": nnz, "cpu_seconds": time.process_time() - cpu0,
                "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
                "subdomains": int(len(linear.layout.subdomains(rank))) if len(linear.layout.subdomain_rank) else 0,
                "seconds": {k: float(v) for k, v in linear.timings.items()},
                "linearization": "distributed" if getattr(opt, "distributed", False) else "replicated",
                "factors": int(opt.part.n_factors) if getattr(opt, "part", None) is not None else None,
                "poses_held": int(len(opt.part.hold)) if getattr(opt, "part", None) is not None else None}
        if getattr(opt, "part", None) is not None:
            work["seconds"].update({f"linearize_{k}": float(v) for k, v in opt.part.seconds.items()})
            work["seconds"].update(optimizer_init=float(opt.init_seconds), distributed_setup=float(opt.setup_seconds))
        per_rank = comm.gather(work, root=0)
    phase_max = {k: float(comm.allreduce(v, op=_max())) for k, v in split.items()}
    import resource

    rss = float(comm.allreduce(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0, op=_max()))
    report = {
        **info, "backend": "serial" if args.serial else "petsc", "ranks": comm.Get_size(),
        "local_solver": linear.local_solver if linear is not None else None,
        "method": args.method, "preconditioner": args.preconditioner, "partition": args.partition,
        "subdomains": s["subdomains"], "overlap": params.overlap_layers(), "coarse_size": s["coarse_size"],
        "iterations": s["iterations"], "linear_solves": s["linear_solves"],
        "cg_iterations": s["cg_iterations"], "cg_mean": s["cg_mean"],
        "lambda_min": [h.lambda_min for h in opt.history], "lambda_max": [h.lambda_max for h in opt.history],
        "initial_error": s["initial_error"], "final_error": s["final_error"],
        "converged": s["converged"], "stop_reason": s["stop_reason"],
        "seconds": {"total": seconds, "linearize": split["linearize"] + split["export"],
                    "setup": split["setup"], "cg": split["cg"], "update": split["update"]},
        "seconds_max_over_ranks": {"linearize": phase_max["linearize"] + phase_max["export"],
                                   "setup": phase_max["setup"], "cg": phase_max["cg"], "update": phase_max["update"]},
        "linearization": "serial" if args.serial else ("distributed" if getattr(opt, "distributed", False)
                                                       else "replicated"),
        "replicated_reason": getattr(opt, "replicated", "") or None,
        "peak_rss_mb_max_over_ranks": rss, "ranks_agree": bool(agree), "per_rank": per_rank, "output": args.output,
    }
    if args.output and rank == 0:
        _write(args, loaded, graph, values)
    return report


def _max():
    from mpi4py import MPI

    return MPI.MAX


def _write(args, loaded, graph, values):
    from ...io import GraphFileError, write_g2o
    from ...io.tum import write_tum

    try:
        if args.output.lower().endswith(".tum"):
            write_tum(args.output, values)
        else:
            write_g2o(args.output, graph, values, force=args.force, input_path=args.file)
    except GraphFileError as exc:
        raise UsageError(str(exc)) from None
    except OSError as exc:
        raise UsageError(f"{args.output}: cannot write: {exc.strerror or exc}") from None


def main(argv=None) -> int:
    from mpi4py import MPI

    comm = MPI.COMM_WORLD
    rank = comm.Get_rank()
    prog = "gtsam-schwarz-mpi"
    try:
        args = build_parser().parse_args(argv)
        _check_output(args)
        if args.serial and comm.Get_size() > 1:
            raise UsageError("--serial runs on one rank")
        report = solve(args, comm)
    except UsageError as exc:
        if rank == 0:
            print(f"{prog}: error: {exc}", file=sys.stderr, flush=True)
        return 2
    except Exception as exc:  # noqa: BLE001 — one line per failing rank, then abort every rank
        print(f"{prog} (rank {rank}): error: {type(exc).__name__}: {exc}", file=sys.stderr, flush=True)
        if comm.Get_size() > 1:
            comm.Abort(1)
        return 1
    if rank == 0:
        if args.json:
            print(json.dumps(json_safe(report), allow_nan=False), flush=True)
        else:
            r = report
            sec = r["seconds"]
            print(f"{'converged' if r['converged'] else 'stopped'} after {r['iterations']} iterations "
                  f"({r['stop_reason']}): error {r['initial_error']:.8g} -> {r['final_error']:.8g}; "
                  f"{r['subdomains']} subdomains, coarse space {r['coarse_size']}, {r['cg_mean']:.1f} CG iterations "
                  f"per solve; {sec['total']:.2f} s (linearize {sec['linearize']:.2f}, setup {sec['setup']:.2f}, "
                  f"cg {sec['cg']:.2f}); {r['ranks']} rank(s)"
                  + ("" if r["ranks_agree"] else "; WARNING: ranks disagree"), flush=True)
            if args.output:
                print(f"wrote optimized poses to {args.output}", flush=True)
    return 0 if report["ranks_agree"] else 1


if __name__ == "__main__":
    sys.exit(main())
