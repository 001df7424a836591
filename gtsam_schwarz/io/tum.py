"""TUM trajectory files: ``timestamp tx ty tz qx qy qz qw``, one pose per line (the format of the
TUM RGB-D benchmark, read by evo and most SLAM evaluation tools).

We write the pose's key as its timestamp; a Pose2 becomes z = 0 and the quaternion of its yaw.
"""

from __future__ import annotations

import math
import os

import gtsam
import numpy as np

from .atomic import atomic_write


class TumFileError(ValueError):
    """A defect of a TUM file: one line ``path:line: what``."""


def rotation_to_quaternion(R: np.ndarray) -> np.ndarray:
    """Unit quaternions (x, y, z, w), w ≥ 0, of rotation matrices ``R`` (..., 3, 3) (Shepperd's method)."""
    R = np.asarray(R, dtype=float)
    shape = R.shape[:-2]
    R = R.reshape(-1, 3, 3)
    m00, m11, m22 = R[:, 0, 0], R[:, 1, 1], R[:, 2, 2]
    trace = m00 + m11 + m22
    # the largest of 4w², 4x², 4y², 4z² decides which formula is well conditioned
    cand = np.stack([1 + trace, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], axis=1)
    k = np.argmax(cand, axis=1)
    q = np.empty((len(R), 4))
    s = 2.0 * np.sqrt(np.maximum(cand[np.arange(len(R)), k], 1e-300))
    d = {0: (R[:, 2, 1] - R[:, 1, 2]), 1: (R[:, 0, 2] - R[:, 2, 0]), 2: (R[:, 1, 0] - R[:, 0, 1])}
    p = {0: (R[:, 0, 1] + R[:, 1, 0]), 1: (R[:, 0, 2] + R[:, 2, 0]), 2: (R[:, 1, 2] + R[:, 2, 1])}
    for case in range(4):
        i = k == case
        if not i.any():
            continue
        si = s[i]
        if case == 0:  # w largest
            q[i] = np.column_stack([d[0][i] / si, d[1][i] / si, d[2][i] / si, si / 4])
        elif case == 1:  # x largest
            q[i] = np.column_stack([si / 4, p[0][i] / si, p[1][i] / si, d[0][i] / si])
        elif case == 2:  # y largest
            q[i] = np.column_stack([p[0][i] / si, si / 4, p[2][i] / si, d[1][i] / si])
        else:  # z largest
            q[i] = np.column_stack([p[1][i] / si, p[2][i] / si, si / 4, d[2][i] / si])
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q[q[:, 3] < 0] *= -1
    return q.reshape(*shape, 4)


def quaternion_to_rotation(q: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of quaternions (x, y, z, w) (normalized first)."""
    q = np.asarray(q, dtype=float)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = np.moveaxis(q, -1, 0)
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


def values_to_arrays(values: gtsam.Values) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """(keys, translations (n, 3), rotations (n, 3, 3), dimension) of the Pose2 or Pose3 in ``values``,
    sorted by key; Pose2 become z = 0 and a rotation about z."""
    p2 = gtsam.utilities.allPose2s(values)
    if p2.size():
        keys = np.array(sorted(p2.keys()), dtype=np.uint64)
        xyt = np.asarray(gtsam.utilities.extractPose2(p2)).reshape(-1, 3)
        c, s = np.cos(xyt[:, 2]), np.sin(xyt[:, 2])
        R = np.zeros((len(xyt), 3, 3))
        R[:, 0, 0], R[:, 0, 1], R[:, 1, 0], R[:, 1, 1], R[:, 2, 2] = c, -s, s, c, 1.0
        return keys, np.column_stack([xyt[:, :2], np.zeros(len(xyt))]), R, 2
    p3 = gtsam.utilities.allPose3s(values)
    keys = np.array(sorted(p3.keys()), dtype=np.uint64)
    m = np.asarray(gtsam.utilities.extractPose3(p3)).reshape(-1, 12)
    return keys, m[:, 9:12].copy(), m[:, :9].reshape(-1, 3, 3), 3


def tum_lines(values: gtsam.Values):
    """The TUM lines of the poses in ``values`` (key order; timestamp = key; shortest round-trip numbers)."""
    keys, t, R, _ = values_to_arrays(values)
    q = rotation_to_quaternion(R) if len(keys) else np.zeros((0, 4))
    rows = np.column_stack([t, q]).tolist()
    for key, row in zip(keys.tolist(), rows):
        yield f"{key} " + " ".join(map(repr, row)) + "\n"


def write_tum(path, values: gtsam.Values) -> str:
    """Write the poses of ``values`` as a TUM trajectory, atomically (temp file, fsync, rename).
    Raises ``OSError`` (no folder is created)."""
    return atomic_write(path, "".join(tum_lines(values)))


def read_tum(path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(timestamps (n,), translations (n, 3), quaternions (n, 4) as x y z w) of a TUM file.

    Blank lines and ``#`` comments are skipped (commas are accepted as separators, as evo does).
    Raises :class:`TumFileError` naming the line, or ``OSError``."""
    path = os.fspath(path)
    stamps, rows = [], []
    with open(path, encoding="utf-8", errors="strict") as fh:
        for lineno, raw in enumerate(fh, 1):
            text = raw.split("#", 1)[0].replace(",", " ").split()
            if not text:
                continue
            if len(text) != 8:
                raise TumFileError(f"{path}:{lineno}: expected 8 fields (timestamp tx ty tz qx qy qz qw), "
                                   f"got {len(text)}")
            try:
                numbers = [float(v) for v in text]
            except ValueError:
                raise TumFileError(f"{path}:{lineno}: not a number in {raw.strip()!r}") from None
            if not all(math.isfinite(v) for v in numbers):
                raise TumFileError(f"{path}:{lineno}: non-finite number in {raw.strip()!r}")
            norm = math.sqrt(sum(v * v for v in numbers[4:]))
            if abs(norm - 1.0) > 1e-3:
                raise TumFileError(f"{path}:{lineno}: quaternion norm {norm:.6g} is not 1")
            stamps.append(numbers[0])
            rows.append(numbers[1:])
    if not rows:
        raise TumFileError(f"{path}: no poses")
    data = np.array(rows)
    return np.array(stamps), data[:, :3], data[:, 3:] / np.linalg.norm(data[:, 3:], axis=1, keepdims=True)
