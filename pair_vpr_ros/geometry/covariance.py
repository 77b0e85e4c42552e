"""Covariance of a fitted pose from its own inliers, plus what no residual can show.

The pose is T_match_query = (R, t). Its error is parameterised in ROS order
d = (d_x, d_y, d_z, d_rx, d_ry, d_rz): R_true = Exp(d_rot) R, t_true = t + d_t, both along the
match camera's axes. At the solution PoseLib's refinement reached, J = d residuals / d d (central
differences of the residuals through the cameras' own models) gives the information matrix
H = J^T W J, W the weights of the refinement's robust loss there (`solvers.loss_weights`), and
the a-posteriori variance of the inliers sigma^2 = sum r^2 / (n - p) the pixel noise the
residuals show, larger or smaller than anyone assumed; the covariance of that robust estimate
is sigma^2 H^-1 (J^T W^2 J) H^-1 (`sandwich`: with W = I, sigma^2 (J^T J)^-1).
`PoseConfig.floor_px` is a lower bound on sigma only (a noise-free render is not certainty).
The matches' errors are not quite independent: `PoseConfig.covariance_scale` makes up for that
as measured on the demo world.

Then `with_systematic` adds errors that bend every residual alike and so hide in the fit: a
per-camera term `systematic_px` (a rolling shutter read out while the camera turns, an image
stamp off by a few ms; docs/real-cameras.md says how to choose it) as that many pixels' angle
at the focal length on each rotation axis, at least `floor_rotation_deg`, and the translation
floor (a + b |t|). The model checks (`checks.py`) add what the data show.
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


def posterior_covariance(
    jac: np.ndarray, res: np.ndarray, weights: np.ndarray, floor: float
) -> tuple[np.ndarray, float] | None:
    """J [n, p], inlier residuals [n] and the loss's weights at them [n] -> (covariance
    [p, p], sigma): sigma^2 = sum r^2 / (n - p), at least floor^2, carried through the robust
    estimator (`sandwich`); None when degenerate or n <= p."""
    n, p = jac.shape
    if n <= p:
        return None
    sigma = max(math.sqrt(float(np.sum(res**2)) / (n - p)), floor)
    cov = sandwich(jac.T @ (weights[:, None] * jac), jac.T @ ((weights**2)[:, None] * jac))
    return None if cov is None else (cov * sigma**2, sigma)


def sandwich(h: np.ndarray, meat: np.ndarray) -> np.ndarray | None:
    """Covariance H^-1 M H^-1 [p, p] of the estimator that solved sum w_i r_i^2 = min, with H
    = sum w J^T J its information and M = sum w^2 J^T S J (S: each residual's covariance);
    None when H is singular (the residuals do not fix every parameter: degenerate geometry)."""
    eig = np.linalg.eigvalsh(h)
    if eig[0] <= eig[-1] * 1e-12:
        return None
    inv = np.linalg.inv(h)
    cov = inv @ meat @ inv
    return (cov + cov.T) / 2


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


def with_systematic(
    cov: np.ndarray, t: np.ndarray, config: Any, cameras: tuple, scaled: bool = True
) -> np.ndarray:
    """6x6 covariance of a pose between `cameras` plus the independent systematic terms of
    `config` (`PoseConfig`): `systematic_rotation_deg` on each rotation axis and, for a pose
    with a scale, (floor_translation_m + floor_translation_rel |t|) on each translation axis."""
    out = cov.copy()
    out[3:, 3:] += np.eye(3) * np.radians(systematic_rotation_deg(config, *cameras)) ** 2
    if scaled:
        trans = config.floor_translation_m + config.floor_translation_rel * np.linalg.norm(t)
        out[:3, :3] += np.eye(3) * float(trans) ** 2
    return out


def systematic_rotation_deg(config: Any, *cameras: Any) -> float:
    """Systematic rotation std (deg per axis) of a pose between `cameras` (`CameraModel`):
    `config.systematic_px` pixels' angle at their mean focal length (a camera with more,
    smaller pixels sees a smaller turn), at least `config.floor_rotation_deg`."""
    f = sum((c.fx + c.fy) / 2 for c in cameras) / len(cameras)
    return max(config.floor_rotation_deg, math.degrees(config.systematic_px / f))
