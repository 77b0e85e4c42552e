"""Metric pose of a loop from one keyframe's depth and the other's pixels (PnP), weighted by
the depth-noise model, with the second depth image as a check.

Points beyond `PoseConfig.max_depth_m` are left out; PnP-RANSAC finds the inliers and
`pnp_uncertainty.refine_with_covariance` refines the pose with each point weighted by its own
depth noise. With depth in both keyframes, enough matches must agree in 3-D within
`depth_agreement_sigmas` of their depth noise, misregistration and the pose's own covariance
(`depth_agreement`): a fixed tolerance refuses good far pairs, whose depth noise grows with z^2.
"""

from __future__ import annotations

import math

import numpy as np

from pair_vpr_ros.geometry import covariance as cv
from pair_vpr_ros.geometry.depth_noise import point_covariances
from pair_vpr_ros.geometry.pnp import solve_pnp
from pair_vpr_ros.geometry.pnp_uncertainty import refine_with_covariance

# A chessboard held 12-24 squares from a stereo rig (SGBM depth) has a relief of 1-3 % of its
# size; a desk scene (TUM fr1) 10-40 %.
PLANAR_RELIEF = 0.05
# A pose must agree with the second depth image on 30 % of its inliers that have depth in both
# (wrong matches that fit a wrong pose by chance do not), and on at least 8. On real Kinect
# pairs 35-50 % of the inliers agree where frame and depth are 13-18 ms apart, and ORB
# inliers number 18-22 on pairs 32 deg apart: a fixed count of 15 refused good poses.
AGREEING_FRACTION = 0.3
MIN_AGREEING = 8


def within(limit: float) -> str:
    """ " within N m" for a finite depth limit, else ""."""
    return f" within {limit:g} m" if math.isfinite(limit) else ""


def metric_fit(q, m, pairs: np.ndarray, side: str, z: np.ndarray, c):
    """Features q, m, matches [K, 2], the side whose depth z [K] gives the 3-D points, a
    `PoseConfig` -> (R, t, covariance [6, 6], inliers, inlier 3-D points [N, 3]) of
    T_match_query, or (reason, inliers)."""
    ok = np.isfinite(z) & (z <= c.depth_limit)  # far points: too noisy for PnP
    kp_q, kp_m = q.keypoints[pairs[ok, 0]], m.keypoints[pairs[ok, 1]]
    s_z = _own_sigma(m if side == "match" else q, pairs[ok, 0 if side == "query" else 1])
    if side == "match":  # 3D in the match frame, seen by the query camera
        pts, px, k = m.camera.rays(kp_m) * z[ok, None], q.camera.undistort(kp_q), q.camera.k
    else:
        pts, px, k = q.camera.rays(kp_q) * z[ok, None], m.camera.undistort(kp_m), m.camera.k
    sol = solve_pnp(pts, px, k, c.ransac_px, c.min_inliers)
    if isinstance(sol, str):
        return sol, -1
    r_ba, t_ba, idx = sol
    r, t = (r_ba.T, -r_ba.T @ t_ba) if side == "match" else (r_ba, t_ba)
    depth_ab = (c.depth_sigma_a, c.depth_sigma_b)
    fit = refine_with_covariance(pts[idx], px[idx], k, r, t, side == "match", c.min_sigma_px,
                                 depth_ab, None if s_z is None else s_z[idx])  # fmt: skip
    if fit is None:
        return "degenerate geometry: the inliers do not constrain every axis", len(idx)
    r, t, cov, _, _ = fit
    cov = cov * c.covariance_scale
    agree = depth_agreement(q, m, pairs[ok][idx], r, t, cov, c)
    if agree is not None and agree[0] < agreement_needed(agree[1]):
        return (f"pose disagrees with the other keyframe's depth ({agree[0]} of {agree[1]} "
                f"inliers with depth in both agree, {agreement_needed(agree[1])} needed)",
                len(idx))  # fmt: skip
    s_t, s_r = cv.sigmas(cov)
    if s_t > c.max_translation_sigma_m or s_r > c.max_rotation_sigma_deg:
        return f"pose too uncertain (std {s_t:.2f} m, {s_r:.2f} deg)", len(idx)
    return r, t, cov, len(idx), pts[idx]


