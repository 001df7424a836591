"""Checks run under ``mpiexec -n K python tests/backends/mpi_checks.py`` by test_petsc.py.

On the model problem: the PETSc preconditioner applied to random vectors equals the serial
``TwoLevelSchwarz`` operator (after the first build and after a numeric update at another
linearization point), and one PETSc CG solve equals the serial ``krylov.pcg`` (iterations,
solution). The per-rank linearization (``DistributedOptimizer``) against the serial optimizer on
Pose2 and Pose3 graphs. Rank 0 prints one JSON object.
"""

from __future__ import annotations

import json
import sys

import numpy as np
import scipy.sparse as sp


def main() -> int:
    from mpi4py import MPI

    import gtsam_schwarz as gs
    from gtsam_schwarz.backends.petsc.solver import PetscSchwarzSolver
    from gtsam_schwarz.krylov import pcg
    from gtsam_schwarz.linearization.gtsam_export import GtsamLinearizer
    from gtsam_schwarz.nonlinear import LinearSolverParams
    from gtsam_schwarz.schwarz import create_preconditioner

    comm = MPI.COMM_WORLD
    loops, points = (int(a) for a in sys.argv[1:3])
    out = {"ranks": comm.Get_size(), "cases": []}
    pb = gs.square_loops(loops, points)
    lin = GtsamLinearizer(pb.graph, pb.initial)
    state = lin.state(pb.initial)
    system = lin.linearize(state)
    H0 = sp.csr_matrix(system.H)
    # a second linearization point: the poses moved by a small step (new numbers, same pattern)
    rng = np.random.default_rng(1)
    state1 = lin.retract(state, 0.01 * rng.standard_normal(H0.shape[0]))
    H1 = sp.csr_matrix(lin.linearize(state1).H)
    for name, partition, subdomains, coarse in (("gdsw", "segments", loops, "harmonic"),
                                                ("gdsw", "segments", loops, "galerkin"),
                                                ("rgdsw", "metis", max(comm.Get_size(), 5), "harmonic"),
                                                ("one-level", "segments", loops, "harmonic")):
        params = LinearSolverParams(preconditioner=name, partition=partition, subdomains=subdomains)
        solver = PetscSchwarzSolver(params, lin.offsets, lin.translation_mask(), coarse_matrix=coarse)
        case = {"preconditioner": name, "partition": partition, "subdomains": subdomains, "coarse_matrix": coarse,
                "apply": []}
        for H, st in ((H0, state), (H1, state1)):
            geometry = lin.geometry(st)
            # the PETSc solve builds the PC for H; the serial operator is built for the same H
            rhs = -np.asarray(H @ np.ones(H.shape[0]))
            result = solver.solve(H, rhs, 1e-10, lambda: geometry)
            M = create_preconditioner(name, H.shape[0], solver.decomposition, lin.translation_mask(),
                                      interface_grouping=params.interface_grouping,
                                      coarse_modes=params.coarse_modes)
            M.setup(H)
            M.update(H, geometry if M.uses_geometry else None)
            x = rng.standard_normal(H.shape[0])
            x = comm.bcast(x, root=0)
            y_petsc = solver.apply_preconditioner(x)
            y_serial = M.apply(x)
            case["apply"].append(float(np.linalg.norm(y_petsc - y_serial) / np.linalg.norm(y_serial)))
            xs, info = pcg(H, rhs, M, tol=1e-10)
            case.setdefault("cg_petsc", []).append(result.iterations)
            case.setdefault("cg_serial", []).append(info.iterations)
            case.setdefault("x_error", []).append(float(np.linalg.norm(result.x - xs) / np.linalg.norm(xs)))
            case.setdefault("lambda", []).append([result.lambda_min, result.lambda_max, info.lambda_min,
                                                  info.lambda_max])
            case["coarse_size"] = [result.coarse_size, M.coarse_size]
            # the step is the same full vector on every rank
            gathered = comm.allgather(result.x)
            case.setdefault("x_same_on_ranks", []).append(all(np.array_equal(g, result.x) for g in gathered))
            solver.moved(1.0)  # far enough: the next solve rebuilds (no lagging)
        case["local_solver"] = solver.local_solver
        solver.destroy()
        out["cases"].append(case)
    # the lagging policy: the same sequence of matrices and moves through the serial PreconditionedCG
    # and the PETSc solver gives the same lagged / rebuilt decisions, iterations and steps
    from gtsam_schwarz.nonlinear.linear_solver import PreconditionedCG

    far = lin.retract(state, 0.3 * rng.standard_normal(H0.shape[0]))
    far = comm.bcast(far, root=0)
    damped = H0.copy()
    damped.setdiag(damped.diagonal() + 1e-3)  # LM's damping: new numbers in the same pattern
    rescaled = H1.copy()  # H1 with its rows and columns rescaled, in its pattern: far beyond lag_change
    w = np.sqrt(np.random.default_rng(1).uniform(1.0, 30.0, H1.shape[0]))
    rescaled.data *= w[np.repeat(np.arange(H1.shape[0]), np.diff(H1.indptr))] * w[H1.indices]
    # lag_change 1: the far linearization is tried lagged (and given up at the cap); the rescaled H1 is not
    sequence = [(H0, state, 0.0), (damped, state, 0.01),
                (sp.csr_matrix(lin.linearize(far).H), far, 0.01), (H1, state1, 0.5), (H1, state1, 0.0),
                (rescaled, state1, 0.0)]
    params = LinearSolverParams(preconditioner="gdsw", partition="segments", subdomains=loops, lag_growth=1.0,
                                lag_distance=0.1, lag_change=1.0)
    serial, solver = PreconditionedCG(params, lin.offsets, lin.translation_mask()), \
        PetscSchwarzSolver(params, lin.offsets, lin.translation_mask())
    lag = []
    for H, st, moved in sequence:
        geometry = lin.geometry(st)
        rhs = -np.asarray(H @ np.ones(H.shape[0]))
        a = serial.solve(H, rhs, 1e-8, lambda: geometry)
        b = solver.solve(H, rhs, 1e-8, lambda: geometry)
        lag.append({"serial": [a.iterations, a.lagged, a.rebuilt], "petsc": [b.iterations, b.lagged, b.rebuilt],
                    "x_error": float(np.linalg.norm(a.x - b.x) / np.linalg.norm(a.x))})
        serial.moved(moved)
        solver.moved(moved)
    out["lag_sequence"] = lag
    out["distributed"] = distributed_cases(comm, loops, points)
    if comm.Get_rank() == 0:
        print(json.dumps(out), flush=True)
    return 0


