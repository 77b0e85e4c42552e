"""Relative pose of a loop closure from the two keyframes' features.

``T_match_query`` = (R, t) is the pose of the query keyframe's camera in the match keyframe's
camera frame (optical: x right, y down, z forward): ``X_match = R X_query + t``, so ``t`` is the
query camera's position seen from the match camera. The frames are those of the two images'
``header.frame_id`` at their stamps. Its covariance is described in ``covariance.py``.

* metric: depth at the keypoints of either keyframe (the match's, else the query's) -> PnP;
* metric from odometry: no usable depth, but a map keyframe next to the match keyframe with an
  odometry pose -> essential matrix (USAC) -> R and the direction of t; its length from points
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
from pair_vpr_ros.geometry.epipolar import (
    centre_rim_chi2,
    direction_basis,
    essential_pose,
    parallax_deg,
    row_split_variance,
    sampson_residuals,
)
from pair_vpr_ros.geometry.features import Features, match_features
from pair_vpr_ros.geometry.metric_pose import is_planar, metric_fit, within
from pair_vpr_ros.geometry.odometry_scale import Neighbour, loop_length, triangulate_match
from pair_vpr_ros.geometry.pnp import project
from pair_vpr_ros.geometry.rotations import exp_so3, log_so3, matrix_quaternion

METRIC, METRIC_ODOMETRY, SCALE_FREE = "metric", "metric-odometry", "scale-free"


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
    depth_registration_px: float = 2.0  # depth-to-colour misregistration allowed in agreement
    # Errors no residual shows (intrinsics a little off, distortion, timing, rolling shutter):
    # rotation std per axis of floor_rotation_px pixels' angle at the focal length (at least
    # floor_rotation_deg), translation a + b |t|. TUM's Kinect (f 517) needs 1.8 px (docs).
    floor_rotation_px: float = 1.8
    floor_rotation_deg: float = 0.0
    floor_translation_m: float = 0.005
    floor_translation_rel: float = 0.01
    max_model_disagreement_chi2: float = 16.0  # PnP vs essential-matrix rotation (3 dof) chi2:
    # above it the covariance is scaled by chi2 / it

    def __post_init__(self) -> None:
        for name in ("ratio", "ransac_px", "essential_px", "max_rotation_sigma_deg",
                     "max_translation_sigma_m", "max_direction_sigma_deg",
                     "covariance_scale", "scale_max_gap_s", "scale_min_baseline_m",
                     "scale_max_turn_deg", "scale_max_turn_mismatch_deg",
                     "scale_min_parallax_deg", "scale_sigma_floor", "scale_lever_m",
                     "depth_sigma_b", "depth_agreement_sigmas",
                     "max_model_disagreement_chi2"):  # fmt: skip
            if not getattr(self, name) > 0:
                raise ConfigError(f"pose {name}={getattr(self, name)!r} must be > 0")
        for name in ("scale_neighbours", "scale_tries", "scale_min_points"):
            if not getattr(self, name) >= 1:
                raise ConfigError(f"pose {name}={getattr(self, name)!r} must be >= 1")
        floors = [n for n in vars(self) if n.startswith("floor_")]
        for name in ("depth_sigma_a", "max_depth_m", *floors, "depth_registration_px"):
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
    t [3], covariance [6, 6] and inliers, or status "" with the reason (a scale-free pose:
    why it has no scale)."""

    status: str = ""
    reason: str = ""
    inliers: int = -1
    rotation: np.ndarray | None = None
    translation: np.ndarray | None = None
    covariance: np.ndarray | None = None

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


