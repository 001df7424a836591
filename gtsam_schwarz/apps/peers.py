"""Peer solvers for ``gtsam-schwarz bench``: g2o's Gauss–Newton and Levenberg–Marquardt (g2opy) on OUR problem.

The optional extra ``[peers]`` installs g2opy (PyPI ``g2opy``, import name ``g2opy``), g2o's Python binding.
Without it nothing here fails at import: :func:`available` says False, and :func:`import_g2o` raises
:class:`PeerNotInstalled`, which the bench turns into a row with status ``not installed``.

The same problem as ours, from the same gtsam graph and initial Values:

- every ``BetweenFactorPose2`` / ``BetweenFactorPose3`` becomes an ``EdgeSE2`` / ``EdgeSE3`` with the same
  measurement; every pose a ``VertexSE2`` / ``VertexSE3`` at its initial value (g2o ids 0..n-1 in key order);
- the gauge prior (``PriorFactorPose2/3``) becomes a fixed vertex, held at the prior's mean. The between
  factors are invariant under a global rigid motion, so GTSAM's optimum puts that pose exactly at the
  prior's mean: fixing it there gives the same minimum. Without a prior the first key is fixed;
- information matrices: in 2D unchanged (``EdgeSE2``'s error (dx, dy, dθ) of Z⁻¹(Xi⁻¹Xj) and GTSAM's
  ``Pose2.Logmap`` of the same relative pose agree to first order). In 3D GTSAM's error is
  Logmap(Z⁻¹ Xi⁻¹ Xj) = (ω, v) in (rotation, translation) order, g2o's ``EdgeSE3`` error is (t, q_vec)
  of the same relative pose, with q_vec = sin(θ/2)·axis ≈ ω/2 and t ≈ v. So e_gtsam ≈ M e_g2o with
  M = [[0, 2·I3], [I3, 0]], and Ω_g2o = Mᵀ Ω_gtsam M (the (r,t)→(t,r) permutation and the
  S = diag(I3, 2·I3) scaling of the rotation rows and columns): see :func:`information_to_g2o`.
  The two error maps agree to first order at zero, so both problems have their minimum at the same
  place up to second-order terms in the residuals (checked on sphere2500: benchmarks/README.md).

Solver: ``SparseOptimizer`` with ``BlockSolverSE2/SE3`` over ``LinearSolverEigen`` (Eigen's sparse
simplicial Cholesky; g2opy's wheel binds no CHOLMOD or CSparse solver), g2o's Gauss–Newton or
Levenberg–Marquardt algorithm. Stopping: g2o's own convergence test, ``SparseOptimizerTerminateAction``
(after each iteration: stop when the relative chi2 decrease (χ²_prev − χ²)/χ² lies in [0, 1e-5), GTSAM's
default relative tolerance) or ``max_iterations`` (100, GTSAM's cap).
"""

from __future__ import annotations

import os
import tempfile

import time
from dataclasses import dataclass, field

__all__ = ["G2O_MODULE", "PEER_SOLVERS", "PeerNotInstalled", "available", "import_g2o", "g2o_version",
           "information_to_g2o", "G2oProblem", "build_g2o", "solve_g2o", "RELATIVE_TOL", "MAX_ITERATIONS"]

G2O_MODULE = "g2opy"  # the import name of PyPI's g2opy
PEER_SOLVERS = {"g2o-gn": "gn", "g2o-lm": "lm"}  # bench solver name -> g2o algorithm
INSTALL_HINT = "pip install 'gtsam-schwarz[peers]'"
RELATIVE_TOL = 1e-5  # GTSAM's default relative error decrease
MAX_ITERATIONS = 100  # GTSAM's default cap
LINEAR_SOLVER = "LinearSolverEigen (Eigen sparse simplicial Cholesky, AMD block ordering)"


class PeerNotInstalled(ImportError):
    """g2opy cannot be imported; the message says why and how to install it."""


def available() -> bool:
    """Whether g2opy imports (a few ms). A real import, not ``find_spec``: an install that is present
    but broken counts as absent, so the bench's default solvers leave it out."""
    try:
        import_g2o()
    except PeerNotInstalled:
        return False
    return True


def import_g2o():
    """The g2opy module, or :class:`PeerNotInstalled` (one line: why, and the install command)."""
    try:
        import g2opy
    except (ImportError, OSError) as exc:  # absent, or present but its shared library does not load
        raise PeerNotInstalled(f"{G2O_MODULE} not importable ({exc}); {INSTALL_HINT}") from None
    return g2opy


def g2o_version() -> str | None:
    """g2opy's installed version, or None."""
    import importlib.metadata

    try:
        return importlib.metadata.version("g2opy")
    except importlib.metadata.PackageNotFoundError:
        return None


