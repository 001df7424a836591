"""Starting points for the nonlinear loop: the given values, or a global initialization.

"chordal": rotations by chordal relaxation, then translations by linear least squares
(``initialization.chordal``), the field's standard start for pose graphs (Carlone et al. 2015);
the anchor is the pose of a prior (kept where it is) or the first pose.
"""

from __future__ import annotations

import numpy as np

from ..initialization.chordal import chordal_initialization
from ..solvers import pattern_cholesky_cost
from ..util.sparse import edge_pattern
from ..util.threads import side_thread
from .linear_solver import CostModel

INITIALIZATIONS = ("file", "chordal")

# The 3D rotation system (3×3 blocks on the pose graph's pattern) by CG with the chordal module's
# two-level Schwarz (aggregates of 16 poses, local frames, no overlap) costs about this many seconds
# per entry of the matrix, solved to 1e-6 (3D surveys of 32 768 and 91 125 poses: 1.0 and 1.1 µs,
# 30-31 iterations; CG_TOL's 1e-4 takes 19: the estimate keeps a margin). Its direct factorization
# is predicted by the linear solver's cost model, which 3×3 blocks run DIRECT_SLOWDOWN× slower than
# (smaller supernodes than H's 6×6 blocks: 16 384, 32 768 and 91 125 poses 1.35 / 4.2 / 24.0 s
# measured, 0.86 / 2.69 / 15.7 predicted).
CG_SECONDS_PER_ENTRY = 1.1e-6
DIRECT_SLOWDOWN = 1.5
CG_MIN_POSES = 4096  # below, the factorization costs too little to be worth its analysis
# 2D: one complex unknown per pose, by CG on aggregates (``chordal._AggregateSchwarz``) to CG_TOL_2D or
# factorized twice (rotations, then translations as x + iy on the same factor). Lawnmower 200x200,
# 300x300, 600x600, 1000x1000: CG 0.19 / 0.45 / 2.1 / 8.5 s (1.0-1.7 µs per entry of the one-unknown
# matrix, CG_SECONDS_PER_ENTRY with a margin), direct 0.28 / 0.75 / 3.7 / 12.5 s, 3.6-3.9× the linear
# solver's cost model of a real factorization of the vertex pattern (complex numbers and two
# factorizations); the 262 145-pose model problem (no fill) 0.17 s direct against 0.9 s CG. Since
# CHOLMOD's OpenMP runs one thread (the cost model's supernodal rates 0.4-0.5x the old ones) the
# direct start at 300x300 measured 0.50-0.66 s against CG's 0.49-0.51 s: 5.2-6.9x the model
DIRECT_SLOWDOWN_2D = 6.0
CG_MIN_POSES_2D = 16384  # below, CG and the factorization take about the same (lawnmower 100x100: 0.05 s)
# 2D graphs with fewer independent cycles per pose are not analysed (the model problems have 0.004,
# the lawnmowers ~1): the analysis (262 145 poses: 80 ms) would repeat the direct start's own, whose
# simplicial factor hands its column counts to the linear solver for free
CYCLES_PER_POSE_2D = 0.25
# a start for the nonlinear loop, not its answer: 3D survey 32x32x32 LM ends at the same error to 1e-10
# relative from starts solved to 1e-4 and 1e-6 (91 125 poses: 19 instead of 31 CG per column, -2.1 s),
# and from 1e-2: the same LM iterations and final error to 3e-11 (32x32x32), 2.3e-8 (45x45x45) and
# 5e-12 (torus3D, forced Schwarz); the start costs 1.13 s instead of 1.56 s at 32x32x32
CG_TOL = 1e-2
# 2D lawnmowers from a start solved to 1e-2 end 1.4e-7 and 1.3e-7 (600x600, 1000x1000) above the exact start's LM
# error; with the rotations solved to 1e-3 below it (1076.122861 and 2993.952033 against 1076.122895 and
# 2993.952050; 15 rotation CG instead of 8 at 360 000 poses), and so with the positions to CG_TOL
# (1076.122858 and 2993.952028; 20 position CG instead of 29, 1.73 against 2.10 s at 360 000 poses)
CG_TOL_2D = 1e-3


def rotation_solver(n: int, i: np.ndarray, j: np.ndarray, d: int) -> tuple[str, str]:
    """"cg" or "direct" for the chordal systems, and why: direct on small or sparse graphs, CG where
    the factor fills in (3×3 blocks in 3D, one complex unknown per pose in 2D). The analysis is the
    vertex pattern's, the same one the automatic linear solver makes of H next (kept: done once)."""
    if n < (CG_MIN_POSES if d == 3 else CG_MIN_POSES_2D):
        return "direct", ""
    if d == 2 and len(i) - n + 1 < CYCLES_PER_POSE_2D * n:
        return "direct", ""   # nearly a tree: little fill, and the factorization brings its own counts
    B = edge_pattern(n, i, j)
    cost = pattern_cholesky_cost(B, np.full(n, d if d == 3 else 1))
    t_direct = (DIRECT_SLOWDOWN if d == 3 else DIRECT_SLOWDOWN_2D) * CostModel().direct(cost)
    t_cg = CG_SECONDS_PER_ENTRY * cost.nnz_A
    choice = "cg" if t_cg < t_direct else "direct"
    return choice, f"rotations {choice}: {t_direct:.3g} s direct vs {t_cg:.3g} s CG predicted"


