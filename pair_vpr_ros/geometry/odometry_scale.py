"""Metric scale of a monocular loop from a short odometry baseline next to the match keyframe.

At a loop the two keyframes are far apart in time, so the odometry *between them* has drifted:
its distance is exactly what the loop is there to correct and is never used. The odometry
between the match keyframe M and a map keyframe N recorded just before or after it is locally
accurate (a short time, a short distance), so:

1. M-N essential matrix -> R_mn and the direction of t_mn; its length is the odometry's distance
   between the two keyframes (the baseline); the visual and the odometry turn must agree;
2. triangulate M's keypoints seen in both -> metric depth at M's keypoints (the median over the
   neighbours used);
3. for each loop inlier whose M keypoint has such a point X, the query camera at s * t_hat
   (t_hat: the loop's unit translation) sees X along v = R_mq ray_q: X - s t_hat || v gives
   s_i = ((X x v) . (t_hat x v)) / |t_hat x v|^2; the length s is their median.

On the demo world (seed 8) the length error comes mostly from the loop's own direction and
rotation (6 % median; 1 % with the true ones), so the covariance carries them into the length:
s is recomputed at the sigma points of the essential matrix's covariance. A PnP against the
triangulated points instead (as with a depth image) was worse (8 %, biased short): points
triangulated over a forward baseline of ~1 m are too noisy for it.

The odometry's distance is that of its own frame (base_link), and the pipeline does not know
where the camera is mounted: the two distances are equal when the camera sits on the axis the
robot turns about or the robot does not turn, and differ by up to 2 sin(turn / 2) x (the
camera's offset from that axis) otherwise. So neighbours that turned more than
``scale_max_turn_deg`` are not used, and the turn adds 2 sin(turn / 2) x ``scale_lever_m`` (an
assumed bound on that offset) / baseline to the length's relative std. The length also carries
the odometry's own scale error (a few per cent for wheel odometry: ``scale_sigma_floor``).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from pair_vpr_ros.geometry import solvers
from pair_vpr_ros.geometry.covariance import sigmas
from pair_vpr_ros.geometry.epipolar import direction_basis, triangulate
from pair_vpr_ros.geometry.features import Features, match_features
from pair_vpr_ros.geometry.rotations import exp_so3, quaternion_matrix, rotation_angle_deg
from pair_vpr_ros.types import Pose


@dataclass(frozen=True)
class Neighbour:
    """A map keyframe next to the match keyframe: its id, the odometry's distance (m) and turn
    (deg) between the two, and a loader of its features (read from the map only when tried)."""

    id: int
    baseline_m: float
    turn_deg: float
    load: Callable[[], Features | None]


def pick_neighbours(
    match_stamp: float,
    match_pose: Pose | None,
    candidates: Sequence[tuple[int, float, Pose | None]],
    load: Callable[[int], Features | None],
    config,
) -> list[Neighbour]:
    """Map keyframes (id, stamp, odometry pose) near the match keyframe -> those fit for a
    baseline (both poses known, stamps within ``scale_max_gap_s``, distance at least
    ``scale_min_baseline_m``, turn at most ``scale_max_turn_deg``), least turn first."""
    if match_pose is None:
        return []
    p_m, r_m = np.asarray(match_pose[:3]), quaternion_matrix(match_pose[3:])
    out = []
    for kf_id, stamp, pose in candidates:
        if pose is None or abs(stamp - match_stamp) > config.scale_max_gap_s:
            continue
        baseline = float(np.linalg.norm(np.asarray(pose[:3]) - p_m))
        turn = rotation_angle_deg(r_m.T @ quaternion_matrix(pose[3:]))
        if baseline >= config.scale_min_baseline_m and turn <= config.scale_max_turn_deg:
            out.append(Neighbour(kf_id, baseline, turn, lambda i=kf_id: load(i)))
    # least turn (lever arm) first, whole degrees; then the longest (more parallax)
    return sorted(out, key=lambda n: (round(n.turn_deg), -n.baseline_m))


@dataclass(frozen=True)
class Triangulated:
    """Depth [M] (m, NaN: none) of the match keyframe's keypoints from the odometry baselines,
    the neighbours used and the relative std of the scale that the odometry gives them."""

    depth: np.ndarray
    neighbours: tuple[int, ...]
    relative_sigma: float


def triangulate_match(
    match: Features, neighbours: Sequence[Neighbour], config
) -> Triangulated | str:
    """Metric depth of the match keyframe's keypoints over its odometry baselines (up to
    ``scale_tries`` neighbours; a keypoint seen over several gets their median), or why none."""
    if not neighbours:
        return (f"no map keyframe next to the match keyframe has an odometry baseline (both "
                f"poses known, stamps within {config.scale_max_gap_s:g} s, at least "
                f"{config.scale_min_baseline_m:g} m apart, turned at most "
                f"{config.scale_max_turn_deg:g} deg)")  # fmt: skip
    reasons, depths, used, rel = [], [], [], config.scale_sigma_floor
    for n in neighbours[: config.scale_tries]:
        got = _depth_over(match, n, config)
        if isinstance(got, str):
            reasons.append(f"keyframe {n.id}: {got}")
            continue
        depths.append(got)
        used.append(n.id)
        # the camera's unknown offset from the odometry's turn axis (module docstring)
        lever = 2 * math.sin(math.radians(n.turn_deg) / 2) * config.scale_lever_m / n.baseline_m
        rel = max(rel, math.hypot(config.scale_sigma_floor, lever))
    if not used:
        return "; ".join(reasons)
    with warnings.catch_warnings():  # keypoints triangulated over no baseline stay NaN
        warnings.simplefilter("ignore", RuntimeWarning)
        depth = np.nanmedian(np.stack(depths), axis=0).astype(np.float32)
    return Triangulated(depth, tuple(used), rel)


def _depth_over(match: Features, n: Neighbour, config) -> np.ndarray | str:
    """Depth [M] (m, NaN: none) of the match's keypoints triangulated over the baseline to
    `n`, or why none."""
    feats = n.load()
    if feats is None or feats.camera is None or feats.kind != match.kind:
        return "no usable features"
    pairs = match_features(feats, match, config.ratio)  # (neighbour, match)
    if len(pairs) < config.min_matches:
        return f"too few feature matches ({len(pairs)})"
    kn, km = feats.keypoints[pairs[:, 0]], match.keypoints[pairs[:, 1]]
    r_mn, t_mn, mask = solvers.relative_pose(kn, km, (feats.camera, match.camera),
                                             config.essential_px)  # fmt: skip
    idx = np.flatnonzero(mask)
    if len(idx) < config.min_inliers:
        return f"too few essential-matrix inliers ({len(idx)} < {config.min_inliers})"
    ray_n, ray_m = feats.camera.rays(kn), match.camera.rays(km)
    visual_turn = rotation_angle_deg(r_mn)
    if abs(visual_turn - n.turn_deg) > config.scale_max_turn_mismatch_deg:
        return (f"the images turned {visual_turn:.1f} deg, the odometry {n.turn_deg:.1f} deg: "
                "odometry and images disagree")  # fmt: skip
    depth, ok = triangulate(ray_m[idx], ray_n[idx] @ r_mn.T, t_mn, config.scale_min_parallax_deg)
    out = np.full(len(match), np.nan)
    out[pairs[idx[ok], 1]] = depth[ok] * n.baseline_m
    return out


def loop_length(
    match: Features,
    depth: np.ndarray,
    loop_pairs: np.ndarray,
    rays_q: np.ndarray,
    min_parallax_deg: float,
) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
    """-> function of the loop's (R_mq, unit t) giving the per-point lengths s_i [P] (module
    docstring, step 3) of the loop inliers loop_pairs [K, 2] (query, match keypoint indices;
    rays_q [K, 3] their query rays) whose match keypoint has a triangulated `depth`."""
    z = depth[loop_pairs[:, 1]]
    ok = np.isfinite(z)
    x = match.camera.rays(match.keypoints[loop_pairs[ok, 1]]) * z[ok, None]
    rays = rays_q[ok]
    min_sin = math.sin(math.radians(min_parallax_deg))

    def lengths(r: np.ndarray, t_hat: np.ndarray) -> np.ndarray:
        v = rays @ r.T
        v /= np.linalg.norm(v, axis=1, keepdims=True)
        tv, xv = np.cross(t_hat, v), np.cross(x, v)
        ntv = np.linalg.norm(tv, axis=1)
        # rays near the baseline, or near the match ray, fix no length
        far = np.linalg.norm(xv, axis=1) >= min_sin * np.linalg.norm(x, axis=1)
        good = (ntv >= min_sin) & far
        return np.einsum("ni,ni->n", xv[good], tv[good]) / ntv[good] ** 2

    return lengths


def scaled_pose(q, m, inliers, fit, c, neighbours) -> tuple[np.ndarray, np.ndarray, str] | str:
    """The essential-matrix pose `fit` (R, unit t, cov5) of the loop inliers [K, 2] (query,
    match keypoint indices) -> (its translation with the length from the match's keypoints
    triangulated over odometry baselines, its covariance [6, 6], what gave the length), or why
    not.

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
    s_t, _ = sigmas(cov)
    if s_t > c.max_translation_sigma_m:
        return f"too uncertain (std {s_t:.2f} m)"
    used = ", ".join(map(str, tri.neighbours))
    why = f"scale from the odometry to keyframes {used} ({len(s_i)} points)"
    return t * s, (cov + cov.T) / 2, why
