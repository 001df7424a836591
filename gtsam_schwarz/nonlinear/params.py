"""Parameters, named like GTSAM's where they mean the same thing.

:class:`LinearSolverParams` configures the linear solve (preconditioner, decomposition, CG,
lagging, forcing); :class:`GaussNewtonParams` the nonlinear loop's stopping rules, with a
``linear_solver``; :class:`LevenbergMarquardtParams` adds λ. :class:`SchwarzParams` is the flat form
(every field of all three plus ``method``), as the documented API has always taken it.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields

from ..dd.partition import PARTITIONS
from ..schwarz.registry import preconditioner_names
from ..solvers.memory import parse_bytes

METHODS = ("gn", "lm")
BACKENDS = ("serial", "petsc")  # where the linear solves run (petsc: PETSc over MPI, docs/distributed.md)
FORCING = ("auto", "none", "eisenstat-walker")
LINEARIZATIONS = ("auto", "native", "gtsam")
INITIALIZATIONS = ("chordal", "file")


def _choice(name, value, allowed):
    if value not in allowed:
        raise ValueError(f"unknown {name} {value!r}; choose one of {', '.join(allowed)}")


def linear_solver_names() -> tuple[str, ...]:
    """Every name ``preconditioner`` accepts: the registered preconditioners, "direct" and "auto"."""
    return preconditioner_names() + ("direct", "auto")


@dataclass
class LinearSolverParams:
    """How H δ = −g is solved: "auto" (direct or GDSW-preconditioned CG, whichever the cost model
    predicts faster for this graph), CG with a preconditioner from the registry, or "direct".

    ``forcing="eisenstat-walker"`` makes the CG tolerance an inexact-Newton forcing term; "auto" does
    so where the steps are solved by Schwarz-preconditioned CG (each CG iteration costs local solves:
    3D survey 32x32x32, CG per solve 47 + 17 -> 15 + 13, LM 17.3 -> 14.0 s, the same error to 2e-9) and
    keeps ``cg_tol`` for the direct factorization (its lagged CG is cheap, and inexact steps cost LM
    iterations: one more on sphere2500, M3500 and city10000). Under a forcing term the run's first
    inexact solve probes the looser ``forcing_probe`` and keeps that step where its model error
    exceeds what CG left of the decrease (CG is continued otherwise).
    """

    preconditioner: str = "auto"  # auto | direct | a registered preconditioner (none, jacobi, …, gdsw, rgdsw)
    subdomains: int | None = None  # None: about `subdomain_size` poses each
    subdomain_size: int | None = None  # None: 100 poses in 2D (250 with forcing "none"), 32 in 3D (64 under 16 384 poses; dd.partition.default_subdomain_size)
    partition: str = "auto"  # auto (segments, geometric or metis, the smallest interface) | segments | geometric | metis
    overlap: int | None = None  # None: 0 for rgdsw-linear / gdsw-linear (their edge subdomains share the interface
    # poses already; one layer more cost time and CG iterations on every survey, docs/survey.md), 1 otherwise
    grow_along: str = "odometry"  # odometry | all
    interface_grouping: str = "components"  # components | vertices | two-hop (rgdsw-linear / gdsw-linear always use two-hop)
    coarse_modes: str = "rigid"  # rigid (rigid-body modes about component centroids) | unit
    cg_tol: float = 1e-8
    cg_max_iterations: int | None = None  # None: 10 × the system dimension
    forcing: str = "auto"  # auto (eisenstat-walker for Schwarz-CG, none for direct) | none | eisenstat-walker
    forcing_max: float = 1e-3  # measured: 0.1 and 0.01 let LM drift to worse minima on M3500a
    # the run's first inexact solve goes to this looser tolerance first, and is continued to the forcing
    # term unless the step's model error (predicted against actual decrease) exceeds what CG had left
    # (Forcing.probe; 0: off). 2D lawnmowers from the chordal start (model error 1.3 % of the decrease):
    # 10 CG instead of 15-16; 3D surveys (model error ~1e-5): continued, one evaluation more
    forcing_probe: float = 1e-2
    backend: str = "serial"  # serial (this process) | petsc (PETSc over MPI, gtsam_schwarz.backends.petsc)
    reuse_symbolic: bool = True  # keep interface, patterns and symbolic factorizations across solves
    lagged_preconditioner: bool = True  # keep M (all its numbers) while H has hardly changed
    lag_change: float = 1e-4  # lagged: rebuild M once H's entries changed by this since its build (scaled RMS, solvers.EntryChange)
    lag_distance: float = 1.0  # lagged: rebuild M once the steps since its build sum to this (max-norm)
    lag_growth: float = 1.5  # lagged: CG cap = this × the CG count right after the build; beyond it, rebuild
    # a rebuild keeps the two-level operator's subdomain factorizations (recomputes the coarse level only)
    # while H's entries changed by less than this since they were computed (EntryChange; measured: the
    # same CG counts at 3e-4 to 1.2e-3, 200+ CG at 6e-2; 0: refactor them on every rebuild)
    subdomain_lag_change: float = 2e-3
    # while the subdomains are kept (above), the coarse level is carried to the new poses (Φ's vertex
    # blocks times Ad(X_new⁻¹ X_old), A_0 kept) instead of rebuilt (lawnmower 600x600: 15 CG against 14)
    transport_coarse: bool = True
    memory_limit: float | str | None = None  # bytes the linear solver may use ("2G"); None: $GTSAM_SCHWARZ_MEMORY_LIMIT or what is available

    def __post_init__(self):
        _choice("preconditioner", self.preconditioner, linear_solver_names())
        _choice("backend", self.backend, BACKENDS)
        _choice("partition", self.partition, PARTITIONS)
        _choice("forcing", self.forcing, FORCING)
        _choice("grow_along", self.grow_along, ("odometry", "all"))
        _choice("interface_grouping", self.interface_grouping, ("components", "vertices", "two-hop"))
        _choice("coarse_modes", self.coarse_modes, ("rigid", "unit"))
        if self.subdomains is not None and self.subdomains < 1:
            raise ValueError(f"subdomains must be >= 1, got {self.subdomains}")
        if self.overlap is not None and self.overlap < 0:
            raise ValueError(f"overlap must be >= 0, got {self.overlap}")
        if not self.cg_tol > 0:
            raise ValueError(f"cg_tol must be > 0, got {self.cg_tol}")
        if not (self.forcing_probe is None or self.forcing_probe >= 0):
            raise ValueError(f"forcing_probe must be >= 0, got {self.forcing_probe}")
        if not self.lag_distance >= 0:
            raise ValueError(f"lag_distance must be >= 0, got {self.lag_distance}")
        if not self.lag_change >= 0:
            raise ValueError(f"lag_change must be >= 0, got {self.lag_change}")
        if not self.subdomain_lag_change >= 0:
            raise ValueError(f"subdomain_lag_change must be >= 0, got {self.subdomain_lag_change}")
        if self.memory_limit is not None and not parse_bytes(self.memory_limit) > 0:
            raise ValueError(f"memory_limit must be > 0, got {self.memory_limit!r}")
        if not self.lag_growth >= 1:
            raise ValueError(f"lag_growth must be >= 1, got {self.lag_growth}")

    def overlap_layers(self, preconditioner: str | None = None) -> int:
        """The overlap δ for ``preconditioner`` (default: this one): ``overlap``, or when it is None,
        0 for the linear coarse spaces (and auto, whose Schwarz candidate is one) and 1 otherwise."""
        if self.overlap is not None:
            return self.overlap
        return 0 if (preconditioner or self.preconditioner) in ("rgdsw-linear", "gdsw-linear", "auto") else 1

    @property
    def inexact_krylov(self) -> bool:
        """Whether steps solved by preconditioned CG go to Eisenstat-Walker tolerances ("auto" does)."""
        return self.forcing in ("auto", "eisenstat-walker")


@dataclass
class StoppingParams:
    """The nonlinear loop's stopping rules and reporting.

    The paper's (‖g‖ ≤ ``gradient_tol`` or ‖g‖ ≤ ``relative_gradient_tol``·‖g₀‖; None: 1e-6 for
    Gauss–Newton, off for Levenberg–Marquardt, which starts from real files' poor initial guesses
    where ‖g₀‖ is huge), GTSAM's error decrease (relative ``relative_error_tol``, absolute
    ``absolute_error_tol``, ``error_tol``), and ``max_iterations``. GTSAM's error rule stops only
    once the estimated remaining decrease is below ``remaining_decrease_tol`` × error (0: GTSAM's rule
    alone): the last decrease d_k continued geometrically, d_k·r/(1−r) with r = d_k/d_{k−1}, so a
    linearly converging run is not stopped at its first small decrease (MIT, M3500a: 1e-5 above the
    minimum with GTSAM's rule alone).
    """

    max_iterations: int = 100
    gradient_tol: float = 1e-8
    relative_gradient_tol: float | None = None
    relative_error_tol: float = 1e-5
    absolute_error_tol: float = 1e-5
    error_tol: float = 0.0
    remaining_decrease_tol: float = 1e-7  # relative to the error; 0 turns the remaining-decrease check off
    # Newton-decrement rule (CG only): CG stops, and the loop after that step, once krylov.cg's energy
    # bound shows the exact step to be one after which the error rule above would stop and all but
    # remaining_decrease_tol × error of it is reached; the PETSc back-end solves every step to cg_tol
    newton_decrement: bool = True
    blas_threads: int | None = 1  # BLAS threads while iterating (None: leave the process setting; CG's own vector operations run on one thread either way, util.blas)
    linearization: str = "auto"  # auto (native kernels for pose-graph factors, GTSAM for the rest) | native | gtsam
    initialization: str = "chordal"  # chordal (global: rotations, then translations; kept if it lowers the error) | file
    verbose: bool = False  # a line per linear solve on stdout
    iteration_hook: object = None  # callable(record) after every linear solve, like GTSAM's iterationHook

    def _check_stopping(self, method: str):
        _choice("linearization", self.linearization, LINEARIZATIONS)
        _choice("initialization", self.initialization, INITIALIZATIONS)
        if self.max_iterations < 0:
            raise ValueError(f"max_iterations must be >= 0, got {self.max_iterations}")
        if not self.remaining_decrease_tol >= 0:
            raise ValueError(f"remaining_decrease_tol must be >= 0, got {self.remaining_decrease_tol}")
        if self.relative_gradient_tol is None:
            self.relative_gradient_tol = 1e-6 if method == "gn" else 0.0


@dataclass
class DampingParams:
    """Levenberg–Marquardt's λ, like GTSAM's (λ₀ = 1e-5, factor 10, λ ≤ 1e5)."""

    lambda_initial: float = 1e-5
    lambda_factor: float = 10.0
    lambda_upper_bound: float = 1e5
    lambda_lower_bound: float = 0.0
    diagonal_damping: bool = False
    min_model_fidelity: float = 1e-3

    def _check_damping(self):
        if not self.lambda_factor > 1:
            raise ValueError(f"lambda_factor must be > 1, got {self.lambda_factor}")


@dataclass
class GaussNewtonParams(StoppingParams):
    """Gauss–Newton: a rejected step (error increase) stops the loop."""

    linear_solver: LinearSolverParams = field(default_factory=LinearSolverParams)
    method = "gn"

    def __post_init__(self):
        self._check_stopping(self.method)


@dataclass
class LevenbergMarquardtParams(DampingParams, GaussNewtonParams):
    """Levenberg–Marquardt: a rejected step raises λ and is retried."""

    method = "lm"

    def __post_init__(self):
        self._check_stopping(self.method)
        self._check_damping()


@dataclass
class SchwarzParams(DampingParams, StoppingParams, LinearSolverParams):
    """All settings in one flat object (the documented API): ``method`` picks Gauss–Newton
    ("gn") or Levenberg–Marquardt ("lm"); λ fields only matter for "lm"."""

    method: str = "lm"  # lm | gn (the same default as the command line)

    def __post_init__(self):
        _choice("method", self.method, METHODS)
        LinearSolverParams.__post_init__(self)
        self._check_stopping(self.method)
        self._check_damping()

    @property
    def linear_solver(self) -> LinearSolverParams:
        """The linear-solver part (this object itself carries every field)."""
        return self

    def nonlinear(self) -> GaussNewtonParams:
        """The typed nonlinear params for ``method``: GaussNewtonParams or LevenbergMarquardtParams."""
        cls = LevenbergMarquardtParams if self.method == "lm" else GaussNewtonParams
        names = {f.name for f in fields(cls)} - {"linear_solver"}
        return cls(**{n: getattr(self, n) for n in names}, linear_solver=self.linear_params())

    def linear_params(self) -> LinearSolverParams:
        return LinearSolverParams(**{f.name: getattr(self, f.name) for f in fields(LinearSolverParams)})


def from_gtsam(params, linear_solver: LinearSolverParams | None = None) -> GaussNewtonParams:
    """Our params from GTSAM's ``LevenbergMarquardtParams`` / ``GaussNewtonParams``: tolerances,
    maximum iterations, λ settings, verbosity and ``iterationHook(iteration, errorBefore, errorAfter)``
    carried over; the linear solve from ``linear_solver`` (GTSAM's linear solver type is ignored:
    ours replaces it)."""
    common = {"max_iterations": params.getMaxIterations(), "relative_error_tol": params.getRelativeErrorTol(),
              "absolute_error_tol": params.getAbsoluteErrorTol(), "error_tol": params.getErrorTol(),
              "verbose": str(params.getVerbosity()) not in ("SILENT", "Verbosity.SILENT"),
              "linear_solver": linear_solver or LinearSolverParams()}
    hook = getattr(params, "iterationHook", None)
    if callable(hook):
        common["iteration_hook"] = _gtsam_hook(hook)
    if hasattr(params, "getlambdaInitial"):
        return LevenbergMarquardtParams(
            **common, lambda_initial=params.getlambdaInitial(), lambda_factor=params.getlambdaFactor(),
            lambda_upper_bound=params.getlambdaUpperBound(), lambda_lower_bound=params.getlambdaLowerBound(),
            diagonal_damping=params.getDiagonalDamping())
    return GaussNewtonParams(**common)


def _gtsam_hook(hook):
    """GTSAM's iterationHook(iteration, errorBefore, errorAfter), called once per accepted step."""
    def call(record):
        if record.accepted:
            hook(record.iteration, record.error_before, record.error)
    return call


def as_nonlinear(params, linear_solver: LinearSolverParams | None = None) -> GaussNewtonParams:
    """GaussNewtonParams / LevenbergMarquardtParams for any accepted params object: ours (flat or
    typed), GTSAM's, or None (defaults: Levenberg–Marquardt)."""
    if params is None:
        params = SchwarzParams()
    if isinstance(params, SchwarzParams):
        params = params.nonlinear()
    if isinstance(params, GaussNewtonParams):
        if linear_solver is not None:
            params.linear_solver = linear_solver
        return params
    if hasattr(params, "getMaxIterations") and hasattr(params, "getRelativeErrorTol"):
        return from_gtsam(params, linear_solver)
    raise TypeError(f"params must be SchwarzParams, GaussNewtonParams, LevenbergMarquardtParams or GTSAM's, "
                    f"got {type(params).__name__}")
