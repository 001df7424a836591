"""Pose → landmark observations of g2o files as GTSAM factors (``EDGE_SE2_XY``, ``EDGE_SE3_TRACKXYZ``).

g2o's measurement is the landmark's position in the observing pose's frame (3D: in the frame of the
sensor mounted at ``offset`` on the pose, g2o's ``PARAMS_SE3OFFSET``)::

    e = R_iᵀ (l_j − t_i) − z                               (2D, and 3D with the identity offset)
    e = R_oᵀ (R_iᵀ (l_j − t_i) − t_o) − z                  (3D with offset (R_o, t_o))

GTSAM's Python wheel has no pose-to-point factor with this measurement, so :func:`point_observation_factor`
builds a ``gtsam.CustomFactor`` whose error function, an :class:`PointObservation`, returns e and its
analytic Jacobians in GTSAM's tangent conventions: a Pose2 moves as x·Exp(ξ) with ξ = (vx, vy, ω)
(position by R·v, angle by ω), a Pose3 as x·Exp(ξ) with ξ = (ω, v), a point as l + δ. With
q = R_iᵀ (l_j − t_i):

    2D   ∂e/∂ξ = [[−1, 0, q_y], [0, −1, −q_x]]          ∂e/∂l = R_iᵀ
    3D   ∂e/∂ξ = R_oᵀ [ [q]ₓ | −I ]                      ∂e/∂l = R_oᵀ R_iᵀ

A CustomFactor holds no Python attributes, so the writer finds the measurement, information and offset of
such a factor with :func:`observation_of`: it evaluates the factor once while a thread-local probe is
armed, and the error function, when it is one of ours, hands itself over instead of computing.
"""

from __future__ import annotations

import math
import threading

import gtsam
import numpy as np

__all__ = ["PointObservation", "point_observation_factor", "observation_of", "landmark_from_observation"]


class _Probe(threading.local):
    active = False
    hit = None


_PROBE = _Probe()


def _frozen(a, shape) -> np.ndarray:
    out = np.array(a, dtype=float).reshape(shape)
    out.setflags(write=False)
    return out


class PointObservation:
    """Error function of one pose → point observation (the ``errorFunction`` of a ``gtsam.CustomFactor``).

    ``dim`` is 2 (Pose2, Point2) or 3 (Pose3, Point3); ``measured`` the point in the pose's (sensor's)
    frame; ``information`` the (dim, dim) information matrix given to the factor's noise model, kept here
    so that the writer can put back the file's exact numbers; ``offset`` (3D only) the sensor pose on the
    robot as (x y z qx qy qz qw) or None for the identity, and ``offset_id`` the file's parameter id.
    The keys come from the factor (``this.keys()``), so rekeyed copies stay correct.
    """

    __slots__ = ("dim", "measured", "information", "offset", "offset_id", "_Ro_T", "_to")

    def __init__(self, dim: int, measured, information, offset=None, offset_id: int = 0):
        if dim not in (2, 3):
            raise ValueError(f"dim must be 2 or 3, got {dim!r}")
        if offset is not None and dim != 3:
            raise ValueError("a sensor offset exists only for 3D observations")
        self.dim = dim
        self.measured = _frozen(measured, (dim,))
        self.information = _frozen(information, (dim, dim))
        self.offset_id = int(offset_id)
        self.offset = self._Ro_T = self._to = None
        if offset is not None:
            self.offset = _frozen(offset, (7,))
            o = self.offset
            pose = gtsam.Pose3(gtsam.Rot3.Quaternion(o[6], o[3], o[4], o[5]), np.array(o[:3]))
            self._Ro_T = pose.rotation().matrix().T
            self._to = np.asarray(pose.translation(), dtype=float)

    def __call__(self, this, values: gtsam.Values, H) -> np.ndarray:
        if _PROBE.active:  # observation_of(): hand this object over instead of computing
            _PROBE.hit = self
            return np.zeros(self.dim)
        i, j = this.keys()
        if self.dim == 2:
            pose = values.atPose2(i)
            l = values.atPoint2(j)
            th = pose.theta()
            c, s = math.cos(th), math.sin(th)
            dx, dy = l[0] - pose.x(), l[1] - pose.y()
            qx, qy = c * dx + s * dy, -s * dx + c * dy
            if H is not None:
                H[0] = np.array([[-1.0, 0.0, qy], [0.0, -1.0, -qx]])
                H[1] = np.array([[c, s], [-s, c]])
            z = self.measured
            return np.array([qx - z[0], qy - z[1]])
        pose = values.atPose3(i)
        l = values.atPoint3(j)
        Rt = pose.rotation().matrix().T
        q = Rt @ (np.asarray(l, dtype=float) - pose.translation())
        if H is not None:
            qx, qy, qz = q
            Hpose = np.array([[0.0, -qz, qy, -1.0, 0.0, 0.0],
                              [qz, 0.0, -qx, 0.0, -1.0, 0.0],
                              [-qy, qx, 0.0, 0.0, 0.0, -1.0]])
            Hpoint = Rt
            if self._Ro_T is not None:
                Hpose, Hpoint = self._Ro_T @ Hpose, self._Ro_T @ Rt
            H[0] = Hpose
            H[1] = Hpoint
        if self._Ro_T is not None:
            q = self._Ro_T @ (q - self._to)
        return q - self.measured

    def landmark(self, pose) -> np.ndarray:
        """The landmark position this measurement puts at ``pose`` (Pose2 / Pose3): t + R z (3D:
        through the sensor offset)."""
        z = self.measured
        if self.dim == 2:
            th = pose.theta()
            c, s = math.cos(th), math.sin(th)
            return np.array([pose.x() + c * z[0] - s * z[1], pose.y() + s * z[0] + c * z[1]])
        p = np.asarray(z, dtype=float)
        if self._Ro_T is not None:
            p = self._Ro_T.T @ p + self._to
        return np.asarray(pose.translation(), dtype=float) + pose.rotation().matrix() @ p


