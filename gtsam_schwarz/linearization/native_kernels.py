"""Numpy kernels of the native pose-graph linearization: residuals, Jacobians, H blocks, assembly.

No gtsam in here (the conventions are GTSAM 4.3's; tests/linearization/test_native.py checks them
against the wheel): tangent Pose2 = (vx, vy, ω), Pose3 = (ω, v); retraction x ⊕ ξ = x·Exp(ξ)
(Values.retract uses Expmap for Pose2 and Pose3 in this wheel); between error
e = Log(z⁻¹·xi⁻¹·xj) (= Local(z, xi⁻¹xj)); prior error e = Log(z⁻¹·x). Jacobians are w.r.t. right
perturbations x·Exp(δ): ∂e/∂δj = Jr⁻¹(e), ∂e/∂δi = −Jr⁻¹(e)·Ad(xj⁻¹·xi).

Layouts: Pose2 poses are struct-of-arrays (4, n) = (x, y, cos θ, sin θ) (no sin/cos per residual);
Pose3 poses are R (n, 3, 3) world-from-body and t (n, 3). Every kernel works on all factors of a
group at once, in chunks of CHUNK factors so that temporaries stay in cache.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from ..util import sorted_unique

# ---------------------------------------------------------------------------------------------
# Power series of the coefficient functions (argument x = θ²), for small angles
# ---------------------------------------------------------------------------------------------

# β(θ) = (1 − (θ/2)·cot(θ/2)) / θ²  (Bernoulli numbers)
_BETA = (1 / 12, 1 / 720, 1 / 30240, 1 / 1209600, 1 / 47900160, 691 / 1307674368000)
# −α'(θ)/θ with α(θ) = (θ/2)·cot(θ/2)
_DALPHA = (1 / 6, 1 / 180, 1 / 5040, 1 / 151200, 1 / 4790016, 691 / 108972864000)


def _factorial_series(k_first: int, weight=lambda k: 1.0, terms: int = 9) -> tuple:
    from math import factorial
    return tuple((-1) ** k * weight(k) / factorial(2 * k + k_first) for k in range(terms))


_C1 = _factorial_series(3)                      # (θ − sin θ)/θ³
_C2 = _factorial_series(4)                      # (cos θ − 1 + θ²/2)/θ⁴
_C3 = _factorial_series(5, lambda k: k + 1.0)   # (2θ − 3 sin θ + θ cos θ)/(2θ⁵)

_SMALL_BETA = 0.3   # below: Bernoulli series (truncation < 1e-17), above: closed form
_SMALL_C = 1.0      # below: factorial series (truncation < 1e-17)


def _poly(x: np.ndarray, coeffs) -> np.ndarray:
    """Σ coeffs[k]·x^k by Horner's rule."""
    out = np.full_like(x, coeffs[-1])
    for c in coeffs[-2::-1]:
        out *= x
        out += c
    return out


def _sinc(x: np.ndarray) -> np.ndarray:
    """sin(x)/x, exact at 0."""
    return np.sinc(x * (1.0 / np.pi))


def beta_coeff(theta: np.ndarray) -> np.ndarray:
    """β(θ) = (1 − (θ/2)cot(θ/2))/θ², the W² coefficient of Jr⁻¹ = I + W/2 + βW² (SO(3))."""
    theta = np.abs(theta)
    x = theta * theta
    with np.errstate(all="ignore"):
        h = 0.5 * theta
        exact = (1.0 - h * np.cos(h) / np.sin(h)) / x
    return np.where(theta < _SMALL_BETA, _poly(x, _BETA), exact)


def _c_coeffs(theta: np.ndarray):
    """c1, c2, c3 of Barfoot's Q(ρ, φ) (SE(3) Jacobians), series below θ = 1."""
    x = theta * theta
    small = theta < _SMALL_C
    with np.errstate(all="ignore"):
        s, c = np.sin(theta), np.cos(theta)
        t3, t4 = x * theta, x * x
        e1 = (theta - s) / t3
        e2 = (c - 1.0 + 0.5 * x) / t4
        e3 = (2.0 * theta - 3.0 * s + theta * c) / (2.0 * t4 * theta)
    return (np.where(small, _poly(x, _C1), e1), np.where(small, _poly(x, _C2), e2),
            np.where(small, _poly(x, _C3), e3))


# ---------------------------------------------------------------------------------------------
# Robust loss functions (GTSAM's mEstimator::weight / loss, Block reweighting)
# ---------------------------------------------------------------------------------------------

GAUSSIAN, HUBER, CAUCHY, TUKEY, GEMAN_MCCLURE, WELSCH, DCS, FAIR, L2_DEAD_ZONE, TLS, DCS_AGARWAL = range(11)
ROBUST_NAMES = {"null": GAUSSIAN, "huber": HUBER, "cauchy": CAUCHY, "tukey": TUKEY,
                "gemanmcclure": GEMAN_MCCLURE, "welsch": WELSCH, "dcs": DCS, "fair": FAIR,
                "l2withdeadzone": L2_DEAD_ZONE, "truncatedleastsquares": TLS}