def relative_pose(
    query: Features | None,
    match: Features | None,
    config: PoseConfig | None = None,
    neighbours: Sequence[Neighbour] = (),
) -> RelativePose:
    """T_match_query of a loop from the query and match keyframes' features; `neighbours`:
    map keyframes next to the match with an odometry baseline (``pick_neighbours``), for the
    scale of a pose without depth. Every covariance carries the floor of `PoseConfig`, its
    rotation part from the two cameras' focal lengths (`covariance.rotation_floor_deg`)."""
    c = config or PoseConfig()
    out = _relative_pose(query, match, c, neighbours)
    if out.status:
        cameras, scaled = (query.camera, match.camera), out.status != SCALE_FREE
        out.covariance = cv.with_floor(out.covariance, out.translation, c, cameras, scaled)
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
    """-> ("match" | "query" | None, depth [K] of the used side, reason when None)."""
    valid = {}
    for name, f, col in (("match", m, 1), ("query", q, 0)):
        z = f.depth[pairs[:, col]] if f.depth is not None else np.full(len(pairs), np.nan)
        valid[name] = (int((np.isfinite(z) & (z <= max_depth)).sum()), z)
    best = max(valid, key=lambda k: valid[k][0])  # ties: the match (from the map) first
    count, z = valid[best]
    if count >= need:
        return best, z, ""
    if q.depth is None and m.depth is None:
        return None, None, "no depth image (monocular): the translation is a direction only"
    return None, None, (f"no depth at the keypoints ({count} of {len(pairs)} matches have "
                        f"depth{within(max_depth)}): the translation is a direction "
                        "only")  # fmt: skip


def _metric(q, m, pairs, side, z, c: PoseConfig) -> RelativePose:
    fit = metric_fit(q, m, pairs, side, z, c)
    if isinstance(fit[0], str):
        return _fail(*fit)
    r, t, cov, inliers, points = fit
    if is_planar(points):  # the essential matrix cannot check a pose of a plane
        return RelativePose(METRIC, "", inliers, r, t, cov)
    chi2, angle = _model_disagreement(q, m, pairs, r, cov, c)
    if chi2 <= c.max_model_disagreement_chi2:
        return RelativePose(METRIC, "", inliers, r, t, cov)
    # The disagreement becomes plausible under the scaled covariance; the pose is kept (a back
    # end's robust kernel and this weak factor cannot bend the graph), its reason says why.
    cov = cov * (chi2 / c.max_model_disagreement_chi2)
    why = (f"PnP and essential-matrix rotations disagree by {angle:.2f} deg (chi-square "
           f"{chi2:.0f} > {c.max_model_disagreement_chi2:g}): intrinsics or distortion wrong? "
           "check camera_info or the camera_* parameters")  # fmt: skip
    return RelativePose(METRIC, f"covariance x{chi2 / c.max_model_disagreement_chi2:.1f}: {why}",
                        inliers, r, t, cov)  # fmt: skip


def _model_disagreement(q, m, pairs, r, cov, c: PoseConfig) -> tuple[float, float]:
    """(chi-square, 3 dof, angle in deg) of the difference between the PnP rotation (depth +
    pixels) and the essential matrix's (pixels only) under both covariances ((0, 0): no E).
    A wrong camera model bends the two differently: the sign of a confident wrong pose."""
    e = _essential_fit(q, m, pairs, c)
    if isinstance(e, RelativePose):
        return 0.0, 0.0
    d = log_so3(e[0] @ r.T)
    floor = 2 * np.eye(3) * math.radians(cv.rotation_floor_deg(c, q.camera, m.camera)) ** 2
    both = cov[3:, 3:] + e[3][2:, 2:] + floor
    return float(d @ np.linalg.solve(both, d)), math.degrees(float(np.linalg.norm(d)))


def _monocular(q, m, pairs, c: PoseConfig, neighbours, why: str) -> RelativePose:
    """Essential-matrix pose; metric when the odometry next to the match gives the length."""
    fit = _essential_fit(q, m, pairs, c)
    if isinstance(fit, RelativePose):
        return fit
    r, t, idx, cov5 = fit
    k = q.camera.k  # the check's ideal pixels, as _essential_fit's
    px_q, px_m = (project(k, f.camera.rays(f.keypoints[pairs[idx, col]]))
                  for f, col in ((q, 0), (m, 1)))  # fmt: skip
    rows_var, rows_angle = row_split_variance(px_q, px_m, k, (r, t), c.min_sigma_px)
    chi2, angle = centre_rim_chi2(px_q, px_m, k, (r, t), cov5[2:, 2:])
    if chi2 > c.max_model_disagreement_chi2:  # as PnP vs essential matrix: a weaker pose
        cov5 = cov5 * (chi2 / c.max_model_disagreement_chi2)
        # a lens model that bends the rim biases both halves: half their angle on each axis
        cov5[2:, 2:] += np.eye(3) * math.radians(angle / 2) ** 2
        why += (f"; covariance x{chi2 / c.max_model_disagreement_chi2:.1f}: rotations of "
                f"the image centre and rim disagree by {angle:.2f} deg (distortion left "
                "out?)")  # fmt: skip
    if rows_var > 0.0:  # a rolling shutter bends the rows: the pose is off by about as much
        cov5[2:, 2:] += np.eye(3) * rows_var
        why += f"; the upper and lower rows disagree by {rows_angle:.2f} deg (rolling shutter?)"
    scaled: RelativePose | str = "switched off (odometry_scale false)"
    if c.odometry_scale:
        scaled = _odometry_scaled(q, m, pairs[idx], (r, t, cov5), c, neighbours)
    if isinstance(scaled, RelativePose):
        return scaled
    cov = cv.embed_rotation(cov5[2:, 2:], cv.SCALE_FREE_VARIANCE)
    return RelativePose(SCALE_FREE, f"{why}; no scale from odometry: {scaled}", len(idx), r, t,
                        cov)  # fmt: skip


