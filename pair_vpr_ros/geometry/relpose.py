"""Relative pose of a loop closure from the two keyframes' features.

``T_match_query`` = (R, t) is the pose of the query keyframe's camera in the match keyframe's
camera frame (optical: x right, y down, z forward): ``X_match = R X_query + t``, so ``t`` is the
query camera's position seen from the match camera. The frames are those of the two images'
``header.frame_id`` at their stamps. Its covariance is described in ``covariance.py``.

The estimation is PoseLib's (`solvers.py`); what is ours: which model, the checks, the frames
and the covariance (`covariance.py`).

* metric: depth at the keypoints of either keyframe (the match's, else the query's) -> absolute
  pose (P3P, LO-RANSAC), checked against the other depth image (`metric_pose.py`);
* metric from odometry: no usable depth, but a map keyframe next to the match keyframe with an
  odometry pose -> essential matrix (5-point) -> R and the direction of t; its length from points
  triangulated over that short odometry baseline (``odometry_scale.py``), never from the
  odometry between the loop's two keyframes, which holds the drift the loop is to remove;
* scale-free: none of that -> R and the direction of t (a unit vector) with a 1e6 m^2
  translation variance, never a made-up metric length; no pose: a reason.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from pair_vpr_ros.errors import ConfigError
from pair_vpr_ros.geometry import covariance as cv
from pair_vpr_ros.geometry.checks import (
    CHI2_3DOF_95,
    is_planar,
    radial_check,
    split_keys,
    split_variances,
)
from pair_vpr_ros.geometry.epipolar import (
    EssentialFit,
    essential_fit,
    essential_lens_refit,
    essential_refit,
    redraw_variance,
)
from pair_vpr_ros.geometry.features import Features, match_features
from pair_vpr_ros.geometry.metric_pose import (
    MetricFit,
    agreement_problem,
    metric_fit,
    metric_lens_refit,
    metric_refit,
    within,
)
from pair_vpr_ros.geometry.odometry_scale import Neighbour, scaled_pose
from pair_vpr_ros.geometry.rotations import log_so3, matrix_quaternion

METRIC, METRIC_ODOMETRY, SCALE_FREE = "metric", "metric-odometry", "scale-free"


@dataclass(frozen=True)
class PoseConfig:
    """Relative-pose settings (thresholds in pixels of the images, through their cameras)."""

    ratio: float = 0.8  # Lowe's ratio test
    min_matches: int = 12  # mutual ratio-test matches needed to try
    min_inliers: int = 15  # PnP / essential-matrix inliers needed for a pose
    ransac_px: float = 2.0  # PnP inlier threshold
    essential_px: float = 1.0  # essential-matrix inlier threshold (Sampson error)
    min_parallax_deg: float = 1.0  # scale-free: median parallax needed for a direction
    max_rotation_sigma_deg: float = 2.0  # reject poses less certain than this ...
    max_translation_sigma_m: float = 0.5  # ... (metric) ...
    max_direction_sigma_deg: float = 10.0  # ... a direction this uncertain gets no length
    # Gauss-Newton covariances came out too confident on the demo world's seed-8 loops (median
    # normalised error x1.9 of chi-square's, metric and scale-free alike): they are scaled by this.
    covariance_scale: float = 2.0
    odometry_scale: bool = True  # monocular scale from the odometry next to the match keyframe
    scale_neighbours: int = 2  # map keyframes up to this many ids before / after the match
    scale_tries: int = 2  # of those, how many to use (least turn, then longest, first)
    scale_max_gap_s: float = 10.0  # stamps of the match and the neighbour at most this apart
    scale_min_baseline_m: float = 0.2  # odometry distance between them at least this
    scale_max_turn_deg: float = 10.0  # odometry turn between them at most this (lever arm)
    scale_max_turn_mismatch_deg: float = 1.0  # visual and odometry turn agree within this
    scale_min_parallax_deg: float = 1.0  # triangulated points need this much parallax
    scale_min_points: int = 8  # loop inliers with a triangulated point needed
    scale_sigma_floor: float = 0.03  # relative std of the scale at least (odometry error)
    scale_lever_m: float = 1.0  # assumed camera offset from the odometry's turn axis, at most
    # Depth noise sigma_z = a + b z^2 (depth_noise.py, Kinect-class), no depth beyond max_depth_m
    # (0: no limit) in PnP, depth agreement within this many sigmas (metric_pose.py).
    depth_sigma_a: float = 0.0012
    depth_sigma_b: float = 0.0019
    max_depth_m: float = 0.0
    depth_agreement_sigmas: float = 3.0
    depth_registration_px: float = 3.0  # depth-to-colour misregistration allowed in agreement
    # The pixel noise of the covariance is the inliers' own (a posteriori), at least floor_px.
    # Errors no residual shows: systematic_px pixels' angle at the focal length on each
    # rotation axis (a rolling shutter, a late stamp: docs/real-cameras.md), at least
    # floor_rotation_deg; translation a + b |t|.
    floor_px: float = 0.25
    systematic_px: float = 0.0
    floor_rotation_deg: float = 0.0
    floor_translation_m: float = 0.005
    floor_translation_rel: float = 0.01
    lens_check: bool = True  # look for lens distortion nobody declared (checks.radial_check)

    def __post_init__(self) -> None:
        for name in ("ratio", "ransac_px", "essential_px", "max_rotation_sigma_deg",
                     "max_translation_sigma_m", "max_direction_sigma_deg",
                     "covariance_scale", "scale_max_gap_s", "scale_min_baseline_m",
                     "scale_max_turn_deg", "scale_max_turn_mismatch_deg",
                     "scale_min_parallax_deg", "scale_sigma_floor", "scale_lever_m",
                     "depth_sigma_b", "depth_agreement_sigmas"):  # fmt: skip
            if not getattr(self, name) > 0:
                raise ConfigError(f"pose {name}={getattr(self, name)!r} must be > 0")
        for name in ("scale_neighbours", "scale_tries", "scale_min_points"):
            if not getattr(self, name) >= 1:
                raise ConfigError(f"pose {name}={getattr(self, name)!r} must be >= 1")
        floors = [n for n in vars(self) if n.startswith("floor_")]
        for name in ("depth_sigma_a", "max_depth_m", *floors, "systematic_px",
                     "depth_registration_px", "min_parallax_deg"):  # fmt: skip
            if not getattr(self, name) >= 0:
                raise ConfigError(f"pose {name}={getattr(self, name)!r} must be >= 0")
        if not 0 < self.ratio <= 1:
            raise ConfigError(f"pose ratio={self.ratio!r} must be in (0, 1]")
        if self.min_inliers < 6 or self.min_matches < 5:
            raise ConfigError("pose min_inliers must be >= 6 and min_matches >= 5")

    @property
    def depth_limit(self) -> float:
        """Largest depth used for PnP, m (inf: no limit)."""
        return self.max_depth_m if self.max_depth_m > 0 else math.inf


@dataclass
class RelativePose:
    """Result for one loop: status "metric" / "metric-odometry" / "scale-free" with R [3, 3],
    t [3], covariance [6, 6], the inlier count and the inlier matches [N, 2] (query, match
    keypoint indices), or status "" with the reason (a scale-free pose: why it has no scale).
    `lens_k1`: the radial distortion that fits far better than the cameras' own model (checks.py;
    0: none found)."""

    status: str = ""
    reason: str = ""
    inliers: int = -1
    rotation: np.ndarray | None = None
    translation: np.ndarray | None = None
    covariance: np.ndarray | None = None
    inlier_pairs: np.ndarray | None = None
    lens_k1: float = 0.0

    def matrix(self) -> np.ndarray:
        """[4, 4] homogeneous T_match_query (needs a pose)."""
        out = np.eye(4)
        out[:3, :3], out[:3, 3] = self.rotation, self.translation
        return out

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


def _why(*parts: str) -> str:
    return "; ".join(p for p in parts if p)


def relative_pose(
    query: Features | None,
    match: Features | None,
    config: PoseConfig | None = None,
    neighbours: Sequence[Neighbour] = (),
) -> RelativePose:
    """T_match_query of a loop from the query and match keyframes' features; `neighbours`:
    map keyframes next to the match with an odometry baseline (``pick_neighbours``), for the
    scale of a pose without depth. Every covariance carries the systematic terms of
    `PoseConfig` (`covariance.with_systematic`)."""
    c = config or PoseConfig()
    out = _relative_pose(query, match, c, neighbours)
    if out.status:
        cameras, scaled = (query.camera, match.camera), out.status != SCALE_FREE
        out.covariance = cv.with_systematic(out.covariance, out.translation, c, cameras, scaled)
    return out


def _relative_pose(query, match, c: PoseConfig, neighbours) -> RelativePose:
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
    side, z, why = _depth_side(query, match, pairs, c.min_inliers, c.depth_limit)
    if side is None:
        return _monocular(query, match, pairs, c, neighbours, why)
    return _metric(query, match, pairs, side, z, c)


def _depth_side(q: Features, m: Features, pairs: np.ndarray, need: int, max_depth: float):
    """-> ("match" | "query" | None, depth [K] of the used side, reason when None): the match's
    depth (from the map) when enough matches have it, else the query's."""
    counts = []
    for name, f, col in (("match", m, 1), ("query", q, 0)):
        z = f.depth[pairs[:, col]] if f.depth is not None else np.full(len(pairs), np.nan)
        count = int((np.isfinite(z) & (z <= max_depth)).sum())
        if count >= need:
            return name, z, ""
        counts.append(count)
    if q.depth is None and m.depth is None:
        return None, None, "no depth image (monocular): the translation is a direction only"
    return None, None, (f"no depth at the keypoints ({max(counts)} of {len(pairs)} matches "
                        f"have depth{within(max_depth)}): the translation is a direction "
                        "only")  # fmt: skip


