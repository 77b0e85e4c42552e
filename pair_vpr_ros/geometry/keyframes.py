"""The pipeline's geometry: features of each keyframe (kept in the place map) and the relative
pose of each accepted loop, with every problem of the inputs counted rather than raised."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from pair_vpr_ros.errors import ConfigError, GeometryInputError
from pair_vpr_ros.geometry.camera import CameraModel
from pair_vpr_ros.geometry.epipolar import verified_matches
from pair_vpr_ros.geometry.features import (
    KINDS,
    Features,
    extract_features,
    pack_features,
    unpack_features,
)
from pair_vpr_ros.geometry.odometry_scale import Neighbour, pick_neighbours
from pair_vpr_ros.geometry.relpose import PoseConfig, RelativePose, relative_pose
from pair_vpr_ros.geometry.stereo import StereoInputError, stereo_depth

LOG = logging.getLogger("pair_vpr_ros.geometry")
# Loops whose inliers must point to one sign of k1 before a camera is said to lack its lens
# model: one loop's few inliers can fit a k1 by chance (the rig demo's ideal pinhole renders:
# 1 of 749 loops, 46 inliers, k1 +0.035), while an undeclared lens shows on most loops.
LENS_WARN_AFTER = 3


@dataclass(frozen=True)
class GeometryConfig:
    """relative_pose: compute T_match_query for accepted loops (features are then extracted
    for every keyframe and stored in the map); features: "sift" or "orb"; compact_features:
    store them compactly (feature_codec.py) rather than as extracted."""

    relative_pose: bool = True
    features: str = "sift"
    max_features: int = 1000
    compact_features: bool = True
    pose: PoseConfig = field(default_factory=PoseConfig)

    def __post_init__(self) -> None:
        if self.features not in KINDS:
            raise ConfigError(f"features={self.features!r} must be one of {', '.join(KINDS)}")
        if not 50 <= self.max_features <= 100_000:
            raise ConfigError(f"max_features={self.max_features} must be in [50, 100000]")


class KeyframeGeometry:
    """Extracts, packs and unpacks keyframe features; poses loops. `counts`: the pipeline's
    `PipelineCounts` (input problems and pose outcomes are counted there)."""

    def __init__(self, config: GeometryConfig | None, counts: Any) -> None:
        self.config = config or GeometryConfig()
        self.counts = counts
        self.last_stereo_problem = ""
        self.camera_warnings: list[str] = []  # once per camera (lens distortion left out)
        self._warned: set[CameraModel] = set()
        self._lens_k1: dict[CameraModel, list[float]] = {}  # each camera's findings so far

    def wanted(self, verification: bool) -> bool:
        return self.config.relative_pose or verification

    def extract(
        self,
        rgb: np.ndarray,
        depth: np.ndarray | None,
        camera: CameraModel | None,
        right: np.ndarray | None = None,
        baseline: float = 0.0,
    ) -> Features:
        """Features of one keyframe; a depth or camera model that does not fit the image is
        dropped and counted (the keyframe still counts for place recognition). Without depth,
        a rectified stereo pair (`right`, `baseline` m) gives it (`stereo.stereo_depth`); a
        pair that cannot is counted (`stereo_invalid`, `last_stereo_problem` says why)."""
        h, w = rgb.shape[:2]
        if depth is not None and depth.shape != (h, w):
            self.counts.depth_wrong_size += 1
            depth = None
        if camera is not None and (camera.width, camera.height) != (w, h):
            self.counts.intrinsics_wrong_size += 1
            camera = None
        sigma = None  # the depth's own std per pixel (stereo matching), else the model's
        if depth is None and right is not None:
            depth, sigma = self._stereo(rgb, right, camera, baseline)
        c = self.config
        noise = (c.pose.depth_sigma_a, c.pose.depth_sigma_b)
        return extract_features(rgb, c.features, c.max_features, depth=depth, camera=camera,
                                depth_noise=noise, depth_sigma=sigma)  # fmt: skip

    def _stereo(self, left, right, camera: CameraModel | None, baseline: float):
        try:
            if camera is None:
                raise StereoInputError("stereo pair without intrinsics (no camera_info)")
            if not baseline > 0:
                raise StereoInputError(f"stereo baseline {baseline!r} m must be > 0 (right "
                                       "camera_info missing or without P[0, 3])")  # fmt: skip
            depth, sigma = stereo_depth(left, right, camera.fx, baseline)
        except StereoInputError as err:
            self.counts.stereo_invalid += 1
            self.last_stereo_problem = str(err)
            return None, None
        self.counts.stereo_depth += 1
        return depth, sigma

    def pack(self, features: Features | None) -> bytes:
        if features is None:
            return b""
        return pack_features(features, self.config.compact_features)

    def unpack(self, data: bytes) -> Features | None:
        """Stored bytes -> Features (None when there are none or they are damaged)."""
        if not data:
            return None
        try:
            return unpack_features(data)
        except GeometryInputError:
            self.counts.features_damaged += 1
            return None

    def neighbours(
        self, match: Any, near: Sequence[Any], load: Callable[[int], Features | None]
    ) -> list[Neighbour]:
        """Baselines for a monocular scale: the match keyframe's metadata and that of the map
        keyframes `near` it (`KeyframeMeta`), `load`: id -> stored features; empty when
        switched off."""
        c = self.config.pose
        if not c.odometry_scale:
            return []
        candidates = [(n.id, n.stamp, n.pose) for n in near]
        return pick_neighbours(match.stamp, match.pose, candidates, load, c)

    @staticmethod
    def verify(query: Features | None, match: Features | None) -> tuple[int, float]:
        """Fundamental-matrix verification; (-1, NaN) when either side has no features."""
        inliers, ratio, _ = KeyframeGeometry.verify_points(query, match)
        return inliers, ratio

    @staticmethod
    def verify_points(
        query: Features | None, match: Features | None
    ) -> tuple[int, float, np.ndarray]:
        """`verify` with the inliers' points [I, 4] float32 (query x, y, match x, y in the
        keypoints' pixels; `epipolar.verified_matches`), what the loop image draws."""
        if query is None or match is None:
            return -1, float("nan"), np.zeros((0, 4), np.float32)
        return verified_matches(query, match)

    def pose(
        self,
        record: Any,
        query: Features | None,
        match: Features | None,
        neighbours: Sequence[Neighbour] = (),
    ) -> float:
        """Fill the pose fields of an accepted `record` (`neighbours`: odometry baselines next
        to the match, for a monocular scale); -> milliseconds spent."""
        t0 = time.perf_counter()
        result: RelativePose = relative_pose(query, match, self.config.pose, neighbours)
        for name, value in result.record_fields().items():
            setattr(record, name, value)
        name = f"pose_{(result.status or 'none').replace('-', '_')}"
        setattr(self.counts, name, getattr(self.counts, name) + 1)
        if result.lens_k1 and query.camera not in self._warned:
            self._lens_finding(query.camera, result.lens_k1)
        return (time.perf_counter() - t0) * 1e3

    def _lens_finding(self, camera: CameraModel, k1: float) -> None:
        """Say once per camera that its images look distorted while its model has none, when
        `LENS_WARN_AFTER` loops' inliers fit a k1 of one sign (each such loop's covariance is
        widened whether or not it is said)."""
        found = self._lens_k1.setdefault(camera, [])
        found.append(k1)
        same = [k for k in found if (k > 0) == (k1 > 0)]
        if len(same) < LENS_WARN_AFTER:
            return
        self._warned.add(camera)
        note = (
            f"camera {camera.width}x{camera.height} (fx {camera.fx:g}): {len(same)} loops' "
            f"inliers fit a radial distortion k1 = {float(np.median(same)):+.3f} (median) far "
            "better than the camera model without one: is the lens distortion missing from "
            "camera_info (D) or the camera_distortion parameters? Their poses got wider "
            "covariances, as will later loops' that show it"
        )
        self.camera_warnings.append(note)
        LOG.warning(note)
