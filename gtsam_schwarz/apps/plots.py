"""The paper's figures: fig:scalability, fig:hat, fig:sparsity and fig:optimized_results (Agg PNGs)."""

from __future__ import annotations

import io
import os

import gtsam
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.patches import Rectangle  # noqa: E402
from matplotlib.ticker import ScalarFormatter  # noqa: E402

from ..dd import GraphStructure, decompose  # noqa: E402
from ..linearization.gtsam_export import KeyMap, export_linear_system  # noqa: E402
from ..schwarz import make_preconditioner  # noqa: E402
from ..io import atomic_write  # noqa: E402

COLORS = {"none": "tab:gray", "one-level": "tab:orange", "gdsw-norot": "tab:green", "gdsw": "tab:blue"}
LABELS = {"none": "no preconditioner", "one-level": "one-level Schwarz", "gdsw-norot": "GDSW without rotation",
          "gdsw": "GDSW"}


PLOT_FORMATS = ("png", "pdf", "svg")  # chosen by the file's extension


def plot_format(path) -> str:
    """The image format of ``path`` from its extension (png, pdf or svg); ValueError for any other."""
    suffix = os.path.splitext(os.fspath(path))[1].lower().lstrip(".")
    if suffix not in PLOT_FORMATS:
        raise ValueError(f"{os.fspath(path)}: unsupported plot format "
                         f"{('.' + suffix) if suffix else '(no extension)'}; use .png, .pdf or .svg")
    return suffix


def save(fig, path, *, parents: bool = True) -> str:
    """Render into memory in the format of ``path``'s extension (:func:`plot_format`), then write
    atomically (temp file beside ``path`` + os.replace); ``parents=False``: no folder is created."""
    fmt = plot_format(path)
    buf = io.BytesIO()
    try:
        fig.savefig(buf, format=fmt, dpi=130, bbox_inches="tight")
    finally:
        plt.close(fig)
    atomic_write(path, buf.getvalue(), parents=parents)
    return str(path)


def _poses(values: gtsam.Values) -> np.ndarray:
    return np.asarray(gtsam.utilities.extractPose2(values))


def _system(problem, values):
    keymap = KeyMap.from_graph(problem.graph, values)
    system = export_linear_system(problem.graph.linearize(values), keymap)
    structure = GraphStructure.from_matrix(system.H, keymap.offsets)
    return keymap, system, structure


# -- fig:scalability ------------------------------------------------------------------------------
def _plain_log_axes(ax):
    ax.set_xscale("log", base=2)
    ax.set_yscale("log")
    for axis in (ax.xaxis, ax.yaxis):
        axis.set_major_formatter(ScalarFormatter())
    ax.grid(True, which="both", alpha=0.3)


def scalability_figure(path, model: list[dict], paper_weak, paper_null, pps: int = 16) -> str:
    """CG iterations per GN step vs loops (log-log): ours to 1024 loops next to the paper's to 128."""
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(12, 4.8))
    paper = {"none": {int(r[0]): r[2] for r in paper_weak}, "one-level": {int(r[0]): r[4] for r in paper_weak},
             "gdsw": {int(r[0]): r[6] for r in paper_weak}, "gdsw-norot": {int(r[0]): r[2] for r in paper_null}}
    for pc in ("none", "one-level", "gdsw-norot", "gdsw"):
        rows = sorted((r for r in model if r["preconditioner"] == pc and r["overlap"] == 1
                       and r["points_per_side"] == pps and r["cg_mean"] is not None), key=lambda r: r["loops"])
        if rows:
            x = [r["loops"] for r in rows]
            y = [r["cg_mean"] for r in rows]
            ax.plot(x, y, "-o", color=COLORS[pc], label=f"{LABELS[pc]} (ours)")
            cap = [(r["loops"], r["cg_mean"]) for r in rows if r["capped"]]
            if cap:
                ax.plot(*zip(*cap), "o", mfc="white", color=COLORS[pc], ms=9, label=f"{LABELS[pc]}: capped")
        px = sorted(paper[pc])
        ax.plot(px, [paper[pc][k] for k in px], "--x", color=COLORS[pc], alpha=0.7, label=f"{LABELS[pc]} (paper)")
    ax.set(xlabel="loops = subdomains", ylabel="average CG iterations per GN step",
           title=f"Weak scaling, {pps} points per side, overlap 1")
    _plain_log_axes(ax)
    ax.legend(fontsize=7, ncol=2)
    styles = {1: "-o", 2: "-s", 3: "-^"}
    for pc in ("one-level", "gdsw"):
        for ov in (1, 2, 3):
            rows = sorted((r for r in model if r["preconditioner"] == pc and r["overlap"] == ov
                           and r["points_per_side"] == pps and r["cg_mean"] is not None), key=lambda r: r["loops"])
            if rows:
                ax2.plot([r["loops"] for r in rows], [r["cg_mean"] for r in rows], styles[ov], color=COLORS[pc],
                         alpha=1.0 - 0.25 * (ov - 1), label=f"{LABELS[pc]}, overlap {ov}")
                cap = [(r["loops"], r["cg_mean"]) for r in rows if r["capped"]]
                if cap:
                    ax2.plot(*zip(*cap), "o", mfc="white", color=COLORS[pc], ms=10,
                             label=f"{LABELS[pc]}, overlap {ov}: capped")
    ax2.set(xlabel="loops = subdomains", ylabel="average CG iterations per GN step",
            title="Overlap 1, 2, 3 (beyond the paper)")
    _plain_log_axes(ax2)
    ax2.legend(fontsize=7)
    return save(fig, path)


