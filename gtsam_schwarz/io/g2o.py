"""Pose-graph files: load g2o (SE2, SE3:QUAT) and TORO (2D) into GTSAM, write g2o back atomically.

Every defect of an input file becomes a one-line :class:`GraphFileError` ``"<path>:<line>: <what>"``
(never a traceback, never a silently different graph). Conventions, chosen to agree with
``gtsam.readG2o``: keys are the file's integer vertex ids; g2o/TORO information matrices become
``noiseModel.Gaussian.Information`` (Pose3 information permuted from g2o's (t, r) order to GTSAM's
(r, t) order); quaternions within 1e-3 of unit norm are normalized (g2o does the same), others are
refused. Files without VERTEX lines get an initial guess by chaining the edges along a BFS spanning
tree from the smallest id. A graph whose poses are not all connected to an anchored pose is refused,
since its Hessian is singular.

Landmarks: ``VERTEX_XY`` / ``VERTEX_TRACKXYZ`` lines are Point2 / Point3 values at the file's id (one id
space with the poses), and ``EDGE_SE2_XY`` / ``EDGE_SE3_TRACKXYZ`` (g2o's pose → point measurement, the
point in the pose's frame; 3D through the sensor offset of a ``PARAMS_SE3OFFSET`` line) become the
CustomFactors of :mod:`.landmarks`. A landmark without a VERTEX line starts where the first edge that
sees it puts it; landmark edges connect their pose and point in the connectivity check.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from typing import Iterator

import gtsam
import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import breadth_first_order, connected_components

from ..util import sorted_unique
from .atomic import atomic_write
from .landmarks import PointObservation, landmark_from_observation, observation_of, point_observation_factor
from .tum import quaternion_to_rotation

__all__ = ["GraphFileError", "LoadedGraph", "load_graph", "read_vertices", "write_g2o", "QUATERNION_TOLERANCE"]

#: quaternions whose norm is within this of 1 are normalized; farther ones are refused
QUATERNION_TOLERANCE = 1e-3
_MAX_ID = 2**63 - 1
# Cholesky pivots below this times the largest diagonal entry count as singular (roundoff level);
# the public datasets' smallest ratio (INTEL, parking-garage) is ~1e-11, far above.
_PIVOT_RTOL = 64 * np.finfo(float).eps
#: eigenvalue floor (relative to the largest) when a non-positive-definite information matrix is repaired
PD_FLOOR = 1e-6


class GraphFileError(ValueError):
    """A pose-graph file that cannot be read or written; the message is one line ``path:line: what``."""


@dataclass
class LoadedGraph:
    """A pose graph read by :func:`load_graph`, with what was inferred while reading it."""

    graph: gtsam.NonlinearFactorGraph
    initial: gtsam.Values
    dimension: int  # 2 (Pose2) or 3 (Pose3)
    poses: int
    edges: int  # between factors
    format: str  # "g2o" or "toro"
    initial_guess: str  # "file" or "spanning-tree"
    prior_added: bool  # True when load_graph added the gauge prior on the first pose
    warnings: list[str] = field(default_factory=list)
    path: str = ""
    # the parsed numbers, for NativeLinearizer.from_arrays(**arrays); {} when the graph has landmarks
    # (their factors are CustomFactors: linearize through the gtsam graph)
    arrays: dict = field(default_factory=dict)
    landmarks: int = 0  # Point2 / Point3 values (VERTEX_XY / VERTEX_TRACKXYZ, or seen by a landmark edge)
    landmark_edges: int = 0  # pose -> point factors (EDGE_SE2_XY / EDGE_SE3_TRACKXYZ), after the between factors


@dataclass(frozen=True)
class _Record:
    """Layout of one known line type: its role, dimension, format and field names after the tag."""

    role: str  # "vertex" or "edge"
    dim: int
    fmt: str  # "g2o" or "toro"
    fields: tuple[str, ...]  # ids first (1 for a vertex, 2 for an edge), then parameter ids, then numbers
    point: bool = False  # a landmark record: a point vertex, or a pose -> point edge
    params: int = 0  # parameter ids after the vertex ids (EDGE_SE3_TRACKXYZ: its sensor offset)

    @property
    def ids(self) -> int:
        return 1 if self.role == "vertex" else 2


_SE3_INFO = tuple(f"I{a}{b}" for i, a in enumerate("123456") for b in "123456"[i:])
_RECORDS = {
    "VERTEX_SE2": _Record("vertex", 2, "g2o", ("id", "x", "y", "theta")),
    "VERTEX2": _Record("vertex", 2, "toro", ("id", "x", "y", "theta")),
    "VERTEX_SE3:QUAT": _Record("vertex", 3, "g2o", ("id", "x", "y", "z", "qx", "qy", "qz", "qw")),
    "EDGE_SE2": _Record("edge", 2, "g2o", ("i", "j", "dx", "dy", "dtheta",
                                            "I11", "I12", "I13", "I22", "I23", "I33")),
    "EDGE2": _Record("edge", 2, "toro", ("i", "j", "dx", "dy", "dtheta",
                                         "Ixx", "Ixy", "Iyy", "Itt", "Ixt", "Iyt")),
    "EDGE_SE3:QUAT": _Record("edge", 3, "g2o", ("i", "j", "dx", "dy", "dz", "qx", "qy", "qz", "qw")
                             + _SE3_INFO),
    "VERTEX_XY": _Record("vertex", 2, "g2o", ("id", "x", "y"), point=True),
    "EDGE_SE2_XY": _Record("edge", 2, "g2o", ("i", "j", "dx", "dy", "I11", "I12", "I22"), point=True),
    "VERTEX_TRACKXYZ": _Record("vertex", 3, "g2o", ("id", "x", "y", "z"), point=True),
    "EDGE_SE3_TRACKXYZ": _Record("edge", 3, "g2o", ("i", "j", "param", "dx", "dy", "dz",
                                                    "I11", "I12", "I13", "I22", "I23", "I33"), point=True, params=1),
}
_VERTEX_TAG = {("g2o", 2): "VERTEX_SE2", ("toro", 2): "VERTEX2", ("g2o", 3): "VERTEX_SE3:QUAT"}
_POINT_TAGS = {2: ("VERTEX_XY", "EDGE_SE2_XY"), 3: ("VERTEX_TRACKXYZ", "EDGE_SE3_TRACKXYZ")}
_OFFSET_TAG = "PARAMS_SE3OFFSET"  # g2o's sensor offset of EDGE_SE3_TRACKXYZ: id x y z qx qy qz qw
_OFFSET_FIELDS = ("id", "x", "y", "z", "qx", "qy", "qz", "qw")
# positions, in the 6 stored entries, of the row-major 3x3 information matrix (x, y, theta)
_INFO2_INDEX = {"g2o": [0, 1, 2, 1, 3, 4, 2, 4, 5],  # I11 I12 I13 I22 I23 I33
                "toro": [0, 1, 4, 1, 2, 5, 4, 5, 3]}  # Ixx Ixy Iyy Itt Ixt Iyt
# g2o's Pose3 tangent order is (x y z rx ry rz), GTSAM's is (rx ry rz x y z)
_G2O_TO_GTSAM_3D = np.array([3, 4, 5, 0, 1, 2])
# row-major upper triangles, g2o's storage order; for 3D written straight from GTSAM's (r, t) matrix
_UPPER2 = np.triu_indices(3)
_UPPER3_FROM_GTSAM = tuple(_G2O_TO_GTSAM_3D[ix] for ix in np.triu_indices(6))


def _fail(path: str, line: int | None, what: str) -> GraphFileError:
    """The one-line error ``path:line: what`` (``path: what`` when no single line is at fault)."""
    return GraphFileError(f"{path}: {what}" if line is None else f"{path}:{line}: {what}")


def _parse_id(token: str) -> int | None:
    """A vertex id: a plain non-negative decimal integer that fits in GTSAM's Key; None if not."""
    if not (token.isascii() and token.isdigit()):
        return None
    value = int(token)
    return value if value <= _MAX_ID else None


