"""Weighted refinement and covariance of a PnP pose with noisy 3-D points (depth images).

Each inlier i has 3-D point X_i (from a depth image, covariance Sigma_X from the depth-noise
model, `depth_noise.point_covariances`) seen at pixel p_i in the other camera. Its reprojection
residual has covariance S_i = sigma_px^2 I + J_X Sigma_X J_X^T (J_X: the projection's Jacobian
with respect to the point), so far points, whose depth is poor, count less. The pose is refined
by Gauss-Newton on the whitened residuals S_i^-1/2 r_i and its covariance is
(sum J_i^T S_i^-1 J_i)^-1 times the variance factor max(0.1, chi^2 / (2n - 6)): the residuals
say when the pixel noise is larger than assumed (blur, rolling shutter, a poor calibration)
or smaller (a chessboard's corners: whitened RMS 0.31, docs/real-cameras.md); at most a factor
of 10 smaller, so a noise-free render is not taken as certainty.
"""

from __future__ import annotations

import numpy as np

from pair_vpr_ros.geometry import covariance as cv
from pair_vpr_ros.geometry.depth_noise import point_covariances
from pair_vpr_ros.geometry.pnp import project

ITERATIONS = 3
MIN_VARIANCE_FACTOR = 0.1  # residuals may shrink the assumed noise variance at most 10x


def _camera_points(pts, r, t, points_in_match: bool) -> tuple[np.ndarray, np.ndarray]:
    """-> (points [N, 3] in the camera that sees the pixels, R of that mapping [3, 3])."""
    if points_in_match:  # X_q = R^T (X_m - t)
        return (pts - t) @ r, r.T
    return pts @ r.T + t, r


def residual_covariances(pts, cov_x, k, r, t, points_in_match: bool, sigma_px: float):
    """[N, 2, 2] covariances of the reprojection residuals (pixel noise + point noise)."""
    cam, rot = _camera_points(pts, r, t, points_in_match)
    x, y, z = cam.T
    jp = np.zeros((len(cam), 2, 3))
    jp[:, 0, 0], jp[:, 0, 2] = k[0, 0] / z, -k[0, 0] * x / z**2
    jp[:, 1, 1], jp[:, 1, 2] = k[1, 1] / z, -k[1, 1] * y / z**2
    jx = jp @ rot  # [N, 2, 3]
    return sigma_px**2 * np.eye(2) + jx @ cov_x @ jx.transpose(0, 2, 1)


def _whitener(s: np.ndarray) -> np.ndarray:
    """[N, 2, 2] covariances -> [2N, 2N] block-diagonal inverse square roots (as [N, 2, 2])."""
    lam, vec = np.linalg.eigh(s)
    return vec @ (vec.transpose(0, 2, 1) / np.sqrt(lam)[:, :, None])


def refine_with_covariance(
    pts: np.ndarray,
    px: np.ndarray,
    k: np.ndarray,
    r: np.ndarray,
    t: np.ndarray,
    points_in_match: bool,
    sigma_px: float,
    depth_ab: tuple[float, float],
    depth_sigma: np.ndarray | None = None,
):
    """Inlier 3-D points [N, 3] and pixels [N, 2] (ideal), T_match_query (R, t) from PnP,
    the points' own depth std [N] (m, NaN: the model a + b z^2 of `depth_ab`) ->
    (R, t, cov [6, 6], variance factor, whitened chi^2 per residual); None when degenerate."""
    f = float(k[0, 0] + k[1, 1]) / 2
    rays = pts / pts[:, 2:3]
    cov_x = point_covariances(rays, pts[:, 2], sigma_px, f, *depth_ab, depth_sigma)

    def raw(rr, tt):
        cam, _ = _camera_points(pts, rr, tt, points_in_match)
        return project(k, cam) - px  # [N, 2]

    for _ in range(ITERATIONS):
        w = _whitener(residual_covariances(pts, cov_x, k, r, t, points_in_match, sigma_px))

        def white(rr, tt, w=w):
            return np.einsum("nij,nj->ni", w, raw(rr, tt)).ravel()

        jac, res = cv.jacobian(white, r, t), white(r, t)
        info = jac.T @ jac
        if np.linalg.eigvalsh(info)[0] <= np.linalg.eigvalsh(info)[-1] * 1e-12:
            return None
        step = -np.linalg.solve(info, jac.T @ res)
        r_new, t_new = cv.perturbed(r, t, step)
        if np.sum(white(r_new, t_new) ** 2) < np.sum(res**2):
            r, t = r_new, t_new
    w = _whitener(residual_covariances(pts, cov_x, k, r, t, points_in_match, sigma_px))

    def white_final(rr, tt):
        return np.einsum("nij,nj->ni", w, raw(rr, tt)).ravel()

    jac, res = cv.jacobian(white_final, r, t), white_final(r, t)
    dof = len(res) - 6
    if dof <= 0:
        return None
    factor = max(MIN_VARIANCE_FACTOR, float(np.sum(res**2)) / dof)
    cov = np.linalg.inv(jac.T @ jac) * factor
    return r, t, (cov + cov.T) / 2, factor, res