# -- fig:hat --------------------------------------------------------------------------------------
def coarse_basis(problem, overlap: int = 1):
    """GDSW coarse basis (unit modes, paper Sec. 3.3) at the ground truth, in world coordinates.

    Returns (poses, interface vertices, B) with B[j, d] the (n_poses, 3) world-frame values
    (x, y, θ) of interface vertex j's mode d; GTSAM's body-frame translations are rotated by each
    pose's heading so the modes read as displacements of the trajectory.
    """
    keymap, system, structure = _system(problem, problem.ground_truth)
    dec = decompose(structure, problem.loops, "segments", overlap)
    M = make_preconditioner("gdsw", system.H, dec, keymap.translation_mask(), None, "vertices")
    Phi = M.coarse_space.Phi.tocsc()
    gamma = M.interface.vertices
    poses = _poses(problem.ground_truth)
    c, s = np.cos(poses[:, 2]), np.sin(poses[:, 2])
    B = np.zeros((len(gamma), 3, len(poses), 3))
    rows = (keymap.offsets[gamma][:, None] + np.arange(3)).ravel()
    hit = Phi.tocsr()[rows]  # an interface dof's row holds exactly its own mode's 1
    hit.sort_indices()
    if not np.all(np.diff(hit.indptr) == 1):
        raise RuntimeError("coarse basis: expected one unit entry per interface dof")
    cols = hit.indices
    dense = Phi[:, cols].toarray().reshape(len(poses), 3, len(gamma), 3)  # pose, dof, vertex, mode
    body = np.moveaxis(dense, (2, 3), (0, 1))  # vertex, mode, pose, dof
    B[..., 0] = c * body[..., 0] - s * body[..., 1]
    B[..., 1] = s * body[..., 0] + c * body[..., 1]
    B[..., 2] = body[..., 2]
    return poses, gamma, B


