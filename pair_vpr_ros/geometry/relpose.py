"""Relative pose of a loop closure from the two keyframes' features.

``T_match_query`` = (R, t) is the pose of the query keyframe's camera in the match keyframe's
camera frame (optical: x right, y down, z forward): ``X_match = R X_query + t``, so ``t`` is the
query camera's position seen from the match camera. The frames are those of the two images'
``header.frame_id`` at their stamps. Its covariance is described in ``covariance.py``.

* metric: depth at the keypoints of either keyframe (the match's from the map, else the
  query's) gives 3D points -> PnP-RANSAC -> Levenberg-Marquardt on the inliers;
* scale-free: no usable depth -> essential matrix (USAC) -> R and the direction of t (a unit
  vector) with a 1e6 m^2 translation variance, never a made-up metric length;
* no pose: a reason (no features, no intrinsics, too few matches or inliers, degenerate motion,
  too uncertain).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pair_vpr_ros.errors import ConfigError
from pair_vpr_ros.geometry import covariance as cv
from pair_vpr_ros.geometry.epipolar import essential_pose, parallax_deg, sampson_residuals
from pair_vpr_ros.geometry.features import Features, match_features
from pair_vpr_ros.geometry.pnp import project, reprojection_residuals, solve_pnp
from pair_vpr_ros.geometry.rotations import matrix_quaternion

METRIC, SCALE_FREE = "metric", "scale-free"


@dataclass(frozen=True)
class PoseConfig:
    """Relative-pose settings (pixels are ideal, undistorted pixels)."""

    ratio: float = 0.8  # Lowe's ratio test
    min_matches: int = 12  # mutual ratio-test matches needed to try
    min_inliers: int = 15  # PnP / essential-matrix inliers needed for a pose
    ransac_px: float = 2.0  # PnP inlier threshold
    essential_px: float = 1.0  # essential-matrix inlier threshold
    min_sigma_px: float = 0.5  # floor of the residual std in the covariance
    min_parallax_deg: float = 1.0  # scale-free: median parallax needed for a direction
    max_rotation_sigma_deg: float = 2.0  # reject poses less certain than this ...
    max_translation_sigma_m: float = 0.5  # ... (metric) ...
    max_direction_sigma_deg: float = 10.0  # ... or whose direction is this uncertain
    # Gauss-Newton covariances came out too confident on the demo world's seed-8 loops (median
    # normalised error x1.9 of chi-square's, metric and scale-free alike): they are scaled by this.
    covariance_scale: float = 2.0

    def __post_init__(self) -> None:
        for name in ("ratio", "ransac_px", "essential_px", "max_rotation_sigma_deg",
                     "max_translation_sigma_m", "max_direction_sigma_deg",
                     "covariance_scale"):  # fmt: skip
            if not getattr(self, name) > 0:
                raise ConfigError(f"pose {name}={getattr(self, name)!r} must be > 0")
        if not 0 < self.ratio <= 1:
            raise ConfigError(f"pose ratio={self.ratio!r} must be in (0, 1]")
        if self.min_inliers < 6 or self.min_matches < 5:
            raise ConfigError("pose min_inliers must be >= 6 and min_matches >= 5")


@dataclass
class RelativePose:
    """Result for one loop: status "metric" / "scale-free" with R [3, 3], t [3], covariance
    [6, 6] and inliers, or status "" with the reason."""

    status: str = ""
    reason: str = ""
    inliers: int = -1
    rotation: np.ndarray | None = None
    translation: np.ndarray | None = None
    covariance: np.ndarray | None = None

    def record_fields(self) -> dict:
        """The ``LoopRecord`` pose fields of this result."""
        out = dict(pose_status=self.status, pose_reason=self.reason, pose_inliers=self.inliers)
        if self.status and self.rotation is not None:
            q = matrix_quaternion(self.rotation)
            out.update(zip(("tx", "ty", "tz"), map(float, self.translation), strict=True))
            out.update(zip(("qx", "qy", "qz", "qw"), q, strict=True))
            out["covariance"] = tuple(float(v) for v in self.covariance.ravel())
        return out


def _fail(reason: str, inliers: int = -1) -> RelativePose:
    return RelativePose(reason=reason, inliers=inliers)


def relative_pose(
    query: Features | None, match: Features | None, config: PoseConfig | None = None
) -> RelativePose:
    """T_match_query of a loop from the query and match keyframes' features."""
    c = config or PoseConfig()
    if match is None:
        return _fail("match keyframe has no features (kept only for keyframes added since "
                     "features are stored: maps saved before that have none)")  # fmt: skip
    if query is None:
        return _fail("query keyframe has no features")
    for name, f in (("query", query), ("match", match)):
        if f.camera is None:
            return _fail(f"no intrinsics for the {name} keyframe (no camera_info received and "
                         "no intrinsics parameters set)")  # fmt: skip
    for name, f in (("query", query), ("match", match)):
        if len(f) == 0:
            return _fail(f"the {name} image has no keypoints (featureless, dark or blurred)")
    if query.kind != match.kind:
        return _fail(f"feature kinds differ (query {query.kind}, match {match.kind})")
    pairs = match_features(query, match, c.ratio)
    if len(pairs) < c.min_matches:
        return _fail(f"too few feature matches ({len(pairs)} < {c.min_matches})")
    side, z, why = _depth_side(query, match, pairs, c.min_inliers)
    if side is None:
        pose = _scale_free(query, match, pairs, c)
        if pose.status:
            pose.reason = why
        return pose
    return _metric(query, match, pairs, side, z, c)


