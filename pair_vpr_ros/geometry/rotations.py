"""Rotation helpers: quaternions (x, y, z, w, as ROS orders them), exponential map, angles."""

from __future__ import annotations

import math

import cv2
import numpy as np


def quaternion_matrix(q) -> np.ndarray:
    """(qx, qy, qz, qw) -> [3, 3] rotation matrix (normalised first)."""
    x, y, z, w = np.asarray(q, np.float64) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def matrix_quaternion(r: np.ndarray) -> tuple[float, float, float, float]:
    """[3, 3] rotation matrix -> (qx, qy, qz, qw) with qw >= 0."""
    rvec = cv2.Rodrigues(np.asarray(r, np.float64))[0].ravel()
    angle = float(np.linalg.norm(rvec))
    axis = rvec / angle if angle > 0 else np.zeros(3)
    s = math.sin(angle / 2)
    q = (float(axis[0] * s), float(axis[1] * s), float(axis[2] * s), math.cos(angle / 2))
    return q if q[3] >= 0 else tuple(-v for v in q)  # type: ignore[return-value]


def skew(v: np.ndarray) -> np.ndarray:
    """[3] -> [3, 3] cross-product matrix: skew(v) @ x = v x x."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def exp_so3(w: np.ndarray) -> np.ndarray:
    """Rotation vector [3] (rad) -> [3, 3] rotation matrix."""
    return cv2.Rodrigues(np.asarray(w, np.float64).reshape(3, 1))[0]


def rotation_angle_deg(r: np.ndarray) -> float:
    """Angle of a rotation matrix [3, 3], degrees."""
    c = (float(np.trace(r)) - 1.0) / 2.0
    return math.degrees(math.acos(min(1.0, max(-1.0, c))))


def log_so3(r: np.ndarray) -> np.ndarray:
    """[3, 3] rotation matrix -> rotation vector [3] (rad); inverse of `exp_so3`."""
    return cv2.Rodrigues(np.asarray(r, np.float64))[0].ravel()
