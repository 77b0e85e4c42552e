"""Loops made up from ground truth, for tests, benchmarks and robustness checks only.

Nothing in the loop-closure pipeline uses this module: real loops get their relative pose from
the two keyframes' images. Here a loop's pose is the ground-truth relative pose of the two camera
frames with seeded Gaussian noise drawn from the covariance it reports, and a *false* loop joins
two places that are far apart while claiming a pose a true revisit would have (a few metres
sideways, a few tens of degrees), so the graph cannot spot it by its size alone.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import replace

import gtsam
import numpy as np

from pair_vpr_ros.errors import PoseGraphError
from pair_vpr_ros.messages.factor import LoopFactor
from pair_vpr_ros.posegraph.config import IDENTITY
from pair_vpr_ros.posegraph.transforms import pose3, pose7


def loop_covariance(sigma_m: float = 0.1, sigma_deg: float = 1.0) -> np.ndarray:
    """Isotropic 6x6 covariance in ROS order (x, y, z, rx, ry, rz): the same in every frame."""
    rad = math.radians(sigma_deg)
    return np.diag([sigma_m**2] * 3 + [rad**2] * 3)


def make_factor(
    query_stamp: float, match_stamp: float, pose: gtsam.Pose3, covariance: np.ndarray
) -> LoopFactor:
    """A metric ``LoopFactor`` with ``T_match_query = pose``."""
    x, y, z, qx, qy, qz, qw = pose7(pose)
    return LoopFactor(
        query_stamp=float(query_stamp), match_stamp=float(match_stamp), query_frame_id="camera",
        match_frame_id="camera", translation=(x, y, z), rotation=(qx, qy, qz, qw),
        covariance=tuple(float(v) for v in np.asarray(covariance).reshape(-1)), metric=True,
        inliers=-1,
    )  # fmt: skip


def ground_truth_loops(
    stamps: np.ndarray,
    poses: np.ndarray,
    pairs: Sequence[tuple[float, float]],
    rng: np.random.Generator,
    covariance: np.ndarray | None = None,
    camera_to_base: Sequence[float] = IDENTITY,
) -> list[LoopFactor]:
    """One loop per ``(query_stamp, match_stamp)`` pair, its pose from the ground-truth base
    poses (``stamps [P]``, ``poses [P, 7]``, nearest stamp) plus noise drawn from ``covariance``
    (default ``loop_covariance()``)."""
    truth = (stamps, poses)
    return trajectory_loops(truth, truth, pairs, rng, covariance, camera_to_base)


def trajectory_loops(
    query_truth: tuple[np.ndarray, np.ndarray],
    match_truth: tuple[np.ndarray, np.ndarray],
    pairs: Sequence[tuple[float, float]],
    rng: np.random.Generator,
    covariance: np.ndarray | None = None,
    camera_to_base: Sequence[float] = IDENTITY,
    query: tuple[str, str] = ("", ""),
    match: tuple[str, str] = ("", ""),
) -> list[LoopFactor]:
    """``ground_truth_loops`` between two trajectories: the query stamps in ``query_truth``
    (``stamps [P]``, ``poses [P, 7]``), the match stamps in ``match_truth``, both in one world
    frame; the factors name the ``query`` and ``match`` (robot, session)."""
    cov = loop_covariance() if covariance is None else np.asarray(covariance, dtype=np.float64)
    names = dict(query_robot=query[0], query_session=query[1], match_robot=match[0],
                 match_session=match[1])  # fmt: skip
    out = []
    for query_stamp, match_stamp in pairs:
        q = pose3(query_truth[1][_nearest(query_truth[0], query_stamp)])
        m = pose3(match_truth[1][_nearest(match_truth[0], match_stamp)])
        q, m = q.compose(pose3(camera_to_base)), m.compose(pose3(camera_to_base))
        loop = make_factor(query_stamp, match_stamp, m.between(q), cov)
        noise = rng.multivariate_normal(np.zeros(6), loop.gtsam_covariance())
        measured = m.between(q).compose(gtsam.Pose3.Expmap(noise))
        out.append(replace(make_factor(query_stamp, match_stamp, measured, cov), **names))
    return out


def false_loops(
    stamps: np.ndarray,
    poses: np.ndarray,
    count: int,
    rng: np.random.Generator,
    min_distance_m: float = 30.0,
    min_separation_s: float = 10.0,
    covariance: np.ndarray | None = None,
    camera_to_base: Sequence[float] = IDENTITY,
) -> list[LoopFactor]:
    """``count`` wrong pairs: stamps at least ``min_separation_s`` apart whose ground-truth
    positions are at least ``min_distance_m`` apart, each with a plausible revisit pose (1-3 m
    sideways, 10-25 deg turned, up to 2 m along) and the covariance a true loop would carry."""
    cov = loop_covariance() if covariance is None else np.asarray(covariance, dtype=np.float64)
    camera = pose3(camera_to_base)
    out: list[LoopFactor] = []
    for _ in range(1000 * max(count, 1)):
        if len(out) == count:
            return out
        i, j = sorted(int(k) for k in rng.integers(len(stamps), size=2))
        far = np.linalg.norm(poses[i, :3] - poses[j, :3]) >= min_distance_m
        if not far or stamps[j] - stamps[i] < min_separation_s:
            continue
        side = rng.choice([-1.0, 1.0]) * rng.uniform(1.0, 3.0)
        yaw = math.radians(rng.choice([-1.0, 1.0]) * rng.uniform(10.0, 25.0))
        along = rng.uniform(-2.0, 2.0)
        # Drawn in the base frame (x forward, y left, z up), then seen from the camera.
        base = gtsam.Pose3(gtsam.Rot3.Rz(yaw), np.array([along, side, 0.0]))
        claimed = camera.inverse().compose(base).compose(camera)
        out.append(make_factor(stamps[j], stamps[i], claimed, cov))
    if len(out) < count:
        raise PoseGraphError(
            f"cannot find {count} stamp pairs {min_distance_m} m and {min_separation_s} s apart "
            "in this trajectory: inject fewer false loops or use a longer drive"
        )
    return out


def _nearest(stamps: np.ndarray, stamp: float) -> int:
    i = int(np.searchsorted(stamps, stamp))
    near = [j for j in (i - 1, i) if 0 <= j < len(stamps)]
    return min(near, key=lambda j: abs(stamps[j] - stamp))
