"""Local and coarse solvers: CHOLMOD, SuperLU and dense Cholesky behind one interface, a registry."""

from .base import LOCAL_SOLVERS, LocalSolver, SingularLocalMatrixError, make_solver, register_solver
from .block_cholesky import BlockCholesky
from .block_diagonal import BlockDiagonalSolver, block_diagonal
from .change import EntryChange
from .cost import CholeskyCost, cholesky_cost, pattern_cholesky_cost, vertex_pattern
from .dense import DenseCholesky
from .factory import DENSE_FACTOR_MAX, factorize
from .gather import Gather, SparsityPattern, Submatrix
from .sparse import HAVE_CHOLMOD, SPARSE_BACKEND, CholmodCholesky, SparseCholesky, SuperLUCholesky

__all__ = ["BlockCholesky", "BlockDiagonalSolver", "CholeskyCost", "CholmodCholesky", "cholesky_cost", "pattern_cholesky_cost", "vertex_pattern", "DENSE_FACTOR_MAX", "DenseCholesky", "EntryChange", "Gather", "Submatrix",
           "HAVE_CHOLMOD", "LOCAL_SOLVERS", "LocalSolver", "SPARSE_BACKEND", "SingularLocalMatrixError",
           "SparseCholesky", "SparsityPattern", "SuperLUCholesky", "block_diagonal", "factorize",
           "make_solver", "register_solver"]
