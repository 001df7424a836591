"""Typed records of the nonlinear loop: one :class:`IterationRecord` per linear solve."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, fields

import numpy as np

PHASES = ("linearize", "export", "setup", "cg", "update")


@dataclass
class SolveResult:
    """What a linear solver returns: the step and how it was found."""

    x: np.ndarray
    iterations: int = 0
    converged: bool = True
    lambda_min: float = float("nan")
    lambda_max: float = float("nan")
    residuals: list = field(default_factory=list)
    tolerance: float = float("nan")
    setup_seconds: float = 0.0
    coarse_size: int = 0
    rebuilt: bool = True  # the preconditioner's numbers were recomputed for this matrix
    lagged: bool = False  # CG started with the previous preconditioner (lagged)
    subdomains_kept: bool = False  # rebuilt with the subdomain factorizations of an earlier build (coarse level only)
    coarse_transported: bool = False  # the coarse level carried to the new poses (Φ ← diag(T_v) Φ, A_0 kept), not rebuilt
    decrement_stop: bool = False  # CG stopped early: the exact step would lower the model by < decrement_tol
    decrement_bound: float = float("nan")  # that bound on the exact step's model decrease
    left_bound: float = float("nan")  # asked for (``bound_left``): the model decrease beyond x, at most
    exact: bool = False  # x solves the (damped) system to rounding: a direct factorization of this matrix


@dataclass
class IterationRecord(Mapping):
    """One linear solve of the nonlinear loop (LM may try several per iteration; ``accepted``
    tells which step was kept). Readable as a dict too: ``record["cg_iterations"]``, ``dict(record)``."""

    iteration: int
    error_before: float
    error: float
    gradient_norm: float
    step_norm: float
    step_max: float
    lambda_: float  # the damping of this solve (key "lambda")
    model_fidelity: float
    predicted_decrease: float
    cg_iterations: int
    cg_converged: bool
    cg_tolerance: float
    lambda_min: float  # Lanczos estimates of the preconditioned operator's spectrum
    lambda_max: float
    coarse_size: int
    preconditioner_rebuilt: bool
    preconditioner_lagged: bool
    cg_residuals: list
    subdomains_kept: bool = False  # rebuilt with the subdomain factorizations of an earlier build (coarse level only)
    coarse_transported: bool = False  # the coarse level carried to the new poses (Φ ← diag(T_v) Φ, A_0 kept), not rebuilt
    accepted: bool = False
    seconds: dict = field(default_factory=dict)  # per phase: linearize, export, setup, cg, update
    decrement_stop: bool = False  # CG stopped once the exact step's model decrease was bounded below tolerance
    decrement_bound: float = float("nan")  # that bound (the last CG iterate's), if CG computed one
    # the run's first inexact solve went to the looser ``forcing_probe`` first: "kept" (the step's
    # nonlinearity outweighed what CG had left) or "refined" (CG continued to the forcing term); "": none
    probe: str = ""

    @staticmethod
    def _attr(key: str) -> str:
        return "lambda_" if key == "lambda" else key

    def __getitem__(self, key: str):
        if key == "lambda_" or key not in _KEYS:
            raise KeyError(key)
        return getattr(self, self._attr(key))

    def __iter__(self):
        return iter(_KEYS)

    def __len__(self) -> int:
        return len(_KEYS)

    def to_dict(self) -> dict:
        """The record as the plain dict the JSON output has always had."""
        return {k: self[k] for k in _KEYS}


_KEYS = tuple("lambda" if f.name == "lambda_" else f.name for f in fields(IterationRecord))
