"""Covariance of a fitted pose from its inlier residuals (Gauss-Newton at the solution).

The pose is T_match_query = (R, t). Its error is parameterised in ROS order
d = (d_x, d_y, d_z, d_rx, d_ry, d_rz): R_true = Exp(d_rot) R, t_true = t + d_t, both along the
match camera's axes. With J = d residuals / d d at the solution (central differences), and
sigma^2 = sum(r^2) / (n - p) from the inlier residuals (floored at `min_sigma`, so a perfect fit
on noise-free images is not taken as certainty), cov = sigma^2 (J^T J)^-1. This is the
reprojection-only covariance: it does not include errors of the depth image, and it treats the
matches' errors as independent, which they are not quite (`PoseConfig.covariance_scale` makes up
for it as measured on the demo world; the tails stay heavier than Gaussian: use a robust kernel).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

from pair_vpr_ros.geometry.rotations import exp_so3

Residuals = Callable[[np.ndarray, np.ndarray], np.ndarray]  # (R [3,3], t [3]) -> r [n]
STEP = 1e-6  # m and rad: central-difference step
SCALE_FREE_VARIANCE = 1e6  # m^2 on each translation axis of a pose without scale


def perturbed(r: np.ndarray, t: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) moved by d = (d_t [3], d_rot [3]) in the match frame (the convention above)."""
    return exp_so3(d[3:]) @ r, t + d[:3]


def jacobian(residuals: Residuals, r: np.ndarray, t: np.ndarray) -> np.ndarray:
    """d residuals / d (d_t, d_rot) at (R, t) -> [n, 6]."""
    cols = []
    for k in range(6):
        d = np.zeros(6)
        d[k] = STEP
        plus = residuals(*perturbed(r, t, d))
        minus = residuals(*perturbed(r, t, -d))
        cols.append((plus - minus) / (2 * STEP))
    return np.stack(cols, axis=1)


def gauss_newton_covariance(
    jac: np.ndarray, res: np.ndarray, min_sigma: float
) -> tuple[np.ndarray, float] | None:
    """J [n, p] and residuals [n] -> (cov [p, p], sigma); None when J^T J is singular (the
    residuals do not constrain every parameter: degenerate geometry)."""
    n, p = jac.shape
    if n <= p:
        return None
    sigma = max(float(np.sqrt(np.sum(res**2) / (n - p))), min_sigma)
    info = jac.T @ jac
    eig = np.linalg.eigvalsh(info)
    if eig[0] <= eig[-1] * 1e-12:
        return None
    cov = sigma**2 * np.linalg.inv(info)
    return (cov + cov.T) / 2, sigma


def embed_rotation(cov_rot: np.ndarray, translation_variance: float) -> np.ndarray:
    """6x6 (x, y, z, rx, ry, rz) covariance from a rotation block [3, 3] and an isotropic
    translation variance (m^2), no cross terms: for a pose whose translation has no scale."""
    cov = np.zeros((6, 6))
    cov[:3, :3] = np.eye(3) * translation_variance
    cov[3:, 3:] = cov_rot
    return cov


def sigmas(cov: np.ndarray) -> tuple[float, float]:
    """(largest translation std, m; largest rotation std, deg) of a 6x6 covariance."""
    trans = float(np.sqrt(np.linalg.eigvalsh(cov[:3, :3])[-1]))
    rot = float(np.degrees(np.sqrt(np.linalg.eigvalsh(cov[3:, 3:])[-1])))
    return trans, rot


def with_floor(
    cov: np.ndarray, t: np.ndarray, config: Any, cameras: tuple, scaled: bool = True
) -> np.ndarray:
    """6x6 covariance of a pose between `cameras` plus the independent floor noise of `config`
    (`PoseConfig`): `rotation_floor_deg` on each rotation axis and, for a pose with a scale,
    (floor_translation_m + floor_translation_rel |t|) on each translation axis."""
    out = cov.copy()
    out[3:, 3:] += np.eye(3) * np.radians(rotation_floor_deg(config, *cameras)) ** 2
    if scaled:
        trans = config.floor_translation_m + config.floor_translation_rel * np.linalg.norm(t)
        out[:3, :3] += np.eye(3) * float(trans) ** 2
    return out


def rotation_floor_deg(config: Any, *cameras: Any) -> float:
    """Rotation floor (deg per axis) of a pose fitted on the pixels of `cameras` (`CameraModel`):
    `config.floor_rotation_px` pixels' angle at their mean focal length (a camera with more,
    smaller pixels sees a smaller turn), at least `config.floor_rotation_deg`."""
    f = sum((c.fx + c.fy) / 2 for c in cameras) / len(cameras)
    return max(config.floor_rotation_deg, math.degrees(config.floor_rotation_px / f))
