"""Choose a factorization for a matrix: dense Cholesky when small and fairly full, else sparse."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from . import block_cholesky, cholmod_native
from .base import LocalSolver
from .dense import DenseCholesky
from .sparse import SparseCholesky

# local factors that keep their symbolic analysis: refactor(K) for new numbers, release_numeric()
KEEPS_ANALYSIS = (SparseCholesky, cholmod_native.SimplicialCholesky, block_cholesky.BlockCholesky)
DENSE_FACTOR_MAX = 4000  # a matrix this small and at least 10 % full is factorized densely


def _zero_solver(rhs):
    return np.zeros_like(rhs)


def factorize(K: sp.spmatrix, what: str = "local matrix", ordering: str | None = None) -> LocalSolver:
    """Factorize an SPD matrix; returns a solver callable as ``solve(rhs)``.

    Small, fairly dense matrices (e.g. a coarse matrix A_0) get a dense Cholesky, everything else
    a sparse Cholesky (:class:`SparseCholesky`; ``ordering``: its CHOLMOD ordering method, "natural"
    for a matrix already in a fill-reducing order). A singular matrix raises a clear error.
    """
    n = K.shape[0]
    if n == 0:
        return _zero_solver
    if n <= DENSE_FACTOR_MAX and K.nnz >= 0.1 * n * n:
        return DenseCholesky(K, what)
    return SparseCholesky(K, what, ordering=ordering)


def factorize_local(K: sp.spmatrix, what: str = "local matrix", natural: bool = False,
                    dense: bool = True, block: int | None = None, block_dtype=None) -> LocalSolver:
    """:func:`factorize` (``dense=False``: never a dense factor), except that a factor CHOLMOD would
    make simplicial goes through :mod:`.cholmod_native` where it works: its solves hold no GIL, so
    they can run on the local threads. ``natural``: K is already in a fill-reducing order. There,
    a K made of dense ``block``×``block`` vertex blocks is factorized by blocks, its factor's numbers
    in ``block_dtype`` (:class:`.BlockCholesky`; None: not by blocks)."""
    n = K.shape[0]
    if n == 0 or (dense and n <= DENSE_FACTOR_MAX and K.nnz >= 0.1 * n * n):
        return factorize(K, what)
    if natural and block_dtype is not None and block_cholesky.applies(K, block):
        return block_cholesky.BlockCholesky(K, block, what, dtype=block_dtype)
    if cholmod_native.available():
        factor = cholmod_native.SimplicialCholesky(K, what, natural=natural, factor=False)
        if not factor.supernodal_preferred():
            return factor.refactor(K)
        del factor
    return SparseCholesky(K, what, ordering="natural" if natural else None)