def _own_sigma(f, idx: np.ndarray) -> np.ndarray | None:
    """The depth's own std [K] (m, NaN: none) of keypoints `idx` of features f, or None."""
    return None if f.depth_sigma is None else f.depth_sigma[idx]


def agreement_needed(both: int) -> int:
    """Inliers that must agree with the second depth image, of `both` with depth in both."""
    return max(MIN_AGREEING, math.ceil(AGREEING_FRACTION * both))


def depth_agreement(q, m, pairs, r, t, cov, c) -> tuple[int, int] | None:
    """With depth in both keyframes: (of the PnP inlier matches `pairs` [K, 2], those whose two
    3-D points agree under (R, t); those with both depths within max_depth_m); None otherwise.
    A PnP solution found on a few outliers fits the pixels but not the second depth image.

    The gap g = R X_q + t - X_m of a match agrees when g^T S^-1 g < 3 s^2 (s =
    `depth_agreement_sigmas`): S holds both points' depth noise, their lateral noise (a
    keypoint's pixel error plus `depth_registration_px` of depth-to-colour misregistration:
    depth and colour are taken apart in time and space) and the pose's own covariance `cov`
    [6, 6] with its floor carried to the point. A fixed tolerance refused good real pairs."""
    if q.depth is None or m.depth is None:
        return None
    zq, zm = q.depth[pairs[:, 0]], m.depth[pairs[:, 1]]
    ok = np.isfinite(zq) & np.isfinite(zm) & (zq <= c.depth_limit) & (zm <= c.depth_limit)
    rays_q = q.camera.rays(q.keypoints[pairs[ok, 0]])
    rays_m = m.camera.rays(m.keypoints[pairs[ok, 1]])
    xq, xm = rays_q * zq[ok, None], rays_m * zm[ok, None]
    seen = xq @ r.T  # the query's points in the match frame, before t
    gap = seen + t - xm
    ab, px = (c.depth_sigma_a, c.depth_sigma_b), c.min_sigma_px + c.depth_registration_px
    own = [_own_sigma(f, pairs[ok, col]) for f, col in ((q, 0), (m, 1))]
    s = (r @ point_covariances(rays_q, zq[ok], px, q.camera.fx, *ab, own[0]) @ r.T
         + point_covariances(rays_m, zm[ok], px, m.camera.fx, *ab, own[1]))  # fmt: skip
    pose_cov = cv.with_floor(cov, t, c, (q.camera, m.camera))
    jac = np.zeros((len(seen), 3, 6))  # d gap / d (d_t, d_rot): I, -[R X_q]x
    jac[:, :, :3] = np.eye(3)
    x, y, z = seen.T
    jac[:, 0, 4], jac[:, 0, 5], jac[:, 1, 3] = z, -y, -z
    jac[:, 1, 5], jac[:, 2, 3], jac[:, 2, 4] = x, y, -x
    s = s + jac @ pose_cov @ jac.transpose(0, 2, 1)
    d2 = np.einsum("ni,ni->n", gap, np.linalg.solve(s, gap[:, :, None])[:, :, 0])
    return int((d2 < 3 * c.depth_agreement_sigmas**2).sum()), int(ok.sum())


def is_planar(points: np.ndarray, relief: float = PLANAR_RELIEF) -> bool:
    """Whether 3-D points [N, 3] lie on one plane: their spread along the plane's normal is
    under `relief` of their spread along the plane's shorter axis. The essential matrix of a
    plane is ill-posed (a family of solutions fits it), so it cannot check such a pose."""
    if len(points) < 4:
        return True
    lam = np.linalg.eigvalsh(np.cov(points.T))  # ascending
    return bool(lam[0] <= relief**2 * lam[1])
