"""Trajectory accuracy against a ground truth: ATE and RPE with evo's definitions.

- **ATE** (absolute trajectory error) = ``evo_ape --align`` with the default pose relation
  (translation part): the estimate is first aligned to the reference by the rigid-body
  (rotation + translation, no scale) Umeyama fit of the positions, SE(3) for 3D trajectories and
  SE(2) for planar ones; then RMSE over the poses of ‖t_ref,i − t_est,i‖.
- **RPE** (relative pose error) = ``evo_rpe`` with its defaults (translation part, delta = 1 frame,
  consecutive pairs, no alignment; a rigid alignment would not change it): RMSE over i of the
  translation of (P_ref,i⁻¹ P_ref,i+1)⁻¹ (P_est,i⁻¹ P_est,i+1).

Poses are matched by key; for a TUM file the timestamp is the key (as ``gtsam-schwarz solve -o
out.tum`` writes it), or, when its timestamps are not the keys, by order if the counts agree.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

ALIGNMENT = "rigid (rotation + translation, no scale) Umeyama alignment"
ATE_DEFINITION = f"RMSE of the position error after {ALIGNMENT} (evo_ape --align)"
RPE_DEFINITION = "RMSE of the relative translation error over consecutive poses, delta 1 (evo_rpe defaults)"


class TrajectoryError(ValueError):
    """A ground truth that cannot be read or matched to the estimate (one line)."""


@dataclass
class Trajectory:
    """Poses as arrays, sorted by key: translations (n, 3), rotations (n, 3, 3); Pose2 have z = 0."""

    keys: np.ndarray
    t: np.ndarray
    R: np.ndarray
    dimension: int  # 2 or 3

    def __len__(self) -> int:
        return len(self.keys)

    @classmethod
    def from_values(cls, values) -> "Trajectory":
        from ..io.tum import values_to_arrays

        keys, t, R, dim = values_to_arrays(values)
        return cls(keys, t, R, dim)

    def subset(self, index) -> "Trajectory":
        return Trajectory(self.keys[index], self.t[index], self.R[index], self.dimension)

    @property
    def planar(self) -> bool:
        """All positions in z = 0 and all rotations about z."""
        return bool(np.allclose(self.t[:, 2], 0.0, atol=1e-12) and np.allclose(self.R[:, 2, 2], 1.0, atol=1e-12))


def read_trajectory(path) -> Trajectory:
    """A ground truth from a TUM file (``.tum``, ``.txt``) or the VERTEX lines of a g2o / TORO file.
    Raises :class:`TrajectoryError` with one line."""
    from ..io.tum import TumFileError, quaternion_to_rotation, read_tum

    path = os.fspath(path)
    if not os.path.exists(path):
        raise TrajectoryError(f"{path}: no such file")
    if os.path.isdir(path):
        raise TrajectoryError(f"{path}: is a directory, expected a g2o or TUM file")
    if path.lower().endswith((".tum", ".txt")):
        try:
            stamps, t, q = read_tum(path)
        except TumFileError as exc:
            raise TrajectoryError(str(exc)) from None
        except (OSError, UnicodeDecodeError) as exc:
            raise TrajectoryError(f"{path}: cannot read: {getattr(exc, 'strerror', None) or exc}") from None
        R = quaternion_to_rotation(q)
        if np.all(stamps == np.round(stamps)) and np.all(stamps >= 0) and len(np.unique(stamps)) == len(stamps):
            keys = stamps.astype(np.uint64)
        else:
            keys = np.full(len(stamps), np.iinfo(np.uint64).max, dtype=np.uint64)  # matched by order
        order = np.argsort(keys, kind="stable")
        traj = Trajectory(keys[order], t[order], R[order], 3)
        return Trajectory(traj.keys, traj.t, traj.R, 2 if traj.planar else 3)
    return _g2o_vertices(path)


def _g2o_vertices(path: str) -> Trajectory:
    """The VERTEX poses of a g2o or TORO file (edges are not needed), with the loader's line checks."""
    from ..io import GraphFileError
    from ..io.g2o import read_vertices  # the loader's tokenizer: same line-numbered errors

    try:
        dim, keys, v = read_vertices(path)
    except GraphFileError as exc:
        raise TrajectoryError(str(exc)) from None
    if not len(keys):
        raise TrajectoryError(f"{path}: no VERTEX lines, nothing to compare with")
    n = len(keys)
    if dim == 2:
        c, s = np.cos(v[:, 2]), np.sin(v[:, 2])
        R = np.zeros((n, 3, 3))
        R[:, 0, 0], R[:, 0, 1], R[:, 1, 0], R[:, 1, 1], R[:, 2, 2] = c, -s, s, c, 1.0
        return Trajectory(keys, np.column_stack([v[:, :2], np.zeros(n)]), R, 2)
    from ..io.tum import quaternion_to_rotation

    return Trajectory(keys, v[:, :3].copy(), quaternion_to_rotation(v[:, 3:7]), 3)


