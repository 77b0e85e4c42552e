"""The demo robot's rear camera (issue 49): the same camera as the front one, mounted
`REAR_OFFSET_M` behind ``base_link`` at the same height and looking backwards.

A rig bag (`pairvpr-make-demo-bag --rig`) holds both cameras (``/camera/...`` as always, and
``/rear_camera/...``), their poses in ``base_link`` on ``/tf_static``, and a world whose lap 1 is
driven the other way round (`WorldConfig.reverse_laps`): on that lap the rear camera sees the
streets as the front camera saw them on lap 0. The front camera's frames are rendered exactly as
in a bag without the rear camera (same poses, same noise).
"""

from __future__ import annotations

import numpy as np

from pair_vpr_ros.demo.camera import Camera
from pair_vpr_ros.demo.depth import render_depth
from pair_vpr_ros.demo.render import render_view
from pair_vpr_ros.demo.world import World

REAR_OFFSET_M = 1.0  # the rear camera sits this far behind base_link
REAR_IMAGE_TOPIC = "/rear_camera/image_raw"
REAR_CAMERA_INFO_TOPIC = "/rear_camera/camera_info"
REAR_DEPTH_TOPIC = "/rear_camera/depth/image_raw"
REAR_FRAME = "rear_camera"
TF_STATIC_TOPIC = "/tf_static"
RIG_REVERSE_LAPS = (1,)  # the lap of a rig world driven the other way round


def rear_pose(pose: np.ndarray) -> np.ndarray:
    """The rear camera's planar pose (x, y, yaw) for the base pose `pose` (x, y, yaw)."""
    x, y, yaw = (float(v) for v in pose)
    return np.array([x - REAR_OFFSET_M * np.cos(yaw), y - REAR_OFFSET_M * np.sin(yaw),
                     np.angle(np.exp(1j * (yaw + np.pi)))])  # fmt: skip


def rear_to_base(cam: Camera) -> tuple[float, ...]:
    """Pose of the rear camera's optical frame in ``base_link``: `REAR_OFFSET_M` behind, its z
    axis along -x, its x axis along +y (x, y, z, qx, qy, qz, qw)."""
    return (-REAR_OFFSET_M, 0.0, float(cam.height_m), 0.5, 0.5, -0.5, -0.5)


def render_rear(world: World, i: int) -> np.ndarray:
    """Frame `i` of the rear camera -> [H, W, 3] uint8 RGB (its own sensor noise)."""
    cam = Camera(world.config.width, world.config.height)
    pose = rear_pose(world.poses[i])
    return render_view(world.layout, pose, world.lighting_of(i), world.occluders_of(i), cam,
                       (world.seed, i, 1))  # fmt: skip


def rear_depth(world: World, i: int) -> np.ndarray:
    """Depth [H, W] float32 m seen by the rear camera at frame `i`."""
    cam = Camera(world.config.width, world.config.height)
    return render_depth(world.layout, rear_pose(world.poses[i]), cam, world.occluders_of(i))


def tf_static_msg(t: dict, stamp: object, poses: dict[str, tuple[float, ...]]) -> object:
    """tf2_msgs/TFMessage: ``base_link`` -> each camera frame of `poses` (its pose in it)."""
    out = []
    for child, (x, y, z, qx, qy, qz, qw) in poses.items():
        out.append(t["geometry_msgs/msg/TransformStamped"](
            header=t["std_msgs/msg/Header"](stamp=stamp, frame_id="base_link"),
            child_frame_id=child,
            transform=t["geometry_msgs/msg/Transform"](
                translation=t["geometry_msgs/msg/Vector3"](x=x, y=y, z=z),
                rotation=t["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw),
            ),
        ))  # fmt: skip
    return t["tf2_msgs/msg/TFMessage"](transforms=out)