def _odometry_scaled(q, m, inliers, fit, c: PoseConfig, neighbours) -> RelativePose | str:
    """The essential-matrix pose `fit` (R, unit t, cov5) with its length from the match's
    keypoints triangulated over odometry baselines (odometry_scale.py), or why not.

    Covariance: with L = V sqrt(Lambda) of cov5 = V Lambda V^T and J_k the change of the length
    s between the sigma points +-L_k, the errors are d_t = (s B L_dir + t J^T) xi and
    d_rot = L_rot xi (xi ~ N(0, I_5)), plus an independent length error along t: the median's
    standard error and the odometry's relative error (``scale_sigma_floor``, the lever arm)."""
    r, t, cov5 = fit
    tri = triangulate_match(m, neighbours, c)
    if isinstance(tri, str):
        return tri
    rays_q = q.camera.rays(q.keypoints[inliers[:, 0]])
    lengths = loop_length(m, tri.depth, inliers, rays_q, c.scale_min_parallax_deg)
    s_i = lengths(r, t)
    if len(s_i) < c.scale_min_points:
        return (f"too few loop inliers with a triangulated point ({len(s_i)} < "
                f"{c.scale_min_points})")  # fmt: skip
    s = float(np.median(s_i))
    lam, vec = np.linalg.eigh(cov5)
    sq = vec * np.sqrt(np.clip(lam, 0.0, None))  # [5, 5]: column k is L_k
    basis = direction_basis(t)
    jac = np.empty(5)
    for k in range(5):
        ends = []
        for sign in (1.0, -1.0):
            d = sign * sq[:, k]
            t_k = t + basis @ d[:2]
            s_k = lengths(exp_so3(d[2:]) @ r, t_k / np.linalg.norm(t_k))
            ends.append(float(np.median(s_k)) if len(s_k) else math.nan)
        jac[k] = (ends[0] - ends[1]) / 2
    if not np.isfinite(jac).all():  # a pose one std away leaves no point in front: no length
        return "no length for poses within the pose's std (its points fall behind a camera)"
    a = np.zeros((6, 5))
    a[:3] = s * basis @ sq[:2] + np.outer(t, jac)
    a[3:] = sq[2:]
    spread = 1.4826 * float(np.median(np.abs(s_i - s))) * math.sqrt(math.pi / 2 / len(s_i))
    cov = a @ a.T
    cov[:3, :3] += (spread**2 + (tri.relative_sigma * s) ** 2) * np.outer(t, t)
    s_t, _ = cv.sigmas(cov)
    if s_t > c.max_translation_sigma_m:
        return f"too uncertain (std {s_t:.2f} m)"
    used = ", ".join(map(str, tri.neighbours))
    why = f"scale from the odometry to keyframes {used} ({len(s_i)} points)"
    return RelativePose(METRIC_ODOMETRY, why, len(inliers), r, t * s, (cov + cov.T) / 2)


def _essential_fit(q, m, pairs, c: PoseConfig):
    """-> (R, unit t, inlier indices, covariance [5, 5] of (direction [2], rotation [3])) or a
    failed RelativePose."""
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
    basis[:3, :2], basis[3:, 2:] = direction_basis(t), np.eye(3)
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
    return r, t, idx, cov5
