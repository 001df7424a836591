"""``gtsam-schwarz bench``: end-to-end solves of ours against GTSAM's optimizers, one child process per run.

Each solver run is a child (``python -m gtsam_schwarz.apps.bench --case ... --solver ...``) so that it has
its own peak memory and a crash or a timeout becomes a row of the table, not the end of the benchmark.
GTSAM's children run under ``ulimit -s unlimited`` (its recursive elimination needs a deep stack);
ours runs with the default stack. Every child records the stack limit it ran under.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import importlib.metadata
import json
import math
import os
import pathlib
import platform
import resource
import shlex
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass

import numpy as np

from . import peers
from ..util.heap import HeapPeak, trim_heap
from .report import markdown_table

# our optimizer: the automatic choice, and each of its two linear solvers forced (over any --param)
OURS = {"ours": {}, "ours-direct": {"preconditioner": "direct"}, "ours-schwarz": {"preconditioner": "rgdsw-linear"}}
CORE_SOLVERS = (*OURS, "gtsam-lm", "gtsam-lm-pcg", "gtsam-lm-subgraph")
PEERS = tuple(peers.PEER_SOLVERS)  # g2o-gn, g2o-lm: need the [peers] extra (g2opy)
KNOWN_SOLVERS = CORE_SOLVERS + PEERS  # what --solvers accepts; a peer that is not installed is a row "not installed"
SOLVERS = CORE_SOLVERS + (PEERS if peers.available() else ())  # the default: the peers when installed
SPEEDUP_OVER_OURS = ("ours-direct", "ours-schwarz", "gtsam-lm-pcg", "gtsam-lm-subgraph", *PEERS)  # "that / ours"
NOT_INSTALLED = "not installed"
SIZES = ("tiny", "small", "large")
PHASES = ("linearize", "export", "setup", "cg", "update")
BASE_PARAMS = {"method": "lm", "preconditioner": "auto"}
TOLERANCE = 1e-6  # relative final-error difference to GTSAM LM that counts as "the same answer"
OUT_OF_MEMORY = "would not fit in memory"  # a run of ours refused before the heavy work
STDERR_TAIL = 4000  # characters of a child's stderr kept


@dataclass(frozen=True)
class Case:
    """One benchmark problem: the paper's model problem (loops × points per side), a survey grid
    (``grid``: rows, cols for the 2D lawnmower; floors, rows, cols for the 3D survey) or a dataset file."""

    name: str
    loops: int = 0
    points_per_side: int = 0
    file: str = ""
    grid: tuple[int, ...] = ()

    @property
    def description(self) -> str:
        if self.file:
            return f"../shared/datasets/{self.file}"
        if len(self.grid) == 2:
            return f"2D lawnmower survey, {self.grid[0]} x {self.grid[1]} grid (sigma 0.01, seed 0)"
        if len(self.grid) == 3:
            return (f"3D survey, {self.grid[0]} floors of {self.grid[1]} x {self.grid[2]} lawnmower grids "
                    "(sigma 0.01, seed 0)")
        return f"model problem, {self.loops} loops x {self.points_per_side} points per side (sigma 0.01, seed 0)"

    @property
    def model_poses(self) -> int | None:
        if self.file:
            return None
        return math.prod(self.grid) if self.grid else 4 * self.loops * self.points_per_side + 1


def _model(loops: int, points_per_side: int) -> Case:
    return Case(f"sq{loops}x{points_per_side}", loops=loops, points_per_side=points_per_side)


def _lawnmower(rows: int, cols: int) -> Case:
    return Case(f"lawn{rows}x{cols}", grid=(rows, cols))


def _survey3d(floors: int, rows: int, cols: int) -> Case:
    return Case(f"survey{floors}x{rows}x{cols}", grid=(floors, rows, cols))


CASES = {
    "tiny": (_model(8, 16), Case("smallGrid3D", file="smallGrid3D.g2o")),
    "small": (_model(32, 128), _model(128, 64), Case("M3500", file="input_M3500_g2o.g2o"),
              Case("city10000", file="city10000.g2o"), Case("sphere2500", file="sphere2500.g2o"),
              _lawnmower(100, 100), _survey3d(8, 24, 24)),
    "large": (_model(1024, 64), _model(1024, 256), _lawnmower(600, 600), _lawnmower(1000, 1000),
              _survey3d(32, 32, 32), _survey3d(45, 45, 45), _survey3d(60, 60, 60)),
}
ALL_CASES = {c.name: c for size in SIZES for c in CASES[size]}


CHECKOUT = pathlib.Path(__file__).resolve().parents[2]  # the folder that holds the gtsam_schwarz package


def default_datasets_dir() -> pathlib.Path:
    """``../shared/datasets`` from the current folder, else beside this checkout."""
    here = pathlib.Path.cwd().parent / "shared" / "datasets"
    return here if here.is_dir() else CHECKOUT.parent / "shared" / "datasets"


# -- the child -----------------------------------------------------------------------------------
def _memory_mib() -> tuple[float, float]:
    """(current, peak) resident set size in MiB: VmRSS and VmHWM from one read of /proc/self/status,
    so peak >= current always holds (``ru_maxrss`` lags by the kernel's per-thread RSS caches);
    ``ru_maxrss`` for both where /proc is missing."""
    try:
        with open("/proc/self/status") as f:
            fields = dict(l.split(":", 1) for l in f if l.startswith(("VmRSS:", "VmHWM:")))
        rss, hwm = (int(fields[k].split()[0]) / 1024 for k in ("VmRSS", "VmHWM"))
        return rss, max(rss, hwm)
    except (OSError, KeyError, ValueError):
        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # KiB on Linux
        return peak, peak


def _reset_peak() -> bool:
    """Reset this process's peak RSS (Linux ``clear_refs`` 5), so the solve's own peak can be read."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def stack_limit() -> dict:
    """The soft stack limit of this process: bytes (None = unlimited) and as text."""
    soft, _ = resource.getrlimit(resource.RLIMIT_STACK)
    if soft == resource.RLIM_INFINITY:
        return {"bytes": None, "text": "unlimited"}
    return {"bytes": soft, "text": f"{soft / 2**20:g} MiB"}


def load_case(case: Case, datasets: pathlib.Path):
    """(problem, poses, dimension) of a case: ``problem`` has ``graph``, ``initial`` and ``arrays``
    (the loader's parsed numbers; ``{}`` where GTSAM must linearize); the survey problems build their
    GTSAM objects on first use."""
    if case.file:
        from ..io import load_graph
        g = load_graph(datasets / case.file)
        return g, g.poses, g.dimension
    from ..problems import lawnmower, square_loops, survey3d
    if case.grid:
        p = (lawnmower if len(case.grid) == 2 else survey3d)(*case.grid)
        return p, p.poses, p.dimension
    p = square_loops(case.loops, case.points_per_side)
    return p, p.poses, 2


def _from_arrays(solver: str, overrides: dict, arrays) -> bool:
    """Whether our run ``solver`` linearizes from the loader's arrays alone (no GTSAM graph needed)."""
    params = {**BASE_PARAMS, **overrides, **OURS.get(solver, {})}
    return solver in OURS and bool(arrays) and params.get("linearization", "auto") != "gtsam"


def _solve_ours(graph, initial, overrides: dict, arrays: dict | None = None) -> dict:
    from .compare import run_ours
    from ..nonlinear import SchwarzParams
    from ..solvers.memory import InsufficientMemoryError

    _load_our_modules()
    try:
        r = run_ours(graph, initial, SchwarzParams(**{**BASE_PARAMS, **overrides}), arrays, release_arrays=True)
    except InsufficientMemoryError as exc:  # refused before the heavy work (predicted): a row of its own
        return {"failed": f"{OUT_OF_MEMORY}: {exc}", "values": None, "iterations": 0, "seconds": float("nan")}
    its = r["iterations"]
    per = {k: (v / its if its else float("nan")) for k, v in r["split"].items()}
    keep = ("iterations", "seconds", "linear_solves", "cg_mean", "subdomains", "coarse_size", "converged",
            "stop_reason", "linear_solver")
    return {**{k: r[k] for k in keep}, "values": r["values"], "split": r["split"], "split_per_iteration": per}


def _load_our_modules() -> None:
    """Import what our optimizer imports on first use (the native linearizer's modules, 18 ms;
    threadpoolctl and CHOLMOD's library handle, 3 ms each), so that module and library loading stays
    outside the timed solve, as it does for GTSAM and g2o (imported before their timers start).
    Work done on first use is still timed."""
    from ..util.blas import blas_limits
    from ..linearization import native  # noqa: F401
    from ..solvers import cholmod_symbolic

    cholmod_symbolic._library()  # dlopen of CHOLMOD after an ldconfig lookup (a subprocess): library loading
    with blas_limits(1):  # threadpoolctl's one scan of the loaded libraries per process
        pass


def _solve_gtsam(graph, initial, name: str) -> dict:
    from .compare import ITERATIVE_TOL, run_gtsam

    r = run_gtsam(graph, initial, name, iterative_tol=ITERATIVE_TOL)
    return {k: r[k] for k in ("iterations", "seconds", "values", "failed") if k in r}


def _solve_peer(problem: peers.G2oProblem, name: str) -> dict:
    """g2o's GN or LM on its graph (``problem``, built from GTSAM's, not timed); estimates back in gtsam Values."""
    r = peers.solve_g2o(None, None, peers.PEER_SOLVERS[name], problem=problem)
    return {k: r[k] for k in ("iterations", "seconds", "values", "failed", "init_seconds", "g2o_chi2",
                              "g2o_initial_chi2", "converged", "stop_reason") if k in r}


def solve(case: Case, solver: str, overrides: dict, datasets: pathlib.Path) -> dict:
    """Load (not timed), then time the optimizer's construction + optimize(); memory and stack figures.

    ``peak_mib`` is the whole child's peak RSS; ``solve_peak_mib`` the peak since loading ended
    (the same figure where the peak cannot be reset); ``live_peak_mib`` the most heap in use during the
    solve (glibc's count, sampled every 50 ms; None elsewhere). A peer (g2o) that cannot be imported gives
    ``{"not_installed": why}`` before anything is loaded."""
    if solver in PEERS:
        try:
            peers.import_g2o()
        except peers.PeerNotInstalled as exc:
            return {"not_installed": str(exc), "stack": stack_limit()}
    problem, poses, dimension = load_case(case, datasets)
    arrays, peer = problem.arrays, None
    if _from_arrays(solver, overrides, arrays):
        # the GTSAM graph is neither built (survey problems) nor held: our native linearizer reads the
        # arrays; the start Values stay, as the optimizer's API takes them
        graph, initial = None, problem.initial
    elif solver in PEERS:   # g2o holds its own graph only, as when it reads a file itself
        peer = peers.build_g2o(problem.graph, problem.initial, peers.PEER_SOLVERS[solver])
        graph = initial = arrays = None
    else:
        graph, initial = problem.graph, problem.initial
        if solver not in OURS:
            arrays = None   # only our native linearizer reads the loader's arrays (ours releases them once it is built)
    del problem
    trim_heap()   # the dropped objects' pages go back: the solve does not reuse them warm
    loaded, load_peak = _memory_mib()
    reset = _reset_peak()
    with HeapPeak() as live:
        if solver in OURS:
            r = _solve_ours(graph, initial, {**overrides, **OURS[solver]}, arrays)
        elif solver in PEERS:
            r = _solve_peer(peer, solver)
            del peer
        else:
            r = _solve_gtsam(graph, initial, solver)
    solve_peak = _memory_mib()[1]
    values = r.pop("values")
    if values is not None and graph is None:   # GTSAM's own evaluation of the result, after the peak was read
        graph = load_case(case, datasets)[0].graph
    r["final_error"] = float(graph.error(values)) if values is not None else float("nan")
    return {**r, "poses": poses, "dimension": dimension, "loaded_mib": loaded,
            "peak_mib": max(load_peak, solve_peak), "solve_peak_mib": solve_peak, "peak_reset": reset,
            "live_peak_mib": live.mib,
            "stack": stack_limit()}


def worker_main(argv=None) -> int:
    """Child entry point: solve one (case, solver) and write the result as JSON to ``--result``."""
    from ..util.heap import tune_allocator
    tune_allocator()
    ap = argparse.ArgumentParser(prog="python -m gtsam_schwarz.apps.bench", description="one benchmark run (a child)")
    ap.add_argument("--case", required=True, choices=sorted(ALL_CASES))
    ap.add_argument("--solver", required=True, choices=KNOWN_SOLVERS)
    ap.add_argument("--params", default="{}", help="JSON object of SchwarzParams overrides (ours)")
    ap.add_argument("--datasets", type=pathlib.Path, default=None)
    ap.add_argument("--result", required=True, help="file to write the JSON result to")
    args = ap.parse_args(argv)
    from ..io.jsonout import json_safe

    row = solve(ALL_CASES[args.case], args.solver, json.loads(args.params), args.datasets or default_datasets_dir())
    pathlib.Path(args.result).write_text(json.dumps(json_safe(row), allow_nan=False))
    return 0


# -- the parent: one child per run ---------------------------------------------------------------
def _last_line(text: str) -> str:
    lines = [l.strip() for l in text.splitlines() if l.strip()]
    return lines[-1] if lines else ""


def _status(rc: int, stderr: str) -> str:
    if rc == 0:
        return "ok"
    if rc < 0:
        try:
            return f"crashed ({signal.Signals(-rc).name})"
        except ValueError:
            return f"crashed (signal {-rc})"
    return f"error (exit {rc}): {_last_line(stderr) or 'no message'}"


def run_child(argv: list[str], timeout: float, unlimited_stack: bool = False, env: dict | None = None) -> dict:
    """Run ``argv`` in its own process group; status ok / crashed (SIGxxx) / timeout after N s / error."""
    if unlimited_stack:  # raise the soft limit as far as allowed, then exec: the child keeps bash's pid
        argv = ["bash", "-c", 'ulimit -s unlimited 2>/dev/null || ulimit -s "$(ulimit -H -s)"; exec "$@"',
                "bash", *argv]
    t = time.perf_counter()
    proc = subprocess.Popen(argv, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, errors="replace", start_new_session=True, env=env)
    try:
        out, err = proc.communicate(timeout=timeout)
        status = _status(proc.returncode, err)
    except subprocess.TimeoutExpired:
        _kill_group(proc)
        out, err = proc.communicate()
        status = f"timeout after {timeout:g} s"
    except BaseException:  # e.g. Ctrl-C: the child is in its own session and would not get it
        _kill_group(proc)
        proc.wait()
        raise
    return {"status": status, "returncode": proc.returncode, "stdout": out, "stderr": err[-STDERR_TAIL:],
            "child_seconds": time.perf_counter() - t}


def _kill_group(proc: subprocess.Popen) -> None:
    try:
        os.killpg(proc.pid, signal.SIGKILL)
    except ProcessLookupError:
        pass


def _child_env() -> dict:
    """This environment with this package's folder first on PYTHONPATH: the child runs the same code."""
    root = str(CHECKOUT)
    path = os.environ.get("PYTHONPATH")
    return {**os.environ, "PYTHONPATH": root + (os.pathsep + path if path else "")}


def run_solver(case: Case, solver: str, overrides: dict, datasets: pathlib.Path, timeout: float,
               env: dict | None = None) -> dict:
    """One benchmark run in a child (``env``: extra environment variables); a crash or a timeout is
    a row with that status."""
    with tempfile.TemporaryDirectory(prefix="gtsam-schwarz-bench-") as tmp:
        result = pathlib.Path(tmp) / "result.json"
        argv = [sys.executable, "-m", "gtsam_schwarz.apps.bench", "--case", case.name, "--solver", solver,
                "--params", json.dumps(overrides), "--datasets", str(datasets), "--result", str(result)]
        child = run_child(argv, timeout, unlimited_stack=solver not in OURS, env={**_child_env(), **(env or {})})
        row = json.loads(result.read_text()) if child["status"] == "ok" and result.exists() else {}
    if child["status"] == "ok" and not row:
        child["status"] = "error: the child wrote no result"
    if row.get("not_installed"):
        status = NOT_INSTALLED
    else:
        status = f"failed: {row['failed']}" if row.get("failed") else child["status"]
    keep = {"stderr": child["stderr"]} if status != "ok" else {}
    return {"case": case.name, "solver": solver, **row, "status": status, "child_seconds": child["child_seconds"],
            **keep}


# -- figures derived from the runs ---------------------------------------------------------------
def _num(v) -> float:
    return float(v) if isinstance(v, (int, float)) and v is not None else float("nan")


def _ratio(a, b) -> float:
    a, b = _num(a), _num(b)
    return a / b if math.isfinite(a) and math.isfinite(b) and b > 0 else float("nan")


def add_comparisons(rows: list[dict]) -> None:
    """Per case: relative error difference and time ratio to gtsam-lm; other solver / ours speedup."""
    for case in dict.fromkeys(r["case"] for r in rows):
        group = [r for r in rows if r["case"] == case]
        ok = {r["solver"]: r for r in group if r["status"] == "ok"}
        lm, ours = ok.get("gtsam-lm", {}), ok.get("ours", {})
        e_lm = _num(lm.get("final_error"))
        for r in group:
            ok_row = r["status"] == "ok"
            e = _num(r.get("final_error")) if ok_row else float("nan")
            rel = abs(e - e_lm) / e_lm if math.isfinite(e) and math.isfinite(e_lm) and e_lm > 0 else float("nan")
            r["rel_error_diff"] = rel
            r["same_error"] = bool(rel <= TOLERANCE) if math.isfinite(rel) else None
            r["ratio_to_gtsam_lm"] = _ratio(r.get("seconds"), lm.get("seconds")) if ok_row else float("nan")
            r["over_ours"] = (_ratio(r.get("seconds"), ours.get("seconds"))
                              if ok_row and r["solver"] in SPEEDUP_OVER_OURS else float("nan"))


def direct_vs_schwarz(rows: list[dict]) -> list[dict]:
    """Per case with an ok ours-direct and ours-schwarz row: time and peak-memory ratios Schwarz ÷
    direct, the faster of the two, and what ``auto`` (the ours row) chose and whether that was it."""
    out = []
    for case in dict.fromkeys(r["case"] for r in rows):
        ok = {r["solver"]: r for r in rows if r["case"] == case and r["status"] == "ok"}
        direct, schwarz, auto = ok.get("ours-direct"), ok.get("ours-schwarz"), ok.get("ours")
        refused = next((r for r in rows if r["case"] == case and r["solver"] == "ours-direct"
                        and OUT_OF_MEMORY in r["status"]), None)
        if schwarz is None or (direct is None and refused is None):
            continue
        if direct is None:  # direct would not fit: Schwarz finishing is the comparison
            direct, seconds, faster = {"seconds": None, "peak_mib": None}, float("nan"), "schwarz"
        else:
            seconds = _ratio(schwarz.get("seconds"), direct.get("seconds"))
            faster = "schwarz" if seconds < 1 else "direct"
        chose = auto.get("linear_solver", {}).get("used") if auto else None
        picked = None if chose is None else ("direct" if chose == "direct" else "schwarz")
        out.append({"case": case, "direct_seconds": direct.get("seconds"), "schwarz_seconds": schwarz.get("seconds"),
                    "auto_seconds": auto.get("seconds") if auto else None, "schwarz_over_direct": seconds,
                    "peak_schwarz_over_direct": _ratio(schwarz.get("peak_mib"), direct.get("peak_mib")),
                    "live_schwarz_over_direct": _ratio(schwarz.get("live_peak_mib"), direct.get("live_peak_mib")),
                    "delta_schwarz_over_direct": _ratio(_delta(schwarz), _delta(direct)),
                    "schwarz_cg_mean": schwarz.get("cg_mean"), "schwarz_subdomains": schwarz.get("subdomains"),
                    "schwarz_coarse_size": schwarz.get("coarse_size"), "faster": faster, "auto_chose": chose,
                    "auto_picked_faster": None if picked is None else picked == faster})
    return out


def _delta(r: dict) -> float:
    """The solver's own memory: peak RSS during the solve minus RSS after loading (MiB)."""
    return _num(r.get("solve_peak_mib")) - _num(r.get("loaded_mib"))


def _case_poses(case: Case, rows: list[dict]):
    found = next((r["poses"] for r in rows if r["case"] == case.name and "poses" in r), None)
    return found if found is not None else case.model_poses


# -- Markdown ------------------------------------------------------------------------------------
def _f(v, fmt: str, missing: str = "–") -> str:
    v = _num(v)
    return format(v, fmt) if math.isfinite(v) else missing


def _table(header: list[str], rows: list[list[str]]) -> list[str]:
    return markdown_table(header, rows, left=("case", "solver", "status", "stack", "linear solver", "auto chose",
                                              "auto picked the faster"))


def _same(r: dict) -> str:
    if r.get("same_error") is None:
        return "–"
    return f"{r['rel_error_diff']:.1e} {'✓' if r['same_error'] else '✗'}"


def _main_row(r: dict, poses) -> list[str]:
    delta = _delta(r)
    return [r["case"], str(poses) if poses is not None else "?", r["solver"], r["status"],
            _f(r.get("final_error"), ".10g"), _same(r), str(r.get("iterations", "–")),
            _f(r.get("seconds"), ".3f"), _f(r.get("ratio_to_gtsam_lm"), ".2f"), _f(r.get("over_ours"), ".2f"),
            _f(r.get("peak_mib"), ".0f"), _f(r.get("live_peak_mib"), ".0f"), _f(delta, ".0f"),
            r.get("stack", {}).get("text", "–")]


def _count(v) -> str:
    return "–" if v is None else str(v)


def _split_row(r: dict) -> list[str]:
    per = r.get("split_per_iteration", {})
    total = r.get("split", {})
    cells = [_f(_num(per.get(k)) * 1e3, ".1f") for k in PHASES]
    return [r["case"], r["solver"], str(r.get("iterations", "–")), str(r.get("linear_solves", "–")), *cells,
            _f(sum(_num(per.get(k)) for k in PHASES) * 1e3, ".1f"), _f(sum(_num(total.get(k)) for k in PHASES), ".3f"),
            _f(r.get("cg_mean"), ".1f"), _count(r.get("subdomains")), _count(r.get("coarse_size")),
            r.get("linear_solver", {}).get("used", "–")]


def _header(report: dict) -> list[str]:
    m = report["machine"]
    return [f"# Benchmark: size {report['size']}", "",
            f"- command: `{report['command']}`",
            f"- date: {report['date']}",
            f"- machine: {m['cpu_count']} CPUs ({m['cpu']}), {m['memory_gib']} GiB, {m['platform']}"
            + (f"; fresh memory's first touch {m['first_touch_ms_per_mib']:g} ms/MiB (64 MiB, before the runs: a lower "
               "bound, see docs/survey.md, thirty-third pass)"
               if m.get("first_touch_ms_per_mib") is not None else ""),
            f"- versions: Python {m['python']}, gtsam {m['gtsam']}, numpy {m['numpy']}, scipy {m['scipy']}, "
            f"gtsam-schwarz {m['gtsam_schwarz']}; local factorizations: {m.get('sparse_backend', '?')}"
            + (f"; OpenMP thread limit (CHOLMOD's supernodal regions) {m['openmp_thread_limit']}"
               if m.get("openmp_thread_limit") is not None else ""),
            f"- ours: `SchwarzParams({', '.join(f'{k}={v!r}' for k, v in report['params'].items())})`; "
            + "; ".join(f"{name}: the same with preconditioner={opts['preconditioner']!r}"
                        for name, opts in OURS.items() if opts) + "; "
            "GTSAM: `LevenbergMarquardtOptimizer` with default parameters (Cholesky; PCG with block-Jacobi; "
            "SubgraphSolver; the iterative ones with CG tolerance 1e-8 relative and at most 20000 CG "
            "iterations, as ours: GTSAM's default 1e-3 stops LM early at a worse error); all stop on "
            "relative/absolute error decrease 1e-5 or 100 iterations",
            *_peer_header(report),
            f"- every run in its own child process, timeout {report['timeout']:g} s; GTSAM's and g2o's children "
            "under `ulimit -s unlimited`, ours with the default stack (column *stack*)",
            "- what each child holds through the solve: GTSAM's the gtsam graph and start Values; g2o's its own "
            "graph (built from them, which are then dropped); ours the start Values and the loader's arrays, "
            "no gtsam graph (the native linearizer reads the arrays; where it cannot, the graph); what a child "
            "drops goes back to the kernel before the solve (`malloc_trim`), so no solver reuses it warm; the final "
            "error is GTSAM's `graph.error`, evaluated after the peak is read (the graph built again where "
            "it was not held)", ""]


def _peer_header(report: dict) -> list[str]:
    """The g2o line of the header, when a g2o row was asked for."""
    if not any(s in PEERS for s in report.get("solvers", ())):
        return []
    version = report["machine"].get("g2opy")
    return [f"- g2o ({'g2opy ' + version if version else 'g2opy not installed'}): `SparseOptimizer`, "
            f"`BlockSolverSE2/SE3` + {peers.LINEAR_SOLVER}, Gauss–Newton (`g2o-gn`) or Levenberg–Marquardt "
            "(`g2o-lm`), built from the same gtsam graph and initial values (not timed, before the peak "
            "is reset); the prior's pose "
            "is a fixed vertex; Pose3 information converted to g2o's (t, q_vec) error, Ω_g2o = MᵀΩM; stops "
            f"on relative chi2 decrease < {peers.RELATIVE_TOL:g} (g2o's `SparseOptimizerTerminateAction`) "
            f"or {peers.MAX_ITERATIONS} iterations; timed: `initialize_optimization()` + `optimize()`; "
            "final error: our `graph.error` at g2o's estimates"]


LEGEND = ("*rel. diff vs LM*: |e − e_LM| / e_LM of the final error, ✓ when ≤ 1e-6; *seconds*: optimizer "
          "construction + optimize(), problem loading (and building g2o's graph) excluded; *÷ GTSAM LM*: seconds / "
          "GTSAM LM's seconds (for ours: the key figure ours / GTSAM-LM); *÷ ours*: that solver's seconds / ours "
          "(ours-direct, ours-schwarz, GTSAM's iterative solvers and g2o; above 1: ours is faster); *peak MiB*: "
          "the child's peak RSS; *live MiB*: the most heap in use during the solve (glibc's `mallinfo2`, sampled "
          "every 50 ms: the peak RSS less the heap's free pieces, pages faulted in ahead and what lies outside the "
          "heap); *Δ MiB*: the peak RSS during the solve minus the RSS right after loading the "
          "problem (the solver's own memory); *stack*: the "
          "child's stack limit.")


def markdown(report: dict) -> str:
    """The header, the main table (one group of rows per case) and our time split."""
    rows, poses = report["runs"], {c["name"]: c["poses"] for c in report["cases"]}
    head = ["case", "poses", "solver", "status", "final error", "rel. diff vs LM", "its",
            "seconds", "÷ GTSAM LM", "÷ ours", "peak MiB", "live MiB", "Δ MiB", "stack"]
    out = _header(report) + _table(head, [_main_row(r, poses[r["case"]]) for r in rows]) + ["", LEGEND]
    repeated = [r for r in rows if r.get("seconds_runs")]
    if repeated:
        out += ["", f"Each row is the median of {repeated[0]['repeats']} runs, solvers interleaved; every run's "
                    "seconds in the order run:", ""]
        out += [f"- {r['case']} {r['solver']}: " + ", ".join(_f(t, ".3f") for t in r["seconds_runs"])
                for r in repeated]
    ours = [r for r in rows if r["solver"] in OURS and r["status"] == "ok"]
    if ours:
        head = ["case", "solver", "its", "solves", "linearize", "export", "setup", "CG", "update", "ms / it",
                "total s", "CG / solve", "subdomains", "coarse", "linear solver"]
        out += ["", "## Our time split per nonlinear iteration (ms)", ""] + _table(head, [_split_row(r) for r in ours])
        out += [""] + [f"- {r['case']}: auto chose {r['linear_solver']['used']} ({r['linear_solver']['reason']})"
                       for r in ours if r["solver"] == "ours" and r.get("linear_solver", {}).get("reason")]
    pairs = report.get("direct_vs_schwarz") or direct_vs_schwarz(rows)
    if pairs:
        head = ["case", "direct s", "schwarz s", "schwarz ÷ direct", "peak ÷", "live ÷", "Δ ÷", "CG / solve",
                "subdomains", "coarse", "auto chose", "auto s", "auto picked the faster"]
        out += ["", f"## Direct vs Schwarz (ours-direct vs ours-schwarz = {OURS['ours-schwarz']['preconditioner']})",
                ""] + _table(head, [_pair_row(p) for p in pairs])
        out += ["", PAIR_LEGEND]
    return "\n".join(out) + "\n"


PAIR_LEGEND = ("*schwarz ÷ direct*: ours-schwarz's seconds / ours-direct's (below 1: Schwarz is faster); *peak ÷*, "
               "*live ÷* and *Δ ÷*: the same for the child's peak RSS, for the most heap in use and for the solver's "
               "own memory (live MiB and Δ MiB above); "
               "*auto chose*: the linear solver our "
               "default (`ours`, preconditioner auto) picked, its reason in the bullets above; *auto picked the "
               "faster*: whether that is the faster of direct and Schwarz in this run.")


def _pair_row(p: dict) -> list[str]:
    yes_no = {True: "yes", False: "no", None: "–"}[p.get("auto_picked_faster")]
    direct = "does not fit" if p.get("direct_seconds") is None else _f(p.get("direct_seconds"), ".3f")
    return [p["case"], direct, _f(p.get("schwarz_seconds"), ".3f"),
            _f(p.get("schwarz_over_direct"), ".2f"), _f(p.get("peak_schwarz_over_direct"), ".2f"),
            _f(p.get("live_schwarz_over_direct"), ".2f"), _f(p.get("delta_schwarz_over_direct"), ".2f"),
            _f(p.get("schwarz_cg_mean"), ".1f"),
            _count(p.get("schwarz_subdomains")), _count(p.get("schwarz_coarse_size")),
            p.get("auto_chose") or "–", _f(p.get("auto_seconds"), ".3f"), yes_no]


# -- the command ---------------------------------------------------------------------------------
def _version(name: str) -> str:
    try:
        return importlib.metadata.version(name)
    except importlib.metadata.PackageNotFoundError:
        return "?"


def _proc_field(path: str, key: str) -> str:
    try:
        with open(path) as f:
            return next((l.split(":", 1)[1].strip() for l in f if l.startswith(key)), "?")
    except OSError:
        return "?"


def machine() -> dict:
    mem = _proc_field("/proc/meminfo", "MemTotal").split()
    return {"cpu_count": os.cpu_count(), "cpu": _proc_field("/proc/cpuinfo", "model name"),
            "memory_gib": round(int(mem[0]) / 2**20, 1) if mem and mem[0].isdigit() else None,
            "platform": platform.platform(), "python": platform.python_version(), "gtsam": _version("gtsam"),
            "numpy": _version("numpy"), "scipy": _version("scipy"), "gtsam_schwarz": _version("gtsam-schwarz"),
            "sparse_backend": _sparse_backend(), "openmp_thread_limit": _openmp_limit(), "g2opy": peers.g2o_version(),
            "first_touch_ms_per_mib": first_touch_ms_per_mib()}


def first_touch_ms_per_mib(mib: int = 64) -> float:
    """Milliseconds per MiB to write fresh memory once (page faults and zeroing; in a virtual machine
    also the host backing the page): 0.1-0.3 on this project's machines at best, 1-10 when the host
    has taken the pages back. Every solver pays it for the memory it allocates (Δ MiB), so it scales the
    rows. A lower bound of what the children meet: the guest hands freed pages back to the host a few
    seconds after they are freed (free page reporting), so this small probe mostly gets pages freed
    moments before, while a child, which loads its case for seconds first, gets pages taken back."""
    t = time.perf_counter()
    a = np.ones(mib * 2**17)  # mib MiB of float64, written once
    seconds = time.perf_counter() - t
    del a
    return round(1e3 * seconds / mib, 3)


def _openmp_limit() -> int | None:
    """OpenMP's thread limit in our processes (CHOLMOD's supernodal regions; None without libgomp)."""
    from ..solvers.openmp import limit_threads

    return limit_threads()


def _sparse_backend() -> str:
    """Which sparse Cholesky our local solves use (CHOLMOD when scikit-sparse is installed)."""
    from ..solvers import SPARSE_BACKEND

    return SPARSE_BACKEND + (f" (scikit-sparse {_version('scikit-sparse')})" if SPARSE_BACKEND == "cholmod" else "")


def _parse_value(text: str):
    """int, float, true/false, none, else the string."""
    low = text.lower()
    if low in ("none", "null"):
        return None
    if low in ("true", "false"):
        return low == "true"
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            pass
    return text


def parse_params(items: list[str]) -> dict:
    """``key=value`` overrides of SchwarzParams, validated by constructing the params."""
    from .commands import UsageError
    from ..nonlinear import SchwarzParams

    names = [f.name for f in dataclasses.fields(SchwarzParams) if f.name != "iteration_hook"]
    overrides = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or key.strip() not in names:
            raise UsageError(f"--param {item!r}: expected KEY=VALUE with KEY one of {', '.join(names)}")
        overrides[key.strip()] = _parse_value(value.strip())
    try:
        SchwarzParams(**{**BASE_PARAMS, **overrides})
    except (ValueError, TypeError) as exc:
        raise UsageError(f"--param: {exc}") from None
    return overrides


def _select(kind: str, text: str | None, valid: list[str], where: str = "") -> list[str]:
    """The names of a comma list, in order, each checked against ``valid``."""
    from .commands import UsageError

    if text is None:
        return list(valid)
    names = [n.strip() for n in text.split(",") if n.strip()]
    bad = [n for n in names if n not in valid]
    if bad or not names:
        raise UsageError(f"--{kind} {text!r}: unknown {kind[:-1]} {bad[0] if bad else '(empty)'!r}{where}; "
                         f"valid: {', '.join(valid)}")
    return list(dict.fromkeys(names))


def _check_inputs(cases: list[Case], datasets: pathlib.Path, out: str | None) -> None:
    from .commands import UsageError

    missing = [c.file for c in cases if c.file and not (datasets / c.file).is_file()]
    if missing:
        raise UsageError(f"dataset {datasets / missing[0]} not found (use --datasets DIR)")
    if out and pathlib.Path(out).is_dir():
        raise UsageError(f"--out {out}: is a directory, expected a Markdown file name")
    parent = next((p for p in pathlib.Path(out or ".").resolve().parents if p.exists()), None) if out else None
    if parent is not None and not os.access(parent, os.W_OK):
        raise UsageError(f"--out {out}: {parent} is not writable")


def _command(args, overrides: dict) -> str:
    parts = ["gtsam-schwarz", "bench", "--size", args.size]
    for flag, value in (("--cases", args.cases), ("--solvers", args.solvers), ("--datasets", args.datasets)):
        if value is not None:
            parts += [flag, str(value)]
    if args.timeout != 600:
        parts += ["--timeout", f"{args.timeout:g}"]
    if getattr(args, "repeat", 1) != 1:
        parts += ["--repeat", str(args.repeat)]
    for key, value in overrides.items():
        parts += ["--param", f"{key}={value}"]
    return " ".join(shlex.quote(p) for p in parts)


def warm_kernels() -> None:
    """Compile numba's kernels of our solvers (the factor form's products, the block factors) for
    Pose2 and Pose3 into its on-disk cache."""
    from ..linearization import factor_form
    from ..solvers import block_cholesky

    factor_form.warm_up((3, 6))
    for d in (3, 6):
        block_cholesky.warm_up(d, block_cholesky.PRECISION or np.float32)


def compile_kernels(timeout: float = 600) -> float | None:
    """:func:`warm_kernels` in a child before the timed children: the first run after an install
    compiles them (~10 s), every later one loads them from the cache (~1 s, timed as part of the solve,
    as it is in every use). Its seconds; None where numba is missing or the child failed."""
    from ..util.compiled import AVAILABLE

    if not AVAILABLE:
        return None
    start = time.perf_counter()
    code = "from gtsam_schwarz.apps.bench import warm_kernels; warm_kernels()"
    done = subprocess.run([sys.executable, "-c", code], stdin=subprocess.DEVNULL, capture_output=True,
                          timeout=timeout, env=_child_env())
    return time.perf_counter() - start if done.returncode == 0 else None


def benchmark(cases: list[Case], solvers: list[str], overrides: dict, datasets: pathlib.Path, timeout: float,
              progress=None, repeat: int = 1) -> list[dict]:
    """Every (case, solver) in its own child, ``repeat`` times per case with the solvers' order
    rotated each round (interleaved: a slow spell of the machine hits every solver); one row per
    (case, solver): its median run (see :func:`median_run`). Comparisons added per case."""
    jobs = [(c, solvers[r % len(solvers):] + solvers[:r % len(solvers)]) for c in cases for r in range(repeat)]
    jobs = [(c, s) for c, order in jobs for s in order]
    large = {c.name for c in CASES["large"]}   # the cases whose solves take them (from 4M entries of H)
    if any(s.startswith("ours") for s in solvers) and any(c.name in large for c in cases):
        seconds = compile_kernels()
        if progress and seconds is not None:
            progress(f"numba's kernels compiled or found in its cache, untimed: {seconds:.2f} s")
    runs: dict[tuple[str, str], list[dict]] = {}
    for i, (case, solver) in enumerate(jobs, 1):
        if progress:
            progress(f"[{i}/{len(jobs)}] {case.name} {solver} …")
        row = run_solver(case, solver, overrides, datasets, timeout)
        runs.setdefault((case.name, solver), []).append(row)
        if progress:
            seconds = row.get("seconds")
            progress(f"        {row['status']}" + (f", {seconds:.2f} s" if seconds is not None else ""))
    rows = [median_run(runs[c.name, s]) for c in cases for s in solvers]
    add_comparisons(rows)
    return rows


def median_run(runs: list[dict]) -> dict:
    """The run of median time (the lower middle one of an even count) when all succeeded, else the
    first that did not; with more than one run, every run's seconds in ``seconds_runs``."""
    failed = [r for r in runs if r["status"] != "ok" or r.get("seconds") is None]
    row = failed[0] if failed else sorted(runs, key=lambda r: r["seconds"])[(len(runs) - 1) // 2]
    if len(runs) > 1:
        row = {**row, "seconds_runs": [r.get("seconds") for r in runs], "repeats": len(runs)}
    return row


def _report_head(args, overrides: dict, solvers: list[str]) -> dict:
    """What the report says about the run itself: command, date, machine, parameters."""
    from ..nonlinear import SchwarzParams

    full = dataclasses.asdict(SchwarzParams(**{**BASE_PARAMS, **overrides}))
    full.pop("iteration_hook", None)
    return {"command": _command(args, overrides),
            "date": datetime.datetime.now().astimezone().isoformat(timespec="seconds"),
            "machine": machine(), "size": args.size, "timeout": args.timeout, "tolerance": TOLERANCE,
            "params": {**BASE_PARAMS, **overrides}, "params_full": full, "solvers": solvers}


def run_bench(args) -> int:
    from ..io.jsonout import json_safe
    from ..io import atomic_write

    valid = [c.name for c in CASES[args.size]]
    cases = [ALL_CASES[n] for n in _select("cases", args.cases, valid, f" for --size {args.size}")]
    solvers = (_select("solvers", args.solvers, list(KNOWN_SOLVERS)) if args.solvers is not None
               else list(SOLVERS))
    overrides = parse_params(args.param)
    datasets = pathlib.Path(args.datasets) if args.datasets else default_datasets_dir()
    _check_inputs(cases, datasets, args.out)
    progress = (lambda msg: print(msg, file=sys.stderr, flush=True)) if sys.stderr.isatty() else None
    report = _report_head(args, overrides, solvers)
    rows = benchmark(cases, solvers, overrides, datasets.resolve(), args.timeout, progress, args.repeat)
    report["cases"] = [{"name": c.name, "description": c.description, "poses": _case_poses(c, rows)} for c in cases]
    report["runs"] = rows
    report["direct_vs_schwarz"] = direct_vs_schwarz(rows)
    text = markdown(report)
    if args.out:
        atomic_write(args.out, text, parents=True)
    if args.json:
        print(json.dumps(json_safe(report), allow_nan=False))
    else:
        print(text, end="")
    if args.out:
        print(f"wrote {args.out}", file=sys.stderr)
    return 0


def add_bench(sub) -> None:
    from .commands import positive_float, positive_int

    p = sub.add_parser("bench", help="ours against GTSAM's LM (Cholesky, PCG, subgraph), one child process per run",
                       description="End-to-end solves of our default (LM, chordal start, automatic linear "
                                   "solver), of the same forced to direct factorization and to rgdsw-linear Schwarz, "
                                   "against GTSAM's LevenbergMarquardtOptimizer with Cholesky, PCG "
                                   "(block-Jacobi) and SubgraphSolver, and g2o; every run in its own child process "
                                   "(own peak memory; a crash or timeout is a row of the table).")
    p.add_argument("--size", choices=SIZES, default="small",
                   help="tiny: a few seconds; small: model problems, M3500, city10000, sphere2500, a 100x100 "
                        "lawnmower survey and an 8x24x24 3D survey; large: model problems with 262k and 1M poses, "
                        "lawnmowers 600x600 and 1000x1000, 3D surveys 32x32x32, 45x45x45 and 60x60x60 (default small)")
    p.add_argument("--cases", help="comma list of case names of the size (default: all)")
    p.add_argument("--solvers", help=f"comma list from {','.join(KNOWN_SOLVERS)} (default: all; "
                                      f"{','.join(PEERS)} only when g2opy is installed: the [peers] extra); "
                                      "ours: preconditioner auto, ours-direct: direct, ours-schwarz: rgdsw-linear")
    p.add_argument("--param", action="append", default=[], metavar="KEY=VALUE",
                   help="a SchwarzParams override for ours (repeatable), e.g. --param subdomain_size=1000")
    p.add_argument("--timeout", type=positive_float, default=600.0, metavar="SECONDS",
                   help="per-run wall-clock limit; the child's process group is killed (default 600)")
    p.add_argument("--repeat", type=positive_int, default=1, metavar="N",
                   help="run every (case, solver) N times, solvers interleaved (their order rotated each round); "
                        "each row is its median run and lists every run's seconds (default 1)")
    p.add_argument("--datasets", default=None, metavar="DIR", help="folder of the datasets (../shared/datasets)")
    p.add_argument("--out", metavar="FILE.md", help="also write the Markdown report to this file (atomically)")
    p.add_argument("--json", action="store_true", help="print exactly one JSON object on stdout")
    p.set_defaults(run=run_bench)


if __name__ == "__main__":
    sys.exit(worker_main())
