"""Launch `vpr_node` with the installed config/vpr_node.yaml.

    ros2 launch pair_vpr_ros vpr_node.launch.py weights:=/path/pairvpr-vitB.pth \\
        image:=/camera/image_raw loop_closure:=/lio_loop/loop_closure_detection

Not tested in CI: `launch` / `launch_ros` are not on PyPI (the node itself is, see test_node*.py).
"""

from __future__ import annotations

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node


def generate_launch_description() -> LaunchDescription:
    share = get_package_share_directory("pair_vpr_ros")
    arguments = [
        DeclareLaunchArgument("weights", description="Pair-VPR checkpoint (.pth)"),
        DeclareLaunchArgument("image", default_value="image", description="image topic"),
        DeclareLaunchArgument(
            "loop_closure",
            default_value="/lio_loop/loop_closure_detection",
            description="topic of the [t_current, t_previous] pair (LIO-SAM's by default)",
        ),
        DeclareLaunchArgument(
            "params_file",
            default_value=os.path.join(share, "config", "vpr_node.yaml"),
            description="node parameters",
        ),
    ]
    node = Node(
        package="pair_vpr_ros",
        executable="vpr_node",
        name="vpr_node",
        output="screen",
        parameters=[
            LaunchConfiguration("params_file"),
            {"weights": LaunchConfiguration("weights")},
        ],
        remappings=[
            ("image", LaunchConfiguration("image")),
            ("loop_closure", LaunchConfiguration("loop_closure")),
        ],
    )
    return LaunchDescription([*arguments, node])