def associate(estimate: Trajectory, reference: Trajectory) -> tuple[Trajectory, Trajectory]:
    """The poses present in both (by key), in key order; by order when the reference has no keys
    (TUM timestamps that are not pose keys) and the counts agree."""
    unkeyed = np.iinfo(np.uint64).max
    if len(reference) and np.all(reference.keys == unkeyed):
        if len(reference) != len(estimate):
            raise TrajectoryError(f"the ground truth's timestamps are not pose keys and it has {len(reference)} "
                                  f"poses, the estimate {len(estimate)}: cannot match them")
        return estimate, reference
    common, ie, ir = np.intersect1d(estimate.keys, reference.keys, assume_unique=True, return_indices=True)
    if len(common) < 2:
        raise TrajectoryError(f"the ground truth shares {len(common)} pose keys with the estimate; need at least 2")
    return estimate.subset(ie), reference.subset(ir)


def umeyama(x: np.ndarray, y: np.ndarray, with_scale: bool = False) -> tuple[np.ndarray, np.ndarray, float]:
    """R, t, c minimizing Σ‖y_i − (c R x_i + t)‖² over rotations R (det +1) (Umeyama 1991; evo's
    ``umeyama_alignment``). ``x``, ``y``: (n, d) point sets."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    n, d = x.shape
    mx, my = x.mean(axis=0), y.mean(axis=0)
    xc, yc = x - mx, y - my
    sigma_x = (xc ** 2).sum() / n
    cov = yc.T @ xc / n
    U, D, Vt = np.linalg.svd(cov)
    S = np.eye(d)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[-1, -1] = -1.0
    R = U @ S @ Vt
    c = float(np.trace(np.diag(D) @ S) / sigma_x) if with_scale and sigma_x > 0 else 1.0
    t = my - c * R @ mx
    return R, t, c


def align(estimate: Trajectory, reference: Trajectory) -> Trajectory:
    """The estimate moved by the rigid Umeyama fit of its positions to the reference's (SE(2) in the
    plane when both are planar, SE(3) otherwise)."""
    d = 2 if (estimate.planar and reference.planar) else 3
    R_d, t_d, _ = umeyama(estimate.t[:, :d], reference.t[:, :d])
    R, t = np.eye(3), np.zeros(3)
    R[:d, :d], t[:d] = R_d, t_d
    return Trajectory(estimate.keys, estimate.t @ R.T + t, np.einsum("ij,njk->nik", R, estimate.R),
                      estimate.dimension)


def _rmse(e: np.ndarray) -> float:
    return float(np.sqrt(np.mean(e ** 2))) if len(e) else float("nan")


def ate_errors(estimate: Trajectory, reference: Trajectory, aligned: bool = True) -> np.ndarray:
    """Per-pose position error after (by default) rigid alignment; the inputs must be associated."""
    est = align(estimate, reference) if aligned else estimate
    return np.linalg.norm(est.t - reference.t, axis=1)


def rpe_errors(estimate: Trajectory, reference: Trajectory, delta: int = 1) -> np.ndarray:
    """Per-pair relative translation error ‖trans((Q_i⁻¹Q_j)⁻¹ (P_i⁻¹P_j))‖, j = i + delta."""
    def relative(tr):
        Ri, dt = tr.R[:-delta], tr.t[delta:] - tr.t[:-delta]
        return np.einsum("nji,nj->ni", Ri, dt), np.einsum("nji,njk->nik", Ri, tr.R[delta:])

    t_est, _ = relative(estimate)
    t_ref, R_ref = relative(reference)
    # translation of E = rel_ref⁻¹ rel_est is R_ref,relᵀ (t_est,rel − t_ref,rel); its norm:
    return np.linalg.norm(np.einsum("nji,nj->ni", R_ref, t_est - t_ref), axis=1)


def evaluate(estimate, reference) -> dict:
    """ATE and RPE (RMSE, metres) of ``estimate`` (gtsam.Values or :class:`Trajectory`) against
    ``reference`` (likewise), with evo's definitions (module docstring)."""
    est = estimate if isinstance(estimate, Trajectory) else Trajectory.from_values(estimate)
    ref = reference if isinstance(reference, Trajectory) else Trajectory.from_values(reference)
    est, ref = associate(est, ref)
    ate = ate_errors(est, ref)
    rpe = rpe_errors(est, ref)
    return {"ate_rmse": _rmse(ate), "ate_max": float(ate.max()), "rpe_rmse": _rmse(rpe),
            "rpe_max": float(rpe.max()) if len(rpe) else float("nan"), "poses": len(est),
            "alignment": "SE(2)" if (est.planar and ref.planar) else "SE(3)"}
