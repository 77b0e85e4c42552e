"""Launch `vpr_node` with the installed config/vpr_node.yaml.

    ros2 launch pair_vpr_ros vpr_node.launch.py weights:=/path/pairvpr-vitB.pth \\
        image:=/camera/image_raw loop_closure:=/lio_loop/loop_closure_detection

Without `weights:=` the node finds its checkpoint as everywhere else: the `weights` entry of
`params_file`, else $PAIRVPR_WEIGHTS, else the one .pth in $XDG_DATA_HOME/pair_vpr_ros/.
Not run in CI (`launch` / `launch_ros` are not on PyPI): test/ros/test_launch_file.py runs it
with stand-ins for them and checks what it would start against what setup.py installs.
"""

from __future__ import annotations

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node


def _node(context) -> list[Node]:
    parameters: list = [LaunchConfiguration("params_file").perform(context)]
    weights = LaunchConfiguration("weights").perform(context)
    if weights:  # only when given: '' would hide the parameter file's own `weights` entry
        parameters.append({"weights": weights})
    return [
        Node(
            package="pair_vpr_ros",
            executable="vpr_node",
            name="vpr_node",
            output="screen",
            parameters=parameters,
            remappings=[
                ("image", LaunchConfiguration("image").perform(context)),
                ("loop_closure", LaunchConfiguration("loop_closure").perform(context)),
            ],
        )
    ]


def generate_launch_description() -> LaunchDescription:
    share = get_package_share_directory("pair_vpr_ros")
    arguments = [
        DeclareLaunchArgument(
            "weights",
            default_value="",
            description="Pair-VPR checkpoint (.pth); '' = the params_file's weights entry, else "
            "$PAIRVPR_WEIGHTS, else the one .pth in $XDG_DATA_HOME/pair_vpr_ros/",
        ),
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
    return LaunchDescription([*arguments, OpaqueFunction(function=_node)])