@dataclass
class _Parsed:
    """Raw records of a file, in file order, before graph-level checks."""

    dim: int = 0
    fmt: str = ""
    first_tag: str = ""
    first_line: int = 0
    vertex_ids: list[int] = field(default_factory=list)
    vertex_values: list[list[float]] = field(default_factory=list)
    vertex_line: dict[int, int] = field(default_factory=dict)
    edge_ids: list[tuple[int, int]] = field(default_factory=list)
    edge_values: list[list[float]] = field(default_factory=list)
    edge_lines: list[int] = field(default_factory=list)
    point_ids: list[int] = field(default_factory=list)  # VERTEX_XY / VERTEX_TRACKXYZ
    point_values: list[list[float]] = field(default_factory=list)
    obs_ids: list[tuple[int, int]] = field(default_factory=list)  # EDGE_SE2_XY / EDGE_SE3_TRACKXYZ (pose, point)
    obs_values: list[list[float]] = field(default_factory=list)
    obs_lines: list[int] = field(default_factory=list)
    obs_params: list[int] = field(default_factory=list)  # EDGE_SE3_TRACKXYZ: its PARAMS_SE3OFFSET id
    offsets: dict[int, tuple[list[float], int]] = field(default_factory=dict)  # PARAMS_SE3OFFSET id -> (values, line)
    fixed: dict[int, int] = field(default_factory=dict)  # FIX id -> line
    unknown: dict[str, list[int]] = field(default_factory=dict)  # tag -> [count, first line]
    warnings: list[str] = field(default_factory=list)


def _read_text(path: str) -> str:
    """The file's text; unreadable or non-UTF-8 files become a GraphFileError."""
    try:
        with open(path, "rb") as fh:
            data = fh.read()
    except OSError as exc:
        raise _fail(path, None, f"cannot read: {exc.strerror or exc}") from None
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = data.count(b"\n", 0, exc.start) + 1
        raise _fail(path, line, f"not a UTF-8 text file (invalid byte 0x{data[exc.start]:02x})") from None


