"""Native vectorized linearization of pose graphs: H = Σ JᵀJ and g = Σ JᵀW r with numpy, no gtsam per iteration.

Between/prior factors on Pose2/Pose3 with Gaussian (isotropic, diagonal, full) or robust (Huber,
Cauchy, Tukey, Geman–McClure, Welsch, DCS, Fair, L2WithDeadZone, TLS; Block reweighting) noise are
linearized all at once on arrays of poses (kernels in :mod:`.native_kernels`) and gathered straight
into the graph's fixed CSR block pattern by one precomputed index. Every other factor (landmarks,
custom factors, constrained or unsupported noise) is linearized by GTSAM and added to the same H, g;
non-pose variables are retracted by GTSAM. Variables are in sorted key order, as GTSAM's natural
ordering and :class:`~gtsam_schwarz.linearization.gtsam_export.KeyMap`.
"""

from __future__ import annotations

import sys
import threading
import time
from collections import deque
from dataclasses import dataclass

import gtsam
import numpy as np
import scipy.sparse as sp

from ..dd.geometry import VertexGeometry
from ..util import sorted_unique, with_small_pages
from ..util.gathered import GatheredCSR
from ..util.heap import populate_ahead
from ..util.threads import background_thread
from . import factor_form
from . import native_kernels as nk
from .base import LinearSystem

__all__ = ["NativeLinearizer", "NativeState"]


# ---------------------------------------------------------------------------------------------
# State
# ---------------------------------------------------------------------------------------------

class NativeState:
    """Poses as arrays plus a ``gtsam.Values`` of the other variables; immutable by convention.

    ``pose2`` (4, n2) = (x, y, cos θ, sin θ) rows (see :func:`~.native_kernels.pose2_state`);
    ``R3`` (n3, 3, 3) world-from-body rotations and ``t3`` (n3, 3) translations; ``others`` the non-pose variables (None if there are none). Each kind's poses are in
    sorted key order. Caches what was computed at it (the error, other variables' ``gtsam.Values``)."""

    __slots__ = ("pose2", "R3", "t3", "others", "_cache")

    def __init__(self, pose2=None, R3=None, t3=None, others=None):
        self.pose2, self.R3, self.t3, self.others = pose2, R3, t3, others
        self._cache = {}


def _insert_all(values: gtsam.Values, keys: list, poses, kind: str) -> None:
    """``values.insert(k, pose)`` for all pairs, naming the overload by keyword: pybind11 then skips the
    overloads before it (vectors, matrices, …) without trying to convert, ~3× cheaper per call."""
    insert = values.insert
    it = zip(keys, poses)
    for k, p in it:  # the first one finds out whether this gtsam names the arguments (j, pose2/pose3)
        try:
            insert(j=k, **{kind: p})
        except TypeError:
            insert(k, p)
            for k2, p2 in it:
                insert(k2, p2)
            return
        break
    if kind == "pose2":
        for k, p in it:
            insert(j=k, pose2=p)
    else:
        for k, p in it:
            insert(j=k, pose3=p)


# ---------------------------------------------------------------------------------------------
# Noise models and m-estimators from gtsam
# ---------------------------------------------------------------------------------------------

# fresh memory the construction touches per entry of H (its pattern, gather plan and their
# temporaries; page faults counted: model problems 24.6-33, lawnmowers 24-36, 3D surveys 19-23,
# M3500 and sphere2500 20): faulted in on a helper thread meanwhile (tuned heap only; lawnmower
# 1000x1000: 2.6-4.4 s -> 1.8-2.6 s, medians 3.6 -> 2.1 s, the same faults; 600x600 0.76-0.78 -> 0.56-0.59 s;
# 262 145 poses 0.29-0.33 -> 0.26 s). Below CONSTRUCTION_POPULATE_FROM bytes the construction is over
# before a helper could get ahead of it (sq128x64: 18 MB, 35 ms), and the optimizer's own request
# would wait behind it
CONSTRUCTION_BYTES_PER_ENTRY = 20
CONSTRUCTION_POPULATE_FROM = 64 << 20
# entries of H from which its pattern and plan are made on the background thread. Fresh bench children,
# alternated with the commit before: the 262k-pose model problem (7M entries) 2.44 / 2.23 / 2.16 ->
# 2.30 / 2.16 / 1.89 s, peak 897 -> 814-829 MiB; sq32x128 (0.74M) 0.134-0.140 -> 0.139-0.145 s and
# sq128x64 (1.5M) within the spread: below, a thread start and the chordal start's GIL cost what it saves
BACKGROUND_PLAN_FROM = 2_000_000
# residuals of an error evaluation kept for the same state's linearization up to this many bytes
# (Pose2: 112 per factor; the 1M-pose model problem 120 MB: linearize 268-364 -> 204-272 ms, peak
# +10-40 MiB of 2 910); runs with a Schwarz preconditioner keep none (keep_residuals: its memory peak)
KEEP_RESIDUALS_BYTES = 256 << 20
_TAKE_CHUNK = 1 << 20  # entries of H gathered per np.take (int32 positions become intp a chunk at a time)


def _group_width(n: int, columns: int) -> int:
    """Columns of the diagonal contributions summed per pose at a time (2D): about max(n, 2^18), so
    that each group's bincounts over the n poses cost no more than its columns, plus two chunks."""
    return min(columns, max(n, 1 << 18) + 2 * nk.CHUNK)


_M = gtsam.noiseModel.mEstimator
_ESTIMATORS = {getattr(_M, name): code for name, code in (
    ("Null", nk.GAUSSIAN), ("Huber", nk.HUBER), ("Cauchy", nk.CAUCHY), ("Tukey", nk.TUKEY),
    ("GemanMcClure", nk.GEMAN_MCCLURE), ("Welsch", nk.WELSCH), ("DCS", nk.DCS), ("Fair", nk.FAIR),
    ("L2WithDeadZone", nk.L2_DEAD_ZONE), ("TruncatedLeastSquares", nk.TLS)) if hasattr(_M, name)}


def mestimator_spec(est) -> tuple[int, float] | None:
    """(code, parameter) of a GTSAM m-estimator that the kernels reproduce, else None.

    The parameter and the reweight scheme are read from its serialization (exact digits); only
    Block reweighting (GTSAM's default) is native. The formulas are then checked against the
    estimator's own ``weight``/``loss`` at a few distances, so a changed GTSAM falls back, not drifts."""
    code = _ESTIMATORS.get(type(est))
    if code is None:
        return None
    if code == nk.DCS:  # GTSAM versions differ in DCS's loss: take the variant this one computes
        return mestimator_spec_as(est, nk.DCS) or mestimator_spec_as(est, nk.DCS_AGARWAL)
    return mestimator_spec_as(est, code)


def mestimator_spec_as(est, code: int) -> tuple[int, float] | None:
    """(code, parameter) if the kernels' formulas of ``code`` reproduce ``est``, else None."""
    try:
        tokens = est.serialize().split("\n")[1].split()
        scheme = int(tokens[3])
        param = float(tokens[4]) if code != nk.GAUSSIAN else 0.0
    except (IndexError, ValueError, RuntimeError):
        return None
    if scheme != int(_M.Base.ReweightScheme.Block):
        return None
    scale = param if param > 0 else 1.0
    base = np.array([0.0, 1e-3, 0.1, 0.5, 0.999, 1.0, 1.001, 1.7, 3.0, 10.0, 1e3])
    d = np.concatenate([scale * base, np.sqrt(scale) * base[1:]])  # thresholds on d and on d²
    w, rho = nk.robust_weight_loss(code, np.full_like(d, param), d * d)
    ref_w = np.array([est.weight(x) for x in d])
    ref_rho = np.array([est.loss(x) for x in d])
    ok = np.allclose(w, ref_w, rtol=1e-12, atol=1e-300) and np.allclose(rho, ref_rho, rtol=1e-12, atol=1e-300)
    return (code, param) if ok else None


def noise_spec(noise, d: int) -> tuple[np.ndarray, int, float] | None:
    """(upper-triangular R, robust code, parameter) of a noise model, None if it is not native
    (constrained, other dimension, unsupported m-estimator)."""
    code, param = nk.GAUSSIAN, 0.0
    if isinstance(noise, gtsam.noiseModel.Robust):
        est = mestimator_spec(noise.robust())
        if est is None:
            return None
        code, param = est
        noise = noise.noise()
    if not isinstance(noise, gtsam.noiseModel.Gaussian) or noise.isConstrained() or noise.dim() != d:
        return None
    R = np.asarray(noise.R(), dtype=np.float64)
    if R.shape != (d, d) or not np.all(np.isfinite(R)):
        return None
    return upper_sqrt_information(R[None])[0], code, param


