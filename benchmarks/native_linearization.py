"""Time the native linearization per nonlinear iteration (retract, error, linearize) at 262k / 1M poses.

    python benchmarks/native_linearization.py 262144 21          # from arrays (what a file loader hands over)
    python benchmarks/native_linearization.py 262144 21 graph    # from a gtsam graph (construction timed too)
    python benchmarks/native_linearization.py 1048576 9
"""

import sys
import time

import numpy as np

from gtsam_schwarz.linearization.native import NativeLinearizer


def benchmark(n_poses: int = 262144, repeats: int = 15, from_graph: bool = False, seed: int = 0) -> dict:
    """Median seconds per phase of one Gauss–Newton iteration (retract, error, linearize) on a Pose2
    chain with a loop closure every 256 poses, BLAS single-threaded.

    ``from_graph``: build the graph with gtsam (``problems.square_loops``, n_poses rounded to 256·k)
    and time the construction from it too; otherwise :meth:`NativeLinearizer.from_arrays`."""
    from threadpoolctl import threadpool_limits

    rng = np.random.default_rng(seed)
    out = {}
    with threadpool_limits(1):
        t0 = time.perf_counter()
        if from_graph:
            from gtsam_schwarz.problems import square_loops
            prob = square_loops(max(1, n_poses // 256), 64)
            out["gtsam_graph_build"] = time.perf_counter() - t0
            t0 = time.perf_counter()
            lin = NativeLinearizer(prob.graph, prob.initial)
            out["construct"] = time.perf_counter() - t0
            out["construct_extract"] = lin.seconds_extract
            t0 = time.perf_counter()
            st = lin.state(prob.initial)
            out["state"] = time.perf_counter() - t0
        else:
            n = n_poses
            th = np.cumsum(rng.normal(size=n) * 0.05)
            xy = np.cumsum(np.column_stack([np.cos(th), np.sin(th)]) * 0.1, axis=0)
            poses = np.column_stack([xy, th])
            E = np.vstack([np.column_stack([np.arange(n - 1), np.arange(1, n)]),
                           np.column_stack([np.arange(0, n - 256, 256), np.arange(256, n, 256)])])
            Z = rng.normal(size=(len(E), 3)) * 0.1
            lin = NativeLinearizer.from_arrays("pose2", np.arange(n), poses, E, Z, information=np.diag([20.0, 20, 100]),
                                               prior_keys=[0], prior_measurements=poses[:1],
                                               prior_information=np.eye(3) * 100)
            out["construct"] = time.perf_counter() - t0
            st = lin.initial_state()
        out["construct_pattern"] = lin.seconds_pattern
        out["poses"], out["factors"], out["nnz"] = len(lin.keys), lin.n_factors, lin.pattern.nnz
        x = rng.normal(size=lin.dim) * 1e-3
        rec = {k: [] for k in ("retract", "error", "linearize", "iteration", "blocks", "gather")}
        for _ in range(repeats):
            t0 = time.perf_counter()
            s1 = lin.retract(st, x)
            t1 = time.perf_counter()
            lin.error(s1)
            t2 = time.perf_counter()
            system = lin.linearize(s1)
            t3 = time.perf_counter()
            del system
            for k, v in (("retract", t1 - t0), ("error", t2 - t1), ("linearize", t3 - t2), ("iteration", t3 - t0),
                         ("blocks", lin.seconds["blocks"]), ("gather", lin.seconds["gather"])):
                rec[k].append(v)
        for k, v in rec.items():
            out[k] = float(np.median(v))
        out["iteration_min"] = float(np.min(rec["iteration"]))
    return out


if __name__ == "__main__":   # python benchmarks/native_linearization.py [n_poses] [repeats] [graph]
    args = sys.argv[1:]
    res = benchmark(int(float(args[0])) if args else 262144, int(args[1]) if len(args) > 1 else 15,
                    from_graph=len(args) > 2 and args[2] == "graph")
    print(", ".join(f"{k} {v * 1e3:.1f} ms" if isinstance(v, float) else f"{k} {v}" for k, v in res.items()))