def distributed_cases(comm, loops: int, points: int) -> list:
    """Per-rank linearization (DistributedOptimizer) against the serial optimizer: the gathered H and
    g at the start equal the whole graph's linearization, and the optimized poses (gathered on rank 0)
    and error equal the serial ones. Pose2 without priors (an anchor), Pose2 with a prior, Pose3."""
    from gtsam_schwarz.backends.petsc.distributed import DistributedOptimizer
    from gtsam_schwarz.nonlinear import SchwarzOptimizer, SchwarzParams
    from gtsam_schwarz.problems import square_loops
    from gtsam_schwarz.problems.survey import lawnmower, survey3d

    import gtsam

    loops_pb = square_loops(loops, points)
    free = gtsam.NonlinearFactorGraph()  # the same graph without its prior: gauge-free, one anchor
    for k in range(loops_pb.graph.size()):
        f = loops_pb.graph.at(k)
        if not isinstance(f, gtsam.PriorFactorPose2):
            free.push_back(f)
    free_pb = type("Free", (), {"graph": free, "initial": loops_pb.initial})
    # loop closures with a Huber of Scalar reweighting, which the native kernels leave to GTSAM
    M = gtsam.noiseModel.mEstimator
    scalar = gtsam.noiseModel.Robust.Create(M.Huber.Create(1.345, M.Base.ReweightScheme.Scalar),
                                            gtsam.noiseModel.Isotropic.Sigma(3, 0.05))
    mixed = gtsam.NonlinearFactorGraph()
    for k in range(loops_pb.graph.size()):
        f = loops_pb.graph.at(k)
        keys = f.keys()
        if isinstance(f, gtsam.BetweenFactorPose2) and abs(int(keys[1]) - int(keys[0])) > 1:
            f = gtsam.BetweenFactorPose2(keys[0], keys[1], f.measured(), scalar)
        mixed.push_back(f)
    mixed_pb = type("Mixed", (), {"graph": mixed, "initial": loops_pb.initial})
    cases = []
    for name, pb, kw in (("square_loops", loops_pb,
                          dict(method="gn", preconditioner="gdsw", subdomains=loops, partition="segments")),
                         ("no_prior", free_pb, dict(preconditioner="gdsw", subdomains=loops, partition="segments")),
                         ("lawnmower", lawnmower(10, 10), dict(preconditioner="rgdsw-linear", subdomains=4)),
                         ("survey3d", survey3d(2, 4, 4), dict(preconditioner="gdsw", subdomains=4)),
                         ("gtsam_factors", mixed_pb, dict(preconditioner="gdsw", subdomains=loops,
                                                          partition="segments"))):
        # every step solved to its forcing term, as the distributed loop does (no Newton-decrement stop, no
        # first-step probe); the back-end rebuilds its coarse level: the serial run does too
        serial = SchwarzOptimizer(pb.graph, pb.initial, SchwarzParams(**kw, newton_decrement=False, transport_coarse=False,
                                                                      forcing_probe=0.0))
        ref = serial.optimize()
        opt = DistributedOptimizer(pb.graph, pb.initial, SchwarzParams(**kw))
        full = opt.linearizer
        start = full.linearize(opt._full_state(opt._state, None))
        H, g, _ = opt.part.linearize(opt._state)
        lay = opt.linear_solver.layout
        lo, hi = lay.rows(comm.Get_rank())
        indptr, indices, data = H.getValuesCSR()
        rows = np.repeat(np.arange(lo, hi), np.diff(indptr))
        parts = comm.allgather((rows, indices, data, np.asarray(g.getArray()).copy()))
        Hd = sp.csr_matrix((np.concatenate([p[2] for p in parts]), (np.concatenate([p[0] for p in parts]),
                                                                       np.concatenate([p[1] for p in parts]))),
                           shape=(lay.n, lay.n))
        Hd = Hd[lay.position][:, lay.position]
        gd = np.concatenate([p[3] for p in parts])[lay.position]
        values = opt.optimize()
        case = {"problem": name, "ranks_factors": comm.allgather(opt.part.n_factors),
                "factors": int(pb.graph.size()), "distributed": opt.distributed,
                "H_error": float(abs(Hd - start.H).max() / abs(start.H).max()),
                "g_error": float(np.abs(gd - start.g).max() / np.abs(start.g).max()),
                "final_error": [opt.error(), serial.error()], "cg": [opt.summary()["cg_iterations"],
                                                                    serial.summary()["cg_iterations"]],
                "anchored": [opt.summary()["anchored"], serial.summary()["anchored"]],
                "errors_on_ranks": comm.allgather(opt.error()),
                "gtsam_factors": comm.allgather(opt.part.local.gtsam_factor_count if opt.part.local else 0),
                "gtsam_factors_whole": full.gtsam_factor_count}
        if comm.Get_rank() == 0:
            a, b = opt.linearizer.state(values), serial.linearizer.state(ref)
            arrays = [(a.pose2, b.pose2)] if a.pose2 is not None else [(a.R3, b.R3), (a.t3, b.t3)]
            case["pose_difference"] = float(max(np.abs(x - y).max() for x, y in arrays))
        case["values_on_rank"] = comm.allgather(values is not None)
        cases.append(case)
        opt.destroy()
    return cases


if __name__ == "__main__":
    sys.exit(main())