def upper_sqrt_information(R: np.ndarray) -> np.ndarray:
    """(m, d, d) square roots of information (RᵀR = Ω) made upper triangular by QR (kept if already)."""
    R = np.asarray(R, dtype=np.float64)
    if not np.any(np.tril(R, -1)):
        return R
    return np.triu(np.linalg.qr(R, mode="r"))


def sqrt_of_information(info: np.ndarray) -> np.ndarray:
    """(m, d, d) information Ω → upper-triangular R with RᵀR = Ω (Cholesky, like GTSAM's Gaussian::Information);
    runs of equal Ω (one noise model for many factors) are factorized once, and one Ω for all factors
    gives its R broadcast (a read-only view: no (m, d, d) array)."""
    info = np.asarray(info, dtype=np.float64)
    m = len(info)
    if m > 1:
        start = np.ones(m, dtype=bool)
        np.any(info[1:] != info[:-1], axis=(1, 2), out=start[1:])
        runs = np.count_nonzero(start)
        if runs == 1:
            return np.broadcast_to(sqrt_of_information(info[:1])[0], info.shape)
        if 2 * runs < m:
            first = np.flatnonzero(start)
            return np.repeat(sqrt_of_information(info[first]), np.diff(np.append(first, m)), axis=0)
    try:
        return np.ascontiguousarray(np.linalg.cholesky(info).transpose(0, 2, 1))
    except np.linalg.LinAlgError:  # semi-definite: symmetric square root, then QR
        lam, V = np.linalg.eigh(0.5 * (info + info.transpose(0, 2, 1)))
        return upper_sqrt_information(np.sqrt(np.maximum(lam, 0.0))[:, :, None] * V.transpose(0, 2, 1))


def _robust_arrays(robust, m: int) -> nk.Robust | None:
    """None, ("huber", k) or (codes, params) → per-factor :class:`~.native_kernels.Robust`."""
    if robust is None:
        return None
    code, param = robust
    if isinstance(code, str):
        key = code.lower().replace("_", "").replace("-", "")
        if key not in nk.ROBUST_NAMES:
            raise ValueError(f"unknown robust kernel {code!r}; known: {sorted(nk.ROBUST_NAMES)}")
        code = nk.ROBUST_NAMES[key]
    return nk.Robust.make(code, param, m)


def _stack_R(sqrt_information, information, m: int, d: int) -> np.ndarray:
    """(m, d, d) upper-triangular R from one (d, d) or per-factor (m, d, d) Ω or R."""
    if (sqrt_information is None) == (information is None):
        raise ValueError("give exactly one of sqrt_information and information")
    given = np.asarray(information if information is not None else sqrt_information, dtype=np.float64)
    one = given.ndim == 2
    M = given.reshape(1, d, d) if one else given.reshape(m, d, d)
    R = sqrt_of_information(M) if information is not None else upper_sqrt_information(M)
    return np.broadcast_to(R, (m, d, d)) if one else R


def _pose3_arrays(poses, what: str) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) tuple, (n, 4, 4) / (n, 3, 4) matrices or (n, 12) rows [R row-major, t] → R (n,3,3), t (n,3)."""
    if isinstance(poses, tuple):
        R, t = poses
        return np.asarray(R, dtype=np.float64).reshape(-1, 3, 3), np.asarray(t, dtype=np.float64).reshape(-1, 3)
    P = np.asarray(poses, dtype=np.float64)
    if P.ndim == 3 and P.shape[1:] in ((4, 4), (3, 4)):
        return P[:, :3, :3], P[:, :3, 3]
    if P.ndim == 2 and P.shape[1] == 12:
        return P[:, :9].reshape(-1, 3, 3), P[:, 9:]
    raise ValueError(f"{what}: expected (R, t), (n, 4, 4), (n, 3, 4) or (n, 12), got shape {P.shape}")


# ---------------------------------------------------------------------------------------------
# Per pose kind: factors, dof map and the assembly plan
# ---------------------------------------------------------------------------------------------

@dataclass
class _Kind:
    """The variables of one pose type (d = 3: Pose2, d = 6: Pose3) and their native factors."""

    d: int
    keys: np.ndarray                  # sorted uint64
    between: object | None = None     # Pose2Factors / Pose3Factors with i set
    prior: object | None = None       # … with i None
    gvar: np.ndarray | None = None    # global variable index of each pose
    dof: np.ndarray | None = None     # (n, d) global dofs, None if they are simply 0..n·d−1
    cidx: np.ndarray | None = None    # vertex of each diagonal contribution: between i, between j, prior
    sym: tuple = ()
    dseg: int = 0                     # offset of the diagonal sums (nsym, n) in the source array
    hseg: int = 0                     # offset of the off-diagonal blocks
    hsize: int = 0
    pairs: tuple | None = None        # duplicate pairs: (pair id, flipped, n pairs)
    symk: np.ndarray | None = None    # (d, d): entry (a, b) of a diagonal block is sum row symk[a, b]
    pair_ends: tuple | None = None    # duplicate pairs: the (lo, hi) poses of each pair
    first_dof: np.ndarray | None = None   # each pose's first dof (the factor form's product)

    @property
    def n(self) -> int:
        return len(self.keys)

    @property
    def nb(self) -> int:
        return 0 if self.between is None else self.between.size

    @property
    def np_(self) -> int:
        return 0 if self.prior is None else self.prior.size


def _sym_pairs(d: int) -> tuple:
    return tuple(zip(*np.triu_indices(d))) if d != 3 else nk.SYM3


@dataclass
class _Others:
    """The factors GTSAM linearizes (anything not native) and the variables GTSAM retracts."""

    graph: gtsam.NonlinearFactorGraph
    keys: np.ndarray            # sorted keys of graph's factors
    dofs: np.ndarray            # global dof of each column of their sparse Jacobian
    var_keys: list              # keys of non-pose variables (retracted by gtsam)
    var_slices: list            # (lo, hi) dofs of each
    touched2: np.ndarray        # local Pose2 / Pose3 indices of poses these factors need
    touched3: np.ndarray


def _pose2_of_rows(rows: np.ndarray) -> np.ndarray:
    """The Pose2 state of ``extractPose2``'s rows (x, y, θ)."""
    return nk.pose2_state(rows[:, 0], rows[:, 1], rows[:, 2])


