"""Pictures for ``solve`` and ``demo``: trajectories coloured by subdomain, convergence histories."""

from __future__ import annotations

import pathlib

import gtsam
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from .plots import save  # noqa: E402


def _xy(values: gtsam.Values) -> np.ndarray:
    P2 = gtsam.utilities.extractPose2(values)
    if len(P2):
        return P2[:, :2]
    P3 = gtsam.utilities.extractPose3(values)
    return P3[:, 9:11]


def _vertex_colors(decomposition, n: int) -> np.ndarray:
    """Subdomain of each vertex (nonoverlapping; the first one for interface poses)."""
    sub = np.zeros(n, dtype=np.int64)
    if decomposition is not None:
        S = decomposition.vertex_subdomains
        has = np.diff(S.indptr) > 0
        sub[has] = S.indices[S.indptr[:-1][has]]
    return sub


def draw_trajectory(ax, initial, optimized, decomposition=None, truth=None) -> None:
    xy0, xy = _xy(initial), _xy(optimized)
    ax.plot(xy0[:, 0], xy0[:, 1], color="0.6", lw=0.8, label="initial guess")
    if truth is not None:
        xt = _xy(truth)
        ax.plot(xt[:, 0], xt[:, 1], color="k", lw=1.0, ls="--", label="ground truth")
    sub = _vertex_colors(decomposition, len(xy))
    ax.scatter(xy[:, 0], xy[:, 1], c=sub % 20, cmap="tab20", s=4, label="optimized (colour = subdomain)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.legend(loc="best", fontsize=7)


def draw_convergence(ax_err, ax_cg, histories: dict) -> None:
    """Error per nonlinear iteration and CG residual histories for each named run."""
    for i, (name, history) in enumerate(histories.items()):
        color = f"C{i}"
        errs = [h["error_before"] for h in history[:1]] + [h["error"] for h in history if h["accepted"]]
        ax_err.semilogy(range(len(errs)), errs, "o-", color=color, label=name)
        for j, h in enumerate(history):
            if h["cg_residuals"]:
                ax_cg.semilogy(h["cg_residuals"], color=color, alpha=0.9 if j == 0 else 0.4,
                               label=name if j == 0 else None)
    ax_err.set_xlabel("nonlinear iteration")
    ax_err.set_ylabel("error ½‖r‖²")
    ax_err.legend(fontsize=7)
    ax_cg.set_xlabel("CG iteration")
    ax_cg.set_ylabel("‖r_k‖ / ‖b‖")
    ax_cg.legend(fontsize=7)


def solve_figure(path, loaded, row) -> str:
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.5))
    draw_trajectory(axes[0], loaded.initial, row["values"], row.get("decomposition"))
    axes[0].set_title(f"{pathlib.Path(loaded.path).name}: {row['subdomains']} subdomains")
    draw_convergence(axes[1], axes[2], {row["solver"]: row["history"]})
    axes[1].set_title("error per iteration")
    axes[2].set_title("CG residual histories")
    return save(fig, path)


def trajectory_figure(path, problem, optimized, subdomains: int | None = None) -> str:
    from ..dd import GraphStructure, segments
    from ..linearization.gtsam_export import KeyMap, export_linear_system

    km = KeyMap.from_graph(problem.graph, problem.initial)
    H = export_linear_system(problem.graph.linearize(problem.initial), km).H
    dec = segments(GraphStructure.from_matrix(H, km.offsets), subdomains or 1)
    fig, ax = plt.subplots(figsize=(6, 6))
    draw_trajectory(ax, problem.initial, optimized, dec, problem.ground_truth)
    ax.set_title(f"{problem.loops} loops × {problem.points_per_side} points per side")
    return save(fig, path)


def convergence_figure(path, problem, subdomains: int, names=("none", "block-jacobi", "one-level", "gdsw")) -> str:
    from ..nonlinear import SchwarzOptimizer, SchwarzParams

    histories = {}
    for name in names:
        opt = SchwarzOptimizer(problem.graph, problem.initial,
                               SchwarzParams(preconditioner=name, subdomains=subdomains))
        opt.optimize()
        histories[name] = opt.history
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    draw_convergence(axes[0], axes[1], histories)
    axes[0].set_title("Gauss–Newton error")
    axes[1].set_title("CG residuals, every Gauss–Newton step")
    return save(fig, path)
