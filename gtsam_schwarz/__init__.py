"""gtsam-schwarz: pose-graph Gauss–Newton for GTSAM with two-level overlapping Schwarz (GDSW) PCG."""

from .bars import BarChain, bar_chain
from .coarse import CoarseSpace, gdsw_coarse_space
from .decomposition import Decomposition, GraphStructure, segment_partition, segments
from .interface import Interface, find_interface
from .io import GraphFileError, LoadedGraph, load_graph, write_g2o
from .krylov import CGInfo, pcg
from .linear_system import KeyMap, LinearSystem, export_linear_system
from .local_solvers import BlockDiagonalSolver, IndexSets, SingularLocalMatrixError
from .optimizer import LINEAR_SOLVERS, SchwarzOptimizer, SchwarzParams
from .preconditioners import (PRECONDITIONERS, AdditiveSchwarz, BlockJacobi, CoarseCorrection,
                              Identity, Jacobi, TwoLevelSchwarz, make_preconditioner)
from .problems import HelixLoops, SquareLoops, helix_loops, square_loops, square_trajectory

__all__ = [
    "AdditiveSchwarz", "BarChain", "BlockDiagonalSolver", "BlockJacobi", "CGInfo", "CoarseCorrection",
    "CoarseSpace", "Decomposition", "GraphStructure", "Identity", "IndexSets", "Interface",
    "HelixLoops", "GraphFileError", "Jacobi", "KeyMap", "LoadedGraph", "LINEAR_SOLVERS", "LinearSystem", "PRECONDITIONERS", "SchwarzOptimizer",
    "SchwarzParams", "SingularLocalMatrixError", "SquareLoops", "TwoLevelSchwarz",
    "bar_chain", "export_linear_system", "find_interface", "gdsw_coarse_space", "make_preconditioner", "pcg",
    "helix_loops", "load_graph", "write_g2o", "segment_partition", "segments", "square_loops", "square_trajectory",
]
__version__ = "0.1.0"