def _metric(q, m, pairs, side, z, c: PoseConfig) -> RelativePose:
    fit = metric_fit(q, m, pairs, side, z, c)
    if not isinstance(fit, MetricFit):
        return _fail(*fit)
    r, t, cov, n = fit.rotation, fit.translation, fit.covariance, len(fit.inliers)
    s_t, s_r = cv.sigmas(cov)
    if s_t > c.max_translation_sigma_m or s_r > c.max_rotation_sigma_deg:
        return _fail(f"pose too uncertain (std {s_t:.2f} m, {s_r:.2f} deg)", n)
    out = RelativePose(METRIC, "", n, r, t, cov.copy(), pairs[fit.inliers])
    lens = radial_check((q.camera, m.camera), *metric_lens_refit(fit)) if c.lens_check else None
    if lens is not None:
        out.covariance, out.reason, out.lens_k1 = lens.widen(cov, True), lens.reason(), lens.k1
    centres = tuple((f.camera.cx, f.camera.cy) for f in (q, m))
    px = q.keypoints[pairs[fit.inliers, 0]], m.keypoints[pairs[fit.inliers, 1]]
    var, words = split_variances(split_keys(*px, centres), metric_refit(fit, c), cov[3:, 3:])
    out.covariance[3:, 3:] += np.eye(3) * var
    out.reason = _why(out.reason, words)
    chi2, angle = (0.0, 0.0) if is_planar(fit.points) else _model_disagreement(q, m, pairs, out, c)
    if chi2 > CHI2_3DOF_95:  # (the essential matrix of a plane cannot check a pose)
        # A weaker factor, not a refusal: refusing cost demo-world loops, and a covariance that
        # admits the error cannot bend the graph.
        out.covariance[3:, 3:] += np.eye(3) * math.radians(angle / 2) ** 2
        why = (f"PnP and essential-matrix rotations disagree by {angle:.2f} deg (chi-square "
               f"{chi2:.0f}): intrinsics, distortion or timing wrong? check camera_info or the "
               "camera_* parameters")  # fmt: skip
        out.reason = _why(out.reason, why)
    problem = agreement_problem(q, m, pairs, fit, out.covariance, c)
    return _fail(problem, n) if problem else out


