"""The ``gtsam-schwarz`` command line: solve, compare, synth (commands.py), demo (demo.py), paper and bench (bench.py).

Conventions: results on stdout (a table, or one JSON object with ``--json``), progress and errors on
stderr; a usage error is one line and exit code 2; a closed stdout (``| head``) ends the command
quietly with exit code 141 (128 + SIGPIPE, as a shell reports a process killed by SIGPIPE).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys

from .bench import add_bench
from .demo import add_demo
from ..io.jsonout import json_safe
from ..solvers.memory import InsufficientMemoryError
from ..util.heap import tune_allocator
from .commands import UsageError, add_all, make_out_dir, nonnegative_int, positive_float

DEFAULT_PAPER_OUT = "paper-results"  # in the current folder: never the committed docs/ unless asked
EXIT_BROKEN_PIPE = 141  # 128 + SIGPIPE


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
    p.add_argument("--out", default=DEFAULT_PAPER_OUT, metavar="DIR",
                   help=f"folder for the report and the figures, created if its parent exists (default: "
                        f"./{DEFAULT_PAPER_OUT}; '--out docs' refreshes the committed report)")
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

    out = make_out_dir("--out", args.out)
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
    from .. import __version__

    parser = Parser(prog="gtsam-schwarz", description="Schwarz-preconditioned Gauss-Newton for GTSAM pose graphs.")
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}",
                        help="print the version and exit")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=Parser,
                                help="one of these; 'gtsam-schwarz COMMAND --help' shows its options")
    sub.required = True
    add_all(sub)
    add_demo(sub)
    add_paper(sub)
    add_bench(sub)
    return parser


def _stderr(line: str) -> None:
    try:
        print(line, file=sys.stderr, flush=True)
    except (OSError, ValueError):  # stderr closed too: nothing left to tell
        pass


def _silence_stdout() -> None:
    """After EPIPE: point fd 1 at /dev/null so that the interpreter's final flush cannot fail again
    (the recipe of Python's documentation, "Note on SIGPIPE")."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    except (OSError, ValueError):
        pass


def _run(argv) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    tune_allocator()  # process tuning belongs to the application, not to the library
    try:
        return args.run(args)
    except UsageError as exc:
        _stderr(f"gtsam-schwarz {args.command}: error: {exc}")
        return 2
    except InsufficientMemoryError as exc:  # predicted before the heavy work: say what to change
        _stderr(f"gtsam-schwarz {args.command}: error: {exc}")
        return 2
    except KeyboardInterrupt:
        _stderr("gtsam-schwarz: interrupted")
        return 130
    except BrokenPipeError:
        raise
    except Exception as exc:  # a failure inside the computation: one line, no traceback
        _stderr(f"gtsam-schwarz {args.command}: error: {type(exc).__name__}: {exc}")
        return 1


def main(argv=None) -> int:
    try:
        code = _run(argv)
        sys.stdout.flush()  # a closed pipe shows here at the latest, not at interpreter exit
        return code
    except BrokenPipeError:  # the reader of stdout went away (| head): stop quietly
        _silence_stdout()
        return EXIT_BROKEN_PIPE


if __name__ == "__main__":
    sys.exit(main())
