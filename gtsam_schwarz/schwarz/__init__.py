"""Schwarz operators (one lifecycle: create, setup, update, apply) and the registry of preconditioners.

Plain numpy/scipy: nothing here knows GTSAM.
"""

from .base import SchwarzOperator, SumOperator
from .one_level import AdditiveSchwarz, BlockJacobi
from .pointwise import Identity, Jacobi
from .registry import (PRECONDITIONERS, REGISTRY, create_preconditioner, make_preconditioner,
                       preconditioner_names, register_preconditioner)
from .two_level import CoarseCorrection, TwoLevelSchwarz

Preconditioner = SchwarzOperator  # the name used before the layered package

__all__ = ["AdditiveSchwarz", "BlockJacobi", "CoarseCorrection", "Identity", "Jacobi", "PRECONDITIONERS",
           "Preconditioner", "REGISTRY", "SchwarzOperator", "SumOperator", "TwoLevelSchwarz",
           "create_preconditioner", "make_preconditioner", "preconditioner_names", "register_preconditioner"]
