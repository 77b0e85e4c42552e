"""Metric pose of a loop from one keyframe's depth and the other's pixels (PoseLib's absolute
pose), its covariance from the depth noise and the residuals, the second depth image as a check.

Points beyond `PoseConfig.max_depth_m` are left out; PoseLib's LO-RANSAC (P3P) finds the inliers
and refines the pose through the pixel camera's own model. The covariance weighs each inlier by
its own noise: its reprojection residual r_i has covariance S_i = sigma^2 I + J_X Sigma_X J_X^T
(J_X: the projection's Jacobian with respect to the point, Sigma_X its depth noise from
`depth_noise.point_covariances`), so far points, whose depth is poor, count less; the pixel
noise sigma is the a-posteriori one, the value at which the inliers' whitened chi-square equals
its degrees of freedom, at least `floor_px`. PoseLib weighs the pixels alike (and by its robust
loss), so the covariance is that estimator's: the sandwich H^-1 (sum w^2 J^T S J) H^-1, H =
sum w J^T J (`covariance.sandwich`). With depth in both keyframes, enough matches must agree in
3-D within `depth_agreement_sigmas` of their depth noise, misregistration and the pose's own
covariance (`depth_agreement`): a fixed tolerance refuses good far pairs (depth noise grows
with z^2).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from pair_vpr_ros.geometry import covariance as cv
from pair_vpr_ros.geometry import solvers
from pair_vpr_ros.geometry.checks import with_k1
from pair_vpr_ros.geometry.depth_noise import point_covariances

# A pose must agree with the second depth image on 30 % of its inliers that have depth in both
# (wrong matches that fit a wrong pose by chance do not), and on at least 8. On real Kinect
# pairs 35-50 % of the inliers agree where frame and depth are 13-18 ms apart, and ORB
# inliers number 18-22 on pairs 32 deg apart: a fixed count of 15 refused good poses.
AGREEING_FRACTION = 0.3
MIN_AGREEING = 8
# Residuals smaller than the depth-noise model allows scale it down, at most this far: the
# stereo chessboard's corners show 0.31 of the assumed noise (RMS), the demo's rendered depth
# is exact; the last pose code's variance factor had the same bound.
MIN_DEPTH_SCALE = 0.1


@dataclass
class MetricFit:
    """T_match_query (R, t), its covariance [6, 6] (before the systematic terms), the inlier
    indices into the matches, the fit's pixel sigma (px), and what PoseLib fitted: the 3-D
    points [N, 3], their pixels [N, 2] in `camera`, their own depth std [N] (None: the
    model's), X_cam = R X + t (`pose`) and where the points came from (`origin`)."""

    rotation: np.ndarray
    translation: np.ndarray
    covariance: np.ndarray
    inliers: np.ndarray
    sigma_px: float
    points: np.ndarray
    pixels: np.ndarray
    camera: Any
    depth_sigma: np.ndarray | None
    pose: tuple[np.ndarray, np.ndarray]
    origin: tuple[Any, np.ndarray, np.ndarray]  # the points' camera, keypoints [N, 2], depth [N]
    points_in_match: bool  # the match keyframe's depth gave the points (else the query's)


def within(limit: float) -> str:
    """ " within N m" for a finite depth limit, else ""."""
    return f" within {limit:g} m" if math.isfinite(limit) else ""


def metric_fit(q, m, pairs: np.ndarray, side: str, z: np.ndarray, c) -> MetricFit | tuple:
    """Features q, m, matches [K, 2], the side whose depth z [K] gives the 3-D points, a
    `PoseConfig` -> MetricFit of T_match_query, or (reason, inliers)."""
    ok = np.flatnonzero(np.isfinite(z) & (z <= c.depth_limit))  # far points: too noisy
    if len(ok) < max(c.min_inliers, 6):
        return f"too few matches with depth ({len(ok)} < {max(c.min_inliers, 6)})", -1
    own, seen, col = (m, q, 1) if side == "match" else (q, m, 0)
    pts = own.camera.rays(own.keypoints[pairs[ok, col]]) * z[ok, None]
    px = seen.keypoints[pairs[ok, 1 - col]].astype(np.float64)
    r_ba, t_ba, mask = solvers.absolute_pose(pts, px, seen.camera, c.ransac_px)
    idx = np.flatnonzero(mask)
    if len(idx) < c.min_inliers:
        return f"too few PnP inliers ({len(idx)} < {c.min_inliers})", -1
    r, t = (r_ba.T, -r_ba.T @ t_ba) if side == "match" else (r_ba, t_ba)
    s_z = None if own.depth_sigma is None else own.depth_sigma[pairs[ok[idx], col]]
    fit = _covariance(pts[idx], px[idx], seen.camera, (r_ba, t_ba), s_z, c)
    if fit is None:
        return "degenerate geometry: the inliers do not constrain every axis", len(idx)
    cov_ba, sigma = fit
    cov = cov_ba if side == "query" else _inverse_covariance(r_ba, t_ba, cov_ba)
    cov = cov * c.covariance_scale
    origin = (own.camera, own.keypoints[pairs[ok[idx], col]], z[ok[idx]])
    return MetricFit(r, t, cov, ok[idx], sigma, pts[idx], px[idx], seen.camera, s_z, (r_ba, t_ba),
                     origin, side == "match")  # fmt: skip


def agreement_problem(q, m, pairs: np.ndarray, fit: MetricFit, cov: np.ndarray, c) -> str:
    """Why the pose (the fit with the covariance `cov` [6, 6] its checks reached) disagrees
    with the other keyframe's depth ("" when it agrees or there is none; `depth_agreement`)."""
    agree = depth_agreement(q, m, pairs[fit.inliers], (fit.rotation, fit.translation, cov),
                            fit.sigma_px, c)  # fmt: skip
    if agree is None or agree[0] >= agreement_needed(agree[1]):
        return ""
    return (
        f"pose disagrees with the other keyframe's depth ({agree[0]} of {agree[1]} inliers "
        f"with depth in both agree, {agreement_needed(agree[1])} needed)"
    )


def metric_refit(fit: MetricFit, c):
    """-> refit(selection [N] bool) -> (R of X_cam = R X + t, its rotation covariance [3, 3]
    or None) refined by PoseLib on those inliers alone (`checks.split_variances`)."""

    def refit(sel: np.ndarray):
        pose = solvers.refine_absolute(fit.points[sel], fit.pixels[sel], fit.camera, fit.pose)
        s_z = None if fit.depth_sigma is None else fit.depth_sigma[sel]
        # linearised where the whole fit is: a near-degenerate half refits far off
        cov = _covariance(fit.points[sel], fit.pixels[sel], fit.camera, fit.pose, s_z, c)
        return pose[0], None if cov is None else cov[0][3:, 3:]

    return refit


def metric_lens_refit(fit: MetricFit):
    """-> (refit(k1) -> (R, t, reprojection residuals [2N]) of T_match_query refined by PoseLib
    through both cameras with a radial k1 (the points' own rays bend with it); the inliers'
    distances from the pixel image's centre [N]) for `checks.radial_check`."""
    own, keypoints, z = fit.origin
    seen = fit.camera

    def refit(k1: float):
        o, s = (own, seen) if k1 == 0.0 else (with_k1(own, k1), with_k1(seen, k1))
        pts = o.rays(keypoints) * z[:, None]
        r, t = solvers.refine_absolute(pts, fit.pixels, s, fit.pose)
        res = (s.project(pts @ r.T + t) - fit.pixels).ravel()
        return (r.T, -r.T @ t, res) if fit.points_in_match else (r, t, res)

    return refit, np.linalg.norm(fit.pixels - (seen.cx, seen.cy), axis=1)


def _covariance(pts, px, camera, pose, s_z, c) -> tuple[np.ndarray, float] | None:
    """Covariance [6, 6] of T_cam_points = pose (R, t) in this module's convention, from the
    inliers' 3-D points [N, 3], their pixels [N, 2] in `camera` and own depth std [N] (or
    None: the model's), and the a-posteriori pixel sigma (module docstring)."""
    r, t = pose
    cam = pts @ r.T + t
    xy = cam[:, :2] / cam[:, 2:]
    proj, jd = camera.solver_camera().project_with_jac(np.ascontiguousarray(xy))
    jn = np.zeros((len(cam), 2, 3))  # d normalised / d camera point
    jn[:, 0, 0] = jn[:, 1, 1] = 1.0 / cam[:, 2]
    jn[:, :, 2] = -xy / cam[:, 2:]
    jx = np.asarray(jd) @ jn @ r  # d pixel / d point
    f = (camera.fx + camera.fy) / 2
    rays = pts / pts[:, 2:3]
    cov_x = point_covariances(rays, pts[:, 2], 0.0, f, c.depth_sigma_a, c.depth_sigma_b, s_z)
    noise = jx @ cov_x @ jx.transpose(0, 2, 1)  # [N, 2, 2]: the points' share
    res = np.asarray(proj) - px
    dof = 2 * len(res) - 6
    if dof <= 0:
        return None

    def chi2(s: float, g: float = 1.0) -> float:
        whiten = np.linalg.inv(g * noise + s * s * np.eye(2))
        return float(np.einsum("ni,nij,nj->", res, whiten, res))

    sigma, g, factor = _posterior_noise(chi2, dof, c.floor_px, c.ransac_px)

    def raw(rr, tt):
        p = pts @ rr.T + tt
        return (camera.project(p) - px).ravel()

    jac = cv.jacobian(raw, r, t).reshape(len(res), 2, 6)
    w = solvers.loss_weights(np.linalg.norm(res, axis=1), c.ransac_px)
    s_i = (g * noise + sigma**2 * np.eye(2)) * factor  # each residual's covariance
    cov = cv.sandwich(
        np.einsum("n,nki,nkj->ij", w, jac, jac),
        np.einsum("n,nki,nkl,nlj->ij", w**2, jac, s_i, jac),
    )
    return None if cov is None else (cov, sigma)


def _posterior_noise(chi2, dof: int, floor: float, ceiling: float) -> tuple[float, float, float]:
    """(pixel sigma, depth-noise scale g, variance factor) at which the inliers' whitened
    chi2(sigma, g) equals its degrees of freedom: the pixel sigma in [floor, ceiling] (g = 1);
    residuals smaller than even the floor and the depth model allow shrink the depth noise
    instead (g down to `MIN_DEPTH_SCALE`: a rendered or well-matched depth is better than the
    Kinect model); ones larger than the ceiling allows scale everything (factor > 1)."""
    if chi2(floor) <= dof:
        if chi2(floor, MIN_DEPTH_SCALE) >= dof:
            return floor, _bisect(lambda g: chi2(floor, g), dof, MIN_DEPTH_SCALE, 1.0), 1.0
        return floor, MIN_DEPTH_SCALE, 1.0
    if chi2(ceiling) >= dof:
        return ceiling, 1.0, chi2(ceiling) / dof
    return _bisect(chi2, dof, floor, ceiling), 1.0, 1.0


def _bisect(fun, target: float, lo: float, hi: float) -> float:
    """x in [lo, hi] (log-spaced bisection) where the falling fun(x) crosses target."""
    a, b = math.log(lo), math.log(hi)
    for _ in range(30):
        mid = (a + b) / 2
        a, b = (mid, b) if fun(math.exp(mid)) > target else (a, mid)
    return math.exp(b)


def _inverse_covariance(r: np.ndarray, t: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """Covariance of (R, t)^-1 = (R^T, -R^T t) in this module's convention, from cov [6, 6] of
    (R, t): d_rot' = -R^T d_rot, d_t' = -R^T d_t - [R^T t]x R^T d_rot (to first order)."""
    a = np.zeros((6, 6))
    a[:3, :3] = a[3:, 3:] = -r.T
    x, y, z = r.T @ t
    a[:3, 3:] = -np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]]) @ r.T
    return a @ cov @ a.T


