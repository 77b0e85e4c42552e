"""PoseLib, the estimation core: minimal solvers inside LO-RANSAC, then robust refinement.

Every call takes the keypoints as detected (distorted pixels) and each camera's own model
(`CameraModel.solver_camera`: camera_info's D), so thresholds and residuals are pixels of the
real images. Conventions: `absolute_pose` gives (R, t) with X_cam = R X + t for 3-D points X and
their pixels in that camera (P3P); `relative_pose` gives (R, unit t) with X_b = R X_a + t for
matched pixels of cameras a and b (5-point essential matrix; PoseLib keeps the solution with the
points in front of both cameras). The options were set on the suite's real frames
(docs/relative-pose.md): PoseLib's own defaults, a fixed seed (the same loop gets the same pose
in the node and the replay), and its Cauchy loss at half the inlier threshold (an inlier at the
threshold keeps a fifth of the weight; the covariance uses the same weights, `loss_weights`).
"""

from __future__ import annotations

import numpy as np
import poselib

from pair_vpr_ros.geometry.camera import CameraModel

SEED = 0
MIN_ITERATIONS = 1000  # PoseLib's default; 200 moved TUM's medians by up to 0.24 deg
LOSS = "CAUCHY"
LOSS_SCALE = 0.5  # x threshold (1 px at 2 px: PoseLib's default); 0.25, 1: medians within 0.1 deg


def ransac_options(threshold_px: float, relative: bool, seed: int = SEED) -> dict:
    key = "max_epipolar_error" if relative else "max_reproj_error"
    return {key: float(threshold_px), "seed": seed, "min_iterations": MIN_ITERATIONS}


def bundle_options(threshold_px: float, loss: str = LOSS) -> dict:
    return {"loss_type": loss, "loss_scale": LOSS_SCALE * float(threshold_px)}


def loss_weights(res_px: np.ndarray, threshold_px: float) -> np.ndarray:
    """IRLS weights [N] of the refinement's Cauchy loss at residual norms res_px [N] (px)."""
    return 1.0 / (1.0 + (np.asarray(res_px) / (LOSS_SCALE * threshold_px)) ** 2)


def _pose(p: poselib.CameraPose) -> tuple[np.ndarray, np.ndarray]:
    return np.asarray(p.R, np.float64), np.asarray(p.t, np.float64).ravel()


def absolute_pose(
    points: np.ndarray, pixels: np.ndarray, camera: CameraModel, threshold_px: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """3-D points [N, 3] and their distorted pixels [N, 2] in `camera` -> (R [3, 3], t [3],
    inlier mask [N]) with X_cam = R X + t."""
    pose, info = poselib.estimate_absolute_pose(
        np.ascontiguousarray(pixels, np.float64), np.ascontiguousarray(points, np.float64),
        camera.solver_camera(), ransac_options(threshold_px, False),
        bundle_options(threshold_px),
    )  # fmt: skip
    return (*_pose(pose), np.asarray(info["inliers"], bool))


def relative_pose(
    px_a: np.ndarray,
    px_b: np.ndarray,
    cameras: tuple[CameraModel, CameraModel],
    threshold_px: float,
    seed: int = SEED,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Matched distorted pixels [N, 2] of cameras (a, b) -> (R [3, 3], unit t [3], inlier mask
    [N]) with X_b = R X_a + t (`threshold_px`: Sampson error, pixels; `seed`: RANSAC's)."""
    pose, info = poselib.estimate_relative_pose(
        np.ascontiguousarray(px_a, np.float64), np.ascontiguousarray(px_b, np.float64),
        cameras[0].solver_camera(), cameras[1].solver_camera(),
        ransac_options(threshold_px, True, seed), bundle_options(threshold_px),
    )  # fmt: skip
    r, t = _pose(pose)
    return r, t / max(float(np.linalg.norm(t)), 1e-12), np.asarray(info["inliers"], bool)


def refine_relative(
    px_a: np.ndarray,
    px_b: np.ndarray,
    cameras: tuple[CameraModel, CameraModel],
    pose: tuple[np.ndarray, np.ndarray],
) -> tuple[np.ndarray, np.ndarray]:
    """(R, unit t) of X_b = R X_a + t refined from `pose` on these matches alone (least
    squares on their Sampson errors: they are inliers already)."""
    start = poselib.CameraPose()
    start.R, start.t = pose[0], pose[1]
    out, _ = poselib.refine_relative_pose(
        np.ascontiguousarray(px_a, np.float64), np.ascontiguousarray(px_b, np.float64), start,
        cameras[0].solver_camera(), cameras[1].solver_camera(), {"loss_type": "TRIVIAL"},
    )  # fmt: skip
    r, t = _pose(out)
    return r, t / max(float(np.linalg.norm(t)), 1e-12)


def refine_absolute(
    points: np.ndarray,
    pixels: np.ndarray,
    camera: CameraModel,
    pose: tuple[np.ndarray, np.ndarray],
) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) of X_cam = R X + t refined from `pose` on these inliers alone (least squares)."""
    start = poselib.CameraPose()
    start.R, start.t = pose[0], pose[1]
    out, _ = poselib.refine_absolute_pose(
        np.ascontiguousarray(pixels, np.float64), np.ascontiguousarray(points, np.float64),
        start, camera.solver_camera(), {"loss_type": "TRIVIAL"},
    )  # fmt: skip
    return _pose(out)