def _parse_lines(path: str, text: str) -> _Parsed:
    """Tokenize and check each line on its own: field counts, numbers, ids, self-loops, duplicates."""
    out = _Parsed()
    for lineno, raw in enumerate(text.split("\n"), 1):
        hash_at = raw.find("#")
        tokens = (raw if hash_at < 0 else raw[:hash_at]).split()
        if not tokens:
            continue
        tag, args = tokens[0], tokens[1:]
        if tag == "FIX":
            _parse_fix(path, lineno, args, out)
            continue
        if tag == _OFFSET_TAG:
            _parse_offset(path, lineno, args, out)
            continue
        rec = _RECORDS.get(tag)
        if rec is None:
            entry = out.unknown.setdefault(tag, [0, lineno])
            entry[0] += 1
            continue
        if not out.dim:
            out.dim, out.fmt, out.first_tag, out.first_line = rec.dim, rec.fmt, tag, lineno
        elif rec.dim != out.dim:
            raise _fail(path, lineno, f"{tag} is a {rec.dim}D record but the file is {out.dim}D "
                                      f"({out.first_tag} at line {out.first_line}); 2D and 3D records cannot be mixed")
        elif rec.fmt != out.fmt:
            raise _fail(path, lineno, f"{tag} is a {rec.fmt.upper() if rec.fmt == 'toro' else rec.fmt} record "
                                      f"but the file uses {out.fmt.upper() if out.fmt == 'toro' else out.fmt} "
                                      f"records ({out.first_tag} at line {out.first_line}); they cannot be mixed")
        if len(args) != len(rec.fields):
            few = "few" if len(args) < len(rec.fields) else "many"
            raise _fail(path, lineno, f"too {few} fields for {tag}: expected {len(rec.fields)} "
                                      f"({' '.join(rec.fields)}), got {len(args)}")
        ids = []
        for name, token in zip(rec.fields[:rec.ids], args[:rec.ids]):
            value = _parse_id(token)
            if value is None:
                raise _fail(path, lineno, f"{tag} field '{name}' is not a vertex id "
                                          f"(a non-negative integer below 2^63): {token!r}")
            ids.append(value)
        label = f"{tag} {ids[0]}" if rec.ids == 1 else f"{tag} {ids[0]} -> {ids[1]}"
        params = []
        for name, token in zip(rec.fields[rec.ids:rec.ids + rec.params], args[rec.ids:rec.ids + rec.params]):
            value = _parse_id(token)
            if value is None:
                raise _fail(path, lineno, f"{label}: field '{name}' is not a parameter id "
                                          f"(a non-negative integer below 2^63): {token!r}")
            params.append(value)
        start = rec.ids + rec.params
        values = _parse_numbers(path, lineno, label, rec.fields[start:], args[start:])
        if rec.dim == 3 and not rec.point:
            _normalize_quaternion(path, lineno, label, values)
        if rec.role == "vertex":
            vid = ids[0]
            if vid in out.vertex_line:
                raise _fail(path, lineno, f"duplicate vertex id {vid} (first defined at line {out.vertex_line[vid]})")
            out.vertex_line[vid] = lineno
            (out.point_ids if rec.point else out.vertex_ids).append(vid)
            (out.point_values if rec.point else out.vertex_values).append(values)
        elif rec.point:
            if ids[0] == ids[1]:
                raise _fail(path, lineno, f"{label} observes itself (pose and landmark cannot share id {ids[0]})")
            out.obs_ids.append((ids[0], ids[1]))
            out.obs_values.append(values)
            out.obs_lines.append(lineno)
            out.obs_params.append(params[0] if params else -1)
        else:
            if ids[0] == ids[1]:
                raise _fail(path, lineno, f"{label} is a self-loop (both ends are pose {ids[0]})")
            out.edge_ids.append((ids[0], ids[1]))
            out.edge_values.append(values)
            out.edge_lines.append(lineno)
    for tag, (count, first) in sorted(out.unknown.items(), key=lambda item: item[1][1]):
        out.warnings.append(f"skipped {count} line{'s' if count > 1 else ''} with unknown tag {tag!r} "
                            f"(first at line {first})")
    return out


def _parse_fix(path: str, lineno: int, args: list[str], out: _Parsed) -> None:
    """``FIX id [id ...]``: g2o's way to hold poses fixed; repeated ids are applied once (warned)."""
    if not args:
        raise _fail(path, lineno, "too few fields for FIX: expected at least one vertex id")
    for token in args:
        vid = _parse_id(token)
        if vid is None:
            raise _fail(path, lineno, f"FIX field is not a vertex id (a non-negative integer below 2^63): {token!r}")
        if vid in out.fixed:
            out.warnings.append(f"FIX {vid} at line {lineno} repeats line {out.fixed[vid]}; it is applied once")
        else:
            out.fixed[vid] = lineno


def _parse_offset(path: str, lineno: int, args: list[str], out: _Parsed) -> None:
    """``PARAMS_SE3OFFSET id x y z qx qy qz qw``: the sensor pose on the robot of EDGE_SE3_TRACKXYZ."""
    if len(args) != len(_OFFSET_FIELDS):
        few = "few" if len(args) < len(_OFFSET_FIELDS) else "many"
        raise _fail(path, lineno, f"too {few} fields for {_OFFSET_TAG}: expected {len(_OFFSET_FIELDS)} "
                                  f"({' '.join(_OFFSET_FIELDS)}), got {len(args)}")
    pid = _parse_id(args[0])
    if pid is None:
        raise _fail(path, lineno, f"{_OFFSET_TAG} field 'id' is not a parameter id "
                                  f"(a non-negative integer below 2^63): {args[0]!r}")
    label = f"{_OFFSET_TAG} {pid}"
    if pid in out.offsets:
        raise _fail(path, lineno, f"duplicate parameter id {pid} (first defined at line {out.offsets[pid][1]})")
    values = _parse_numbers(path, lineno, label, _OFFSET_FIELDS[1:], args[1:])
    _normalize_quaternion(path, lineno, label, values)
    out.offsets[pid] = (values, lineno)


def _parse_numbers(path: str, lineno: int, label: str, names: tuple[str, ...], tokens: list[str]) -> list[float]:
    """Finite floats, or an error naming the field; Python-only spellings ('1_0') are refused."""
    try:
        values = [float(t) for t in tokens]
    except ValueError:
        values = None
    if values is None or "_" in "".join(tokens):
        for name, token in zip(names, tokens):
            try:
                float(token)
                ok = "_" not in token
            except ValueError:
                ok = False
            if not ok:
                raise _fail(path, lineno, f"{label}: field '{name}' is not a number: {token!r}")
    if not all(map(math.isfinite, values)):
        name, token = next((n, t) for n, t, v in zip(names, tokens, values) if not math.isfinite(v))
        raise _fail(path, lineno, f"{label}: field '{name}' is not finite: {token!r}")
    return values


