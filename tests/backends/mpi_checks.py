"""Checks run under ``mpiexec -n K python tests/backends/mpi_checks.py`` by test_petsc.py.

On the model problem: the PETSc preconditioner applied to random vectors equals the serial
``TwoLevelSchwarz`` operator (after the first build and after a numeric update at another
linearization point), and one PETSc CG solve equals the serial ``krylov.pcg`` (iterations,
solution). Rank 0 prints one JSON object.
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
    sequence = [(H0, state, 0.0), (damped, state, 0.01),
                (sp.csr_matrix(lin.linearize(far).H), far, 0.01), (H1, state1, 0.5), (H1, state1, 0.0)]
    params = LinearSolverParams(preconditioner="gdsw", partition="segments", subdomains=loops, lag_growth=1.0)
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
    if comm.Get_rank() == 0:
        print(json.dumps(out), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