def _depth_side(q: Features, m: Features, pairs: np.ndarray, need: int):
    """-> ("match" | "query" | None, depth [K] of the used side, reason when None)."""
    valid = {}
    for name, f, col in (("match", m, 1), ("query", q, 0)):
        z = f.depth[pairs[:, col]] if f.depth is not None else np.full(len(pairs), np.nan)
        valid[name] = (int(np.isfinite(z).sum()), z)
    best = max(valid, key=lambda k: valid[k][0])  # ties: the match (from the map) first
    count, z = valid[best]
    if count >= need:
        return best, z, ""
    if q.depth is None and m.depth is None:
        return None, None, "no depth image (monocular): the translation is a direction only"
    return None, None, (f"no depth at the keypoints ({count} of {len(pairs)} matches have "
                        "depth): the translation is a direction only")  # fmt: skip


def _metric(q, m, pairs, side, z, c: PoseConfig) -> RelativePose:
    ok = np.isfinite(z)
    kp_q, kp_m = q.keypoints[pairs[ok, 0]], m.keypoints[pairs[ok, 1]]
    if side == "match":  # 3D in the match frame, seen by the query camera
        pts, px, k = m.camera.rays(kp_m) * z[ok, None], q.camera.undistort(kp_q), q.camera.k
    else:
        pts, px, k = q.camera.rays(kp_q) * z[ok, None], m.camera.undistort(kp_m), m.camera.k
    sol = solve_pnp(pts, px, k, c.ransac_px, c.min_inliers)
    if isinstance(sol, str):
        return _fail(sol)
    r_ba, t_ba, idx = sol
    r, t = (r_ba.T, -r_ba.T @ t_ba) if side == "match" else (r_ba, t_ba)
    residuals = reprojection_residuals(pts[idx], px[idx], k, points_in_match=side == "match")
    fit = cv.gauss_newton_covariance(cv.jacobian(residuals, r, t), residuals(r, t),
                                     c.min_sigma_px)  # fmt: skip
    if fit is None:
        return _fail("degenerate geometry: the inliers do not constrain every axis", len(idx))
    cov = fit[0] * c.covariance_scale
    agree = _depth_agreement(q, m, pairs, r, t)
    if agree is not None and agree[0] < c.min_inliers:
        return _fail(f"pose disagrees with the other keyframe's depth ({agree[0]} of {agree[1]} "
                     f"points agree, {c.min_inliers} needed)", len(idx))  # fmt: skip
    s_t, s_r = cv.sigmas(cov)
    if s_t > c.max_translation_sigma_m or s_r > c.max_rotation_sigma_deg:
        return _fail(f"pose too uncertain (std {s_t:.2f} m, {s_r:.2f} deg)", len(idx))
    return RelativePose(METRIC, "", len(idx), r, t, cov)


def _depth_agreement(q, m, pairs, r, t) -> tuple[int, int] | None:
    """With depth in both keyframes: (matches whose two 3D points agree under (R, t) within
    5 % of the depth + 5 cm, matches with both depths); None otherwise. A PnP solution found
    on a few outliers fits the pixels but not the second depth image."""
    if q.depth is None or m.depth is None:
        return None
    zq, zm = q.depth[pairs[:, 0]], m.depth[pairs[:, 1]]
    ok = np.isfinite(zq) & np.isfinite(zm)
    xq = q.camera.rays(q.keypoints[pairs[ok, 0]]) * zq[ok, None]
    xm = m.camera.rays(m.keypoints[pairs[ok, 1]]) * zm[ok, None]
    gap = np.linalg.norm(xq @ r.T + t - xm, axis=1)
    return int((gap < 0.05 * zm[ok] + 0.05).sum()), int(ok.sum())


def _scale_free(q, m, pairs, c: PoseConfig) -> RelativePose:
    rays_q = q.camera.rays(q.keypoints[pairs[:, 0]])
    rays_m = m.camera.rays(m.keypoints[pairs[:, 1]])
    k = q.camera.k  # both images as ideal pixels of the query camera
    px_q, px_m = project(k, rays_q), project(k, rays_m)
    sol = essential_pose(px_q, px_m, k, c.essential_px, c.min_inliers)
    if isinstance(sol, str):
        return _fail(sol)
    r, t, idx = sol
    parallax = parallax_deg(rays_q[idx], rays_m[idx], r)
    if parallax < c.min_parallax_deg:
        return _fail(f"degenerate motion: {parallax:.2f} deg parallax is too little for a "
                     "translation direction", len(idx))  # fmt: skip
    residuals = sampson_residuals(px_q[idx], px_m[idx], k)
    basis = np.zeros((6, 5))  # directions of t that change it, then the rotation
    basis[:3, :2] = np.linalg.svd(t[None])[2][1:].T
    basis[3:, 2:] = np.eye(3)
    jac = cv.jacobian(residuals, r, t) @ basis
    fit = cv.gauss_newton_covariance(jac, residuals(r, t), c.min_sigma_px)
    if fit is None:
        return _fail("degenerate geometry: the inliers do not fix the rotation", len(idx))
    cov5 = fit[0] * c.covariance_scale
    s_dir = float(np.degrees(np.sqrt(np.linalg.eigvalsh(cov5[:2, :2])[-1])))
    s_rot = float(np.degrees(np.sqrt(np.linalg.eigvalsh(cov5[2:, 2:])[-1])))
    if s_dir > c.max_direction_sigma_deg or s_rot > c.max_rotation_sigma_deg:
        return _fail(f"pose too uncertain (direction std {s_dir:.1f} deg, rotation std "
                     f"{s_rot:.2f} deg)", len(idx))  # fmt: skip
    cov = cv.embed_rotation(cov5[2:, 2:], cv.SCALE_FREE_VARIANCE)
    return RelativePose(SCALE_FREE, "", len(idx), r, t, cov)
