"""Synthetic loop world: the demo bag (loop closures with no robot, GPU or download), test data and
training data for the small demo model.

    world = generate_world(7)                     # layout + 3-lap drive with revisits
    rgb = render_frame(world, 0)                  # [240, 320, 3] uint8 RGB
    world.poses, world.stamps, world.revisit_of   # ground truth
    write_demo_bag("demo.mcap", seed=7)           # image, camera_info, depth, odom, ground truth
    write_place_dataset("places", seed=7, places=100, views_per_place=6)
"""

from __future__ import annotations

from pair_vpr_ros.demo.bag import (
    CAMERA_INFO_TOPIC,
    COMPRESSED_TOPIC,
    DEPTH_TOPIC,
    GROUND_TRUTH_TOPIC,
    IMAGE_TOPIC,
    ODOM_TOPIC,
    write_demo_bag,
    write_world_bag,
)
from pair_vpr_ros.demo.dataset import write_place_dataset
from pair_vpr_ros.demo.render import render_frame, render_view
from pair_vpr_ros.demo.world import World, WorldConfig, generate_world

__all__ = [
    "CAMERA_INFO_TOPIC",
    "COMPRESSED_TOPIC",
    "DEPTH_TOPIC",
    "GROUND_TRUTH_TOPIC",
    "IMAGE_TOPIC",
    "ODOM_TOPIC",
    "World",
    "WorldConfig",
    "generate_world",
    "render_frame",
    "render_view",
    "write_demo_bag",
    "write_place_dataset",
    "write_world_bag",
]