def _normalize_quaternion(path: str, lineno: int, label: str, values: list[float]) -> None:
    """Normalize (qx qy qz qw) at values[3:7] in place if |q| is within QUATERNION_TOLERANCE of 1."""
    q = values[3:7]
    norm = math.sqrt(sum(v * v for v in q))
    if norm == 0.0:
        raise _fail(path, lineno, f"{label}: quaternion (qx qy qz qw) has zero norm")
    if abs(norm - 1.0) > QUATERNION_TOLERANCE:
        raise _fail(path, lineno, f"{label}: quaternion (qx qy qz qw) has norm {norm:.6g}, not 1 "
                                  f"(only norms within {QUATERNION_TOLERANCE:g} of 1 are normalized)")
    values[3:7] = [v / norm for v in q]


def _information(path: str, parsed: _Parsed, values: np.ndarray, strict: bool = False,
                 points: bool = False) -> np.ndarray:
    """Information matrices (n, d, d) in GTSAM's tangent order, each positive definite.

    One that fails the Cholesky test is refused with ``strict``; otherwise it is replaced by the
    nearest positive definite matrix by eigenvalue clipping (eigenvalues below ``PD_FLOOR`` × the
    largest raised to it; the eigenvectors kept), with one warning naming the first line and the count.
    ``points``: the matrices of the landmark edges ((dx dy) or (dx dy dz), no reordering)."""
    n = len(values)
    if points:
        d = parsed.dim
        rows, cols = np.triu_indices(d)  # row-major upper triangle
        info = np.zeros((n, d, d))
        info[:, rows, cols] = values[:, d:]
        info[:, cols, rows] = values[:, d:]
        ids, lines, what = parsed.obs_ids, parsed.obs_lines, "landmark edge"
    elif parsed.dim == 2:
        info = values[:, 3:9][:, _INFO2_INDEX[parsed.fmt]].reshape(n, 3, 3)
    else:
        info = np.zeros((n, 6, 6))
        rows, cols = np.triu_indices(6)  # row-major upper triangle: g2o's storage order
        info[:, rows, cols] = values[:, 7:]
        info[:, cols, rows] = values[:, 7:]
    if not points:
        ids, lines, what = parsed.edge_ids, parsed.edge_lines, "edge"
    if n == 0:
        return info
    try:
        chol = np.linalg.cholesky(info)
        pivots = np.diagonal(chol, axis1=1, axis2=2) ** 2
        scale = np.diagonal(info, axis1=1, axis2=2).max(axis=1)
        bad = np.flatnonzero(pivots.min(axis=1) <= _PIVOT_RTOL * scale)
    except np.linalg.LinAlgError:
        bad = [k for k in range(n) if not _is_spd(info[k])]
    if len(bad):
        k = int(bad[0])
        i, j = ids[k]
        where = f"information matrix of {what} {i} -> {j} is not symmetric positive definite"
        w, V = np.linalg.eigh(info[bad])
        top = w.max(axis=1)
        if strict or np.any(top <= 0):
            why = "(Cholesky fails or is numerically singular)" if strict else "and has no positive eigenvalue"
            raise _fail(path, lines[k], f"{where} {why}")
        w = np.maximum(w, PD_FLOOR * top[:, None])
        info[bad] = np.einsum("nij,nj,nkj->nik", V, w, V)
        parsed.warnings.append(
            f"{path}:{lines[k]}: {where}; {len(bad)} information matri{'ces' if len(bad) > 1 else 'x'} "
            f"repaired by eigenvalue clipping (floor {PD_FLOOR:g} x the largest eigenvalue)")
    if parsed.dim == 3 and not points:
        info = info[:, _G2O_TO_GTSAM_3D][:, :, _G2O_TO_GTSAM_3D]
    return info


def _is_spd(matrix: np.ndarray) -> bool:
    """Cholesky of one matrix succeeds with pivots above roundoff level."""
    try:
        pivots = np.diag(np.linalg.cholesky(matrix)) ** 2
    except np.linalg.LinAlgError:
        return False
    return bool(pivots.min() > _PIVOT_RTOL * np.diag(matrix).max())


def _pose(dim: int, v) -> gtsam.Pose2 | gtsam.Pose3:
    """Pose from (x y theta) or (x y z qx qy qz qw) with a unit quaternion."""
    if dim == 2:
        return gtsam.Pose2(v[0], v[1], v[2])
    return gtsam.Pose3(gtsam.Rot3.Quaternion(v[6], v[3], v[4], v[5]), np.array(v[:3]))


def _first_line_of(parsed: _Parsed, pose: int) -> int:
    """The line that defines a pose or landmark: its VERTEX line, else the first edge that names it."""
    if pose in parsed.vertex_line:
        return parsed.vertex_line[pose]
    return min(line for (i, j), line in zip(parsed.edge_ids + parsed.obs_ids, parsed.edge_lines + parsed.obs_lines)
               if pose in (i, j))


def read_vertices(path) -> tuple[int, np.ndarray, np.ndarray]:
    """The VERTEX records of a g2o / TORO file: (dimension, ids sorted, values (x y θ) or
    (x y z qx qy qz qw) per id), with the loader's line-numbered errors; edges are not needed."""
    path = os.fspath(path)
    parsed = _parse_lines(path, _read_text(path))
    ids = np.array(parsed.vertex_ids, dtype=np.uint64)
    order = np.argsort(ids, kind="stable")
    return parsed.dim, ids[order], np.array(parsed.vertex_values, dtype=float).reshape(len(ids), -1)[order]


