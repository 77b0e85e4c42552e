"""Metric pose from 3D points of one keyframe (its depth) and their pixels in the other: PnP."""

from __future__ import annotations

import cv2
import numpy as np

from pair_vpr_ros.geometry.rotations import exp_so3

RANSAC_ITERATIONS = 300
RANSAC_CONFIDENCE = 0.999


def project(k: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Camera-frame points [N, 3] -> pixels [N, 2] of the pinhole camera `k` [3, 3]."""
    z = points[:, 2:3]
    return (points[:, :2] / z) * (k[0, 0], k[1, 1]) + (k[0, 2], k[1, 2])


def solve_pnp(
    points: np.ndarray, pixels: np.ndarray, k: np.ndarray, ransac_px: float, min_inliers: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | str:
    """3D points [N, 3] in frame A and their ideal pixels [N, 2] in camera B -> (R_BA [3, 3],
    t_BA [3], inlier indices), with X_B = R_BA X_A + t_BA; or the reason it failed.

    EPnP inside RANSAC, then Levenberg-Marquardt on the inliers, inliers re-selected under the
    refined pose and refined once more."""
    if len(points) < max(min_inliers, 6):
        return f"too few matches with depth ({len(points)} < {max(min_inliers, 6)})"
    pts = np.ascontiguousarray(points, np.float64)
    px = np.ascontiguousarray(pixels, np.float64)
    ok, rvec, tvec, inl = cv2.solvePnPRansac(
        pts, px, k, None,
        iterationsCount=RANSAC_ITERATIONS, reprojectionError=ransac_px,
        confidence=RANSAC_CONFIDENCE, flags=cv2.SOLVEPNP_EPNP,
    )  # fmt: skip
    if not ok or inl is None or len(inl) < min_inliers:
        found = 0 if inl is None else len(inl)
        return f"too few PnP inliers ({found} < {min_inliers})"
    idx = inl[:, 0]
    for _ in range(2):
        rvec, tvec = cv2.solvePnPRefineLM(pts[idx], px[idx], k, None, rvec, tvec)
        r, t = exp_so3(rvec.ravel()), tvec.ravel()
        cam = pts @ r.T + t
        err = np.full(len(pts), np.inf)
        front = cam[:, 2] > 1e-6
        err[front] = np.linalg.norm(project(k, cam[front]) - px[front], axis=1)
        idx = np.flatnonzero(err < ransac_px)
        if len(idx) < min_inliers:
            return f"too few PnP inliers after refinement ({len(idx)} < {min_inliers})"
    return r, t, idx


def reprojection_residuals(
    points: np.ndarray, pixels: np.ndarray, k: np.ndarray, points_in_match: bool
):
    """Residual function of T_match_query = (R, t) for `covariance.jacobian`: reprojection
    errors [2N] of the points (in the match frame if `points_in_match`, else the query frame)
    into the other camera."""

    def residuals(r: np.ndarray, t: np.ndarray) -> np.ndarray:
        cam = (points - t) @ r if points_in_match else points @ r.T + t
        return (project(k, cam) - pixels).ravel()

    return residuals
