"""Pictures for ``solve`` and ``demo``: trajectories coloured by subdomain, convergence histories."""

from __future__ import annotations

import pathlib

import gtsam
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.ticker import MaxNLocator  # noqa: E402

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


def subdomain_colors(n: int) -> np.ndarray:
    """``n`` distinct RGBA colours, neighbours far apart: tab10 / tab20 while they suffice, then hues
    spaced by the golden ratio (never repeating) with alternating lightness."""
    if n <= 10:
        return np.asarray(plt.get_cmap("tab10")(np.arange(n)))
    if n <= 20:  # tab20's dark colours first, then the light ones: neighbours differ in hue
        return np.asarray(plt.get_cmap("tab20")(np.r_[np.arange(0, 20, 2), np.arange(1, 20, 2)][:n]))
    from matplotlib.colors import hsv_to_rgb

    i = np.arange(n)
    hsv = np.column_stack([(i * 0.6180339887498949) % 1.0, 0.55 + 0.35 * (i % 2), 0.95 - 0.3 * ((i // 2) % 2)])
    return np.column_stack([hsv_to_rgb(hsv), np.ones(n)])


def draw_trajectory(ax, initial, optimized, decomposition=None, truth=None) -> None:
    xy0, xy = _xy(initial), _xy(optimized)
    ax.plot(xy0[:, 0], xy0[:, 1], color="0.6", lw=0.8, label="initial guess")
    if truth is not None:  # gtsam.Values or a trajectory.Trajectory
        from .trajectory import Trajectory

        xt = truth.t[:, :2] if isinstance(truth, Trajectory) else _xy(truth)
        ax.plot(xt[:, 0], xt[:, 1], color="k", lw=1.0, ls="--", label="ground truth")
    sub = _vertex_colors(decomposition, len(xy))
    count = int(sub.max()) + 1 if len(sub) else 1
    colors = subdomain_colors(count)
    label = f"optimized (colour = subdomain, {count})" if decomposition is not None else "optimized"
    ax.scatter(xy[:, 0], xy[:, 1], c=colors[sub], s=4, label=label)
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.legend(loc="best", fontsize=7)


MARKERS = ("o", "s", "^", "D", "v", "P", "X", "*", "<", ">")
LINESTYLES = ("-", "--", "-.", ":")


def _same_curve(a, b) -> bool:
    return len(a) == len(b) and np.allclose(a, b, rtol=1e-6, atol=0.0)


def draw_convergence(ax_err, ax_cg, histories: dict) -> None:
    """Error per nonlinear iteration and CG residual histories for each named run.

    Every run has its own colour, marker and line style; runs whose error histories coincide (the
    preconditioner changes CG, not the Gauss-Newton steps) share one error curve and one legend entry."""
    groups: list[tuple[list, list[str], int]] = []  # (errors, names, style index of the first)
    for i, (name, history) in enumerate(histories.items()):
        errs = [h["error_before"] for h in history[:1]] + [h["error"] for h in history if h["accepted"]]
        same = next((g for g in groups if _same_curve(g[0], errs)), None)
        if same is not None:
            same[1].append(name)
        else:
            groups.append((errs, [name], i))
    for errs, names, i in groups:
        label = names[0] if len(names) == 1 else f"{', '.join(names)} (same curve)"
        ax_err.semilogy(range(len(errs)), errs, color=f"C{i}", marker=MARKERS[i % len(MARKERS)],
                        ls=LINESTYLES[i % len(LINESTYLES)], label=label)
    for i, (name, history) in enumerate(histories.items()):
        first = True
        for h in history:
            if h["cg_residuals"]:
                r = h["cg_residuals"]
                ax_cg.semilogy(r, color=f"C{i}", ls=LINESTYLES[i % len(LINESTYLES)], alpha=0.9 if first else 0.4,
                               marker=MARKERS[i % len(MARKERS)], markevery=max(1, len(r) // 8), ms=4,
                               label=name if first else None)
                first = False
    ax_err.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax_err.set_xlabel("nonlinear iteration")
    ax_err.set_ylabel("error ½‖r‖²")
    ax_err.legend(fontsize=7)
    ax_cg.set_xlabel("CG iteration")
    ax_cg.set_ylabel("‖r_k‖ / ‖b‖")
    if ax_cg.lines:
        ax_cg.legend(fontsize=7)


def solve_figure(path, loaded, row, truth=None) -> str:
    """``solve --plot``: trajectory by subdomain, error and CG residuals; the format follows the
    extension (png, pdf, svg), and the folder must exist."""
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.5))
    draw_trajectory(axes[0], loaded.initial, row["values"], row.get("decomposition"), truth)
    axes[0].set_title(f"{pathlib.Path(loaded.path).name}: {row['subdomains']} subdomains")
    draw_convergence(axes[1], axes[2], {row["solver"]: row["history"]})
    axes[1].set_title("error per iteration")
    axes[2].set_title("CG residual histories")
    return save(fig, path, parents=False)


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


def convergence_figure(path, problem, subdomains: int, names=("none", "block-jacobi", "one-level", "gdsw"),
                       progress=None) -> str:
    """Error and CG residuals of one solve per preconditioner (``progress``: a :class:`Progress`)."""
    from ..nonlinear import SchwarzOptimizer, SchwarzParams

    histories = {}
    for name in names:
        if progress is not None:
            progress.start(f"convergence plot: {name}")
        opt = SchwarzOptimizer(problem.graph, problem.initial,
                               SchwarzParams(method="gn", preconditioner=name, subdomains=subdomains))
        opt.optimize()
        histories[name] = opt.history
        if progress is not None:
            progress.done()
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    draw_convergence(axes[0], axes[1], histories)
    axes[0].set_title("Gauss–Newton error")
    axes[1].set_title("CG residuals, every Gauss–Newton step")
    return save(fig, path)
