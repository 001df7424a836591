"""Each speed lever of issue 8 measured alone: the default solver against the solver with one lever off.

    python benchmarks/levers.py                          # sq128x64 and city10000, 3 runs each
    python benchmarks/levers.py --cases sq1024x64 --repeat 1 --json

Every variant runs in its own child process (``python -m gtsam_schwarz.apps.bench``, the benchmark's
worker), so allocator state and imports do not carry over; the time is the optimizer's construction
plus ``optimize()``, problem loading excluded, as in ``gtsam-schwarz bench``. Each variant runs
``--repeat`` times, interleaved (all variants once, then again), and the table shows the median
run, so a slow spell of a shared machine does not land on one variant only.
"""

from __future__ import annotations

import argparse
import json
import sys

from gtsam_schwarz.apps.bench import ALL_CASES, default_datasets_dir, run_solver

# (name, SchwarzParams overrides, environment overrides)
VARIANTS = (
    ("default (every lever on)", {}, {}),
    ("SuperLU instead of CHOLMOD", {}, {"GTSAM_SCHWARZ_SPARSE": "superlu"}),
    ("no symbolic reuse (rebuild M from scratch)", {"reuse_symbolic": False}, {}),
    ("no lagged preconditioner", {"lagged_preconditioner": False}, {}),
    ("BLAS threads not limited", {"blas_threads": None}, {}),
    ("CHOLMOD's OpenMP at its own 4 threads", {}, {"OMP_THREAD_LIMIT": "4"}),
    ("glibc allocator defaults", {}, {"GTSAM_SCHWARZ_MALLOPT": "0"}),
    ("no heap populated ahead", {}, {"GTSAM_SCHWARZ_POPULATE": "0"}),
    ("inexact Newton (Eisenstat-Walker) on", {"forcing": "eisenstat-walker"}, {}),
    ("partition: segments", {"partition": "segments"}, {}),
    ("partition: metis", {"partition": "metis"}, {}),
)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default="sq128x64,city10000", help="comma list of bench case names")
    ap.add_argument("--timeout", type=float, default=1200.0)
    ap.add_argument("--repeat", type=int, default=3, help="runs per variant; the median is shown")
    ap.add_argument("--json", action="store_true", help="print the rows as one JSON list instead of the table")
    args = ap.parse_args(argv)
    cases = [c for c in args.cases.split(",") if c]
    unknown = [c for c in cases if c not in ALL_CASES]
    if unknown:
        ap.error(f"unknown case {unknown[0]!r}; choose from {', '.join(sorted(ALL_CASES))}")
    if args.repeat < 1 or not args.timeout > 0:
        ap.error("--repeat must be at least 1 and --timeout positive")
    datasets = default_datasets_dir()
    runs = {(case, name): [] for case in cases for name, _, _ in VARIANTS}
    for rep in range(args.repeat):
        for case in cases:
            for name, overrides, env in VARIANTS:
                if sys.stderr.isatty():
                    print(f"[run {rep + 1}/{args.repeat}] {case}: {name} …", file=sys.stderr, flush=True)
                runs[case, name].append(run_solver(ALL_CASES[case], "ours", overrides, datasets, args.timeout, env))
    rows = []
    for case in cases:
        for name, overrides, env in VARIANTS:
            done = [r for r in runs[case, name] if r.get("seconds") is not None]
            median = sorted(done, key=lambda r: r["seconds"])[(len(done) - 1) // 2] if done else runs[case, name][0]
            rows.append({"case": case, "variant": name, "params": overrides, "env": env, **median,
                         "all_seconds": [r.get("seconds") for r in runs[case, name]]})
    if args.json:
        print(json.dumps(rows, default=str))
        return 0
    print("| case | variant | status | seconds (median) | all runs | vs default | iterations | solves | CG / solve | setup s | CG s | final error |")
    print("|---|---|---|---:|---|---:|---:|---:|---:|---:|---:|---:|")
    for case in cases:
        group = [r for r in rows if r["case"] == case]
        base = group[0].get("seconds")
        for r in group:
            s = r.get("seconds")
            split = r.get("split", {})
            ratio = f"{s / base:.2f}" if s and base else "–"
            every = ", ".join("–" if x is None else f"{x:.2f}" for x in r["all_seconds"])
            print(f"| {case} | {r['variant']} | {r['status']} | {s:.3f} | {every} | {ratio} | {r.get('iterations', '–')} | "
                  f"{r.get('linear_solves', '–')} | {r.get('cg_mean', float('nan')):.1f} | "
                  f"{split.get('setup', float('nan')):.3f} | {split.get('cg', float('nan')):.3f} | "
                  f"{r.get('final_error', float('nan')):.10g} |" if s is not None else
                  f"| {case} | {r['variant']} | {r['status']} | – | – | – | – | – | – | – | – | – |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