def prepare_chordal(linearizer, solver: str = "auto"):
    """The pose graph of :func:`chordal_state` and its rotation system's solver choice, whose
    analysis (:func:`rotation_solver`) starts on the side thread: called before the given start is
    read, the analysis (CHOLMOD's ordering, no GIL held; 1M 2D poses 0.7 s) runs beside that reading
    and beside the pose graph's arrays, which it does not need (its edges come first where the
    linearizer gives them alone: ``pose_edges``). Returns (graph, a callable giving (solver, why))."""
    edges = linearizer.pose_edges() if hasattr(linearizer, "pose_edges") else None
    job = _submit_rotation_solver(edges, solver) if edges is not None else None
    graph = linearizer.pose_graph(split_information=True) if hasattr(linearizer, "pose_graph") else None
    if graph is None or graph["between"] is None:
        return graph, lambda: (solver, "")
    if job is None:
        b = graph["between"]
        job = _submit_rotation_solver((graph["n"], np.asarray(b["R"]).shape[1], b["i"], b["j"]), solver)
    return graph, job


def _submit_rotation_solver(edges, solver: str):
    """:func:`rotation_solver` of the pose graph's (n, d, i, j) on the side thread where ``solver``
    asks for a choice, else the fixed answer; a callable giving (solver, why)."""
    n, d, i, j = edges
    if solver == "cg-3d" and d == 3:  # the Gauss-Newton systems go to Schwarz-CG: so do large 3D rotation systems
        chosen = ("cg" if n >= CG_MIN_POSES else "direct", "")
        return lambda: chosen
    if solver not in ("auto", "cg-3d"):
        return lambda: (solver, "")
    return side_thread().submit(rotation_solver, n, np.asarray(i), np.asarray(j), d).result


def chordal_state(linearizer, state, solver: str = "auto", prepared=None):
    """The chordal initialization of a pure pose graph as a new linearizer state (None if the
    linearizer cannot describe its graph as one, e.g. with landmarks). ``solver``: "direct", "cg",
    "auto" (:func:`rotation_solver`) or "cg-3d" (for runs whose linear solver is Schwarz-CG by choice:
    CG for 3D graphs from ``CG_MIN_POSES`` poses without an analysis, 2D as "auto", whose analysis of
    a one-unknown pattern is cheap: 0.16 s at 360 000 poses). The translations go the same way,
    as their scalar Laplacian fills in where the rotation system does (91 125-pose survey: 2.9 s
    direct, 1.2 s CG). ``prepared``: :func:`prepare_chordal`'s result for the same ``solver``."""
    graph, choice = prepared if prepared is not None else prepare_chordal(linearizer, solver)
    if graph is None or graph["between"] is None:
        return None, "not a pure Pose2/Pose3 graph: initialization skipped"
    b, prior = graph["between"], graph["prior"]
    if prior is not None and len(prior["j"]):
        anchor, anchor_pose = int(prior["j"][0]), (prior["R"][0], prior["t"][0])
    else:
        anchor, anchor_pose = 0, None
    d = np.asarray(b["R"]).shape[1]
    solver, why = choice()
    options = dict(overlap=0, tol=CG_TOL if d == 3 else CG_TOL_2D, translation_tol=CG_TOL) if solver == "cg" else {}
    result = chordal_initialization(graph["n"], np.column_stack([b["i"], b["j"]]), b["R"], b["t"], b["information"],
                                    anchor=anchor, anchor_pose=anchor_pose, solver=solver, **options)
    if anchor_pose is None:  # no prior: keep the first pose where the given values have it
        geometry = linearizer.geometry(state)
        if geometry is not None:
            R0, p0 = geometry.rotations[0], geometry.positions[0]
            result.rotations[:] = R0 @ result.rotations
            result.positions[:] = (result.positions @ R0.T) + p0
    new = linearizer.with_poses(state, result.rotations, result.positions)
    info = result.info
    iterations = info.get("rotation_iterations", []) + info.get("translation_iterations", [])
    how = f"CG, {sum(iterations)} iterations" if iterations else "direct"
    return new, f"chordal: {info['seconds']:.2f} s ({how}{'; ' + why if why else ''})"