def robust_weight_loss(code: int, c: np.ndarray, s2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weight w(d) and loss ρ(d) of one mEstimator at whitened distances d = √s2 (GTSAM's formulas).

    GTSAM's robust factor error is ρ(‖R e‖) and its linearization scales the whitened A, b by √w(‖R e‖)
    (Block reweighting), so H gets w·AᵀA and g gets w·Aᵀ(R e)."""
    d = np.sqrt(s2)
    with np.errstate(all="ignore"):
        if code == GAUSSIAN:
            return np.ones_like(s2), 0.5 * s2
        if code == HUBER:
            inside = d <= c
            return np.where(inside, 1.0, c / d), np.where(inside, 0.5 * s2, c * (d - 0.5 * c))
        if code == CAUCHY:
            k2 = c * c
            return k2 / (k2 + s2), 0.5 * k2 * np.log1p(s2 / k2)
        if code == TUKEY:
            c2 = c * c
            one = 1.0 - s2 / c2
            inside = d <= c
            return np.where(inside, one * one, 0.0), np.where(inside, c2 * (1.0 - one * one * one) / 6.0, c2 / 6.0)
        if code == GEMAN_MCCLURE:
            c2 = c * c
            den = c2 + s2
            return (c2 * c2) / (den * den), 0.5 * (c2 * s2) / den
        if code == WELSCH:
            c2 = c * c
            xc2 = s2 / c2
            return np.exp(-xc2), c2 * 0.5 * -np.expm1(-xc2)
        if code in (DCS, DCS_AGARWAL):
            w = 2.0 * c / (c + s2)
            weight = np.where(s2 > c, w * w, 1.0)
            if code == DCS:  # GTSAM 4.3 wheel: quadratic inside, 2c·e²/(c + e²) − c/2 outside
                return weight, np.where(s2 <= c, 0.5 * s2, 2.0 * c * s2 / (c + s2) - 0.5 * c)
            den = s2 + c      # later sources: (c²e² + c e⁴)/(e² + c)² (Agarwal et al. 2013, Eq. 9)
            return weight, (c * c * s2 + c * s2 * s2) / (den * den)
        if code == FAIR:
            n = d / c
            return 1.0 / (1.0 + n), c * c * (n - np.log1p(n))
        if code == L2_DEAD_ZONE:
            return np.where(d <= c, 0.0, (d - c) / d), np.where(d < c, 0.0, 0.5 * (c - d) * (c - d))
        if code == TLS:
            inside = s2 <= c * c
            return np.where(inside, 1.0, 0.0), np.where(inside, 0.5 * s2, 0.5 * c * c)
    raise ValueError(f"unknown robust code {code}")


@dataclass
class Robust:
    """Per-factor robust kernels: code (GAUSSIAN, HUBER, …) and parameter of each factor."""

    code: np.ndarray   # (m,) int8
    param: np.ndarray  # (m,) float64
    codes: tuple = ()  # distinct codes present

    @classmethod
    def make(cls, code, param, m: int) -> "Robust | None":
        code = np.broadcast_to(np.asarray(code, dtype=np.int8), (m,)).copy()
        param = np.broadcast_to(np.asarray(param, dtype=np.float64), (m,)).copy()
        codes = tuple(int(c) for c in np.flatnonzero(np.bincount(code.astype(np.int64)))) if m else ()
        if codes in ((), (GAUSSIAN,)):
            return None
        return cls(code, param, codes)

    def slice(self, lo: int, hi: int) -> "Robust":
        return Robust(self.code[lo:hi], self.param[lo:hi], self.codes)

    def weight_loss(self, s2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """w and ρ for every factor (squared whitened norms s2)."""
        if len(self.codes) == 1:
            return robust_weight_loss(self.codes[0], self.param, s2)
        w, rho = np.empty_like(s2), np.empty_like(s2)
        for code in self.codes:
            sel = np.flatnonzero(self.code == code)
            w[sel], rho[sel] = robust_weight_loss(code, self.param[sel], s2[sel])
        return w, rho


# ---------------------------------------------------------------------------------------------
# Chunks: the kernels run on slices of CHUNK factors so that their temporaries stay in cache
# ---------------------------------------------------------------------------------------------

CHUNK = 16384


def chunk_bounds(m: int, size: int = CHUNK) -> list[tuple[int, int]]:
    """[(lo, hi), …] covering range(m) in pieces of at most ``size``."""
    return [(lo, min(lo + size, m)) for lo in range(0, m, size)]


def _view(obj, lo: int, hi: int, fields_1d=(), fields_rows=(), fields_first=()):
    """Shallow copy of a factor group restricted to factors lo:hi (no recomputation)."""
    out = object.__new__(type(obj))
    out.__dict__.update(obj.__dict__)
    for f in fields_1d:
        v = getattr(obj, f)
        setattr(out, f, None if v is None else v[lo:hi])
    for f in fields_rows:
        setattr(out, f, getattr(obj, f)[:, lo:hi])
    for f in fields_first:
        setattr(out, f, getattr(obj, f)[lo:hi])
    out.robust = None if obj.robust is None else obj.robust.slice(lo, hi)
    out._chunks = None
    return out


# ---------------------------------------------------------------------------------------------
# Pose2
# ---------------------------------------------------------------------------------------------

def pose2_state(x, y, theta) -> np.ndarray:
    """(4, n) Pose2 array (x, y, cos θ, sin θ): the rotation as GTSAM's Rot2 keeps it, so that
    residuals need no sin/cos (libm's are ~40 multiplications each here) — only one arctan2."""
    theta = np.asarray(theta, dtype=np.float64)
    return np.stack([np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64), np.cos(theta), np.sin(theta)])


def pose2_theta(P: np.ndarray) -> np.ndarray:
    """θ = atan2(sin, cos) in (−π, π] (GTSAM's Pose2::theta)."""
    return np.arctan2(P[3], P[2])


def pose2_retract(P: np.ndarray, v: np.ndarray) -> np.ndarray:
    """P ⊕ v = P·Exp(v) for (4, n) poses and (n, 3) tangents (vx, vy, ω) — GTSAM's Pose2 retraction:
    t' = t + R [[A, −B], [B, A]] v, A = sin ω/ω, B = (1 − cos ω)/ω; R' = R·R(ω) (renormalized)."""
    out = np.empty_like(P)
    for lo, hi in chunk_bounds(P.shape[1]):
        _pose2_retract(P[:, lo:hi], v[lo:hi], out[:, lo:hi])
    return out


def pose2_local(P0: np.ndarray, P: np.ndarray) -> np.ndarray:
    """(n, 3) local coordinates v with P = P0 ⊕ v: GTSAM's Pose2 Logmap of P0⁻¹P,
    v = ([[α, w/2], [−w/2, α]] R0ᵀ(t − t0), w), α = (w/2)cot(w/2), w the relative angle."""
    x0, y0, c0, s0 = P0
    x, y, c, s = P
    dx, dy = x - x0, y - y0
    d1 = c0 * dx + s0 * dy
    d2 = c0 * dy - s0 * dx
    cE = c0 * c + s0 * s
    sE = c0 * s - s0 * c
    w = np.arctan2(sE, cE)
    h = 0.5 * w
    pos = cE >= 0.0   # α = h·cot(h), cot(h) = (1 + cos w)/sin w = sin w/(1 − cos w)
    num = np.where(pos, 1.0 + cE, sE) * h
    den = np.where(pos, sE, 1.0 - cE)
    a = np.divide(num, den, out=np.ones_like(h), where=den != 0.0)
    return np.stack([a * d1 + h * d2, a * d2 - h * d1, w], axis=1)


def _pose2_retract(P: np.ndarray, v: np.ndarray, out: np.ndarray) -> None:
    x, y, c, s = P
    vx, vy, w = v[:, 0], v[:, 1], v[:, 2]
    h = 0.5 * w
    sh, ch = np.sin(h), np.cos(h)
    sinc_h = np.divide(sh, h, out=np.ones_like(h), where=h != 0.0)   # sin(h)/h, 1 at 0
    A = sinc_h * ch          # sin ω / ω
    sinc_h *= sh             # (1 − cos ω)/ω
    B = sinc_h
    tx = A * vx
    tx -= B * vy
    ty = B * vx
    ty += A * vy
    np.multiply(c, tx, out=out[0])
    out[0] -= s * ty
    out[0] += x
    np.multiply(s, tx, out=out[1])
    out[1] += c * ty
    out[1] += y
    cw = sh * sh
    cw *= -2.0
    cw += 1.0                # cos ω
    sw = sh * ch
    sw *= 2.0                # sin ω
    np.multiply(c, cw, out=out[2])
    out[2] -= s * sw
    np.multiply(s, cw, out=out[3])
    out[3] += c * sw
    k = out[2] * out[2]
    k += out[3] * out[3]
    k *= -0.5
    k += 1.5                 # 1/√(c² + s²) to first order: keeps |R| = 1 over many steps
    out[2] *= k
    out[3] *= k


def pose2_matrices(P: np.ndarray) -> np.ndarray:
    """(n, 2, 2) world-from-body rotations of (4, n) poses."""
    c, s = P[2], P[3]
    return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)


def _rows_kept(R, shape: tuple) -> np.ndarray:
    """R as float64 of ``shape``, contiguous, except that a broadcast R (one for all factors) stays a
    view (2M Pose2 factors: 92 MiB of rows not written)."""
    if (isinstance(R, np.ndarray) and R.dtype == np.float64 and R.shape == shape
            and (R.flags.c_contiguous or 0 in R.strides)):
        return R
    return np.ascontiguousarray(R, dtype=np.float64).reshape(shape)


def _column_runs(R: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """(first factor of every run, (6, runs) its column) where R's columns come in runs of equal ones,
    at least two and on average at least two chunks long (chunks then stay inside runs, at most a
    chunk more per run); None otherwise, or for a broadcast R (one column already)."""
    m = R.shape[1]
    if m < 4 * CHUNK or 0 in R.strides:
        return None
    change = np.flatnonzero(np.any(R[:, 1:] != R[:, :-1], axis=0)) + 1
    if not 1 <= len(change) < m // (2 * CHUNK):
        return None
    starts = np.r_[0, change]
    return starts, np.ascontiguousarray(R[:, starts])


def _shared_product(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a·b per factor; broadcast (one value for all factors) where both are."""
    if a.strides == (0,) and b.strides == (0,):
        return np.broadcast_to(a[0] * b[0], a.shape)
    return a * b


@dataclass
class Pose2Factors:
    """Between (i set) or prior (i None) factors on Pose2: e = Log(z⁻¹·xi⁻¹·xj), ½‖R e‖² or ρ(‖R e‖).

    ``R`` holds the upper-triangular square-root information per factor, rows r00 r01 r02 r11 r12 r22.
    Factors whose R is diag(ρ, ρ, r22) (isotropic translation) take a cheaper kernel; ``n_iso`` of them
    at the front (see :func:`iso_first`) make whole chunks of that kind. Where R comes in a few long runs
    of one information each (odometry, then closures), it is kept as one column per run: ``R`` is then
    None, :meth:`rows` gives it, and every chunk lies inside one run with its R broadcast."""

    j: np.ndarray                 # (m,) int64 index of xj (prior: of x) among the kind's poses
    z: np.ndarray                 # (3, m) measured x, y, θ
    R: np.ndarray                 # (6, m)
    i: np.ndarray | None = None   # (m,) int64 index of xi, None for priors
    robust: Robust | None = None
    n_iso: int = 0                # the first n_iso factors have isotropic translation information
    diagonal: bool = field(init=False)
    iso: bool = field(init=False)
    zc: np.ndarray = field(init=False, repr=False)
    zs: np.ndarray = field(init=False, repr=False)
    u: np.ndarray = field(init=False, repr=False)   # (2, m) R_zᵀ t_z
    r22sq: np.ndarray = field(init=False, repr=False)
    rho2: np.ndarray = field(init=False, repr=False)  # r00²

    def __post_init__(self):
        self.j = np.ascontiguousarray(self.j, dtype=np.int64)
        if self.i is not None:
            self.i = np.ascontiguousarray(self.i, dtype=np.int64)
        self.z = np.ascontiguousarray(self.z, dtype=np.float64).reshape(3, -1)
        self.R = _rows_kept(self.R, (6, len(self.j)))
        self.zc, self.zs = np.cos(self.z[2]), np.sin(self.z[2])
        self.u = np.stack([self.zc * self.z[0] + self.zs * self.z[1], self.zc * self.z[1] - self.zs * self.z[0]])
        self._runs = _column_runs(self.R)
        if self._runs is not None:   # one column per run (1M-pose lawnmower: 92 + 31 MiB of rows not kept)
            self.R = self.r22sq = self.rho2 = None
        else:
            self._products()
        self._flags()
        self._chunks = None

    def _products(self) -> None:
        self.r22sq = _shared_product(self.R[5], self.R[5])
        self.rho2 = _shared_product(self.R[0], self.R[0])

    def _flags(self) -> None:
        R = self.R if self._runs is None else self._runs[1]
        self.diagonal = not (np.any(R[1]) or np.any(R[2]) or np.any(R[4]))
        self.iso = self.diagonal and bool(np.all(R[0] == R[3]))

    @property
    def size(self) -> int:
        return len(self.j)

    def rows(self, sel=None) -> np.ndarray:
        """R's (6, m) rows (of the factors ``sel``), made from the runs where only those are kept."""
        if self._runs is None:
            return self.R if sel is None else self.R[:, sel]
        starts, table = self._runs
        if sel is None:
            return np.repeat(table, np.diff(np.r_[starts, self.size]), axis=1)
        return table[:, np.searchsorted(starts, np.arange(self.size)[sel], side="right") - 1]

    def chunks(self) -> list[tuple[int, int, "Pose2Factors"]]:
        """(lo, hi, factors lo:hi) views of at most CHUNK factors, none straddling n_iso or a run of
        R (built once)."""
        if self._chunks is None:
            runs = self._runs
            cuts = sorted({0, self.n_iso, self.size} | (set() if runs is None else set(runs[0].tolist())))
            bounds = [(lo + a, hi + a) for a, b in zip(cuts[:-1], cuts[1:]) for lo, hi in chunk_bounds(b - a)]
            self._chunks = []
            for lo, hi in bounds:
                if runs is None:
                    c = _view(self, lo, hi, ("j", "i", "zc", "zs", "r22sq", "rho2"), ("z", "R", "u"))
                else:   # inside one run: its column broadcast
                    c = _view(self, lo, hi, ("j", "i", "zc", "zs"), ("z", "u"))
                    k = int(np.searchsorted(runs[0], lo, side="right")) - 1
                    c._runs, c.R = None, np.broadcast_to(runs[1][:, k:k + 1], (6, hi - lo))
                    c._products()
                c._flags()
                self._chunks.append((lo, hi, c))
        return self._chunks


def iso_first(R: np.ndarray) -> tuple[np.ndarray, int]:
    """Stable order putting the factors with R = diag(ρ, ρ, r22) first ((6, m) rows), and their count."""
    iso = (R[1] == 0) & (R[2] == 0) & (R[4] == 0) & (R[0] == R[3])
    return np.argsort(~iso, kind="stable"), int(iso.sum())


@dataclass
class Pose2Residual:
    """e = (V(w)⁻¹·t_E, w) for E = z⁻¹·xi⁻¹·xj, its whitened form and the intermediates of the Jacobian."""

    e: tuple            # e1, e2, w
    we: tuple           # R e
    s2: np.ndarray      # ‖R e‖²
    t: tuple            # t_E
    d: tuple            # R(θi + θz)ᵀ (tj − ti) = t_E + u
    cE: np.ndarray      # cos w, sin w
    sE: np.ndarray
    a: np.ndarray       # α = (w/2)·cot(w/2)
    weight: np.ndarray | None   # robust w, None if not robust
    error: float        # Σ ½ s2 or Σ ρ


def pose2_residual(P: np.ndarray, F: Pose2Factors) -> Pose2Residual:
    """Residuals of all factors in F at (4, n) poses P, and the graph error they contribute.

    R_φ = R_i R_z, t_E = R_φᵀ(tj − ti) − R_zᵀ t_z, R_E = R_φᵀ R_j, w = atan2(sin, cos) of R_E,
    e = ([[α, w/2], [−w/2, α]] t_E, w) with α = (w/2)cot(w/2) — rotations as (cos, sin), no sin/cos."""
    X, Y, Cs, Sn = P
    j = F.j
    cj, sj = Cs.take(j), Sn.take(j)
    if F.i is None:
        dx, dy = X.take(j), Y.take(j)
        cp, sp = F.zc, F.zs
    else:
        i = F.i
        dx = X.take(j)
        dx -= X.take(i)
        dy = Y.take(j)
        dy -= Y.take(i)
        ci, si = Cs.take(i), Sn.take(i)
        cp = ci * F.zc
        cp -= si * F.zs
        sp = si * F.zc
        sp += ci * F.zs
    d1 = cp * dx
    d1 += sp * dy
    d2 = cp * dy
    d2 -= sp * dx
    t1 = d1 - F.u[0]
    t2 = d2 - F.u[1]
    cE = cj * cp
    cE += sj * sp
    sE = sj * cp
    sE -= cj * sp
    w = np.arctan2(sE, cE)
    h = 0.5 * w
    # α = h·cot(h), cot(h) = (1 + cos w)/sin w (well conditioned for cos w ≥ 0) = sin w/(1 − cos w)
    pos = cE >= 0.0
    num = np.where(pos, 1.0 + cE, sE)
    den = np.where(pos, sE, 1.0 - cE)
    num *= h
    a = np.divide(num, den, out=np.ones_like(h), where=den != 0.0)
    e1 = a * t1
    e1 += h * t2
    e2 = a * t2
    e2 -= h * t1
    R = F.R
    we0 = R[0] * e1
    we1 = R[3] * e2
    if not F.diagonal:
        we0 += R[1] * e2
        we0 += R[2] * w
        we1 += R[4] * w
    we2 = R[5] * w
    s2 = we0 * we0
    s2 += we1 * we1
    s2 += we2 * we2
    if F.robust is None:
        weight, error = None, 0.5 * float(s2.sum())
    else:
        weight, rho = F.robust.weight_loss(s2)
        error = float(rho.sum())
    return Pose2Residual((e1, e2, w), (we0, we1, we2), s2, (t1, t2), (d1, d2), cE, sE, a, weight, error)


def _jacobian_terms(res):
    """The entries of the between-factor Jacobian shared by both kernels: P = [[p, −q], [q, p]] on
    the translation, (u1, u2) the rotation column (p = α cos θ_E + (w/2) sin θ_E, q = α sin θ_E −
    (w/2) cos θ_E, u = α′ t_E + ½ J t_E)."""
    t1, t2 = res.t
    cE, sE, a = res.cE, res.sE, res.a
    w = res.e[2]
    h = 0.5 * w
    p = a * cE
    p += h * sE
    q = a * sE
    q -= h * cE
    ap = _alpha_prime(w, cE, sE)
    u1 = ap * t1
    u1 += 0.5 * t2
    u2 = ap * t2
    u2 -= 0.5 * t1
    return p, q, u1, u2


def _alpha_prime(w: np.ndarray, cE: np.ndarray, sE: np.ndarray) -> np.ndarray:
    """dα/dw for α(w) = (w/2)cot(w/2): (sin w − w)/(2(1 − cos w)), series below |w| = 0.3."""
    with np.errstate(all="ignore"):
        exact = (sE - w) / (2.0 * (1.0 - cE))
    small = -w * _poly(w * w, _DALPHA)
    return np.where(np.abs(w) < _SMALL_BETA, small, exact)


# symmetric 3×3 entries in the order the kernels produce them
SYM3 = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))


def pose2_system(F: Pose2Factors, res: Pose2Residual, hjj, gj, hij=None, hii=None, gi=None) -> None:
    """Whitened (robust-reweighted) Gauss–Newton blocks of all factors, written into the given arrays.

    Jj = Jr⁻¹(e) = [[P, u], [0, 1]] with P = V(w)⁻¹R_E, u = ∂(V⁻¹t_E)/∂w; A = R·Jj;
    Hjj = AᵀA (6 symmetric rows SYM3), gj = Aᵀ(R e); for between factors with N = −Ad(xj⁻¹xi):
    Hij = Nᵀ Hjj (9 rows, row-major), Hii = Hij·N (6 rows SYM3), gi = Nᵀ gj. All scaled by the robust w."""
    if F.iso:
        _pose2_system_iso(F, res, hjj, gj, hij, hii, gi)
        return
    t1, t2 = res.t
    cE, sE = res.cE, res.sE
    p, q, u1, u2 = _jacobian_terms(res)
    R = F.R
    if F.diagonal:
        A00 = R[0] * p
        A01 = R[0] * q
        np.negative(A01, out=A01)
        A02 = R[0] * u1
        A12 = R[3] * u2
    else:
        A00 = R[0] * p
        A00 += R[1] * q
        A01 = R[1] * p
        A01 -= R[0] * q
        A02 = R[0] * u1
        A02 += R[1] * u2
        A02 += R[2]
        A12 = R[3] * u2
        A12 += R[4]
    A10 = R[3] * q
    A11 = R[3] * p
    we0, we1, we2 = res.we
    # Hjj = AᵀA, row 2 of A is (0, 0, r22)
    j00, j01, j02, j11, j12, j22 = hjj
    np.multiply(A00, A00, out=j00); j00 += A10 * A10
    np.multiply(A00, A01, out=j01); j01 += A10 * A11
    np.multiply(A00, A02, out=j02); j02 += A10 * A12
    np.multiply(A01, A01, out=j11); j11 += A11 * A11
    np.multiply(A01, A02, out=j12); j12 += A11 * A12
    np.multiply(A02, A02, out=j22); j22 += A12 * A12; j22 += F.r22sq
    g0, g1, g2 = gj
    np.multiply(A00, we0, out=g0); g0 += A10 * we1
    np.multiply(A01, we0, out=g1); g1 += A11 * we1
    np.multiply(A02, we0, out=g2); g2 += A12 * we1; g2 += R[5] * we2
    if res.weight is not None:
        for arr in (*hjj, *gj):
            arr *= res.weight
    if hij is None:
        return
    ncb, nsb, nm1, nm2 = _neg_adjoint(F, res, cE, sE)
    cols = ((j00, j01, j02), (j01, j11, j12), (j02, j12, j22))   # Hjj[c, b] = cols[b][c]
    H = list(hij)  # 9 rows, (a, b) → 3a + b
    for b in range(3):
        H0b, H1b, H2b = cols[b]
        np.multiply(ncb, H0b, out=H[b]); H[b] += nsb * H1b
        np.multiply(ncb, H1b, out=H[3 + b]); H[3 + b] -= nsb * H0b
        np.multiply(nm1, H0b, out=H[6 + b]); H[6 + b] += nm2 * H1b; H[6 + b] -= H2b
    i00, i01, i02, i11, i12, i22 = hii
    np.multiply(H[0], ncb, out=i00); i00 += H[1] * nsb
    np.multiply(H[1], ncb, out=i01); i01 -= H[0] * nsb
    np.multiply(H[4], ncb, out=i11); i11 -= H[3] * nsb
    np.multiply(H[0], nm1, out=i02); i02 += H[1] * nm2; i02 -= H[2]
    np.multiply(H[3], nm1, out=i12); i12 += H[4] * nm2; i12 -= H[5]
    np.multiply(H[6], nm1, out=i22); i22 += H[7] * nm2; i22 -= H[8]
    gi0, gi1, gi2 = gi
    np.multiply(ncb, g0, out=gi0); gi0 += nsb * g1
    np.multiply(ncb, g1, out=gi1); gi1 -= nsb * g0
    np.multiply(nm1, g0, out=gi2); gi2 += nm2 * g1; gi2 -= g2


def _pose2_system_iso(F: Pose2Factors, res: Pose2Residual, hjj, gj, hij, hii, gi) -> None:
    """:func:`pose2_system` for R = diag(ρ, ρ, r22): Hjj = ρ²[[κI, Pᵀu], [uᵀP, |u|²]] + r22² e₃e₃ᵀ with
    κ = p² + q² (P is a scaled rotation), so Hjj's and Hii's translation blocks are κρ²·I and the
    off-diagonal block's is a rotation times κρ²: about a third fewer operations."""
    t1, t2 = res.t
    cE, sE = res.cE, res.sE
    e1, e2, w = res.e
    p, q, u1, u2 = _jacobian_terms(res)
    rho2 = F.rho2
    if res.weight is not None:
        rho2 = rho2 * res.weight
        r22sq = F.r22sq * res.weight
    else:
        r22sq = F.r22sq
    j00, j01, j02, j11, j12, j22 = hjj
    np.multiply(p, p, out=j00); j00 += q * q; j00 *= rho2
    j01.fill(0.0)
    np.copyto(j11, j00)
    np.multiply(p, u1, out=j02); j02 += q * u2; j02 *= rho2
    np.multiply(p, u2, out=j12); j12 -= q * u1; j12 *= rho2
    np.multiply(u1, u1, out=j22); j22 += u2 * u2; j22 *= rho2; j22 += r22sq
    g0, g1, g2 = gj
    np.multiply(p, e1, out=g0); g0 += q * e2; g0 *= rho2
    np.multiply(p, e2, out=g1); g1 -= q * e1; g1 *= rho2
    np.multiply(u1, e1, out=g2); g2 += u2 * e2; g2 *= rho2; g2 += r22sq * w
    if hij is None:
        return
    ncb, nsb, nm1, nm2 = _neg_adjoint(F, res, cE, sE)
    H = list(hij)
    np.multiply(ncb, j00, out=H[0])
    np.multiply(nsb, j00, out=H[1])
    np.multiply(ncb, j02, out=H[2]); H[2] += nsb * j12
    np.negative(H[1], out=H[3])
    np.copyto(H[4], H[0])
    np.multiply(ncb, j12, out=H[5]); H[5] -= nsb * j02
    np.multiply(nm1, j00, out=H[6]); H[6] -= j02
    np.multiply(nm2, j00, out=H[7]); H[7] -= j12
    np.multiply(nm1, j02, out=H[8]); H[8] += nm2 * j12; H[8] -= j22
    i00, i01, i02, i11, i12, i22 = hii
    np.copyto(i00, j00)           # Rᵀ(κρ² I)R = κρ² I
    i01.fill(0.0)
    np.copyto(i11, j00)
    np.multiply(H[0], nm1, out=i02); i02 += H[1] * nm2; i02 -= H[2]
    np.multiply(H[3], nm1, out=i12); i12 += H[4] * nm2; i12 -= H[5]
    np.multiply(H[6], nm1, out=i22); i22 += H[7] * nm2; i22 -= H[8]
    gi0, gi1, gi2 = gi
    np.multiply(ncb, g0, out=gi0); gi0 += nsb * g1
    np.multiply(ncb, g1, out=gi1); gi1 -= nsb * g0
    np.multiply(nm1, g0, out=gi2); gi2 += nm2 * g1; gi2 -= g2


def _neg_adjoint(F: Pose2Factors, res: Pose2Residual, cE, sE):
    """N = −Ad(B⁻¹) for B⁻¹ = xj⁻¹xi = E⁻¹z⁻¹ (rotation R_Eᵀ R_zᵀ, translation t = −R_Eᵀ d), where
    Ad = [[c, −s, t_y], [s, c, −t_x], [0, 0, 1]]: returns −c, −s, −t_y, t_x."""
    d1, d2 = res.d
    zc, zs = F.zc, F.zs
    ncb = sE * zs
    ncb -= cE * zc
    nsb = sE * zc
    nsb += cE * zs
    nm1 = cE * d2
    nm1 -= sE * d1
    nm2 = cE * d1
    nm2 += sE * d2
    np.negative(nm2, out=nm2)
    return ncb, nsb, nm1, nm2


def pose2_jacobians(F: Pose2Factors, res: Pose2Residual) -> tuple[np.ndarray | None, np.ndarray]:
    """Unwhitened (m, 3, 3) Jacobians Ji (None for priors) and Jj = Jr⁻¹(e) — the explicit form of what
    :func:`pose2_system` folds into H (for tests and diagnostics, not the hot path)."""
    t1, t2 = res.t
    a, w, cE, sE = res.a, res.e[2], res.cE, res.sE
    h = 0.5 * w
    p, q = a * cE + h * sE, a * sE - h * cE
    ap = _alpha_prime(w, cE, sE)
    m = len(w)
    Jj = np.zeros((m, 3, 3))
    Jj[:, 0, 0], Jj[:, 0, 1], Jj[:, 0, 2] = p, -q, ap * t1 + 0.5 * t2
    Jj[:, 1, 0], Jj[:, 1, 1], Jj[:, 1, 2] = q, p, ap * t2 - 0.5 * t1
    Jj[:, 2, 2] = 1.0
    if F.i is None:
        return None, Jj
    d1, d2 = res.d
    cb, sb = cE * F.zc - sE * F.zs, -(sE * F.zc + cE * F.zs)
    tb1, tb2 = -(cE * d1 + sE * d2), sE * d1 - cE * d2
    Ad = np.zeros((m, 3, 3))
    Ad[:, 0, 0], Ad[:, 0, 1], Ad[:, 0, 2] = cb, -sb, tb2
    Ad[:, 1, 0], Ad[:, 1, 1], Ad[:, 1, 2] = sb, cb, -tb1
    Ad[:, 2, 2] = 1.0
    return -np.matmul(Jj, Ad), Jj


# ---------------------------------------------------------------------------------------------
# SO(3) / SE(3)
# ---------------------------------------------------------------------------------------------

def skew(w: np.ndarray) -> np.ndarray:
    """(n, 3) → (n, 3, 3) with skew(w)·v = w × v."""
    W = np.zeros(w.shape[:-1] + (3, 3))
    W[..., 0, 1], W[..., 0, 2] = -w[..., 2], w[..., 1]
    W[..., 1, 0], W[..., 1, 2] = w[..., 2], -w[..., 0]
    W[..., 2, 0], W[..., 2, 1] = -w[..., 1], w[..., 0]
    return W


def _outer(a, b):
    return a[:, :, None] * b[:, None, :]


def so3_expmap(w: np.ndarray) -> np.ndarray:
    """Exp(ω) = cos θ I + (sin θ/θ) ω^ + ((1 − cos θ)/θ²) ωωᵀ, (n, 3) → (n, 3, 3)."""
    theta = np.linalg.norm(w, axis=-1)
    h = 0.5 * theta
    sinc_h = _sinc(h)
    A = sinc_h * np.cos(h)          # sin θ / θ
    B = 0.5 * sinc_h * sinc_h       # (1 − cos θ)/θ²
    c = np.cos(theta)
    R = B[:, None, None] * _outer(w, w)
    R += A[:, None, None] * skew(w)
    R[:, 0, 0] += c
    R[:, 1, 1] += c
    R[:, 2, 2] += c
    return R


def so3_logmap(R: np.ndarray) -> np.ndarray:
    """Log of (n, 3, 3) rotations → (n, 3): θ = atan2(‖s‖, (tr R − 1)/2), ω = θ s/‖s‖ with
    s = vee(R − Rᵀ)/2; near θ = π the axis comes from the symmetric part (R + Rᵀ)/2 − cos θ I."""
    s = 0.5 * np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], -1)
    c = 0.5 * (R[:, 0, 0] + R[:, 1, 1] + R[:, 2, 2] - 1.0)
    sn = np.linalg.norm(s, axis=-1)
    theta = np.arctan2(sn, c)
    f = np.divide(theta, sn, out=np.ones_like(theta), where=sn > 0.0)
    w = f[:, None] * s
    near = np.flatnonzero((c < 0.0) & (sn < 1e-3))
    if len(near):
        Rn, cn = R[near], c[near]
        S = 0.5 * (Rn + Rn.transpose(0, 2, 1)) - cn[:, None, None] * np.eye(3)
        k = np.argmax(np.diagonal(S, axis1=1, axis2=2), axis=1)
        col = S[np.arange(len(near)), :, k]
        axis = col / np.linalg.norm(col, axis=1, keepdims=True)
        sign = np.where(np.einsum("ni,ni->n", axis, s[near]) < 0.0, -1.0, 1.0)
        w[near] = (sign * theta[near])[:, None] * axis
    return w


