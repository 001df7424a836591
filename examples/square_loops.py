"""The main job: the paper's model problem solved by every preconditioner, next to GTSAM.

    python examples/square_loops.py [--loops 16] [--points-per-side 16] [--sigma 0.01] [--seed 0]

Builds the unit-square multi-loop pose graph, runs GTSAM's GaussNewtonOptimizer (Cholesky) and our
Gauss–Newton with CG + each preconditioner (one subdomain per loop), and prints a table.
"""

import argparse
import sys
import time

import gtsam
import numpy as np

import gtsam_schwarz as gs


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--loops", type=int, default=16)
    ap.add_argument("--points-per-side", type=int, default=16)
    ap.add_argument("--sigma", type=float, default=0.01)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    if args.loops < 1 or args.points_per_side < 1:
        ap.error("--loops and --points-per-side must be >= 1")

    prob = gs.square_loops(args.loops, args.points_per_side, sigma=args.sigma, seed=args.seed)
    print(f"model problem: {args.loops} loops x {args.points_per_side} points per side = "
          f"{prob.poses} poses, sigma {args.sigma}, seed {args.seed}; initial error "
          f"{prob.graph.error(prob.initial):.6g}")

    t = time.perf_counter()
    ref = gtsam.GaussNewtonOptimizer(prob.graph, prob.initial, gtsam.GaussNewtonParams())
    ref_values = ref.optimize()
    ref_time = time.perf_counter() - t
    ref_error = prob.graph.error(ref_values)
    ref_poses = gtsam.utilities.extractPose2(ref_values)

    header = f"{'solver':<16}{'GN its':>7}{'CG/step':>9}{'final error':>16}{'rel. diff':>11}{'max |dpose|':>13}{'seconds':>9}"
    print(header)
    print("-" * len(header))
    print(f"{'gtsam GN chol.':<16}{ref.iterations():>7}{'-':>9}{ref_error:>16.10g}{'-':>11}{'-':>13}{ref_time:>9.2f}")
    for name in gs.LINEAR_SOLVERS:
        params = gs.SchwarzParams(preconditioner=name, subdomains=args.loops)
        t = time.perf_counter()
        opt = gs.SchwarzOptimizer(prob.graph, prob.initial, params)
        values = opt.optimize()
        seconds = time.perf_counter() - t
        s = opt.summary()
        d = gtsam.utilities.extractPose2(values) - ref_poses
        d[:, 2] = (d[:, 2] + np.pi) % (2 * np.pi) - np.pi
        cg = f"{s['cg_mean']:.1f}" if name != "direct" else "-"
        print(f"{name:<16}{s['iterations']:>7}{cg:>9}{s['final_error']:>16.10g}"
              f"{abs(s['final_error'] - ref_error) / ref_error:>11.1e}{np.abs(d).max():>13.1e}{seconds:>9.2f}",
              flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