def point_observation_factor(pose_key: int, point_key: int, measured, information, *, offset=None,
                             offset_id: int = 0, noise=None) -> gtsam.CustomFactor:
    """A ``gtsam.CustomFactor`` on (pose, point) with error ``R_iᵀ(l_j − t_i) − z`` (see the module).

    ``information`` is the (d, d) information matrix; the noise model is
    ``gtsam.noiseModel.Gaussian.Information(information)`` unless ``noise`` is given. The dimension
    comes from ``measured`` (2 or 3 numbers).
    """
    z = np.asarray(measured, dtype=float).reshape(-1)
    obs = PointObservation(len(z), z, information, offset=offset, offset_id=offset_id)
    if noise is None:
        noise = gtsam.noiseModel.Gaussian.Information(np.array(obs.information))
    return gtsam.CustomFactor(noise, [int(pose_key), int(point_key)], obs)


def landmark_from_observation(pose, measured, offset=None) -> np.ndarray:
    """Position of a landmark seen at ``measured`` from ``pose``: t + R z (3D: through ``offset``)."""
    z = np.asarray(measured, dtype=float).reshape(-1)
    return PointObservation(len(z), z, np.eye(len(z)), offset=offset).landmark(pose)


def observation_of(factor, values: gtsam.Values | None = None) -> PointObservation | None:
    """The :class:`PointObservation` inside ``factor`` if it is a CustomFactor built by
    :func:`point_observation_factor` (or a clone / rekeyed copy of one); None for any other factor.

    The factor is evaluated once at ``values`` (its own error function, if foreign, sees them as in
    ``graph.error``; ours returns at once); a foreign function that raises counts as not ours.
    """
    if not isinstance(factor, gtsam.CustomFactor) or factor.size() != 2:
        return None
    _PROBE.active, _PROBE.hit = True, None
    try:
        factor.unwhitenedError(values if values is not None else gtsam.Values())
    except Exception:  # a foreign error function that cannot run on these values
        pass
    finally:
        hit, _PROBE.active, _PROBE.hit = _PROBE.hit, False, None
    return hit if isinstance(hit, PointObservation) else None