def load_graph(path, *, add_prior: bool = True, prior_sigma: float = 1e-3, strict: bool = False) -> LoadedGraph:
    """Read a g2o (2D/3D) or TORO (2D) pose graph into GTSAM between factors and initial Values.

    ``FIX id`` lines become priors at the file's value with isotropic sigma ``prior_sigma`` (a FIX on a
    landmark: PriorFactorPoint2/3); if there is none and ``add_prior``, one gauge prior of that sigma is
    put on the smallest pose id.
    Landmarks (``VERTEX_XY`` / ``EDGE_SE2_XY``, ``VERTEX_TRACKXYZ`` / ``EDGE_SE3_TRACKXYZ``) become
    Point2 / Point3 values and :mod:`.landmarks` factors, placed after the between factors and before
    the priors. Raises GraphFileError (one line naming file, line and id) for any defect of the file.
    Information matrices that are not positive definite are repaired (see ``_information``) and lines
    of unknown types skipped, each with a warning in ``LoadedGraph.warnings``; ``strict=True`` refuses both.
    """
    if not (isinstance(prior_sigma, (int, float)) and math.isfinite(prior_sigma) and prior_sigma > 0):
        raise ValueError(f"prior_sigma must be a positive finite number, got {prior_sigma!r}")
    path = os.fspath(path)
    parsed = _parse_lines(path, _read_text(path))

    if not parsed.edge_ids and not parsed.obs_ids:
        if parsed.vertex_ids or parsed.point_ids:
            what = f"only {len(parsed.vertex_ids) + len(parsed.point_ids)} vertices"
        elif parsed.unknown:
            what = "no pose-graph records; " + "; ".join(parsed.warnings)
        else:
            what = "no records"
        raise _fail(path, None, f"no edges ({what}): nothing to optimize")
    dim, fmt = parsed.dim, parsed.fmt
    width = (9 if dim == 2 else 28)  # numbers of a pose edge
    edge_values = np.array(parsed.edge_values, dtype=float).reshape(len(parsed.edge_values), width)
    if strict and parsed.unknown:
        raise _fail(path, None, "; ".join(parsed.warnings) + " (strict)")
    info = _information(path, parsed, edge_values, strict)
    edge_ids = np.array(parsed.edge_ids, dtype=np.int64).reshape(-1, 2)
    obs_values = np.array(parsed.obs_values, dtype=float).reshape(len(parsed.obs_values), dim + dim * (dim + 1) // 2)
    obs_info = _information(path, parsed, obs_values, strict, points=True)
    point_set = set(parsed.point_ids) | {j for _, j in parsed.obs_ids}

    # the poses: the VERTEX ids, or (edges only) every id a pose edge names
    vertex_tag = _VERTEX_TAG[(fmt, dim)]
    if parsed.vertex_ids:
        pose_ids = np.array(sorted(parsed.vertex_ids), dtype=np.int64)
        missing = ~np.isin(edge_ids, pose_ids)
        if missing.any():
            k = int(np.flatnonzero(missing.any(axis=1))[0])
            i, j = parsed.edge_ids[k]
            absent = i if missing[k, 0] else j
            why = (f"landmark {absent}, not a pose" if absent in point_set
                   else f"vertex {absent}, which has no {vertex_tag} line")
            raise _fail(path, parsed.edge_lines[k], f"edge {i} -> {j} references {why}")
    else:
        pose_ids = sorted_unique(edge_ids)
        if parsed.point_ids:
            clash = np.flatnonzero(np.isin(edge_ids, np.array(parsed.point_ids, dtype=np.int64)).any(axis=1))
            if len(clash):
                k = int(clash[0])
                i, j = parsed.edge_ids[k]
                bad = i if i in point_set else j
                raise _fail(path, parsed.edge_lines[k], f"edge {i} -> {j} references landmark {bad} "
                                                        f"({_POINT_TAGS[dim][0]} at line {parsed.vertex_line[bad]}), not a pose")
    pose_set = set(pose_ids.tolist())
    for (i, j), line in zip(parsed.obs_ids, parsed.obs_lines):
        label = f"landmark edge {i} -> {j}"
        if i not in pose_set:
            if i in point_set:
                raise _fail(path, line, f"{label} references landmark {i} as its pose")
            what = "" if parsed.vertex_ids else " and no pose-pose edge (no initial guess for it)"
            raise _fail(path, line, f"{label} references pose {i}, which has no {vertex_tag} line{what}")
        if j in pose_set:
            raise _fail(path, line, f"{label} references pose {j} as its landmark")
    offsets = {}
    for pid, line in zip(parsed.obs_params, parsed.obs_lines):
        if pid >= 0 and pid not in offsets:
            if pid not in parsed.offsets:
                raise _fail(path, line, f"{_POINT_TAGS[dim][1]} uses sensor offset parameter {pid}, which has no "
                                        f"{_OFFSET_TAG} line")
            offsets[pid] = parsed.offsets[pid][0]
    for vid, line in parsed.fixed.items():
        if vid not in pose_set and vid not in point_set:
            raise _fail(path, line, f"FIX refers to pose {vid}, which does not appear in the file")

    # connectivity: every component needs an anchor, or the Hessian is singular; nodes are the poses,
    # then the landmarks (sorted ids), and a landmark edge joins its pose and its point
    n = len(pose_ids)
    point_ids = np.array(sorted(point_set), dtype=np.int64)
    nodes = n + len(point_ids)
    index = np.searchsorted(pose_ids, edge_ids)
    obs_ids = np.array(parsed.obs_ids, dtype=np.int64).reshape(-1, 2)
    obs_index = np.stack([np.searchsorted(pose_ids, obs_ids[:, 0]), n + np.searchsorted(point_ids, obs_ids[:, 1])], 1)
    both = np.concatenate([index, obs_index])
    adjacency = sp.coo_matrix((np.ones(len(both)), (both[:, 0], both[:, 1])), shape=(nodes, nodes)).tocsr()
    ncomp, labels = connected_components(adjacency, directed=False)
    node_ids = np.concatenate([pose_ids, point_ids])

    def kind(vid):
        return "landmark" if vid in point_set else "pose"

    if ncomp > 1:
        fixed_index = [int(np.searchsorted(pose_ids, v)) if v in pose_set else n + int(np.searchsorted(point_ids, v))
                       for v in sorted(parsed.fixed)]
        anchored = set(labels[fixed_index].tolist()) if parsed.fixed else {int(labels[0])}
        loose = np.flatnonzero(~np.isin(labels, list(anchored)))
        if len(loose):
            bad = int(node_ids[loose[0]])
            ref = int(pose_ids[0]) if labels[0] in anchored else min(parsed.fixed)
            if bad in point_set and not any(j == bad for _, j in parsed.obs_ids):
                raise _fail(path, _first_line_of(parsed, bad), f"landmark {bad} is not seen by any pose "
                                                               f"(no {_POINT_TAGS[dim][1]} names it)")
            raise _fail(path, _first_line_of(parsed, bad),
                        f"{kind(bad)} {bad} is not connected to {kind(ref)} {ref} (the graph has {ncomp} connected "
                        f"components; a component without a FIX makes the Hessian singular)")

    measured = [_pose(dim, v) for v in edge_values]
    initial = gtsam.Values()
    if parsed.vertex_ids:
        for vid, v in zip(parsed.vertex_ids, parsed.vertex_values):
            initial.insert(vid, _pose(dim, v))
        initial_guess = "file"
    else:
        tree = _spanning_tree_poses(dim, pose_ids, index, measured)
        for vid, pose in tree.items():
            initial.insert(vid, pose)
        initial_guess = "spanning-tree"
        if len(obs_ids):
            pose_components = connected_components(
                sp.coo_matrix((np.ones(len(index)), (index[:, 0], index[:, 1])), shape=(n, n)), directed=False)[0]
            if pose_components > len(set(labels[:n].tolist())):
                parsed.warnings.append(
                    f"{path}: some poses are linked to the others only through landmarks; their initial guess "
                    f"(chained along the pose-pose edges) starts at the identity")

    graph = gtsam.NonlinearFactorGraph()
    between = gtsam.BetweenFactorPose2 if dim == 2 else gtsam.BetweenFactorPose3
    for (i, j), z, m in zip(parsed.edge_ids, measured, info):
        graph.add(between(i, j, z, gtsam.noiseModel.Gaussian.Information(m)))

    # landmarks: the file's VERTEX value, else where the first edge that sees it puts it
    at = initial.atPose2 if dim == 2 else initial.atPose3
    points = dict(zip(parsed.point_ids, parsed.point_values))
    for (i, j), v, m, pid in zip(parsed.obs_ids, obs_values, obs_info, parsed.obs_params):
        offset = offsets.get(pid)
        graph.add(point_observation_factor(i, j, v[:dim], m, offset=offset, offset_id=max(pid, 0)))
        if j not in points:
            points[j] = landmark_from_observation(at(i), v[:dim], offset).tolist()
    for vid in sorted(points):  # as gtsam's Python Values.insert stores numpy points (dynamic-size vectors)
        initial.insert(vid, np.array(points[vid], dtype=float))

    sigma = gtsam.noiseModel.Isotropic.Sigma(3 if dim == 2 else 6, float(prior_sigma))
    point_sigma = gtsam.noiseModel.Isotropic.Sigma(dim, float(prior_sigma))
    anchors = list(parsed.fixed)
    prior_added = not anchors and add_prior
    if prior_added:
        anchors = [int(pose_ids[0])]
    for vid in anchors:
        if vid in point_set:
            prior = gtsam.PriorFactorPoint2 if dim == 2 else gtsam.PriorFactorPoint3
            graph.add(prior(vid, np.array(points[vid], dtype=float), point_sigma))
        else:
            prior = gtsam.PriorFactorPose2 if dim == 2 else gtsam.PriorFactorPose3
            graph.add(prior(vid, at(vid), sigma))

    has_points = bool(point_set)
    arrays = {} if has_points else _arrays(dim, pose_ids, initial, edge_ids, edge_values, info, anchors, prior_sigma)
    return LoadedGraph(graph=graph, initial=initial, dimension=dim, poses=n, edges=len(measured),
                       format=fmt, initial_guess=initial_guess, prior_added=prior_added,
                       warnings=parsed.warnings, path=path, arrays=arrays,
                       landmarks=len(point_ids), landmark_edges=len(parsed.obs_ids))


def _arrays(dim, pose_ids, initial, edge_ids, edge_values, info, anchors, prior_sigma) -> dict:
    """The graph as numpy arrays (keyword arguments of ``NativeLinearizer.from_arrays``): no second
    pass over gtsam factors is needed to linearize it natively."""
    if dim == 2:
        poses = gtsam.utilities.extractPose2(initial)  # (n, 3), keys sorted like pose_ids
        measurements = edge_values[:, :3]
    else:
        poses = gtsam.utilities.extractPose3(initial)  # (n, 12): R row-major, t
        measurements = (quaternion_to_rotation(edge_values[:, 3:7]), edge_values[:, :3])
    at = np.searchsorted(pose_ids, np.asarray(anchors, dtype=np.int64))
    d = 3 if dim == 2 else 6
    return {"kind": "pose2" if dim == 2 else "pose3", "keys": pose_ids, "poses": poses, "edges": edge_ids,
            "measurements": measurements, "information": info, "prior_keys": np.asarray(anchors, dtype=np.int64),
            "prior_measurements": poses[at], "prior_information": np.eye(d) / float(prior_sigma) ** 2}


def _spanning_tree_poses(dim: int, pose_ids: np.ndarray, index: np.ndarray, measured: list) -> dict:
    """Initial poses by chaining measurements along BFS trees, each rooted (at the identity) at the
    smallest id of its connected component.

    Between a BFS parent and child the first edge of the file is used, in whichever direction it
    points. (Several components occur only when each has a FIX; otherwise load_graph refused.)
    """
    n = len(pose_ids)
    adjacency = sp.coo_matrix((np.ones(len(index)), (index[:, 0], index[:, 1])), shape=(n, n)).tocsr()
    # first edge (in file order) joining each unordered pair {a, b}
    codes = index.min(axis=1) * n + index.max(axis=1)
    unique_codes, first_edge = sorted_unique(codes, return_index=True)
    poses = [None] * n
    for root in range(n):
        if poses[root] is not None:
            continue
        order, parent = breadth_first_order(adjacency, root, directed=False, return_predecessors=True)
        child = order[1:]
        par = parent[child]
        edge = first_edge[np.searchsorted(unique_codes, np.minimum(par, child) * n + np.maximum(par, child))]
        poses[root] = gtsam.Pose2() if dim == 2 else gtsam.Pose3()
        for c, p, e in zip(child.tolist(), par.tolist(), edge.tolist()):
            z = measured[e]
            poses[c] = poses[p].compose(z if index[e, 0] == p else z.inverse())
    return dict(zip(pose_ids.tolist(), poses))


# --------------------------------------------------------------------------------------- writing

def _num(x: float) -> str:
    """Shortest text that reads back to exactly the same double."""
    return repr(float(x))


def _information_of(path: str, k: int, factor) -> np.ndarray:
    """The factor's information matrix, refusing noise models that g2o cannot store."""
    model = factor.noiseModel()
    if not isinstance(model, gtsam.noiseModel.Gaussian):
        raise _fail(path, None, f"cannot write factor {k}: its {type(model).__name__} noise model is not "
                                f"Gaussian (g2o stores only an information matrix)")
    info = np.asarray(model.information(), dtype=float)
    if not np.isfinite(info).all():
        raise _fail(path, None, f"cannot write factor {k}: its noise model is constrained (infinite information)")
    return info


def _point_values(path: str, values: gtsam.Values) -> tuple[int, int, int, dict]:
    """(Pose2 count, Pose3 count, dimension, {key: point}) of the values; anything but Pose2/Pose3 poses
    and Point2/Point3 landmarks of one dimension is refused."""
    pose2, pose3 = gtsam.utilities.allPose2s(values), gtsam.utilities.allPose3s(values)
    n2, n3 = pose2.size(), pose3.size()
    if n2 and n3:
        raise _fail(path, None, "cannot write a mix of Pose2 and Pose3 values")
    dim = 2 if n2 else 3 if n3 else 0
    points = {}
    if n2 + n3 != values.size():
        poses = set(pose2.keys()) | set(pose3.keys())
        dims = values.dims()
        for key in values.keys():
            if key in poses:
                continue
            d, p = dims[key], None
            if d in (2, 3):
                try:
                    p = np.asarray(values.atPoint2(key) if d == 2 else values.atPoint3(key), dtype=float)
                except RuntimeError:  # another type of this dimension (Unit3, Rot3, ...)
                    p = None
            if p is None:
                raise _fail(path, None, f"cannot write values other than Pose2/Pose3 and Point2/Point3 to g2o "
                                        f"(key {key})")
            if dim and d != dim:
                raise _fail(path, None, f"cannot write a mix of 2D (Pose2, Point2) and 3D (Pose3, Point3) values "
                                        f"(Point{d} at key {key})")
            dim = d
            points[key] = p
    return n2, n3, dim, points


_IDENTITY_OFFSET = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)


