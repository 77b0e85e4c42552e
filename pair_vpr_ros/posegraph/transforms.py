"""Poses between ROS layouts and GTSAM, ROS-free.

ROS poses travel as 7 floats ``x, y, z, qx, qy, qz, qw``. GTSAM's ``Pose3`` tangent is
``(rx, ry, rz, x, y, z)`` with the perturbation on the right (in the pose's own frame):
``T = T_hat * Exp(xi)``; covariances here are in that order and frame.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import gtsam
import numpy as np


def pose3(pose: Sequence[float]) -> gtsam.Pose3:
    """``(x, y, z, qx, qy, qz, qw)`` -> ``gtsam.Pose3`` (the quaternion is normalised)."""
    x, y, z, qx, qy, qz, qw = (float(v) for v in pose)
    norm = math.sqrt(qx * qx + qy * qy + qz * qz + qw * qw)
    rot = gtsam.Rot3.Quaternion(qw / norm, qx / norm, qy / norm, qz / norm)
    return gtsam.Pose3(rot, np.array([x, y, z]))


def pose7(pose: gtsam.Pose3) -> tuple[float, ...]:
    """``gtsam.Pose3`` -> ``(x, y, z, qx, qy, qz, qw)`` with ``qw >= 0``."""
    q = pose.rotation().toQuaternion()
    qx, qy, qz, qw = q.x(), q.y(), q.z(), q.w()
    if qw < 0:
        qx, qy, qz, qw = -qx, -qy, -qz, -qw
    t = pose.translation()
    return (float(t[0]), float(t[1]), float(t[2]), qx, qy, qz, qw)


def planar_pose7(x: float, y: float, yaw: float, z: float = 0.0) -> tuple[float, ...]:
    """A pose on the ground plane, heading ``yaw`` (rad from +x towards +y)."""
    return (float(x), float(y), float(z), 0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))


def valid_pose7(pose: Sequence[float]) -> str | None:
    """Why ``pose`` cannot be used (None when it can): non-finite values or a zero quaternion."""
    values = np.asarray(pose, dtype=np.float64)
    if values.shape != (7,):
        return f"a pose needs 7 values (x, y, z, qx, qy, qz, qw), got {values.size}"
    if not np.isfinite(values).all():
        return "pose has NaN or infinite values"
    if np.linalg.norm(values[3:]) < 1e-9:
        return "pose has a zero quaternion"
    return None


def transform_covariance(cov: np.ndarray, transform: gtsam.Pose3) -> np.ndarray:
    """Covariance (GTSAM order, right perturbation of pose P) -> that of ``T P T^-1``.

    ``T P Exp(xi) T^-1 = (T P T^-1) Exp(Ad_T xi)``, so the covariance maps by ``Ad_T``.
    """
    adjoint = transform.AdjointMap()
    return adjoint @ np.asarray(cov, dtype=np.float64) @ adjoint.T


def interpolate(a: gtsam.Pose3, b: gtsam.Pose3, fraction: float) -> gtsam.Pose3:
    """The pose ``fraction`` of the way from ``a`` to ``b`` along the geodesic (0 -> a, 1 -> b)."""
    delta = gtsam.Pose3.Logmap(a.between(b))
    return a.compose(gtsam.Pose3.Expmap(float(fraction) * delta))
