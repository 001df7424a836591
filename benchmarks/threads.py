"""Do two threads speed up the local factorizations? Two independent sparse Cholesky factorizations
of the model problem's block-diagonal subdomain matrix, one after the other and then on two threads.

    python benchmarks/threads.py            # sq128x64 (32 769 poses), 5 runs each, medians

If the factorization released the GIL, the threaded time would approach half the serial one.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import threading
import time

from threadpoolctl import threadpool_limits

from gtsam_schwarz.dd import GraphStructure, decompose, default_subdomains
from gtsam_schwarz.linearization.gtsam_export import KeyMap, export_linear_system
from gtsam_schwarz.solvers import SPARSE_BACKEND, SparseCholesky, block_diagonal
from gtsam_schwarz.problems import square_loops


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--loops", type=int, default=128)
    ap.add_argument("--points-per-side", type=int, default=64)
    ap.add_argument("--runs", type=int, default=5)
    args = ap.parse_args(argv)
    if min(args.loops, args.points_per_side, args.runs) < 1:
        ap.error("--loops, --points-per-side and --runs must be at least 1")
    p = square_loops(args.loops, args.points_per_side)
    keymap = KeyMap.from_graph(p.graph, p.initial)
    H = export_linear_system(p.graph.linearize(p.initial), keymap).H
    structure = GraphStructure.from_matrix(H, keymap.offsets)
    dec = decompose(structure, default_subdomains(structure.n_vertices))
    B = block_diagonal(H, dec.index_sets(overlapping=True))
    serial, threaded = [], []
    with threadpool_limits(limits=1, user_api="blas"):
        for _ in range(args.runs):
            t = time.perf_counter()
            SparseCholesky(B)
            SparseCholesky(B)
            serial.append(time.perf_counter() - t)
            workers = [threading.Thread(target=SparseCholesky, args=(B,)) for _ in range(2)]
            t = time.perf_counter()
            for w in workers:
                w.start()
            for w in workers:
                w.join()
            threaded.append(time.perf_counter() - t)
    s, th = statistics.median(serial), statistics.median(threaded)
    print(f"{p.poses} poses, block diagonal {B.shape[0]} dofs, {B.nnz} nonzeros, backend {SPARSE_BACKEND}: "
          f"two factorizations serial {s:.3f} s, on two threads {th:.3f} s (threaded / serial {th / s:.2f})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
