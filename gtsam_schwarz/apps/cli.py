"""The ``gtsam-schwarz`` command line: solve, compare, synth, demo (commands.py), paper and bench (bench.py)."""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import pathlib
import sys

from .bench import add_bench
from .jsonout import json_safe
from .runtime import tune_allocator
from .commands import UsageError, add_all, nonnegative_int, positive_float


class Parser(argparse.ArgumentParser):
    """argparse, but a usage error is one line on stderr (exit code 2)."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message}\n")


def add_paper(sub) -> None:
    p = sub.add_parser("paper", help="reproduce every table and figure of the paper",
                       description="Recompute the paper's tables (bar chain, model problem, weak scaling, "
                                   "coarse space without rotation) and figures, go past its largest case "
                                   "(1024 loops, overlap 2 and 3), and write a Markdown report.")
    p.add_argument("--quick", action="store_true", help="a subset that runs in well under two minutes")
    p.add_argument("--out", default="docs", help="directory for the report and the figures (default: docs)")
    p.add_argument("--json", action="store_true", help="print exactly one JSON object on stdout")
    p.add_argument("--sigma", type=positive_float, default=None,
                   help="odometry noise of the model problem (default 0.005)")
    p.add_argument("--seed", type=nonnegative_int, default=0, help="noise seed (default 0)")
    p.add_argument("--budget", type=positive_float, default=None, metavar="SECONDS",
                   help="wall-clock budget per model case (default 600, quick 30)")
    p.set_defaults(run=run_paper)


@contextlib.contextmanager
def _stdout_to_stderr():
    """Send everything written to fd 1 (Python or C++) to stderr, so stdout carries only the JSON."""
    sys.stdout.flush()
    saved = os.dup(1)
    os.dup2(2, 1)
    try:
        yield
    finally:
        sys.stdout.flush()
        os.dup2(saved, 1)
        os.close(saved)


def run_paper(args) -> int:
    from .paper import Settings, reproduce

    out = pathlib.Path(args.out)
    if out.exists() and not out.is_dir():
        raise UsageError(f"--out {args.out}: exists and is not a directory")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UsageError(f"--out {args.out}: cannot create it: {exc.strerror or exc}") from None
    if not os.access(out, os.W_OK):
        raise UsageError(f"--out {args.out}: not writable")
    settings = Settings(quick=args.quick, seed=args.seed,
                        **({"sigma": args.sigma} if args.sigma is not None else {}),
                        case_seconds=args.budget or (30.0 if args.quick else 600.0),
                        cg_cap=20_000 if args.quick else 100_000)
    tty = sys.stderr.isatty()
    progress = (lambda msg: print(msg, file=sys.stderr, flush=True)) if tty else None
    command = "gtsam-schwarz paper" + (" --quick" if args.quick else "")
    redirect = _stdout_to_stderr() if args.json else contextlib.nullcontext()
    with redirect:
        results = reproduce(out, settings, progress, command)
    if args.json:
        print(json.dumps(json_safe(results), allow_nan=False))
    else:
        bars_ok = all(r[k]["cg"] == r[k]["paper"]["cg"] for r in results["bars1d"] for k in ("one_level", "gdsw"))
        print(f"wrote {results['files']['report']} and {len(results['files']) - 1} figures in {results['seconds']:.0f} s; "
              f"bar chain CG counts {'match' if bars_ok else 'differ from'} the paper; "
              f"{len(results['deviations'])} model cells deviate > 20 % from the paper (listed in the report)")
    return 0


def build_parser() -> Parser:
    parser = Parser(prog="gtsam-schwarz", description="Schwarz-preconditioned Gauss-Newton for GTSAM pose graphs.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=Parser)
    sub.required = True
    add_all(sub)
    add_paper(sub)
    add_bench(sub)
    return parser


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    tune_allocator()  # process tuning belongs to the application, not to the library
    try:
        return args.run(args)
    except UsageError as exc:
        print(f"gtsam-schwarz {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("gtsam-schwarz: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # a failure inside the computation: one line, no traceback
        print(f"gtsam-schwarz {args.command}: error: {type(exc).__name__}: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