def _offset_ids(observations: dict) -> dict:
    """PARAMS_SE3OFFSET ids for the distinct sensor offsets of 3D observations: each keeps the id it was
    read with unless another offset took it first."""
    ids: dict[tuple, int] = {}
    for obs in observations.values():
        if obs.dim != 3:
            continue
        key = _IDENTITY_OFFSET if obs.offset is None else tuple(obs.offset.tolist())
        if key not in ids:
            taken = set(ids.values())
            ids[key] = obs.offset_id if obs.offset_id not in taken else max(taken) + 1
    return ids


def _g2o_lines(path: str, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values) -> Iterator[str]:
    """The g2o text, line by line: PARAMS_SE3OFFSET lines (3D landmark edges only), sorted VERTEX lines,
    EDGE lines in graph order, then FIX lines."""
    n2, n3, dim, points = _point_values(path, values)
    observations = {}
    for k in range(graph.size()):
        factor = graph.at(k)
        if isinstance(factor, gtsam.CustomFactor):
            obs = observation_of(factor, values)
            if obs is not None:
                observations[k] = obs
    offset_ids = _offset_ids(observations)
    for offset, pid in offset_ids.items():
        yield f"{_OFFSET_TAG} {pid} " + " ".join(_num(x) for x in offset) + "\n"
    keys = sorted(values.keys())
    for key in keys:
        p = points.get(key)
        if p is not None:
            yield f"{_POINT_TAGS[dim][0]} {key} " + " ".join(_num(x) for x in p) + "\n"
        elif n2:
            p = values.atPose2(key)
            yield f"VERTEX_SE2 {key} {_num(p.x())} {_num(p.y())} {_num(p.theta())}\n"
        else:
            p = values.atPose3(key)
            t, q = p.translation(), p.rotation().toQuaternion()
            yield (f"VERTEX_SE3:QUAT {key} {_num(t[0])} {_num(t[1])} {_num(t[2])} "
                   f"{_num(q.x())} {_num(q.y())} {_num(q.z())} {_num(q.w())}\n")
    keyset = set(keys)
    fixed: list[int] = []
    for k in range(graph.size()):
        factor = graph.at(k)
        if factor is None:
            continue
        if isinstance(factor, (gtsam.PriorFactorPose2, gtsam.PriorFactorPose3,
                               gtsam.PriorFactorPoint2, gtsam.PriorFactorPoint3)):
            (key,) = factor.keys()
            if key not in keyset:
                raise _fail(path, None, f"cannot write factor {k}: key {key} has no value")
            fixed.append(key)
            continue
        obs = observations.get(k)
        if obs is not None:
            yield _observation_line(path, k, factor, obs, dim, points, keyset, offset_ids)
            continue
        if isinstance(factor, gtsam.BetweenFactorPose2) and not n3:
            edge_dim = 2
        elif isinstance(factor, gtsam.BetweenFactorPose3) and not n2:
            edge_dim = 3
        else:
            raise _fail(path, None, f"cannot write factor {k} ({type(factor).__name__}) with "
                                    f"{'Pose2' if n2 else 'Pose3' if n3 else 'no'} values: g2o holds "
                                    f"BetweenFactorPose2/3 of the values' kind, the landmark factors of "
                                    f"gtsam_schwarz.io.landmarks (and priors, as FIX)")
        i, j = factor.keys()
        for key in (i, j):
            if key not in keyset:
                raise _fail(path, None, f"cannot write factor {k}: key {key} has no value")
            if key in points:
                raise _fail(path, None, f"cannot write factor {k}: key {key} is a landmark, not a pose")
        info = _information_of(path, k, factor)
        z = factor.measured()
        if edge_dim == 2:
            upper = info[_UPPER2]
            head = f"EDGE_SE2 {i} {j} {_num(z.x())} {_num(z.y())} {_num(z.theta())}"
        else:
            upper = info[_UPPER3_FROM_GTSAM]  # g2o (t, r) order
            t, q = z.translation(), z.rotation().toQuaternion()
            head = (f"EDGE_SE3:QUAT {i} {j} {_num(t[0])} {_num(t[1])} {_num(t[2])} "
                    f"{_num(q.x())} {_num(q.y())} {_num(q.z())} {_num(q.w())}")
        yield head + "".join(" " + repr(x) for x in upper.tolist()) + "\n"
    for key in dict.fromkeys(fixed):
        yield f"FIX {key}\n"


