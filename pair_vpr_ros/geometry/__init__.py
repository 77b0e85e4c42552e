"""Geometry of loop closures: camera models, keyframe features, relative pose + covariance.

camera = camera_from_info(camera_info_msg)            # or camera_from_params(...)
feats = extract_features(rgb, depth=depth_m, camera=camera)   # per keyframe
pose = relative_pose(query_feats, match_feats)        # T_match_query, covariance, inliers
inliers, ratio = verify_pair(query_feats, match_feats)        # optional verification
"""

from __future__ import annotations

from pair_vpr_ros.geometry.camera import CameraModel, camera_from_info, camera_from_params
from pair_vpr_ros.geometry.epipolar import verify_pair
from pair_vpr_ros.geometry.features import Features, extract_features, match_features
from pair_vpr_ros.geometry.relpose import PoseConfig, RelativePose, relative_pose

__all__ = [
    "CameraModel",
    "Features",
    "PoseConfig",
    "RelativePose",
    "camera_from_info",
    "camera_from_params",
    "extract_features",
    "match_features",
    "relative_pose",
    "verify_pair",
]
