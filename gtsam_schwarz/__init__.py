"""gtsam-schwarz: pose-graph Gauss–Newton / Levenberg–Marquardt for GTSAM with two-level
overlapping Schwarz (GDSW) preconditioned CG.

Layers (each imports only from those below; see docs/architecture.md):
``io``, ``problems`` → ``dd``, ``solvers``, ``krylov`` → ``coarse``, ``linearization`` →
``schwarz`` → ``nonlinear`` → ``apps``. The top-level names load lazily, so the Schwarz core
(``gtsam_schwarz.dd``, ``coarse``, ``schwarz``, ``solvers``, ``krylov``) imports without gtsam.
"""

from importlib import import_module

from . import _compat

__version__ = "0.1.0"

_EXPORTS = {
    "dd": ["Decomposition", "GraphStructure", "IndexSets", "Interface", "VertexGeometry", "find_interface",
           "segment_partition", "segments"],
    "coarse": ["CoarseSpace", "gdsw_coarse_space"],
    "solvers": ["BlockDiagonalSolver", "SingularLocalMatrixError"],
    "krylov": ["CGInfo", "pcg"],
    "schwarz": ["PRECONDITIONERS", "AdditiveSchwarz", "BlockJacobi", "CoarseCorrection", "Identity", "Jacobi",
                "TwoLevelSchwarz", "make_preconditioner", "register_preconditioner"],
    "linearization": ["KeyMap", "LinearSystem", "export_linear_system", "GtsamLinearizer", "NativeLinearizer"],
    "nonlinear": ["LINEAR_SOLVERS", "SchwarzOptimizer", "SchwarzParams", "GaussNewtonParams",
                  "LevenbergMarquardtParams", "LinearSolverParams", "IterationRecord"],
    "io": ["GraphFileError", "LoadedGraph", "load_graph", "write_g2o"],
    "problems": ["BarChain", "HelixLoops", "Lawnmower", "SquareLoops", "Survey", "Survey3D", "bar_chain",
                 "helix_loops", "lawnmower", "square_loops", "square_trajectory", "survey3d"],
}
_WHERE = {name: module for module, names in _EXPORTS.items() for name in names}

__all__ = sorted(_WHERE)


def __getattr__(name):
    if name in _WHERE:
        value = getattr(import_module(f".{_WHERE[name]}", __name__), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(__all__))


_compat.install(__name__)