def hat_figure(path, problem) -> str:
    """Each interface pose's x, y and θ coarse functions along the trajectory vs the hat functions."""
    poses, gamma, B = coarse_basis(problem)
    n = len(poses)
    t = np.arange(n)
    knots = np.r_[0, gamma, n - 1]
    fig, axes = plt.subplots(3, 1, figsize=(10, 7.5), sharex=True)
    names = ("x translation mode: world x component", "y translation mode: world y component",
             "rotation mode: θ component")
    cmap = plt.get_cmap("tab10")
    for d, ax in enumerate(axes):
        for j, v in enumerate(gamma):
            ax.plot(t, B[j, d, :, d], color=cmap(j % 10), lw=1.8, label=f"GDSW, interface pose {v}" if d == 0 else None)
            # the hat lives between neighbouring interface poses; the end loops have no interface there
            lo, hi = knots[j], knots[j + 2]
            sl = slice(lo if j > 0 else v, (hi if j + 1 < len(gamma) else v) + 1)
            hat = np.interp(t[sl], [lo, v, hi], [0.0, 1.0, 0.0])
            ax.plot(t[sl], hat, "--", color="black", lw=0.9, label="hat function" if (d == 0 and j == 0) else None)
        ax.set_ylabel("value")
        ax.set_title(names[d], fontsize=9)
        ax.grid(alpha=0.3)
        for k in range(1, problem.loops * 4):
            ax.axvline(k * problem.points_per_side, color="0.85", lw=0.6, zorder=0)
    axes[-1].set_xlabel("pose index along the trajectory (thin lines: corners of the square)")
    fig.legend(loc="lower center", ncol=len(gamma) + 1, fontsize=8, bbox_to_anchor=(0.5, -0.02))
    fig.tight_layout(rect=(0, 0.04, 1, 0.93))
    fig.suptitle(f"GDSW coarse basis functions vs hat functions ({problem.loops} loops x "
                 f"{problem.points_per_side} points per side, one subdomain per loop, overlap 1)\n"
                 "first loop: pose 0 is held by the prior and tied to the first interface pose by its loop "
                 "closure; last loop: free end, so the function stays 1", fontsize=9)
    return save(fig, path)


# -- fig:sparsity ---------------------------------------------------------------------------------
def sparsity_figure(path, problem, overlap: int = 1) -> str:
    """Sparsity of H with the loop-closure blocks in red and the overlapping subdomains shaded."""
    keymap, system, structure = _system(problem, problem.initial)
    H = system.H.tocoo()
    owner = keymap.dof_to_variable()
    u, v = owner[H.row], owner[H.col]
    loop = np.abs(u - v) > 1
    n = H.shape[0]
    fig, ax = plt.subplots(figsize=(6.5, 6.5))
    dec = decompose(structure, problem.loops, "segments", overlap)
    sets = dec.index_sets(overlapping=True)
    for i in range(sets.count):
        idx = sets.get(i)
        lo, hi = int(idx.min()), int(idx.max()) + 1
        ax.add_patch(Rectangle((lo - 0.5, lo - 0.5), hi - lo, hi - lo, color=plt.get_cmap("tab20")(i % 20),
                               alpha=0.25, lw=0))
    ms = max(0.3, 300.0 / n)
    ax.plot(H.col[~loop], H.row[~loop], "s", ms=ms, color="black", mew=0, label="odometry / diagonal blocks")
    ax.plot(H.col[loop], H.row[loop], "s", ms=max(2 * ms, 2.0), color="red", mew=0, label="loop-closure blocks")
    ax.set_xlim(-0.5, n - 0.5)
    ax.set_ylim(n - 0.5, -0.5)
    ax.set_aspect("equal")
    ax.set_title(f"H, {problem.loops} loops x {problem.points_per_side} points per side: {n} dofs, "
                 f"nnz {H.nnz}\n(shaded: overlapping subdomains, overlap {overlap})", fontsize=9)
    ax.legend(loc="upper right", fontsize=7, markerscale=3)
    return save(fig, path)


# -- fig:optimized_results ------------------------------------------------------------------------
def optimized_figure(path, problem, optimized: gtsam.Values) -> str:
    """Optimized trajectory vs odometry (dead reckoning) vs ground truth."""
    gt, odo, opt = _poses(problem.ground_truth), _poses(problem.initial), _poses(optimized)
    fig, ax = plt.subplots(figsize=(6.5, 6.5))
    ax.plot(odo[:, 0], odo[:, 1], "-", color="tab:blue", lw=0.9, alpha=0.8, label="odometry (dead reckoning)")
    ax.plot(gt[:, 0], gt[:, 1], "-", color="tab:red", lw=2.5, alpha=0.6, label="ground truth")
    ax.plot(opt[:, 0], opt[:, 1], ".-", color="tab:green", lw=0.8, ms=3, label="optimized (GN + GDSW-PCG)")
    L = problem.loops
    ax.plot(opt[::4 * problem.points_per_side, 0], opt[::4 * problem.points_per_side, 1], "k*", ms=7,
            label="loop-closure poses")
    ax.set_aspect("equal")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="best")
    ax.set_title(f"{L} loops x {problem.points_per_side} points per side, σ = {problem.sigma:g}, "
                 f"seed {problem.seed}", fontsize=9)
    return save(fig, path)