def _model_disagreement(q, m, pairs, pose: RelativePose, c: PoseConfig) -> tuple[float, float]:
    """(chi-square, 3 dof, angle in deg) of the difference between the PnP rotation (depth +
    pixels) and the essential matrix's (pixels only) under both covariances ((0, 0): no E).
    A wrong camera model bends the two differently: the sign of a confident wrong pose."""
    e = essential_fit(q, m, pairs, c)
    if not isinstance(e, EssentialFit):
        return 0.0, 0.0
    d = log_so3(e.rotation @ pose.rotation.T)
    floor = 2 * np.eye(3) * math.radians(cv.systematic_rotation_deg(c, q.camera, m.camera)) ** 2
    both = pose.covariance[3:, 3:] + e.covariance[2:, 2:] + floor
    return float(d @ np.linalg.solve(both, d)), math.degrees(float(np.linalg.norm(d)))


def _monocular(q, m, pairs, c: PoseConfig, neighbours, why: str) -> RelativePose:
    """Essential-matrix pose; metric when the odometry next to the match gives the length."""
    fit = essential_fit(q, m, pairs, c)
    if not isinstance(fit, EssentialFit):
        return _fail(*fit)
    r, t, cov5 = fit.rotation, fit.translation, fit.covariance
    s_rot = float(np.degrees(np.sqrt(np.linalg.eigvalsh(cov5[2:, 2:])[-1])))
    if s_rot > c.max_rotation_sigma_deg:
        return _fail(f"pose too uncertain (rotation std {s_rot:.2f} deg)", len(fit.inliers))
    cams = (q.camera, m.camera)
    lens = radial_check(cams, *essential_lens_refit(fit, cams)) if c.lens_check else None
    k1, checks = 0.0, []
    if lens is not None:
        cov5, k1 = lens.widen(cov5, False), lens.k1
        checks.append(lens.reason())
    keys = split_keys(*fit.keypoints, tuple((cam.cx, cam.cy) for cam in cams))
    var, words = split_variances(keys, essential_refit(fit, cams, c.floor_px),
                                 fit.covariance[2:, 2:])  # fmt: skip
    var2, angle = redraw_variance(fit, q, m, pairs, c)
    cov5[2:, 2:] += np.eye(3) * (var + var2)
    checks.append(words)
    if var2 > 0.0:
        checks.append(f"another RANSAC draw lands {angle:.2f} deg away (ambiguous matches)")
    inl = pairs[fit.inliers]
    scaled = _direction_problem(fit, cov5, c)
    if not scaled:
        scaled = ("switched off (odometry_scale false)" if not c.odometry_scale else
                  scaled_pose(q, m, inl, (r, t, cov5), c, neighbours))  # fmt: skip
    if not isinstance(scaled, str):
        return RelativePose(METRIC_ODOMETRY, _why(scaled[2], *checks), len(inl), r, scaled[0],
                            scaled[1], inl, k1)  # fmt: skip
    cov = cv.embed_rotation(cov5[2:, 2:], cv.SCALE_FREE_VARIANCE)
    return RelativePose(SCALE_FREE, _why(why, *checks, f"no scale from odometry: {scaled}"),
                        len(inl), r, t, cov, inl, k1)  # fmt: skip


def _direction_problem(fit: EssentialFit, cov5: np.ndarray, c: PoseConfig) -> str:
    """Why the pose's translation direction cannot carry a length ("" when it can)."""
    if fit.parallax_deg < c.min_parallax_deg:
        return (f"degenerate motion: {fit.parallax_deg:.2f} deg parallax is too little for a "
                "translation direction (the rotation holds)")  # fmt: skip
    s_dir = float(np.degrees(np.sqrt(np.linalg.eigvalsh(cov5[:2, :2])[-1])))
    if s_dir > c.max_direction_sigma_deg:
        return f"direction too uncertain (std {s_dir:.1f} deg)"
    return ""