def pose3_retract(R: np.ndarray, t: np.ndarray, xi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) ⊕ ξ = (R, t)·Exp(ξ), ξ = (ω, v): R' = R Exp(ω), t' = t + R Jl(ω) v (GTSAM's Pose3 retraction)."""
    w, v = xi[:, :3], xi[:, 3:]
    theta = np.linalg.norm(w, axis=-1)
    h = 0.5 * theta
    sinc_h = _sinc(h)
    B = 0.5 * sinc_h * sinc_h                       # (1 − cos θ)/θ²
    C1 = _c_coeffs(theta)[0]                        # (θ − sin θ)/θ³
    wxv = np.cross(w, v)
    tv = v + B[:, None] * wxv + C1[:, None] * np.cross(w, wxv)
    Rn = np.matmul(R, so3_expmap(w))
    tn = t + np.einsum("nij,nj->ni", R, tv)
    return Rn, tn


def so3_jr_inv(w: np.ndarray, beta: np.ndarray, alpha: np.ndarray, sign: float = 1.0) -> np.ndarray:
    """Jr⁻¹(ω) = α I + ½ω^ + β ωωᵀ (sign −1: Jl⁻¹), α = 1 − βθ² = (θ/2)cot(θ/2)."""
    J = beta[:, None, None] * _outer(w, w)
    J += (0.5 * sign) * skew(w)
    J[:, 0, 0] += alpha
    J[:, 1, 1] += alpha
    J[:, 2, 2] += alpha
    return J


def _barfoot_q(w: np.ndarray, v: np.ndarray, c1, c2, c3) -> np.ndarray:
    """Q(ρ=v, φ=ω) of the SE(3) left Jacobian [[Jl(ω), 0], [Q, Jl(ω)]] in (ω, v) order (Barfoot–Furgale)."""
    Wm, Vm = skew(w), skew(v)
    WV = Wm @ Vm
    VW = Vm @ Wm
    WVW = WV @ Wm
    W2V = Wm @ WV
    VW2 = VW @ Wm
    WVW2 = WVW @ Wm
    W2VW = Wm @ WVW
    Q = 0.5 * Vm
    Q += c1[:, None, None] * (WV + VW + WVW)
    Q += c2[:, None, None] * (W2V + VW2 - 3.0 * WVW)
    Q += c3[:, None, None] * (WVW2 + W2VW)
    return Q


@dataclass
class Pose3Factors:
    """Between (i set) or prior (i None) factors on Pose3: e = Log(z⁻¹·xi⁻¹·xj), ½‖R e‖² or ρ(‖R e‖)."""

    j: np.ndarray
    zR: np.ndarray              # (m, 3, 3)
    zt: np.ndarray              # (m, 3)
    R: np.ndarray               # (m, 6, 6) square-root information (upper triangular)
    i: np.ndarray | None = None
    robust: Robust | None = None
    zRt: np.ndarray = field(init=False, repr=False)
    u: np.ndarray = field(init=False, repr=False)

    def __post_init__(self):
        self.j = np.ascontiguousarray(self.j, dtype=np.int64)
        if self.i is not None:
            self.i = np.ascontiguousarray(self.i, dtype=np.int64)
        self.zR = np.ascontiguousarray(self.zR, dtype=np.float64).reshape(-1, 3, 3)
        self.zt = np.ascontiguousarray(self.zt, dtype=np.float64).reshape(-1, 3)
        self.R = _rows_kept(self.R, (len(self.j), 6, 6))
        self.zRt = np.ascontiguousarray(self.zR.transpose(0, 2, 1))
        self.u = np.einsum("nij,nj->ni", self.zRt, self.zt)
        if self.R.strides[0] == 0:   # one R for all factors: its diagonal broadcast too
            self.Rdiag = np.broadcast_to(np.diagonal(self.R[0]), (len(self.R), 6))
            self.diagonal = not np.any(self.R[0] - np.diag(self.Rdiag[0]))
        else:
            self.Rdiag = np.ascontiguousarray(np.diagonal(self.R, axis1=1, axis2=2))
            self.diagonal = not np.any(self.R - self.Rdiag[:, :, None] * np.eye(6))
        self._chunks = None

    @property
    def size(self) -> int:
        return len(self.j)

    def chunks(self, size: int = 4096) -> list[tuple[int, int, "Pose3Factors"]]:
        """(lo, hi, factors lo:hi) views (built once)."""
        if self._chunks is None:
            self._chunks = [(lo, hi, _view(self, lo, hi, ("j", "i"), (), ("zR", "zt", "R", "zRt", "u", "Rdiag")))
                            for lo, hi in chunk_bounds(self.size, size)]
        return self._chunks


@dataclass
class Pose3Residual:
    e: np.ndarray       # (m, 6) = (ω, v)
    we: np.ndarray      # (m, 6) R e
    s2: np.ndarray
    RE: np.ndarray      # (m, 3, 3)
    d: np.ndarray       # (m, 3) t_E + u
    theta: np.ndarray
    beta: np.ndarray
    weight: np.ndarray | None
    error: float


def pose3_residual(R: np.ndarray, t: np.ndarray, F: Pose3Factors) -> Pose3Residual:
    """E = z⁻¹xi⁻¹xj: R_E = (Ri Rz)ᵀ Rj, t_E = (Ri Rz)ᵀ(tj − ti) − Rzᵀtz; e = (ω, Jl(ω)⁻¹ t_E), ω = Log R_E."""
    Rj, tj = R[F.j], t[F.j]
    if F.i is None:
        M = F.zRt
        dt = tj
    else:
        M = np.matmul(F.zRt, R[F.i].transpose(0, 2, 1))
        dt = tj - t[F.i]
    RE = np.matmul(M, Rj)
    d = np.einsum("nij,nj->ni", M, dt)
    e, theta, beta = se3_logmap(RE, d - F.u)
    we = np.einsum("nij,nj->ni", F.R, e)
    s2 = np.einsum("ni,ni->n", we, we)
    if F.robust is None:
        weight, error = None, 0.5 * float(s2.sum())
    else:
        weight, rho = F.robust.weight_loss(s2)
        error = float(rho.sum())
    return Pose3Residual(e, we, s2, RE, d, theta, beta, weight, error)


def se3_logmap(R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Log of (R, t) in (ω, v) order, ω = Log R, v = Jl(ω)⁻¹ t; also θ = ‖ω‖ and β(θ)."""
    w = so3_logmap(R)
    theta = np.linalg.norm(w, axis=-1)
    beta = beta_coeff(theta)
    alpha = 1.0 - beta * theta * theta
    v = alpha[:, None] * t - 0.5 * np.cross(w, t) + (beta * np.einsum("ni,ni->n", w, t))[:, None] * w
    return np.concatenate([w, v], axis=1), theta, beta


def pose3_local(R0: np.ndarray, t0: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(n, 6) local coordinates ξ with (R, t) = (R0, t0) ⊕ ξ (:func:`pose3_retract`): Log((R0, t0)⁻¹(R, t))."""
    R0t = R0.transpose(0, 2, 1)
    return se3_logmap(np.matmul(R0t, R), np.einsum("nij,nj->ni", R0t, t - t0))[0]


def pose3_jr_inv(e: np.ndarray, theta: np.ndarray, beta: np.ndarray) -> np.ndarray:
    """SE(3) Jr⁻¹(ξ) in (ω, v) order: [[Jr⁻¹(ω), 0], [−Jr⁻¹(ω) Q(−v, −ω) Jr⁻¹(ω), Jr⁻¹(ω)]]."""
    w, v = e[:, :3], e[:, 3:]
    alpha = 1.0 - beta * theta * theta
    Ji = so3_jr_inv(w, beta, alpha)
    c1, c2, c3 = _c_coeffs(theta)
    Q = _barfoot_q(-w, -v, c1, c2, c3)
    J = np.zeros((len(e), 6, 6))
    J[:, :3, :3] = Ji
    J[:, 3:, 3:] = Ji
    J[:, 3:, :3] = -(Ji @ Q @ Ji)
    return J


def pose3_adjoint(Rm: np.ndarray, tv: np.ndarray) -> np.ndarray:
    """Ad(T) = [[R, 0], [t^R, R]] in (ω, v) order."""
    Ad = np.zeros((len(Rm), 6, 6))
    Ad[:, :3, :3] = Rm
    Ad[:, 3:, 3:] = Rm
    Ad[:, 3:, :3] = skew(tv) @ Rm
    return Ad


def pose3_jacobians(F: Pose3Factors, res: Pose3Residual) -> tuple[np.ndarray | None, np.ndarray]:
    """Unwhitened (m, 6, 6) Ji = −Jr⁻¹(e) Ad(xj⁻¹xi) (None for priors) and Jj = Jr⁻¹(e)."""
    Jj = pose3_jr_inv(res.e, res.theta, res.beta)
    if F.i is None:
        return None, Jj
    REt = res.RE.transpose(0, 2, 1)
    return -np.matmul(Jj, pose3_adjoint(np.matmul(REt, F.zRt), -np.einsum("nij,nj->ni", REt, res.d))), Jj


def pose3_whitened_jacobians(F: Pose3Factors, res: Pose3Residual):
    """A_j = √w R Jr⁻¹(e), A_i = −A_j Ad(xj⁻¹xi) (None for priors), b = √w R e."""
    Jj = pose3_jr_inv(res.e, res.theta, res.beta)
    Aj = F.Rdiag[:, :, None] * Jj if F.diagonal else np.matmul(F.R, Jj)
    we = res.we
    if res.weight is not None:
        sw = np.sqrt(res.weight)
        Aj *= sw[:, None, None]
        we = we * sw[:, None]
    Ai = None
    if F.i is not None:
        REt = res.RE.transpose(0, 2, 1)
        Rb = np.matmul(REt, F.zRt)
        tb = -np.einsum("nij,nj->ni", REt, res.d)
        Ai = -np.matmul(Aj, pose3_adjoint(Rb, tb))
    return Aj, Ai, we


def pose3_system(F: Pose3Factors, res: Pose3Residual):
    """Hjj, gj and (between) Hij, Hii, gi as (m, 6, 6) / (m, 6) arrays, robust-reweighted."""
    Aj, Ai, we = pose3_whitened_jacobians(F, res)
    AjT = Aj.transpose(0, 2, 1)
    hjj = np.matmul(AjT, Aj)
    gj = np.einsum("nij,nj->ni", AjT, we)
    if Ai is None:
        return hjj, gj, None, None, None
    AiT = Ai.transpose(0, 2, 1)
    return hjj, gj, np.matmul(AiT, Aj), np.matmul(AiT, Ai), np.einsum("nij,nj->ni", AiT, we)


# ---------------------------------------------------------------------------------------------
# Fixed block pattern of H and the gather plan that fills it
# ---------------------------------------------------------------------------------------------

def in_sorted(a: np.ndarray, sorted_b: np.ndarray) -> np.ndarray:
    """Mask of the entries of a that occur in the sorted array sorted_b."""
    if len(sorted_b) == 0:
        return np.zeros(len(a), dtype=bool)
    pos = np.minimum(np.searchsorted(sorted_b, a), len(sorted_b) - 1)
    return sorted_b[pos] == a


_CHUNK = 1 << 16   # blocks per chunk of the plan's writes (temporaries of ~5 MB with 3×3 blocks)
# entries of H up to which the gather index is laid out by a BSR→CSR conversion: faster, but two more
# index-sized temporaries for a moment (8 bytes per entry of H: 224 MB at the 1M-pose model problem),
# where from 2M entries the plan runs on its background thread anyway (BACKGROUND_PLAN_FROM)
BSR_INDEX_MAX = 4_000_000


class BlockPattern:
    """CSR pattern (sorted indices) holding every entry of every block (u, v) of coupled variables.

    Variables v own dofs offsets[v]:offsets[v+1]; blocks are the diagonal ones plus both orientations of
    every coupled pair, numbered k in row-major order (row v: its lower pairs, its diagonal, its upper
    pairs, from one sort of the distinct pairs). Block entry (a, b) of block k sits at
    indptr[offsets[row_k] + a] + colstart_k + b; if all variables have d dofs that is
    bptr[v]·(d² − d) + k·d + a·rowlen[v]·d + b, and the CSR arrays come from scipy's BSR→CSR conversion."""

    def __init__(self, dims: np.ndarray, rows: np.ndarray, cols: np.ndarray):
        dims = np.asarray(dims, dtype=np.int64)
        nv = len(dims)
        self.nv = nv
        self.dims = dims
        self.offsets = np.zeros(nv + 1, dtype=np.int64)
        np.cumsum(dims, out=self.offsets[1:])
        n = int(self.offsets[-1])
        self.n = n
        rows = np.asarray(rows, dtype=np.int64)
        cols = np.asarray(cols, dtype=np.int64)
        lo, hi = np.minimum(rows, cols), np.maximum(rows, cols)
        off = lo != hi
        pairs = sorted_unique(lo[off] * nv + hi[off])
        ulo, uhi = pairs // nv, pairs % nv
        npairs = len(pairs)
        nup, nlow = np.bincount(ulo, minlength=nv), np.bincount(uhi, minlength=nv)
        rowlen = nup + nlow + 1
        bptr = np.zeros(nv + 1, dtype=np.int64)
        np.cumsum(rowlen, out=bptr[1:])
        nb = int(bptr[-1])
        bc = np.empty(nb, dtype=np.int64)
        bc[bptr[ulo] + nlow[ulo] + 1 + np.arange(npairs) - (np.cumsum(nup) - nup)[ulo]] = uhi
        by_hi = np.argsort(uhi, kind="stable")   # keeps lo increasing within each hi
        bc[bptr[uhi[by_hi]] + np.arange(npairs) - (np.cumsum(nlow) - nlow)[uhi[by_hi]]] = ulo[by_hi]
        self._diag_blocks = bptr[:-1] + nlow
        bc[self._diag_blocks] = np.arange(nv)
        # the blocks' vertex rows and columns in 32 bits where they fit, their search keys (row·nv + col)
        # made when asked and dropped once the plan is made (:meth:`forget_block_keys`): 1M 2D poses,
        # 114 → 38 MB of block arrays beside every later phase
        vtype = np.int32 if nv < 2**31 - 1 else np.int64
        br = np.repeat(np.arange(nv, dtype=vtype), rowlen)
        bc = bc.astype(vtype, copy=False)
        self.block_rows, self.block_cols = br, bc
        self._block_keys = None
        dvals = sorted_unique(dims).tolist()
        self.uniform = len(dvals) == 1
        if self.uniform:   # scipy's BSR→CSR lays out the entries (from 1 byte per entry, not 16)
            d = dvals[0]
            self.d = d
            self.nnz = nb * d * d
            self.index_dtype = np.int32 if max(n, self.nnz) < 2**31 - 1 else np.int64
            C = sp.bsr_matrix((np.ones((nb, d, d), dtype=bool), bc.astype(self.index_dtype),
                               bptr.astype(self.index_dtype)), shape=(n, n), blocksize=(d, d)).tocsr()
            if int(C.indptr[-1]) != self.nnz:
                raise RuntimeError("unexpected BSR→CSR conversion")
            self._indptr_wide = None   # made when asked (the others' entries): 1M 2D poses, 23 MiB not held
            self.indptr = C.indptr.astype(self.index_dtype, copy=False)
            self.indices = C.indices.astype(self.index_dtype, copy=False)
            self._bptr, self._rowlen = bptr, rowlen
            del C
        else:
            cd = dims[bc]
            excl = np.cumsum(cd) - cd
            self.colstart = excl - excl[bptr[br]]
            rowlen = np.add.reduceat(cd, bptr[:-1]) if nv else np.zeros(0, dtype=np.int64)
            indptr = np.zeros(n + 1, dtype=np.int64)
            np.cumsum(np.repeat(rowlen, dims), out=indptr[1:])
            self.nnz = int(indptr[-1])
            self.index_dtype = np.int32 if max(n, self.nnz) < 2**31 - 1 else np.int64
            self._indptr_wide = indptr
            indices = np.empty(self.nnz, dtype=self.index_dtype)
            for dr, dc in ((dr, dc) for dr in dvals for dc in dvals):
                sel = np.flatnonzero((dims[br] == dr) & (dims[bc] == dc))
                if len(sel):
                    pos = self._positions(sel, dr, dc)
                    indices[pos] = (self.offsets[bc[sel]][:, None, None] + np.arange(dc)[None, None, :])
            self.indptr = indptr.astype(self.index_dtype)
            self.indices = indices
        for arr in (self.indptr, self.indices):
            arr.flags.writeable = False

    @property
    def _indptr64(self) -> np.ndarray:
        """indptr in 64 bits: kept for mixed block sizes, whose layout reads it; made when asked otherwise."""
        return self._indptr_wide if self._indptr_wide is not None else self.indptr.astype(np.int64)

    @property
    def block_keys(self) -> np.ndarray:
        """row·nv + col of every block, increasing (the blocks' search keys)."""
        if self._block_keys is None:
            self._block_keys = self.block_rows.astype(np.int64) * self.nv + self.block_cols
        return self._block_keys

    def forget_block_keys(self) -> None:
        """Drop the blocks' search keys (8 bytes per block) until :meth:`block_index` needs them again."""
        self._block_keys = None

    def _positions(self, k: np.ndarray, dr: int, dc: int) -> np.ndarray:
        row0 = self.offsets[self.block_rows[k]]
        return (self._indptr64[row0[:, None] + np.arange(dr)][:, :, None]
                + (self.colstart[k][:, None, None] + np.arange(dc)[None, None, :]))

    def vertex_pattern(self) -> sp.csr_matrix:
        """The vertex-level pattern of H (1 where block (u, v) is stored, rows sorted), as
        :func:`~gtsam_schwarz.util.vertex_pattern` reads it from a matrix of this pattern: the
        structure of H before any linearization."""
        indptr = np.zeros(self.nv + 1, dtype=np.int64)
        np.cumsum(np.bincount(self.block_rows, minlength=self.nv), out=indptr[1:])
        itype = np.int32 if max(self.nv, len(self.block_cols)) < 2**31 else np.int64
        V = sp.csr_matrix((np.ones(len(self.block_cols)), self.block_cols.astype(itype), indptr.astype(itype)),
                          shape=(self.nv, self.nv))
        V.has_sorted_indices = True
        return V

    def block_index(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """Block numbers of blocks (rows, cols) (they must be in the pattern)."""
        rows = np.asarray(rows, dtype=np.int64)
        cols = np.asarray(cols, dtype=np.int64)
        if rows is cols or np.array_equal(rows, cols):   # diagonal blocks: no search
            return self._diag_blocks[rows]
        q = rows * self.nv + cols
        k = np.searchsorted(self.block_keys, q)
        if len(q) and (np.any(k >= len(self.block_keys)) or np.any(self.block_keys[np.minimum(k, len(self.block_keys) - 1)] != q)):
            raise KeyError("block not in pattern")
        return k

    def source_index(self, assignments, fill: int, dtype=np.int64) -> np.ndarray:
        """Gather index of the CSR data: entry (a, b) of block (rows[t], cols[t]) takes source
        base[t] + coef[a, b] for every (rows, cols, base, coef) in ``assignments`` (blocks at most once),
        others ``fill``. ``dtype``: of the index (int32 where the source is that small: half the memory,
        written directly). Uniform blocks up to ``BSR_INDEX_MAX`` entries: written block by block (d²
        contiguous entries each) and laid out by scipy's BSR→CSR conversion, as the pattern itself
        (sq128x64 12-17 → 7 ms, two index-sized temporaries more); above, scattered a chunk of blocks
        at a time (no (t, d, d) temporaries)."""
        if self.uniform:
            d = self.d
            blocks = [(self.block_index(rows, cols), base, coef) for rows, cols, base, coef in assignments]
            covered = sum(len(k) for k, _, _ in blocks) == len(self.block_rows)   # each block at most once
            shape = (len(self.block_rows), d, d) if self.nnz <= BSR_INDEX_MAX else (self.nnz,)
            src = np.empty(shape, dtype=dtype) if covered else np.full(shape, fill, dtype=dtype)
            if len(shape) == 3:   # in block order, then the conversion
                for k, base, coef in blocks:
                    src[k] = np.asarray(base)[:, None, None] + coef
                src = sp.bsr_matrix((src, self.block_cols.astype(self.index_dtype), self._bptr.astype(self.index_dtype)),
                                    shape=(self.n, self.n), blocksize=(d, d)).tocsr().data
                if src.dtype != dtype:
                    raise RuntimeError("unexpected BSR→CSR conversion of the source index")
                return src
            a = np.arange(d)   # entry (a, b) of block k in row v: bptr[v]·(d² − d) + k·d + a·rowlen[v]·d + b
            for k, base, coef in blocks:
                for lo in range(0, len(k), _CHUNK):   # chunks of blocks: small temporaries, local writes
                    kc = k[lo:lo + _CHUNK]
                    v = self.block_rows[kc]
                    row = (self._bptr[v] * (d * d - d) + kc * d)[:, None] + (self._rowlen[v] * d)[:, None] * a
                    src[row[:, :, None] + a] = np.asarray(base[lo:lo + _CHUNK])[:, None, None] + coef
            return src
        src = np.full(self.nnz, fill, dtype=dtype)
        for rows, cols, base, coef in assignments:
            k = self.block_index(rows, cols)
            dr, dc = np.shape(coef)
            pos = self._positions(k, dr, dc)
            src[pos.ravel()] = (np.asarray(base)[:, None, None] + coef[None]).ravel()
        return src

    def entry_positions(self, r: np.ndarray, c: np.ndarray) -> np.ndarray:
        """Positions of dof entries (r, c) in the CSR data (they must be in the pattern)."""
        r = np.asarray(r, dtype=np.int64)
        c = np.asarray(c, dtype=np.int64)
        indptr = self._indptr64   # (made once here where it is not held)
        lo = indptr[r]
        hi = indptr[r + 1]
        # row-major key of every stored entry is increasing: search it
        if not hasattr(self, "_entry_keys"):
            rows_of = np.repeat(np.arange(self.n, dtype=np.int64), np.diff(indptr))
            self._entry_keys = rows_of * self.n + self.indices
        pos = np.searchsorted(self._entry_keys, r * self.n + c)
        ok = (pos >= lo) & (pos < hi)
        ok[ok] = self.indices[pos[ok]] == c[ok]
        if not np.all(ok):
            raise KeyError("entry not in pattern")
        return pos

    def diagonal_positions(self) -> np.ndarray:
        """Positions of the diagonal entries H[r, r] in the CSR data."""
        if self.uniform:   # entry (a, a) of every diagonal block, by the layout arithmetic
            d, a = self.d, np.arange(self.d)
            k = self._diag_blocks
            return ((self._bptr[:-1] * (d * d - d) + k * d)[:, None] + (self._rowlen * d + 1)[:, None] * a).ravel()
        rows_of = np.repeat(np.arange(self.n, dtype=self.index_dtype), np.diff(self._indptr64))
        return np.flatnonzero(rows_of == self.indices)

    def matrix(self, data: np.ndarray) -> sp.csr_matrix:
        """CSR matrix with this pattern (index arrays shared, read-only) and the given data."""
        H = sp.csr_matrix((data, self.indices, self.indptr), shape=(self.n, self.n), copy=False)
        H.has_sorted_indices = True
        H.has_canonical_format = True
        return H
