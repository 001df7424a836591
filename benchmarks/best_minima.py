"""Every public dataset from the file's guess: our defaults against GTSAM LM (default and 1e-10
tolerances, from the file and from GTSAM's own global initialization), final errors and seconds.

    python benchmarks/best_minima.py [--datasets ../shared/datasets] [--out docs/datasets_minima.md]

Each solver runs in this process, one after the other (2-core machine: the seconds are indicative).
"""

from __future__ import annotations

import argparse
import pathlib
import time
import warnings

import gtsam
import numpy as np

import gtsam_schwarz as gs
from gtsam_schwarz.apps.compare import run_ours
from gtsam_schwarz.io import atomic_write, load_graph

FILES = ["input_INTEL_g2o.g2o", "input_M3500_g2o.g2o", "input_M3500a_g2o.g2o", "MIT.g2o", "city10000.g2o",
         "CSAIL_P_toro.graph", "kitti_00.g2o", "sphere2500.g2o", "torus3D.g2o", "parking-garage.g2o",
         "smallGrid3D.g2o", "tinyGrid3D.g2o"]


def gtsam_lm(graph, initial, tol: float | None = None, diagonal: bool = False):
    params = gtsam.LevenbergMarquardtParams()
    if tol is not None:
        params.setRelativeErrorTol(tol)
        params.setAbsoluteErrorTol(tol)
        params.setMaxIterations(1000)
    if diagonal:
        params.setDiagonalDamping(True)
    t = time.perf_counter()
    try:
        values = gtsam.LevenbergMarquardtOptimizer(graph, initial, params).optimize()
        return graph.error(values), time.perf_counter() - t
    except (RuntimeError, ValueError):
        return float("nan"), time.perf_counter() - t


def gtsam_init(graph, loaded):
    """GTSAM's own global initialization: InitializePose3 (3D) or LAGO (2D); None if it throws."""
    try:
        if loaded.dimension == 3:
            return gtsam.InitializePose3.initialize(graph)
        return gtsam.lago.initialize(graph)
    except (RuntimeError, ValueError):  # lago: "assumes diagonal noise model" on INTEL and MIT
        return None


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--datasets", type=pathlib.Path, default=pathlib.Path("../shared/datasets"))
    ap.add_argument("--out", type=pathlib.Path, default=None)
    args = ap.parse_args(argv)
    warnings.simplefilter("ignore", RuntimeWarning)
    head = ["dataset", "poses", "ours (defaults)", "s", "ours from file", "s", "GTSAM LM", "s",
            "GTSAM LM 1e-10", "s", "from file: ours / GTSAM 1e-10 − 1", "GTSAM LM from GTSAM's init", "s", "best",
            "ours ≤ best·(1+1e-6)"]
    rows = []
    for name in FILES:
        L = load_graph(args.datasets / name)
        ours = run_ours(L.graph, L.initial, gs.SchwarzParams(), L.arrays)
        file = run_ours(L.graph, L.initial, gs.SchwarzParams(initialization="file", max_iterations=1000), L.arrays)
        lm, lm_s = gtsam_lm(L.graph, L.initial)
        strict, strict_s = gtsam_lm(L.graph, L.initial, 1e-10)
        t = time.perf_counter()
        init = gtsam_init(L.graph, L)
        own, own_s = gtsam_lm(L.graph, init, 1e-10) if init is not None else (float("nan"), 0.0)
        own_s += time.perf_counter() - t - own_s if init is not None else 0.0
        best = np.nanmin([ours["final_error"], file["final_error"], lm, strict, own])
        ok = ours["final_error"] <= best * (1 + 1e-6)
        rows.append([name, str(L.poses), f"{ours['final_error']:.6f}", f"{ours['seconds']:.2f}",
                     f"{file['final_error']:.6f}", f"{file['seconds']:.2f}", f"{lm:.6f}", f"{lm_s:.2f}",
                     f"{strict:.6f}", f"{strict_s:.2f}", f"{file['final_error'] / strict - 1:.1e}",
                     f"{own:.6f}" if init is not None else "throws",
                     f"{own_s:.2f}" if init is not None else "–", f"{best:.6f}", "✓" if ok else "✗"])
        print(" | ".join(rows[-1]), flush=True)
    table = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)] + ["| " + " | ".join(r) + " |" for r in rows]
    text = "\n".join(table) + "\n"
    if args.out:
        atomic_write(args.out, text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