def information_to_g2o(information, dimension: int):
    """A GTSAM information matrix (in GTSAM's tangent: Pose2 (x, y, θ), Pose3 (ω, v)) in g2o's edge
    parametrization: 2D unchanged; 3D Ω_g2o = Mᵀ Ω M with e_gtsam = M e_g2o, M = [[0, 2I], [I, 0]]
    (g2o's EdgeSE3 error is (t, q_vec), q_vec ≈ ω/2)."""
    import numpy as np

    omega = np.asarray(information, dtype=float)
    if dimension == 2:
        return omega.copy()
    m = np.zeros((6, 6))
    m[0:3, 3:6] = 2.0 * np.eye(3)  # ω = 2 q_vec
    m[3:6, 0:3] = np.eye(3)  # v = t
    return m.T @ omega @ m


@dataclass
class G2oProblem:
    """A g2o SparseOptimizer built from a gtsam graph, and how to read its estimates back."""

    optimizer: object
    dimension: int
    method: str
    keys: list[int]  # gtsam key of g2o vertex id i
    fixed: list[int]  # gtsam keys of the fixed vertices
    edges: int
    keep: list = field(default_factory=list, repr=False)  # Python references that g2o's objects rely on

    def chi2(self) -> float:
        """g2o's χ² = Σ eᵀΩe at the current estimates (≈ 2 × GTSAM's graph.error)."""
        self.optimizer.compute_active_errors()
        return float(self.optimizer.active_chi2())

    def values(self):
        """The g2o vertex estimates as gtsam Values (Pose2 / Pose3) under the original keys."""
        import gtsam

        out = gtsam.Values()
        for vid, key in enumerate(self.keys):
            est = self.optimizer.vertex(vid).estimate()
            if self.dimension == 2:
                x, y, theta = est.to_vector()
                out.insert(key, gtsam.Pose2(float(x), float(y), float(theta)))
            else:
                out.insert(key, gtsam.Pose3(est.matrix()))
        return out


def _factor_kinds():
    import gtsam

    return {gtsam.BetweenFactorPose2: ("between", 2), gtsam.BetweenFactorPose3: ("between", 3),
            gtsam.PriorFactorPose2: ("prior", 2), gtsam.PriorFactorPose3: ("prior", 3)}


def _information(factor):
    import gtsam

    model = factor.noiseModel()
    if isinstance(model, gtsam.noiseModel.Robust):
        raise ValueError("g2o peer: robust noise models are not converted")
    return model.information()


def _g2o_text(keys, index, priors, initial, betweens, dim):
    """The problem as g2o file lines (vertex ids 0..n−1 in key order; Pose3 information converted)."""
    import numpy as np

    for key in keys:
        pose = priors.get(key)
        if dim == 2:
            pose = pose if pose is not None else initial.atPose2(key)
            yield f"VERTEX_SE2 {index[key]} {pose.x()!r} {pose.y()!r} {pose.theta()!r}\n"
        else:
            pose = pose if pose is not None else initial.atPose3(key)
            t, q = pose.translation(), pose.rotation().toQuaternion()
            yield (f"VERTEX_SE3:QUAT {index[key]} {t[0]!r} {t[1]!r} {t[2]!r} "
                   f"{q.x()!r} {q.y()!r} {q.z()!r} {q.w()!r}\n")
    upper = np.triu_indices(3 if dim == 2 else 6)
    for factor in betweens:
        a, b = (int(k) for k in factor.keys())
        if a not in index or b not in index:
            raise ValueError(f"g2o peer: factor on key {a if a not in index else b} without an initial value")
        z = factor.measured()
        info = " ".join(repr(float(x)) for x in information_to_g2o(_information(factor), dim)[upper])
        if dim == 2:
            yield f"EDGE_SE2 {index[a]} {index[b]} {z.x()!r} {z.y()!r} {z.theta()!r} {info}\n"
        else:
            t, q = z.translation(), z.rotation().toQuaternion()
            yield (f"EDGE_SE3:QUAT {index[a]} {index[b]} {t[0]!r} {t[1]!r} {t[2]!r} "
                   f"{q.x()!r} {q.y()!r} {q.z()!r} {q.w()!r} {info}\n")