def agreement_needed(both: int) -> int:
    """Inliers that must agree with the second depth image, of `both` with depth in both."""
    return max(MIN_AGREEING, math.ceil(AGREEING_FRACTION * both))


def depth_agreement(q, m, pairs, pose, sigma_px: float, c) -> tuple[int, int] | None:
    """With depth in both keyframes: (of the PnP inlier matches `pairs` [K, 2], those whose two
    3-D points agree under pose (R, t, cov [6, 6]); those with both depths within
    max_depth_m); None otherwise. A PnP solution found on a few outliers fits the pixels but
    not the second depth image.

    The gap g = R X_q + t - X_m of a match agrees when g^T S^-1 g < 3 s^2 (s =
    `depth_agreement_sigmas`): S holds both points' depth noise, their lateral noise (the
    fit's pixel sigma plus `depth_registration_px` of depth-to-colour misregistration: depth
    and colour are taken apart in time and space) and the pose's own covariance with its
    systematic terms carried to the point. A fixed tolerance refused good real pairs."""
    if q.depth is None or m.depth is None:
        return None
    r, t, cov = pose
    zq, zm = q.depth[pairs[:, 0]], m.depth[pairs[:, 1]]
    ok = np.isfinite(zq) & np.isfinite(zm) & (zq <= c.depth_limit) & (zm <= c.depth_limit)
    rays_q = q.camera.rays(q.keypoints[pairs[ok, 0]])
    rays_m = m.camera.rays(m.keypoints[pairs[ok, 1]])
    xq, xm = rays_q * zq[ok, None], rays_m * zm[ok, None]
    seen = xq @ r.T  # the query's points in the match frame, before t
    gap = seen + t - xm
    ab, px = (c.depth_sigma_a, c.depth_sigma_b), sigma_px + c.depth_registration_px
    own = [None if f.depth_sigma is None else f.depth_sigma[pairs[ok, col]]
           for f, col in ((q, 0), (m, 1))]  # fmt: skip
    s = (r @ point_covariances(rays_q, zq[ok], px, q.camera.fx, *ab, own[0]) @ r.T
         + point_covariances(rays_m, zm[ok], px, m.camera.fx, *ab, own[1]))  # fmt: skip
    pose_cov = cv.with_systematic(cov, t, c, (q.camera, m.camera))
    jac = np.zeros((len(seen), 3, 6))  # d gap / d (d_t, d_rot): I, -[R X_q]x
    jac[:, :, :3] = np.eye(3)
    x, y, z = seen.T
    jac[:, 0, 4], jac[:, 0, 5], jac[:, 1, 3] = z, -y, -z
    jac[:, 1, 5], jac[:, 2, 3], jac[:, 2, 4] = x, y, -x
    s = s + jac @ pose_cov @ jac.transpose(0, 2, 1)
    d2 = np.einsum("ni,ni->n", gap, np.linalg.solve(s, gap[:, :, None])[:, :, 0])
    return int((d2 < 3 * c.depth_agreement_sigmas**2).sum()), int(ok.sum())