def _pose3_of_rows(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(R (n, 3, 3), t (n, 3)) of ``extractPose3``'s rows (R row-major, then t)."""
    return np.ascontiguousarray(rows[:, :9].reshape(-1, 3, 3)), np.ascontiguousarray(rows[:, 9:12])


class NativeLinearizer:
    """:class:`~gtsam_schwarz.linearization.base.Linearizer` with vectorized numpy kernels for pose graphs.

    ``NativeLinearizer(graph, values)`` reads the factors once (``values`` only for the variable types);
    :meth:`from_arrays` builds it from numpy arrays without a gtsam graph (file loaders). The state is a
    :class:`NativeState`; for a pure pose graph no gtsam call happens per iteration.
    """

    @with_small_pages
    def __init__(self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values):
        t0 = time.perf_counter()
        keys = np.asarray(graph.keyVector(), dtype=np.uint64)   # sorted (a KeySet)
        have = np.sort(np.asarray(values.keys(), dtype=np.uint64))
        missing = ~nk.in_sorted(keys, have)
        if np.any(missing):
            raise KeyError(f"graph key {gtsam.DefaultKeyFormatter(int(keys[missing][0]))} has no initial value")
        keys2 = keys[nk.in_sorted(keys, np.sort(np.asarray(gtsam.utilities.allPose2s(values).keys(), dtype=np.uint64)))]
        keys3 = keys[nk.in_sorted(keys, np.sort(np.asarray(gtsam.utilities.allPose3s(values).keys(), dtype=np.uint64)))]
        other_vars = keys[~(nk.in_sorted(keys, keys2) | nk.in_sorted(keys, keys3))]
        lists = {k: ([], [], [], [], []) for k in ("b2", "p2", "b3", "p3")}   # i, j, z, noise spec, factor index
        other_ids = []
        specs, keep = {}, []           # noise model → spec index (shared models are looked at once)
        spec_list = []
        other = gtsam.NonlinearFactorGraph()
        native = {gtsam.BetweenFactorPose2: ("b2", 3), gtsam.PriorFactorPose2: ("p2", 3),
                  gtsam.BetweenFactorPose3: ("b3", 6), gtsam.PriorFactorPose3: ("p3", 6)}
        for idx in range(graph.size()):  # one pass over the factors, a few gtsam calls each
            f = graph.at(idx)
            if f is None:
                continue
            kind = native.get(type(f))
            if kind is not None:
                name, d = kind
                nm = f.noiseModel()
                s = specs.get(id(nm))
                if s is None:
                    keep.append(nm)    # keeps id(nm) unique while the loop runs
                    spec = noise_spec(nm, d)
                    s = specs[id(nm)] = -1 if spec is None else len(spec_list)
                    if spec is not None:
                        spec_list.append(spec)
                fk = f.keys()
                if s >= 0:
                    li, lj, lz, ls, lf = lists[name]
                    if name[0] == "b":
                        if fk[0] != fk[1]:
                            li.append(fk[0])
                            lj.append(fk[1])
                            m = f.measured()
                            lz.append((m.x(), m.y(), m.theta()) if d == 3 else m.matrix())
                            ls.append(s)
                            lf.append(idx)
                            continue
                    else:
                        lj.append(fk[0])
                        m = f.prior()
                        lz.append((m.x(), m.y(), m.theta()) if d == 3 else m.matrix())
                        ls.append(s)
                        lf.append(idx)
                        continue
            other.push_back(f)
            other_ids.append(idx)
        self.seconds_extract = time.perf_counter() - t0

        def factors(name, kind_keys, d):
            li, lj, lz, ls, lf = lists[name]
            if not lj:
                return None
            s = np.asarray(ls, dtype=np.int64)
            uniq, inv = sorted_unique(s, return_inverse=True)   # the distinct noise models
            used = [spec_list[u] for u in uniq.tolist()]
            # one noise model for all (the usual graph): its R broadcast, no (m, d, d) copies
            R = (np.broadcast_to(used[0][0], (len(s),) + used[0][0].shape) if len(used) == 1
                 else np.stack([spec[0] for spec in used])[inv])
            code = np.asarray([spec[1] for spec in used], dtype=np.int8)[inv]
            param = np.asarray([spec[2] for spec in used], dtype=np.float64)[inv]
            j = np.searchsorted(kind_keys, np.asarray(lj, dtype=np.uint64))
            i = np.searchsorted(kind_keys, np.asarray(li, dtype=np.uint64)) if name[0] == "b" else None
            return {"i": i, "j": j, "z": lz, "R": R, "robust": nk.Robust.make(code, param, len(s)),
                    "ids": np.asarray(lf, dtype=np.int64)}

        kinds = {}
        for tag, kk, d in (("2", keys2, 3), ("3", keys3, 6)):
            if len(kk):
                kinds[d] = (kk, factors("b" + tag, kk, d), factors("p" + tag, kk, d))
        all_dims = values.dims() if len(other_vars) else {}
        other_dims = np.asarray([all_dims[int(k)] for k in other_vars], dtype=np.int64)
        self.n_factors = int(graph.size())
        self._setup(kinds, other, other_vars, other_dims, values)
        self._other_ids = np.asarray(other_ids, dtype=np.int64)
        self.seconds_construct = time.perf_counter() - t0

    # -----------------------------------------------------------------------------------------
    @classmethod
    @with_small_pages
    def from_arrays(cls, kind: str, keys, poses, edges=None, measurements=None, *, information=None,
                    sqrt_information=None, robust=None, prior_keys=None, prior_measurements=None,
                    prior_information=None, prior_sqrt_information=None, prior_robust=None) -> "NativeLinearizer":
        """A linearizer of a pure pose graph from numpy arrays (no gtsam graph, e.g. from a g2o reader).

        kind: "pose2" or "pose3". keys (n,): pose ids (any order, unique); poses: Pose2 (n, 3) (x, y, θ);
        Pose3 (R (n,3,3), t (n,3)) or (n, 4, 4) / (n, 3, 4) / (n, 12). edges (m, 2) of ids (i, j) with
        measurements z of xi⁻¹xj in the same formats; information Ω or sqrt_information R, (m, d, d) or
        one (d, d), in GTSAM's tangent order (Pose3: rotation first — g2o files store translation first).
        robust: None, ("huber", k) or (codes, params) per edge. prior_*: the same for priors e = Log(z⁻¹x).
        The variables are the poses some factor touches (as ``graph.keyVector()``), in sorted key order;
        ``initial_state()`` returns their state from ``poses``.
        """
        t0 = time.perf_counter()
        d = {"pose2": 3, "pose3": 6}.get(str(kind).lower())
        if d is None:
            raise ValueError(f"kind must be 'pose2' or 'pose3', not {kind!r}")
        keys = np.asarray(keys, dtype=np.uint64).ravel()
        order = np.argsort(keys, kind="stable")
        skeys = keys[order]
        if len(skeys) > 1 and np.any(skeys[1:] == skeys[:-1]):
            raise ValueError("pose keys are not unique")

        contiguous = len(skeys) > 0 and int(skeys[0]) == 0 and int(skeys[-1]) == len(skeys) - 1  # ids 0..n−1

        def index(ids):
            ids = np.asarray(ids, dtype=np.uint64).ravel()
            if contiguous:   # unique sorted keys 0..n−1: an id is its own index
                if len(ids) and int(ids.max()) >= len(skeys):
                    raise KeyError("an edge or prior refers to an unknown pose id")
                return ids.astype(np.int64)
            pos = np.searchsorted(skeys, ids)
            if len(ids) and (np.any(pos >= len(skeys)) or np.any(skeys[np.minimum(pos, len(skeys) - 1)] != ids)):
                raise KeyError("an edge or prior refers to an unknown pose id")
            return pos

        def meas(z, m):
            if d == 3:
                z = np.asarray(z, dtype=np.float64).reshape(m, 3)
                return z.T
            R, t = _pose3_arrays(z, "measurements")
            return (R, t)

        between = prior = None
        if edges is not None and len(edges):
            E = np.asarray(edges).reshape(-1, 2)
            m = len(E)
            between = {"i": index(E[:, 0]), "j": index(E[:, 1]), "z": meas(measurements, m),
                       "R": _stack_R(sqrt_information, information, m, d), "robust": _robust_arrays(robust, m),
                       "ids": np.arange(m)}
            if np.any(between["i"] == between["j"]):
                raise ValueError("an edge connects a pose to itself")
        if prior_keys is not None and len(np.atleast_1d(prior_keys)):
            pj = index(prior_keys)
            m = len(pj)
            mb = 0 if between is None else len(between["j"])
            prior = {"i": None, "j": pj, "z": meas(prior_measurements, m),
                     "R": _stack_R(prior_sqrt_information, prior_information, m, d),
                     "robust": _robust_arrays(prior_robust, m), "ids": mb + np.arange(m)}
        # the variables are the poses some factor touches (like graph.keyVector()); renumber
        used = np.zeros(len(skeys), dtype=bool)
        for spec in (between, prior):
            if spec is not None:
                used[spec["j"]] = True
                if spec["i"] is not None:
                    used[spec["i"]] = True
        if not np.all(used):
            new_index = np.cumsum(used) - 1
            for spec in (between, prior):
                if spec is not None:
                    spec["j"] = new_index[spec["j"]]
                    if spec["i"] is not None:
                        spec["i"] = new_index[spec["i"]]
            skeys, order = skeys[used], order[used]
        self = cls.__new__(cls)
        self.seconds_extract = time.perf_counter() - t0
        self.n_factors = (0 if between is None else len(between["j"])) + (0 if prior is None else len(prior["j"]))
        self._other_ids = np.zeros(0, np.int64)
        self._setup({d: (skeys, between, prior)}, None, np.zeros(0, np.uint64), np.zeros(0, np.int64), None)
        self.seconds_construct = time.perf_counter() - t0
        if d == 3:
            P = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
        else:
            P = _pose3_arrays(poses, "poses")
        # their state is made when asked (an optimizer given gtsam.Values reads those instead:
        # 1M 2D poses, 30 MB and ~30 ms not spent)
        self._initial, self._initial_poses = None, (d, P, order)
        return self

    def initial_state(self) -> NativeState:
        """The state of the poses given to :meth:`from_arrays` (read from their arrays on the first call)."""
        if self._initial is None:
            if getattr(self, "_initial_poses", None) is None:
                raise RuntimeError("the poses given to from_arrays were released (release_initial)")
            d, P, order = self._initial_poses
            if d == 3:
                P = P[order]
                self._initial = NativeState(pose2=nk.pose2_state(P[:, 0], P[:, 1], P[:, 2]))
            else:
                R, t = P
                self._initial = NativeState(R3=np.ascontiguousarray(R[order]), t3=np.ascontiguousarray(t[order]))
            self._initial_poses = None
        return self._initial

    def release_initial(self) -> None:
        """Drop the poses given to :meth:`from_arrays` where the caller solves from other values and will
        not ask for :meth:`initial_state` (1M 2D poses: 31 MiB held through the solve otherwise)."""
        self._initial_poses = None

    # -----------------------------------------------------------------------------------------
    def _setup(self, kinds: dict, other_graph, other_vars, other_dims, values) -> None:
        """Global variable order, factor arrays, the fixed CSR pattern and its gather plan."""
        k2 = kinds.get(3)
        k3 = kinds.get(6)
        blocks = {d: len(spec[0]) + 2 * (len(spec[1]["j"]) if spec[1] is not None else 0)
                  for d, spec in kinds.items() if spec is not None}   # at most: edges may repeat a pair
        fresh = CONSTRUCTION_BYTES_PER_ENTRY * sum(d * d * nb for d, nb in blocks.items())
        if fresh >= CONSTRUCTION_POPULATE_FROM:
            populate_ahead(fresh)
        parts = [(k2[0], 3) if k2 else (np.zeros(0, np.uint64), 3), (k3[0], 6) if k3 else (np.zeros(0, np.uint64), 6)]
        all_keys = np.concatenate([parts[0][0], parts[1][0], other_vars]).astype(np.uint64)
        all_dims = np.concatenate([np.full(len(parts[0][0]), 3), np.full(len(parts[1][0]), 6), other_dims]).astype(np.int64)
        order = np.argsort(all_keys, kind="stable")
        self.keys = all_keys[order]
        self.dims = all_dims[order]
        self.offsets = np.zeros(len(self.keys) + 1, dtype=np.int64)
        np.cumsum(self.dims, out=self.offsets[1:])
        self.dim = int(self.offsets[-1])

        def var_index(k):
            return np.searchsorted(self.keys, k)

        self._k2 = self._k3 = None
        self._base = None  # (gtsam.Values read by state(), the rows read): the base of values()
        rows, cols = [], []
        for d, spec in ((3, k2), (6, k3)):
            if spec is None:
                continue
            kk, b, p = spec
            K = _Kind(d=d, keys=kk)
            K.gvar = var_index(kk)
            dof = self.offsets[K.gvar][:, None] + np.arange(d)
            K.dof = None if (len(kk) * d == self.dim and np.array_equal(dof.ravel(), np.arange(self.dim))) else dof
            K.between = self._factors(d, b) if b is not None else None
            K.prior = self._factors(d, p) if p is not None else None
            if K.between is not None:
                rows.append(K.gvar[K.between.i])
                cols.append(K.gvar[K.between.j])
            if d == 3:
                self._k2 = K
            else:
                self._k3 = K

        # other factors (GTSAM): their key sets couple variables too
        self._others = None
        if other_graph is not None and (other_graph.size() or len(other_vars)):
            self._others = self._setup_others(other_graph, other_vars, values, var_index, rows, cols)

        self.nnz_estimate = int(sum(d * d * nb for d, nb in blocks.items()))   # H's entries (exact without repeated pairs)
        rows = np.concatenate(rows) if rows else np.zeros(0, np.int64)
        cols = np.concatenate(cols) if cols else np.zeros(0, np.int64)
        # the pattern and its gather plan are needed by the first linearization only: they are made on
        # the background thread meanwhile (reading the start, the chordal start: 1M 2D poses ~1.8 s, of
        # which ~1.1 s on one core), small graphs here
        if self.nnz_estimate >= BACKGROUND_PLAN_FROM:
            self._planning = background_thread().submit(self._make_plan, rows, cols)
        else:
            self._planning = None
            self._make_plan(rows, cols)
        self._translation = self._translation_mask(values)
        self.seconds = {}
        self._buffers = {}
        self._kept_residuals = None  # (state, {id(factor group): residual chunks}) of the last error evaluation
        self.keep_residuals = True  # False: none kept (a caller whose memory peak sits beside the linearization)

    def _make_plan(self, rows: np.ndarray, cols: np.ndarray) -> None:
        """The fixed CSR pattern of H (blocks of the coupled variable pairs ``rows``, ``cols``), its
        diagonal and the gather plan (:meth:`_plan`)."""
        t0 = time.perf_counter()
        self._pattern = nk.BlockPattern(self.dims, rows, cols)
        self._plan()
        self._pattern.forget_block_keys()   # made again only if a later lookup of blocks needs them
        diagonal = self._pattern.diagonal_positions()   # 32 bits where H's entries are numbered so
        self._diagonal = diagonal.astype(np.int32) if self._pattern.nnz < 2**31 - 1 else diagonal
        self._seconds_pattern = time.perf_counter() - t0

    def _planned(self) -> None:
        """Wait for the pattern and plan made on the background thread (re-raising its error)."""
        job = self._planning
        if job is not None:
            job.result()
            self._planning = None

    @property
    def pattern(self) -> nk.BlockPattern:
        """H's fixed CSR pattern (waits for its construction)."""
        self._planned()
        return self._pattern

    @property
    def diagonal(self) -> np.ndarray:
        """Positions of H's diagonal in its data."""
        self._planned()
        return self._diagonal

    @property
    def seconds_pattern(self) -> float:
        """Seconds the pattern and its gather plan took (on whichever thread made them)."""
        self._planned()
        return self._seconds_pattern

    @staticmethod
    def _factors(d: int, spec: dict):
        if d == 3:
            R = spec["R"]
            if R.strides[0] == 0:   # one R for all factors (broadcast): its six rows broadcast too
                r6 = np.broadcast_to(R[0][np.triu_indices(3)][:, None], (6, len(R)))
            else:
                r6 = np.stack([R[:, 0, 0], R[:, 0, 1], R[:, 0, 2], R[:, 1, 1], R[:, 1, 2], R[:, 2, 2]])
            z = spec["z"]
            z = np.asarray(z, dtype=np.float64).reshape(-1, 3).T if isinstance(z, list) else z
            perm, n_iso = nk.iso_first(r6)   # isotropic-translation factors first: cheaper kernel
            if n_iso in (0, len(perm)):
                perm = slice(None)
            rob = spec["robust"]
            if rob is not None:
                rob = nk.Robust.make(rob.code[perm], rob.param[perm], len(r6[0]))
            F = nk.Pose2Factors(j=spec["j"][perm], z=z[:, perm], R=r6[:, perm],
                                i=None if spec["i"] is None else spec["i"][perm], robust=rob, n_iso=n_iso)
            F.ids = np.asarray(spec["ids"])[perm]
            return F
        z = spec["z"]
        if isinstance(z, list):
            M = np.asarray(z, dtype=np.float64).reshape(-1, 4, 4)
            zR, zt = M[:, :3, :3], M[:, :3, 3]
        else:
            zR, zt = z
        F = nk.Pose3Factors(j=spec["j"], zR=zR, zt=zt, R=spec["R"], i=spec["i"], robust=spec["robust"])
        F.ids = spec["ids"]
        return F

    def _setup_others(self, graph, other_vars, values, var_index, rows, cols) -> _Others:
        keys_per_factor = [graph.at(i).keys() for i in range(graph.size()) if graph.at(i) is not None]
        sub_keys = sorted_unique(np.asarray([k for ks in keys_per_factor for k in ks], dtype=np.uint64))
        for ks in keys_per_factor:
            v = var_index(np.asarray(ks, dtype=np.uint64))
            if len(v) > 1:
                a, b = np.meshgrid(v, v, indexing="ij")
                off = a != b
                rows.append(a[off])
                cols.append(b[off])
        vi = var_index(sub_keys)
        dofs = np.concatenate([np.arange(self.offsets[v], self.offsets[v + 1]) for v in vi]) if len(vi) else np.zeros(0, np.int64)
        ov = var_index(other_vars)
        touched2 = touched3 = np.zeros(0, np.int64)
        if self._k2 is not None:
            touched2 = np.flatnonzero(nk.in_sorted(self._k2.keys, sub_keys))
        if self._k3 is not None:
            touched3 = np.flatnonzero(nk.in_sorted(self._k3.keys, sub_keys))
        return _Others(graph=graph, keys=sub_keys, dofs=dofs.astype(np.int64),
                       var_keys=[int(k) for k in other_vars],
                       var_slices=[(int(self.offsets[v]), int(self.offsets[v + 1])) for v in ov],
                       touched2=touched2, touched3=touched3)

    def _plan(self) -> None:
        """The source-array layout and the gather index that fills H's CSR data from it."""
        P = self._pattern
        size = 0
        puts = []   # (block rows, block cols, base, coef): entry (a, b) of block t reads source base[t] + coef[a, b]
        for K in (self._k2, self._k3):
            if K is None:
                continue
            d = K.d
            K.sym = _sym_pairs(d)
            nsym = len(K.sym)
            symk = np.empty((d, d), dtype=np.int64)
            for s, (a, b) in enumerate(K.sym):
                symk[a, b] = symk[b, a] = s
            K.symk = symk
            cidx = [K.between.i, K.between.j] if K.between is not None else []
            if K.prior is not None:
                cidx.append(K.prior.j)
            # summed by bincount only: 32 bits where the poses' numbers fit (1M 2D poses: 15 MiB less)
            itype = np.int32 if K.n < 2**31 - 1 else np.int64
            K.cidx = np.concatenate(cidx).astype(itype) if cidx else np.zeros(0, itype)
            K.dseg = size
            size += nsym * K.n
            puts.append((K.gvar, K.gvar, K.dseg + np.arange(K.n), symk * K.n))
            if K.between is None:
                continue
            F = K.between
            m = F.size
            gi, gj = K.gvar[F.i], K.gvar[F.j]
            lo, hi = np.minimum(gi, gj), np.maximum(gi, gj)
            pk = lo * len(self.keys) + hi
            upk, pid = sorted_unique(pk, return_inverse=True)
            K.hseg = size
            a = np.arange(d)[:, None]
            b = np.arange(d)[None, :]
            if len(upk) == m:  # every pair once: blocks straight from the per-factor arrays
                K.pairs = None
                f = np.arange(m)
                if d == 3:   # SoA (9, m)
                    base, ab, ba = K.hseg + f, (a * 3 + b) * m, (b * 3 + a) * m
                else:        # AoS (m, 6, 6)
                    base, ab, ba = K.hseg + f * 36, a * 6 + b, b * 6 + a
                K.hsize = d * d * m
                puts.append((gi, gj, base, ab))
                puts.append((gj, gi, base, ba))
            else:              # duplicate pairs: summed per (lo, hi) pair into (d², n pairs)
                npairs = len(upk)
                K.pairs = (pid, gi > gj, npairs)
                K.hsize = d * d * npairs
                first = np.zeros(npairs, dtype=np.int64)
                first[pid[::-1]] = np.arange(m - 1, -1, -1)   # first factor of each pair
                plo, phi = lo[first], hi[first]
                forward = gi[first] <= gj[first]   # the pair's ends as poses of this kind (factor form)
                K.pair_ends = (np.where(forward, F.i[first], F.j[first]), np.where(forward, F.j[first], F.i[first]))
                base = K.hseg + np.arange(npairs)
                puts.append((plo, phi, base, (a * d + b) * npairs))
                puts.append((phi, plo, base, (b * d + a) * npairs))
            size += K.hsize
        self._zero = size          # S[size] = 0: entries only GTSAM-linearized factors fill
        self._src_size = size + 1
        # entry-sized: int32 where the source array allows (half the memory)
        self._src = P.source_index(puts, fill=size, dtype=np.int32 if size < 2**31 - 1 else np.int64)
        self._block_map = self._make_block_map(puts, self._src.dtype)
        self._other_pos = None  # (indptr, indices, positions) of the last H of the other factors

    # -----------------------------------------------------------------------------------------
    # Linearizer protocol
    # -----------------------------------------------------------------------------------------
    def state(self, values: gtsam.Values) -> NativeState:
        """Pose arrays (sorted keys) and the other variables of ``values``."""
        st = NativeState()
        if self._k2 is not None:
            rows = self._rows(values, self._k2.keys, gtsam.utilities.allPose2s, gtsam.utilities.extractPose2)
            st.pose2 = _pose2_of_rows(rows)
            read = rows
        if self._k3 is not None:
            rows = self._rows(values, self._k3.keys, gtsam.utilities.allPose3s, gtsam.utilities.extractPose3)
            st.R3, st.t3 = _pose3_of_rows(rows)
            read = rows
        if self._others is not None and self._others.var_keys:
            st.others = values.extract(self._others.var_keys)
        elif (self._k2 is None) != (self._k3 is None) and values.size() == len(self._kind().keys):
            # the result will be these values retracted (one C++ call) by the local coordinates of the
            # final poses, not 2·n pybind11 calls building poses and inserting them. Referenced, not
            # copied (262 145 poses: 85 ms); values() checks that they still hold what was read.
            self._base = (values, read)   # (the start's state is made again from the rows read)
        return st

    @property
    def prior_vertices(self) -> np.ndarray | None:
        """The variables of the prior factors where every factor is native (between factors are unchanged
        by a rigid motion of their component, so only these rows of Hz can be nonzero for one: the gauge
        test reads them alone); None where GTSAM linearizes factors."""
        if self._others is not None:
            return None
        found = [K.gvar[K.prior.j] for K in (self._k2, self._k3) if K is not None and K.prior is not None]
        return np.concatenate(found).astype(np.int64) if found else np.zeros(0, dtype=np.int64)

    def _kind(self):
        """The one pose kind of a graph of Pose2s only or Pose3s only."""
        return self._k2 if self._k2 is not None else self._k3

    @staticmethod
    def _rows(values, keys, all_of, extract) -> np.ndarray:
        table = extract(values)   # rows in key order, like values.keys()
        if len(table) == values.size():   # all values of this kind: no filtered copy of them needed
            have = np.asarray(values.keys(), dtype=np.uint64)
            if np.array_equal(have, keys):
                return table
        else:
            have = np.asarray(all_of(values).keys(), dtype=np.uint64)
        order = np.argsort(have, kind="stable")
        pos = np.searchsorted(have, keys, sorter=order)
        if len(keys) and (np.any(pos >= len(have)) or np.any(have[order[np.minimum(pos, len(have) - 1)]] != keys)):
            raise KeyError("values lack a pose of the graph")
        return table[order[pos]]

    def values(self, state: NativeState) -> gtsam.Values:
        """``gtsam.Values`` of ``state`` (only when asked for). A graph of Pose2s only or Pose3s only,
        read from one ``gtsam.Values``: that Values retracted by the final poses' local coordinates
        (GTSAM's retract, C++; 262 145 Pose2s 0.68 -> 0.49 s, 2 500 Pose3s 17.5 -> 6 ms); otherwise
        one insert per pose. Pose3s are read back and compared (GTSAM's Pose3 chart is a build
        option): a chart other than :func:`~.native_kernels.pose3_retract`'s falls back to inserts."""
        if self._base is not None and state.others is None and self._base_unchanged():
            base, read = self._base
            if self._k2 is not None:
                delta = nk.pose2_local(_pose2_of_rows(read), state.pose2)
            else:
                delta = nk.pose3_local(*_pose3_of_rows(read), state.R3, state.t3)
            vv = gtsam.VectorValues()
            deque(map(vv.insert, self._kind().keys.tolist(), delta), maxlen=0)  # the calls without a Python loop
            out = base.retract(vv)
            if self._k2 is not None or self._same_poses3(out, state):
                return out
        out = gtsam.Values(state.others) if state.others is not None else gtsam.Values()
        self._insert_poses(out, state, None, None)
        return out

    def _same_poses3(self, values: gtsam.Values, state: NativeState, tol: float = 1e-9) -> bool:
        """Whether ``values`` holds the state's Pose3s (to ``tol`` in rotation entries and relative
        translation), by one C++ extraction."""
        rows = self._rows(values, self._k3.keys, gtsam.utilities.allPose3s, gtsam.utilities.extractPose3)
        R, t = rows[:, :9].reshape(-1, 3, 3), rows[:, 9:12]
        scale = 1.0 + np.abs(state.t3).max(initial=0.0)
        return bool(np.abs(R - state.R3).max(initial=0.0) <= tol and np.abs(t - state.t3).max(initial=0.0) <= tol * scale)

    def _base_unchanged(self) -> bool:
        """Whether the values read by state() still hold the poses read (the caller may have changed
        them since): their size, keys and poses, by one C++ extraction (262 145 Pose2s: 40 ms)."""
        base, read = self._base
        if base.size() != len(read):
            return False
        kinds = ((gtsam.utilities.allPose2s, gtsam.utilities.extractPose2) if self._k2 is not None
                 else (gtsam.utilities.allPose3s, gtsam.utilities.extractPose3))
        try:
            now = self._rows(base, self._kind().keys, *kinds)
            return bool(np.array_equal(now, read))
        except KeyError:
            return False

    def _insert_poses(self, out, state, idx2, idx3) -> None:
        if self._k2 is not None:
            keys = self._k2.keys if idx2 is None else self._k2.keys[idx2]
            P = state.pose2 if idx2 is None else state.pose2[:, idx2]
            _insert_all(out, keys.tolist(), map(gtsam.Pose2, P[0].tolist(), P[1].tolist(), nk.pose2_theta(P).tolist()),
                        "pose2")
        if self._k3 is not None:
            keys = self._k3.keys if idx3 is None else self._k3.keys[idx3]
            R = state.R3 if idx3 is None else state.R3[idx3]
            t = state.t3 if idx3 is None else state.t3[idx3]
            _insert_all(out, keys.tolist(), map(gtsam.Pose3, map(gtsam.Rot3, R), t), "pose3")

    def retract(self, state: NativeState, x: np.ndarray) -> NativeState:
        """state ⊕ x: poses x·Exp(δ) in numpy, other variables by ``Values.retract``."""
        x = np.asarray(x, dtype=np.float64)
        if x.shape != (self.dim,):
            raise ValueError(f"step has shape {x.shape}, expected ({self.dim},)")
        out = NativeState()
        out._cache["stepped"] = True   # a step's state: linearized next where LM accepts it
        if self._k2 is not None:
            K = self._k2
            v = x.reshape(-1, 3) if K.dof is None else x[K.dof]
            out.pose2 = nk.pose2_retract(state.pose2, v)
        if self._k3 is not None:
            K = self._k3
            v = x.reshape(-1, 6) if K.dof is None else x[K.dof]
            out.R3, out.t3 = nk.pose3_retract(state.R3, state.t3, v)
        if state.others is not None:
            vv = gtsam.VectorValues()
            for k, (lo, hi) in zip(self._others.var_keys, self._others.var_slices):
                vv.insert(k, x[lo:hi])
            out.others = state.others.retract(vv)
        return out

    def _residual(self, state: NativeState, d: int, Fc):
        return nk.pose2_residual(state.pose2, Fc) if d == 3 else nk.pose3_residual(state.R3, state.t3, Fc)

    def _chunk_residuals(self, state: NativeState, K: _Kind, F):
        """Residuals of the chunks of factor group F at ``state``: those :meth:`_native_error` kept for
        it, else computed one chunk at a time so that a chunk's arrays are still in cache when its
        blocks are built."""
        kept = self._kept_residuals
        if kept is not None and kept[0] is state and id(F) in kept[1]:
            yield from kept[1][id(F)]
            return
        for _, _, Fc in F.chunks():
            yield self._residual(state, K.d, Fc)

    def _native_error(self, state: NativeState) -> float:
        """Σ ½‖R e‖² (robust Σ ρ) of the native factors (cached on the state). Up to
        ``KEEP_RESIDUALS_BYTES`` of residual arrays of a state made by :meth:`retract` are kept
        (``keep_residuals``) for its linearization, which in LM follows an accepted step's evaluation
        (262k-pose model problem: 23 of 78 ms saved there); the last evaluation's only, dropped by that
        linearization or :meth:`release_scratch`. A start's state (evaluated once, then replaced by
        the chordal start's) keeps none."""
        c = state._cache
        if "native_error" not in c:
            keep = self.keep_residuals and c.get("stepped", False) and self._residual_bytes() <= KEEP_RESIDUALS_BYTES
            kept: dict = {}
            total = 0.0
            for K in (self._k2, self._k3):
                if K is not None:
                    for F in (K.between, K.prior):
                        if F is not None:
                            chunks = self._chunk_residuals(state, K, F)
                            if keep:
                                chunks = kept[id(F)] = list(chunks)
                            total += sum(r.error for r in chunks)
            c["native_error"] = total
            if keep:
                self._kept_residuals = (state, kept)
        return c["native_error"]

    def _residual_bytes(self) -> int:
        """Bytes of the residual arrays of all native factors (Pose2: 14 numbers a factor, Pose3: 28)."""
        return 8 * sum(per * (K.nb + K.np_) for K, per in ((self._k2, 14), (self._k3, 28)) if K is not None)

    def _other_values(self, state: NativeState) -> gtsam.Values:
        c = state._cache
        if "other_values" not in c:
            vals = gtsam.Values(state.others) if state.others is not None else gtsam.Values()
            self._insert_poses(vals, state, self._others.touched2, self._others.touched3)
            c["other_values"] = vals
        return c["other_values"]

    def error(self, state: NativeState) -> float:
        """Σ ½‖R e‖² (robust: Σ ρ(‖R e‖)) over all factors, equal to ``graph.error(values)``."""
        total = self._native_error(state)
        if self._others is not None and self._others.graph.size():
            total += float(self._others.graph.error(self._other_values(state)))
        return float(total)

    def linearize(self, state: NativeState) -> LinearSystem:
        """H (fixed CSR pattern), g = Σ JᵀW r and the error at ``state``, all native factors at once."""
        self._planned()
        t1 = time.perf_counter()
        gathered = self.factor_form and self.factor_form_possible()
        # reused: H's data is a fresh gather of it; in the factor form H reads it, so it is pooled
        S = self._pooled("source", self._src_size) if gathered else self._buffer("S", (self._src_size,))
        S[self._zero] = 0.0
        g = np.zeros(self.dim)
        error = 0.0
        for K in (self._k2, self._k3):
            if K is not None:
                error += self._kind_system(K, state, S, g)
        state._cache["native_error"] = error
        self._kept_residuals = None
        t2 = time.perf_counter()
        if gathered:
            P = self.pattern
            index = self._src
            if self._block_map is not None:   # the per-entry index is not held while H comes gathered
                index, self._src = self._block_map, None
            H = GatheredCSR.of(P.indptr, P.indices, (P.n, P.n), S, index, self._factor_product(S),
                               diagonal_at=self.diagonal)
            self.seconds = {"blocks": t2 - t1, "gather": 0.0, "gtsam": 0.0}
            return LinearSystem(H=H, g=g, error=float(error), diagonal=self.diagonal, seconds=dict(self.seconds))
        data = self._data_buffer()
        src = self._entry_sources()
        for lo in range(0, len(src), _TAKE_CHUNK):  # int32 positions: numpy converts them a chunk at a time
            np.take(S, src[lo:lo + _TAKE_CHUNK], mode="clip", out=data[lo:lo + _TAKE_CHUNK])
        t3 = time.perf_counter()
        if self._others is not None and self._others.graph.size():
            error += self._add_others(state, data, g)
        H = self.pattern.matrix(data)
        t4 = time.perf_counter()
        self.seconds = {"blocks": t2 - t1, "gather": t3 - t2, "gtsam": t4 - t3}
        return LinearSystem(H=H, g=g, error=float(error), diagonal=self.diagonal, seconds=dict(self.seconds))

    def _kind_system(self, K: _Kind, state: NativeState, S: np.ndarray, g: np.ndarray) -> float:
        """Blocks of one pose kind into the source array S (diagonal sums, off-diagonal blocks) and g;
        returns the kind's error. Residual and blocks are computed chunk by chunk.

        Diagonal contributions (between i, between j, prior) are summed per pose by bincount, a group
        of chunks at a time; off-diagonal blocks go straight to S (or are summed per pair if pairs repeat)."""
        d, nsym = K.d, len(K.sym)
        mb, mp = K.nb, K.np_
        nc = 2 * mb + mp
        error = 0.0
        if d == 3:
            # diagonal contributions a group of chunks at a time, summed per pose by bincount whenever
            # the group's columns are full (about max(n, 2^18) factor ends: the bincounts' O(n) per group
            # stays below their O(columns)); one nc-long scratch of 6 + 3 rows was most of the
            # linearizer's scratch (360 000 Pose2s 104 MB, 1M 288 MB), allocated again beside a
            # Schwarz preconditioner in the iterations after a build
            n = K.n
            width = _group_width(n, nc)
            C = self._buffer(f"C{d}", (nsym, width))
            G = self._buffer(f"G{d}", (d, width))
            D, Gs = self._diagonal_sums(K, S, g)
            group: list = []   # the pose of every filled column, in pieces
            fill = 0

            def flush():
                nonlocal fill
                if fill:
                    idx = np.concatenate(group, dtype=np.intp)   # bincount's index type, converted once
                    for s in range(nsym):
                        D[s] += np.bincount(idx, C[s, :fill], minlength=n)
                    for a in range(d):
                        Gs[a] += np.bincount(idx, G[a, :fill], minlength=n)
                    group.clear()
                    fill = 0

            def columns(poses: list) -> int:
                """The first of len(poses) columns for these ends (the group summed first if full)."""
                nonlocal fill
                k = sum(len(p) for p in poses)
                if fill + k > width:
                    flush()
                group.extend(poses)
                fill += k
                return fill - k

            if K.between is not None:
                hij = S[K.hseg:K.hseg + 9 * mb].reshape(9, mb) if K.pairs is None else np.empty((9, mb))
                for (lo, hi, Fc), rc in zip(K.between.chunks(), self._chunk_residuals(state, K, K.between)):
                    a, k = columns([K.cidx[lo:hi], K.cidx[mb + lo:mb + hi]]), hi - lo
                    nk.pose2_system(Fc, rc, hjj=tuple(C[:, a + k:a + 2 * k]), gj=tuple(G[:, a + k:a + 2 * k]),
                                    hij=tuple(hij[:, lo:hi]), hii=tuple(C[:, a:a + k]), gi=tuple(G[:, a:a + k]))
                    error += rc.error
                if K.pairs is not None:
                    self._pair_sums(K, hij, S)
            if K.prior is not None:
                o = 2 * mb
                for (lo, hi, Fc), rc in zip(K.prior.chunks(), self._chunk_residuals(state, K, K.prior)):
                    a, k = columns([K.cidx[o + lo:o + hi]]), hi - lo
                    nk.pose2_system(Fc, rc, hjj=tuple(C[:, a:a + k]), gj=tuple(G[:, a:a + k]))
                    error += rc.error
            flush()
        else:  # 6×6 blocks: diagonal contributions summed per pose a chunk at a time (no nc-long
            # 21-row scratch: at 91 125 3D poses 110 MB less beside a Schwarz preconditioner)
            ia, ib = np.array(K.sym).T
            n = K.n
            D, Gs = self._diagonal_sums(K, S, g)

            def add(idx, blocks, grads):  # blocks (m, 6, 6), grads (m, 6) at the poses idx
                vals = blocks[:, ia, ib].T
                for s in range(nsym):
                    D[s] += np.bincount(idx, vals[s], minlength=n)
                for a in range(d):
                    Gs[a] += np.bincount(idx, grads[:, a], minlength=n)

            if K.between is not None:
                hij_all = S[K.hseg:K.hseg + 36 * mb].reshape(mb, 36) if K.pairs is None else np.empty((mb, 36))
                for (lo, hi, Fc), rc in zip(K.between.chunks(), self._chunk_residuals(state, K, K.between)):
                    hjj, gj, hij, hii, gi = nk.pose3_system(Fc, rc)
                    add(np.concatenate([K.cidx[lo:hi], K.cidx[mb + lo:mb + hi]]), np.concatenate([hii, hjj]),
                        np.concatenate([gi, gj]))
                    hij_all[lo:hi] = hij.reshape(hi - lo, 36)
                    error += rc.error
                if K.pairs is not None:
                    self._pair_sums(K, hij_all.T, S)
            if K.prior is not None:
                o = 2 * mb
                for (lo, hi, Fc), rc in zip(K.prior.chunks(), self._chunk_residuals(state, K, K.prior)):
                    hjj, gj, *_ = nk.pose3_system(Fc, rc)
                    add(K.cidx[o + lo:o + hi], hjj, gj)
                    error += rc.error
        if K.dof is not None:   # (else the sums were made in g itself)
            g[K.dof] = Gs.T
        return error

    @staticmethod
    def _diagonal_sums(K: _Kind, S: np.ndarray, g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Zeroed (nsym, n) and (d, n) arrays for the kind's diagonal blocks and gradient summed per pose:
        views of S's diagonal segment and (poses owning all of g's dofs) of g, so that no copies of
        them sit beside a Schwarz preconditioner (1M 2D poses: 96 MB)."""
        nsym, n, d = len(K.sym), K.n, K.d
        D = S[K.dseg:K.dseg + nsym * n].reshape(nsym, n)
        D.fill(0.0)
        if K.dof is None:
            return D, g.reshape(n, d).T   # g is zeros here
        return D, np.zeros((d, n))

    def _data_buffer(self) -> np.ndarray:
        """An array for H's values: a pooled one that nothing references any more (a returned H that
        is still alive keeps its own), else a new one. Saves the page faults of a fresh 8·nnz bytes."""
        return self._pooled("data", self.pattern.nnz)

    def _pooled(self, name: str, size: int) -> np.ndarray:
        """A pooled array of ``size`` numbers that nothing references any more (views count), else a new one."""
        pool = self._buffers.setdefault(name, [])
        for k in range(len(pool)):
            if sys.getrefcount(pool[k]) == 2:   # the pool's reference and the call's argument only
                return pool[k]
        buf = np.empty(size)
        if len(pool) < 3:
            pool.append(buf)
        return buf

    # -- H in the factor form -----------------------------------------------------------------
    # the native factors' source array holds all of H: with a compiled product (factor_form.py) H is
    # handed out as a GatheredCSR, without its CSR values (1M 2D poses: 343 MiB); for iterative solvers
    factor_form = False   # set by the optimizer where the linear solver multiplies by H (CG)

    def factor_form_possible(self) -> bool:
        """Whether H can go without its values: the kernels compiled, and every factor native."""
        return factor_form.AVAILABLE and not (self._others is not None and self._others.graph.size())

    def _make_block_map(self, puts: list, dtype) -> factor_form.BlockSourceMap | None:
        """The gather index as one source offset and one coefficient table per block (the factor form's
        index: the per-entry one is then dropped); None for mixed block sizes or blocks no native factor fills."""
        P = self._pattern
        if not P.uniform or len(puts) > 255:
            return None
        nb, d = len(P.block_rows), P.d
        bsrc, btype = np.empty(nb, dtype=dtype), np.empty(nb, dtype=np.uint8)
        coef = np.empty((len(puts), d, d), dtype=np.int64)
        covered = 0
        for t, (rows, cols, base, c) in enumerate(puts):
            k = P.block_index(rows, cols)
            bsrc[k], btype[k], coef[t] = base, t, c
            covered += len(k)
        if covered != nb:
            return None
        return factor_form.BlockSourceMap(P._bptr, P._rowlen, d, bsrc, btype, coef, P.nnz)

    def _entry_sources(self) -> np.ndarray:
        """The gather index of H's CSR values (made again from the block map where the factor form dropped it)."""
        if self._src is None:
            src = np.empty(self.pattern.nnz, dtype=self._block_map.dtype)
            for lo in range(0, len(src), _TAKE_CHUNK):
                src[lo:lo + _TAKE_CHUNK] = self._block_map.entries(lo, min(lo + _TAKE_CHUNK, len(src)))
            self._src = src
        return self._src

    def prepare_factor_form(self) -> None:
        """Compile (or load) the factor form's kernels on a thread of their own, beside the start (not
        behind the pattern's plan on the background thread: at 1M 2D poses that queue ran until the
        chordal start had ended, and the warm-up's ~1.2 s of Python work then slowed the first
        linearization by ~0.9 s)."""
        if self.factor_form_possible():
            dims = tuple(K.d for K in (self._k2, self._k3) if K is not None)
            threading.Thread(target=factor_form.warm_up, args=(dims,), name="gtsam-schwarz-numba", daemon=True).start()

    def _factor_product(self, S: np.ndarray) -> factor_form.FactorProduct:
        """x ↦ H x from the source array S (views of it: the product keeps S alive)."""
        diagonals, blocks = [], []
        for K in (self._k2, self._k3):
            if K is None:
                continue
            d, nsym = K.d, len(K.sym)
            if K.first_dof is None and not (d == 3 and K.dof is None):   # each pose's first dof, made once
                K.first_dof = self.offsets[K.gvar]
            simple = d == 3 and K.dof is None   # Pose2 dofs 0..3n−1: no table read per pose or factor
            table = np.zeros(0, np.int64) if simple else K.first_dof
            diagonals.append((S[K.dseg:K.dseg + nsym * K.n].reshape(nsym, K.n), K.symk, table))
            if K.between is None:
                continue
            if K.pairs is not None:
                npairs = K.pairs[2]
                blocks.append((S[K.hseg:K.hseg + d * d * npairs].reshape(d * d, npairs), *K.pair_ends, table))
                continue
            m = K.nb
            B = S[K.hseg:K.hseg + d * d * m]
            B = B.reshape(d * d, m) if d == 3 else B.reshape(m, d * d).T   # 2D SoA, 3D AoS
            blocks.append((B, K.between.i, K.between.j, table))
        return factor_form.FactorProduct(self.dim, diagonals, blocks)

    def release_scratch(self, values: bool = False) -> None:
        """Drop the scratch arrays kept between linearizations (about 1.5 × H's values; ``values``: and
        the pooled arrays of H's values and of the factor form's source, which a returned H still alive
        keeps for itself): for runs whose memory peak comes later (a Schwarz build, the result), at the
        price of fresh pages next time."""
        self._buffers = {} if values else {k: self._buffers.get(k, []) for k in ("data", "source")}
        self._kept_residuals = None

    def _buffer(self, name: str, shape: tuple) -> np.ndarray:
        """Scratch array kept between calls (no page faults for large temporaries); not thread-safe."""
        buf = self._buffers.get(name)
        if buf is None or buf.shape != shape:
            buf = self._buffers[name] = np.empty(shape)
        return buf

    @staticmethod
    def _pair_sums(K: _Kind, hij: np.ndarray, S: np.ndarray) -> None:
        """Off-diagonal blocks of factors sharing a pair summed, oriented (lo, hi): (d², n pairs) SoA."""
        pid, flip, npairs = K.pairs
        d = K.d
        for a in range(d):
            for b in range(d):
                w = hij[a * d + b] if a == b else np.where(flip, hij[b * d + a], hij[a * d + b])
                lo = K.hseg + (a * d + b) * npairs
                S[lo:lo + npairs] = np.bincount(pid, w, minlength=npairs)

    def _add_others(self, state: NativeState, data: np.ndarray, g: np.ndarray) -> float:
        """GTSAM's linearization of the other factors added into data (H's CSR values) and g; their error."""
        O = self._others
        vals = self._other_values(state)
        lin = O.graph.linearize(vals)
        T = lin.sparseJacobian_()
        n_sub = len(O.dofs)
        if T.size:
            rows = T[0].astype(np.int64) - 1
            cols = T[1].astype(np.int64) - 1
            is_rhs = cols == n_sub
            m = int(rows.max()) + 1
            J = sp.csr_matrix((T[2][~is_rhs], (rows[~is_rhs], cols[~is_rhs])), shape=(m, n_sub))
            b = np.bincount(rows[is_rhs], weights=T[2][is_rhs], minlength=m)
            Jt = J.T.tocsr()
            Hs = (Jt @ J).tocsr()
            Hs.sum_duplicates()
            Hs.sort_indices()
            last = self._other_pos
            if last is None or not (np.array_equal(last[0], Hs.indptr) and np.array_equal(last[1], Hs.indices)):
                r = np.repeat(np.arange(n_sub), np.diff(Hs.indptr))
                pos = self.pattern.entry_positions(O.dofs[r], O.dofs[Hs.indices])
                self._other_pos = last = (Hs.indptr.copy(), Hs.indices.copy(), pos)
            data[last[2]] += Hs.data
            g[O.dofs] -= Jt @ b
        return float(O.graph.error(vals))

    def pose_edges(self) -> tuple | None:
        """(n, d, i, j) of :meth:`pose_graph`'s between factors alone (no measurement arrays made),
        None where it gives no graph or no between factors."""
        K = self._pure_kind()
        if K is None or K.between is None:
            return None
        return K.n, 2 if K is self._k2 else 3, K.between.i, K.between.j

    def _pure_kind(self):
        """The one pose kind of a graph of Pose2s only or Pose3s only without other variables, else None."""
        if (self._k2 is None) == (self._k3 is None) or (self._others is not None and self._others.var_keys):
            return None
        return self._k2 or self._k3

    def pose_graph(self, split_information: bool = False) -> dict | None:
        """The between and prior factors of a pure Pose2 or Pose3 graph as arrays, for a global
        initialization: poses n, edges (m, 2) (pose indices), R_meas (m, d, d), t_meas (m, d),
        information (m, dof, dof) = RᵀR (GTSAM tangent order), priors (indices, R, t). None when the
        graph has other variables or both pose types. ``split_information``: the between factors'
        information as the chordal start reads it, (rotation weights tr(Ω_RR)/dim (m,), Ω_tt (m, d, d)),
        without the full blocks (2 500 poses to 1M: a third of the arrays, none of them strided)."""
        K = self._pure_kind()
        if K is None:
            return None
        out = {"d": 2 if K is self._k2 else 3, "n": K.n}
        for name, f in (("between", K.between), ("prior", K.prior)):
            if f is None:
                out[name] = None
                continue
            split = split_information and name == "between"
            if K is self._k2:
                c, s_ = np.cos(f.z[2]), np.sin(f.z[2])
                R = np.empty((f.size, 2, 2))
                R[:, 0, 0], R[:, 0, 1], R[:, 1, 0], R[:, 1, 1] = c, -s_, s_, c
                t = f.z[:2].T.copy()
                u00, u01, u02, u11, u12, u22 = f.rows()   # Ω = UᵀU of the upper-triangular U, term by term
                info = np.empty((f.size, 2, 2) if split else (f.size, 3, 3))
                info[:, 0, 0] = u00 * u00
                info[:, 0, 1] = info[:, 1, 0] = u00 * u01
                info[:, 1, 1] = u01 * u01 + u11 * u11
                if split:
                    info = (u02 * u02 + u12 * u12 + u22 * u22, info)
                else:
                    info[:, 0, 2] = info[:, 2, 0] = u00 * u02
                    info[:, 1, 2] = info[:, 2, 1] = u01 * u02 + u11 * u12
                    info[:, 2, 2] = u02 * u02 + u12 * u12 + u22 * u22
            else:
                R, t, U = f.zR, f.zt, f.R
                if split:   # (ω, v): tr(Ω_RR) = Σ U[:, :3]², Ω_tt = U[:, 3:]ᵀ U[:, 3:]
                    Ut = U[:, :, 3:]
                    W = np.swapaxes(Ut, 1, 2) @ Ut
                    info = (np.einsum("kab,kab->k", U[:, :, :3], U[:, :, :3]) / 3.0, 0.5 * (W + np.swapaxes(W, 1, 2)))
                else:
                    info = np.swapaxes(U, 1, 2) @ U
            out[name] = {"i": f.i, "j": f.j, "R": R, "t": t, "information": info}
        return out

    def with_poses(self, state: NativeState, rotations: np.ndarray, positions: np.ndarray) -> NativeState:
        """A state with the poses of a pure Pose2 / Pose3 graph replaced (other variables kept)."""
        if self._k2 is not None:
            theta = np.arctan2(rotations[:, 1, 0], rotations[:, 0, 0])
            return NativeState(pose2=nk.pose2_state(positions[:, 0], positions[:, 1], theta), others=state.others)
        return NativeState(R3=np.ascontiguousarray(rotations), t3=np.ascontiguousarray(positions), others=state.others)

    def geometry(self, state: NativeState) -> VertexGeometry | None:
        """Positions (n, d) and world-from-body rotations (n, d, d) if all variables are Pose2 or all Pose3."""
        if self._others is not None and self._others.var_keys:
            return None
        if self._k2 is not None and self._k3 is None:
            P = state.pose2
            return VertexGeometry(positions=np.ascontiguousarray(P[:2].T), rotations=nk.pose2_matrices(P))
        if self._k3 is not None and self._k2 is None:
            return VertexGeometry(positions=state.t3.copy(), rotations=state.R3.copy())
        return None

    def _translation_mask(self, values) -> np.ndarray:
        mask = np.ones(self.dim, dtype=bool)
        if self._k2 is not None:
            mask[(self.offsets[self._k2.gvar][:, None] + 2).ravel()] = False
        if self._k3 is not None:
            mask[(self.offsets[self._k3.gvar][:, None] + np.arange(3)).ravel()] = False
        if self._others is not None and values is not None:
            for k, (lo, hi) in zip(self._others.var_keys, self._others.var_slices):
                for at in (values.atRot2, values.atRot3):  # rotations are not translations
                    try:
                        at(k)
                    except RuntimeError:
                        continue
                    mask[lo:hi] = False
                    break
        return mask

    def translation_mask(self) -> np.ndarray:
        """True for translation dofs: Pose2 dofs 0, 1; Pose3 dofs 3, 4, 5; other variables unless rotations."""
        return self._translation.copy()

    def factor_errors(self, state: NativeState) -> np.ndarray:
        """Error of every factor, indexed like the graph (``from_arrays``: edges, then priors);
        equal to ``graph.at(k).error(values)``. A diagnostic: loops over the GTSAM-linearized factors."""
        out = np.zeros(self.n_factors)
        for K in (self._k2, self._k3):
            if K is None:
                continue
            for F in (K.between, K.prior):
                if F is None:
                    continue
                for (lo, hi, Fc), r in zip(F.chunks(), self._chunk_residuals(state, K, F)):
                    out[F.ids[lo:hi]] = 0.5 * r.s2 if Fc.robust is None else Fc.robust.weight_loss(r.s2)[1]
        if self._others is not None and len(self._other_ids):
            vals = self._other_values(state)
            for k, idx in enumerate(self._other_ids.tolist()):
                out[idx] = self._others.graph.at(k).error(vals)
        return out

    # -----------------------------------------------------------------------------------------
    @property
    def native_factor_count(self) -> int:
        """Number of factors linearized natively (the rest go through GTSAM)."""
        return sum(K.nb + K.np_ for K in (self._k2, self._k3) if K is not None)

    @property
    def gtsam_factor_count(self) -> int:
        """Number of factors linearized by GTSAM."""
        return 0 if self._others is None else int(self._others.graph.size())