def build_g2o(graph, initial, method: str = "gn", g2o=None) -> G2oProblem:
    """The g2o SparseOptimizer of ``graph`` at ``initial`` (see the module docstring); ``method``
    "gn" or "lm". Factors other than Pose2/Pose3 between factors and priors are a ValueError."""
    if method not in ("gn", "lm"):
        raise ValueError(f"method must be 'gn' or 'lm', got {method!r}")
    g2o = g2o or import_g2o()
    kinds = _factor_kinds()
    betweens, priors, dims = [], {}, set()
    for i in range(graph.size()):
        factor = graph.at(i)
        if factor is None:
            continue
        kind = kinds.get(type(factor))
        if kind is None:
            raise ValueError(f"g2o peer: unsupported factor {type(factor).__name__} (only Pose2/Pose3 "
                             "between factors and priors)")
        dims.add(kind[1])
        if kind[0] == "between":
            betweens.append(factor)
        else:
            priors[int(factor.keys()[0])] = factor.prior()  # the last prior on a key wins (one per key in ours)
    if len(dims) != 1:
        raise ValueError("g2o peer: the graph mixes Pose2 and Pose3 factors" if dims else
                         "g2o peer: the graph has no pose factors")
    dim = dims.pop()
    keys = sorted(int(k) for k in initial.keys())
    index = {k: i for i, k in enumerate(keys)}
    fixed = sorted(priors) if priors else keys[:1]

    optimizer = g2o.SparseOptimizer()
    if dim == 2:
        linear = g2o.LinearSolverEigenSE2()
        block = g2o.BlockSolverSE2(linear)
    else:
        linear = g2o.LinearSolverEigenSE3()
        block = g2o.BlockSolverSE3(linear)
    algorithm = (g2o.OptimizationAlgorithmGaussNewton if method == "gn" else g2o.OptimizationAlgorithmLevenberg)(block)
    optimizer.set_algorithm(algorithm)
    keep = [linear, block, algorithm]
    if dim == 2:
        # g2o's own C++ reader: adding vertices and edges one by one through g2opy costs O(n) per call
        # (measured: 32k edges 14 s, 65k edges 77 s), its file reader is linear
        with tempfile.NamedTemporaryFile("w", suffix=".g2o", delete=False) as fh:
            fh.writelines(_g2o_text(keys, index, priors, initial, betweens, dim))
            path = fh.name
        try:
            if not optimizer.load(path):
                raise ValueError("g2o peer: g2o could not read the problem")
        finally:
            os.unlink(path)
        for key in fixed:
            optimizer.vertex(index[key]).set_fixed(True)
    else:  # g2opy's file reader does not know the SE3 types here: vertices and edges one by one (small graphs)
        for key in keys:
            pose = priors.get(key)
            if dim == 2:
                pose = pose if pose is not None else initial.atPose2(key)
                vertex = g2o.VertexSE2()
                vertex.set_estimate(g2o.SE2(pose.x(), pose.y(), pose.theta()))
            else:
                pose = pose if pose is not None else initial.atPose3(key)
                vertex = g2o.VertexSE3()
                vertex.set_estimate(g2o.Isometry3d(pose.matrix()))
            vertex.set_id(index[key])
            vertex.set_fixed(key in fixed)
            optimizer.add_vertex(vertex)
            keep.append(vertex)

        for factor in betweens:
            a, b = (int(k) for k in factor.keys())
            if a not in index or b not in index:
                raise ValueError(f"g2o peer: factor on key {a if a not in index else b} without an initial value")
            z = factor.measured()
            if dim == 2:
                edge = g2o.EdgeSE2()
                edge.set_measurement(g2o.SE2(z.x(), z.y(), z.theta()))
            else:
                edge = g2o.EdgeSE3()
                edge.set_measurement(g2o.Isometry3d(z.matrix()))
            edge.set_vertex(0, optimizer.vertex(index[a]))
            edge.set_vertex(1, optimizer.vertex(index[b]))
            edge.set_information(information_to_g2o(_information(factor), dim))
            optimizer.add_edge(edge)
            keep.append(edge)
    return G2oProblem(optimizer=optimizer, dimension=dim, method=method, keys=keys, fixed=fixed,
                      edges=len(betweens), keep=keep)


def solve_g2o(graph, initial, method: str = "gn", max_iterations: int = MAX_ITERATIONS,
              relative_tol: float = RELATIVE_TOL, problem: G2oProblem | None = None) -> dict:
    """Build (not timed; or take ``problem``, :func:`build_g2o`'s, and ignore graph and initial), then
    time ``initialize_optimization()`` + ``optimize()`` (the analogue of constructing a GTSAM optimizer
    and calling optimize). The values come back in gtsam Values; the caller evaluates ``graph.error``
    on them. ``failed`` is set when g2o reports no iteration."""
    g2o = import_g2o()
    if problem is None:
        problem = build_g2o(graph, initial, method, g2o)
    opt = problem.optimizer
    t0 = time.perf_counter()
    ok = opt.initialize_optimization()
    init_seconds = time.perf_counter() - t0
    if not ok:
        return {"iterations": 0, "seconds": init_seconds, "values": None,
                "failed": "g2o initialize_optimization() failed"}
    initial_chi2 = problem.chi2()  # not timed
    terminate = g2o.SparseOptimizerTerminateAction()
    terminate.set_gain_threshold(relative_tol)
    terminate.set_max_iterations(max_iterations)
    opt.add_post_iteration_action(terminate)
    problem.keep.append(terminate)
    t1 = time.perf_counter()
    iterations = int(opt.optimize(max_iterations))
    seconds = init_seconds + time.perf_counter() - t1
    if iterations <= 0:
        return {"iterations": max(iterations, 0), "seconds": seconds, "values": None,
                "failed": f"g2o optimize() returned {iterations}"}
    return {"iterations": iterations, "seconds": seconds, "init_seconds": init_seconds,
            "values": problem.values(), "g2o_chi2": problem.chi2(), "g2o_initial_chi2": initial_chi2,
            "converged": iterations < max_iterations,
            "stop_reason": (f"relative chi2 decrease < {relative_tol:g} (g2o SparseOptimizerTerminateAction)"
                            if iterations < max_iterations else f"iteration cap {max_iterations}"),
            "fixed": problem.fixed}
