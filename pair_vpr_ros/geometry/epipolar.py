"""Two-view geometry without depth: fundamental-matrix verification, the essential-matrix pose
(PoseLib) with its covariance, and the rolling-shutter check of a monocular pose.

`verify_pair` is the detector's optional geometric verification (inliers of a fundamental-matrix
RANSAC on the same matches the pose uses). `essential_fit` gives the rotation and the
translation direction of T_match_query with the covariance of (direction, rotation) from the
inliers' Sampson residuals; `essential_refit` and `redraw_variance` serve the checks of
`checks.py`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from pair_vpr_ros.geometry import covariance as cv
from pair_vpr_ros.geometry import solvers
from pair_vpr_ros.geometry.camera import project
from pair_vpr_ros.geometry.checks import half_angle, is_planar, with_k1
from pair_vpr_ros.geometry.features import Features, match_features

REDRAWS = 2  # other RANSAC draws that check a monocular pose


def verify_pair(
    a: Features, b: Features, ratio: float = 0.8, ransac_px: float = 3.0
) -> tuple[int, float]:
    """-> (fundamental-matrix RANSAC inliers, inliers / matches); (0, 0.0) with fewer than 8
    matches."""
    if a.kind != b.kind:
        return 0, 0.0
    pairs = match_features(a, b, ratio)
    if len(pairs) < 8:
        return 0, 0.0
    pa, pb = a.keypoints[pairs[:, 0]], b.keypoints[pairs[:, 1]]
    if not (np.isfinite(pa).all() and np.isfinite(pb).all()):
        return 0, 0.0  # damaged keypoints verify nothing
    f, mask = cv2.findFundamentalMat(pa, pb, cv2.FM_RANSAC, ransac_px, 0.999)
    # no F fitted: OpenCV may hand back a mask of an earlier call, which counts nothing here
    if f is None or f.shape != (3, 3) or mask is None or len(mask) != len(pairs):
        return 0, 0.0
    inliers = int(np.count_nonzero(mask))
    return inliers, inliers / len(pairs)


def skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


@dataclass
class EssentialFit:
    """R and unit t of X_match = R X_query + t, the inlier indices into the matches, the
    covariance [5, 5] of (direction [2], rotation [3]), the inliers' distorted keypoints
    (query, match) [N, 2] and their median parallax (deg)."""

    rotation: np.ndarray
    translation: np.ndarray
    inliers: np.ndarray
    covariance: np.ndarray
    keypoints: tuple[np.ndarray, np.ndarray]
    parallax_deg: float


def essential_fit(q: Features, m: Features, pairs: np.ndarray, c) -> EssentialFit | tuple:
    """PoseLib's relative pose of matches [K, 2] (query, match keypoint indices) with the
    `PoseConfig` thresholds -> EssentialFit, or (reason, inliers)."""
    if len(pairs) < max(c.min_inliers, 5):
        return f"too few feature matches ({len(pairs)} < {max(c.min_inliers, 5)})", -1
    kq, km = (f.keypoints[pairs[:, col]].astype(np.float64) for f, col in ((q, 0), (m, 1)))
    cams = (q.camera, m.camera)
    moved = float(np.median(np.linalg.norm(q.camera.undistort(kq) - m.camera.undistort(km),
                                           axis=1)))  # fmt: skip
    if moved < 0.5:
        return (f"degenerate motion: matched points moved {moved:.2f} px (the same view): no "
                "translation direction", -1)  # fmt: skip
    r, t, mask = solvers.relative_pose(kq, km, cams, c.essential_px)
    idx = np.flatnonzero(mask)
    if len(idx) < c.min_inliers:
        return f"too few essential-matrix inliers ({len(idx)} < {c.min_inliers})", len(idx)
    kq, km = kq[idx], km[idx]
    fit = sampson_covariance(kq, km, cams, (r, t), c.floor_px, c.essential_px)
    if fit is None:
        return "degenerate geometry: the inliers do not fix the rotation", len(idx)
    parallax = parallax_deg(q.camera.rays(kq), m.camera.rays(km), r)
    return EssentialFit(r, t, idx, fit[0] * c.covariance_scale, (kq, km), parallax)


def sampson_covariance(kq, km, cams, pose, floor_px: float, threshold_px: float | None):
    """Distorted keypoints [N, 2] of the query and match cameras `cams`, (R, unit t) ->
    (covariance [5, 5] of (direction, rotation), sigma px) from their Sampson residuals (in
    ideal pixels of the query camera; loss weights when `threshold_px`); None if degenerate."""
    k = cams[0].k
    px_q, px_m = project(k, cams[0].rays(kq)), project(k, cams[1].rays(km))
    residuals = sampson_residuals(px_q, px_m, k)
    basis = np.zeros((6, 5))  # directions of t that change it, then the rotation
    basis[:3, :2], basis[3:, 2:] = direction_basis(pose[1]), np.eye(3)
    res = residuals(*pose)
    w = np.ones(len(res)) if threshold_px is None else solvers.loss_weights(res, threshold_px)
    return cv.posterior_covariance(cv.jacobian(residuals, *pose) @ basis, res, w, floor_px)


def sampson_residuals(px_q: np.ndarray, px_m: np.ndarray, k: np.ndarray):
    """Residual function of (R, t) for `covariance.jacobian`: signed Sampson distances [N] (px)
    of the matches under E = [t/|t|]x R (only the direction of t matters)."""
    kinv = np.linalg.inv(k)
    xq = np.c_[px_q, np.ones(len(px_q))]
    xm = np.c_[px_m, np.ones(len(px_m))]

    def residuals(r: np.ndarray, t: np.ndarray) -> np.ndarray:
        f = kinv.T @ skew(t / np.linalg.norm(t)) @ r @ kinv
        fq = xq @ f.T  # epipolar lines in the match image
        fm = xm @ f  # ... in the query image
        num = np.einsum("ni,ni->n", xm, fq)
        return num / np.sqrt(fq[:, 0] ** 2 + fq[:, 1] ** 2 + fm[:, 0] ** 2 + fm[:, 1] ** 2)

    return residuals


def parallax_deg(rays_q: np.ndarray, rays_m: np.ndarray, r: np.ndarray) -> float:
    """Median angle (deg) between matched rays once the rotation is removed: near 0 for a pure
    rotation, where the translation direction is undefined."""
    a = rays_q @ r.T
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    b = rays_m / np.linalg.norm(rays_m, axis=1, keepdims=True)
    cos = np.clip(np.einsum("ni,ni->n", a, b), -1.0, 1.0)
    return math.degrees(float(np.median(np.arccos(cos))))


def direction_basis(t: np.ndarray) -> np.ndarray:
    """[3, 2]: the two unit directions orthogonal to t (how its direction can change)."""
    return np.linalg.svd(t[None])[2][1:].T


def triangulate(b: np.ndarray, a: np.ndarray, t: np.ndarray, min_parallax_deg: float):
    """Rays b [N, 3] (camera B's frame) and a [N, 3] (camera A's, rotated into B's frame),
    camera A at t (unit) in B's frame: depth along b [N] (unit baseline) and validity [N]."""
    bb, aa, ab = (b * b).sum(1), (a * a).sum(1), (a * b).sum(1)
    tb, ta = b @ t, a @ t
    det = bb * aa - ab**2  # least squares of lam_b b = lam_a a + t
    with np.errstate(divide="ignore", invalid="ignore"):
        lam_b = (tb * aa - ta * ab) / det
        lam_a = (tb * ab - ta * bb) / det
        cos = ab / np.sqrt(aa * bb)
    parallax = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    ok = (lam_b > 0) & (lam_a > 0) & (parallax >= min_parallax_deg) & np.isfinite(lam_b)
    return lam_b, ok


def essential_refit(fit: EssentialFit, cams: tuple, floor_px: float):
    """-> refit(selection [N] bool) -> (R, rotation covariance [3, 3] or None) of the pose
    refined by PoseLib on those inliers alone, or None when they lie on a plane (an essential
    matrix of a plane has a second solution; `checks.split_variances`)."""
    kq, km = fit.keypoints
    rays = cams[1].rays(km)
    depth, ok = triangulate(rays, cams[0].rays(kq) @ fit.rotation.T, fit.translation, 0.0)

    def refit(sel: np.ndarray):
        if is_planar(rays[sel & ok] * depth[sel & ok, None]):
            return None
        pose = solvers.refine_relative(kq[sel], km[sel], cams, (fit.rotation, fit.translation))
        full = (fit.rotation, fit.translation)  # linearised where the whole fit is
        cov = sampson_covariance(kq[sel], km[sel], cams, full, floor_px, None)
        return pose[0], None if cov is None else cov[0][2:, 2:]

    return refit


def essential_lens_refit(fit: EssentialFit, cams: tuple):
    """-> (refit(k1) -> (R, unit t, Sampson residuals [N] in ideal pixels of the query camera)
    of the pose refined by PoseLib through both cameras with a radial k1; the inliers'
    distances from the query image's centre [N]) for `checks.radial_check`."""
    kq, km = fit.keypoints
    k = cams[0].k

    def refit(k1: float):
        bent = cams if k1 == 0.0 else tuple(with_k1(c, k1) for c in cams)
        r, t = solvers.refine_relative(kq, km, bent, (fit.rotation, fit.translation))
        px_q, px_m = project(k, bent[0].rays(kq)), project(k, bent[1].rays(km))
        return r, t, sampson_residuals(px_q, px_m, k)(r, t)

    return refit, np.linalg.norm(kq - k[:2, 2], axis=1)


def redraw_variance(fit: EssentialFit, q, m, pairs: np.ndarray, c) -> tuple[float, float]:
    """(variance, rad^2 per axis; angle, deg) of a pose that other RANSAC draws (`REDRAWS`
    other seeds at twice the threshold) move beyond the fit's covariance: few inliers among
    many wrong matches, or a near-planar or near-degenerate scene, leave several solutions of
    the same support (TUM fr1 ORB: one pair's draws reach 1.5-9.9 deg); half the angle to the
    farthest goes on each axis (`checks.half_angle`)."""
    kq, km = (f.keypoints[pairs[:, col]].astype(np.float64) for f, col in ((q, 0), (m, 1)))
    out = (0.0, 0.0)
    for seed in range(1, REDRAWS + 1):
        r, _, mask = solvers.relative_pose(kq, km, (q.camera, m.camera), 2 * c.essential_px,
                                           seed)  # fmt: skip
        if mask.sum() >= c.min_inliers:
            out = max(out, half_angle(fit.rotation, r, 2 * fit.covariance[2:, 2:]))
    return out