def _observation_line(path: str, k: int, factor, obs: PointObservation, dim: int, points: dict, keyset: set,
                      offset_ids: dict) -> str:
    """The EDGE_SE2_XY / EDGE_SE3_TRACKXYZ line of a landmark factor: the factor's own measurement and,
    unless its noise model was replaced since, the information matrix it was made with (exact numbers)."""
    i, j = factor.keys()
    for key in (i, j):
        if key not in keyset:
            raise _fail(path, None, f"cannot write factor {k}: key {key} has no value")
    if i in points or j not in points or obs.dim != dim:
        raise _fail(path, None, f"cannot write factor {k}: a {obs.dim}D landmark edge needs a Pose{obs.dim} "
                                f"at key {i} and a Point{obs.dim} at key {j}")
    info = _information_of(path, k, factor)
    if np.linalg.norm(info - obs.information) <= 1e-9 * np.linalg.norm(obs.information):
        info = obs.information
    upper = np.asarray(info)[np.triu_indices(dim)]
    z = " ".join(_num(x) for x in obs.measured)
    if dim == 2:
        head = f"{_POINT_TAGS[2][1]} {i} {j} {z}"
    else:
        offset = _IDENTITY_OFFSET if obs.offset is None else tuple(obs.offset.tolist())
        head = f"{_POINT_TAGS[3][1]} {i} {j} {offset_ids[offset]} {z}"
    return head + "".join(" " + repr(x) for x in upper.tolist()) + "\n"


