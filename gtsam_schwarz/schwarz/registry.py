"""Preconditioners by name: each entry is (operator class, options), so adding one is one line.

``make_preconditioner(name, A, decomposition, …)`` creates the operator, runs its symbolic
``setup`` and its first numeric ``update``: the one-call form for scripts and tests. Solvers that
reuse the operator across linearizations call ``create`` / ``setup`` / ``update`` themselves.
"""

from __future__ import annotations

import numpy as np

from ..dd.decomposition import Decomposition
from ..dd.geometry import VertexGeometry
from .base import SchwarzOperator
from .one_level import AdditiveSchwarz, BlockJacobi
from .pointwise import Identity, Jacobi
from .two_level import TwoLevelSchwarz

REGISTRY: dict[str, tuple[type[SchwarzOperator], dict]] = {
    "none": (Identity, {}),
    "jacobi": (Jacobi, {}),
    "block-jacobi": (BlockJacobi, {}),
    "one-level": (AdditiveSchwarz, {}),
    "gdsw": (TwoLevelSchwarz, {"kind": "gdsw"}),
    "gdsw-norot": (TwoLevelSchwarz, {"kind": "gdsw", "rotation": False}),
    "rgdsw": (TwoLevelSchwarz, {"kind": "rgdsw"}),
    "gdsw-linear": (TwoLevelSchwarz, {"kind": "gdsw-linear", "interface_grouping": "two-hop"}),
    "rgdsw-linear": (TwoLevelSchwarz, {"kind": "rgdsw-linear", "interface_grouping": "two-hop"}),
}


def register_preconditioner(name: str, cls: type[SchwarzOperator], **options) -> None:
    """Make ``cls`` (with fixed ``options``) available as ``name`` everywhere (CLI, params, bench)."""
    REGISTRY[name] = (cls, options)


def preconditioner_names() -> tuple[str, ...]:
    return tuple(REGISTRY)


PRECONDITIONERS = preconditioner_names()  # the built-in names, in the order the docs list them


def create_preconditioner(name: str, n: int, decomposition: Decomposition | None = None,
                          translation_mask: np.ndarray | None = None, **options) -> SchwarzOperator:
    """The operator registered as ``name`` for an n-dof system, before any setup (symbolic inputs only)."""
    try:
        cls, fixed = REGISTRY[name]
    except KeyError:
        raise ValueError(f"unknown preconditioner {name!r}; choose one of {', '.join(REGISTRY)}") from None
    return cls.create(n, decomposition, translation_mask, **{**options, **fixed})


def make_preconditioner(name: str, A, decomposition: Decomposition | None = None,
                        translation_mask: np.ndarray | None = None,
                        geometry: VertexGeometry | None = None,
                        interface_grouping: str = "components", **options) -> SchwarzOperator:
    """Build the preconditioner called ``name`` for matrix A: create, setup, first update.

    ``geometry`` (poses at the linearization point) gives the coarse spaces rigid-body modes;
    without it they use unit vectors per interface dof.
    """
    M = create_preconditioner(name, A.shape[0], decomposition, translation_mask,
                              interface_grouping=interface_grouping, **options)
    return M.setup(A).update(A, geometry if M.uses_geometry else None)
