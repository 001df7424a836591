"""Weak and strong scaling runs of the PETSc back-end, as Markdown tables (docs/distributed.md).

``python -m gtsam_schwarz.backends.petsc.scaling weak --ranks 1 2 4 8 --loops-per-rank 32 --points 64
--subdomains-per-rank 16 -- --partition segments`` runs ``square_loops(32·K, 64)`` on K ranks with 16·K
subdomains (fixed poses and subdomains per rank; options it does not know go to run.py); ``strong FILE|--square-loops L P
--ranks 1 2`` runs one problem on each rank count (``--serial`` adds the serial solver in the same
driver). Each run is one ``mpiexec`` child (``run.py --json``); ranks beyond the cores are
oversubscribed, so compare CG iterations and per-rank work there, not seconds.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys

from .env import launch_command, mpi_environment


def run_once(ranks: int, argv: list[str], timeout: float | None = None) -> dict:
    """One ``mpiexec -n ranks python -m gtsam_schwarz.backends.petsc.run ARGV --json``; its report."""
    proc = subprocess.run(launch_command(ranks, [*argv, "--json"]), capture_output=True, text=True,
                          env=mpi_environment(), timeout=timeout)
    lines = [line for line in proc.stdout.splitlines() if line.startswith("{")]
    if proc.returncode != 0 or len(lines) != 1:
        raise RuntimeError(f"mpiexec -n {ranks} {' '.join(argv)} failed ({proc.returncode}): "
                           f"{proc.stderr.strip().splitlines()[-1] if proc.stderr.strip() else proc.stdout[-500:]}")
    return json.loads(lines[0])


def _work(report: dict) -> str:
    per = report.get("per_rank") or []
    if not per:
        return "-"
    rows = [p["rows"] for p in per]
    nnz = [p["nnz"] for p in per]
    subs = [p["subdomains"] for p in per]
    return (f"{min(rows)}–{max(rows)} rows, {min(nnz) / 1e3:.0f}–{max(nnz) / 1e3:.0f}k nnz, "
            f"{min(subs)}–{max(subs)} subdomains")


def _solver_seconds(report: dict) -> str:
    """Per-rank wall seconds of the PETSc solver's own parts (max over ranks): coarse basis, PC setup,
    KSP solve."""
    per = report.get("per_rank") or []
    if not per:
        return "-"
    t = {k: max(p["seconds"][k] for p in per) for k in ("coarse_basis", "pc_setup", "ksp_solve")}
    return f"{t['coarse_basis']:.2f} / {t['pc_setup']:.2f} / {t['ksp_solve']:.2f}"


def _cg(report: dict) -> str:
    return " ".join(str(c) for c in report["cg_iterations"])


def weak_table(reports: list[dict]) -> str:
    head = ("| ranks | poses | subdomains | coarse size | LM its | CG per solve | CG mean | final error | "
            "per-rank work (min–max) | Φ / PC setup / KSP s (max rank) |\n|---|---|---|---|---|---|---|---|---|---|\n")
    rows = []
    for r in reports:
        rows.append(f"| {r['ranks']} | {r['poses']} | {r['subdomains']} | {r['coarse_size']} | {r['iterations']} | "
                    f"{_cg(r)} | {r['cg_mean']:.1f} | {r['final_error']:.10g} | {_work(r)} | "
                    f"{_solver_seconds(r)} |")
    return head + "\n".join(rows) + "\n"


def strong_table(reports: list[dict]) -> str:
    head = ("| solver | ranks | LM its | CG per solve | final error | linearize s | setup s | cg s | update s | "
            "total s |\n|---|---|---|---|---|---|---|---|---|---|\n")
    rows = []
    for r in reports:
        s = r["seconds"]
        rows.append(f"| {r['backend']} | {r['ranks']} | {r['iterations']} | {_cg(r)} | {r['final_error']:.12g} | "
                    f"{s['linearize']:.2f} | {s['setup']:.2f} | {s['cg']:.2f} | {s['update']:.2f} | "
                    f"{s['total']:.2f} |")
    return head + "\n".join(rows) + "\n"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m gtsam_schwarz.backends.petsc.scaling")
    sub = p.add_subparsers(dest="kind", required=True)
    w = sub.add_parser("weak", help="square_loops(loops_per_rank · K, points) on K ranks")
    w.add_argument("--ranks", type=int, nargs="+", default=[1, 2, 4, 8])
    w.add_argument("--loops-per-rank", type=int, default=32)
    w.add_argument("--points", type=int, default=64)
    w.add_argument("--subdomains-per-rank", type=int, default=None,
                   help="subdomains = this × K (default: the solver's, about 250 poses each in 2D, 32 in 3D (64 under 16 384 poses))")
    s = sub.add_parser("strong", help="one problem on each rank count")
    s.add_argument("file", nargs="?")
    s.add_argument("--square-loops", nargs=2, type=int, metavar=("LOOPS", "POINTS"))
    s.add_argument("--ranks", type=int, nargs="+", default=[1, 2])
    s.add_argument("--serial", action="store_true", help="also the serial solver (one rank)")
    for q in (w, s):
        q.add_argument("--json", action="store_true", help="the reports as one JSON list instead of a table")
    args, extra = p.parse_known_args(argv)  # options it does not know go to run.py
    extra = [a for a in extra if a != "--"]
    reports = []
    if args.kind == "weak":
        for k in args.ranks:
            per = ["--subdomains", str(args.subdomains_per_rank * k)] if args.subdomains_per_rank else []
            reports.append(run_once(k, ["--square-loops", str(args.loops_per_rank * k), str(args.points), *per, *extra]))
            print(f"ranks {k}: done", file=sys.stderr, flush=True)
        table = weak_table(reports)
    else:
        problem = [args.file] if args.file else ["--square-loops", *map(str, args.square_loops)]
        if args.serial:
            reports.append(run_once(1, [*problem, "--serial", *extra]))
        for k in args.ranks:
            reports.append(run_once(k, [*problem, *extra]))
            print(f"ranks {k}: done", file=sys.stderr, flush=True)
        table = strong_table(reports)
    print(json.dumps(reports) if args.json else table, end="" if not args.json else "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