def _same_file(a: str, b: str) -> bool:
    """Whether two paths name the same file (inode when both exist, else resolved path)."""
    try:
        return os.path.samefile(a, b)
    except OSError:
        return os.path.realpath(a) == os.path.realpath(b)


def write_g2o(path, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, *, force: bool = False,
              input_path=None) -> None:
    """Write the graph's between factors and the values as g2o, atomically (temp file + fsync + rename).

    Landmarks go back as VERTEX_XY / VERTEX_TRACKXYZ lines, the landmark factors of :mod:`.landmarks`
    as EDGE_SE2_XY / EDGE_SE3_TRACKXYZ lines (3D: with PARAMS_SE3OFFSET lines for their sensor offsets).
    Information matrices go back in g2o order (Pose3: (t, r)); numbers are written exactly
    (shortest round-trip decimal). Pose priors become ``FIX`` lines (their mean and sigma are not
    stored). Overwriting ``input_path`` is refused unless ``force``. On any error or interrupt the
    destination is untouched and no temporary file remains.
    """
    path = os.fspath(path)
    if input_path is not None and not force and _same_file(path, os.fspath(input_path)):
        raise _fail(path, None, f"refusing to overwrite the input file {os.fspath(input_path)} (pass force=True)")
    try:
        atomic_write(path, _g2o_lines(path, graph, values))
    except IsADirectoryError:
        raise _fail(path, None, "cannot write: is a directory") from None
    except OSError as exc:
        raise _fail(path, None, f"cannot write: {exc.strerror or exc}") from None
