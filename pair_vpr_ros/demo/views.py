"""Ground truth of the demo camera for geometry: intrinsics, camera poses, true relative poses.

The demo camera (``camera.py``) is a pinhole without distortion, `height_m` above the ground,
zero pitch and roll; its optical frame is x right, y down, z forward.
"""

from __future__ import annotations

import math

import numpy as np

from pair_vpr_ros.demo.camera import Camera
from pair_vpr_ros.demo.depth import render_depth
from pair_vpr_ros.demo.render import render_frame
from pair_vpr_ros.demo.world import World
from pair_vpr_ros.geometry.camera import CameraModel
from pair_vpr_ros.geometry.rotations import rotation_angle_deg


def camera_model(cam: Camera) -> CameraModel:
    """The demo camera's intrinsics as a CameraModel (what its CameraInfo says)."""
    return CameraModel(cam.width, cam.height, cam.f, cam.f, cam.cx, cam.cy)


def camera_in_world(pose: np.ndarray, cam: Camera) -> np.ndarray:
    """[4, 4] pose of the optical frame in the world (x east, y north, z up) for a camera pose
    (x, y, yaw): columns are the camera's x (right), y (down), z (forward) axes."""
    x, y, yaw = (float(v) for v in pose[:3])
    c, s = math.cos(yaw), math.sin(yaw)
    out = np.eye(4)
    out[:3, :3] = [[s, 0.0, c], [-c, 0.0, s], [0.0, -1.0, 0.0]]
    out[:3, 3] = (x, y, cam.height_m)
    return out


def true_relative_pose(match_pose: np.ndarray, query_pose: np.ndarray, cam: Camera) -> np.ndarray:
    """[4, 4] true T_match_query of two demo camera poses (x, y, yaw)."""
    return np.linalg.inv(camera_in_world(match_pose, cam)) @ camera_in_world(query_pose, cam)


def render_keyframe(world: World, i: int) -> tuple[np.ndarray, np.ndarray]:
    """Frame `i` -> (RGB [H, W, 3] uint8, depth [H, W] float32 m, 0 = none), aligned."""
    cam = Camera(width=world.config.width, height=world.config.height)
    depth = render_depth(world.layout, world.poses[i], cam, world.occluders_of(i))
    return render_frame(world, i), depth


def pose_errors(estimate: np.ndarray, truth: np.ndarray) -> tuple[float, float, float]:
    """[4, 4] estimated and true T_match_query -> (rotation error deg, translation error m,
    translation direction error deg)."""
    d = np.linalg.inv(truth) @ estimate
    rot = rotation_angle_deg(d[:3, :3])
    te, tt = estimate[:3, 3], truth[:3, 3]
    cos = float(te @ tt / max(np.linalg.norm(te) * np.linalg.norm(tt), 1e-12))
    direction = math.degrees(math.acos(min(1.0, max(-1.0, cos))))
    return rot, float(np.linalg.norm(te - tt)), direction
