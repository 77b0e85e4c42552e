"""Launch `vpr_node` and the reference pose graph `posegraph_node` together.

    ros2 launch pair_vpr_ros vpr_posegraph.launch.py weights:=/path/pairvpr-vitB.pth \\
        image:=/camera/image_raw odom:=/odom

`posegraph_node` reads `vpr_node`'s between-factors (`<loop_closure>/factor`) and the odometry
`odom`, and publishes `corrected_path`, `map_to_odom` and `corrected_odom`. When either node
exits (e.g. vpr_node finds no weights), the launch shuts the other down. `camera_to_base`
(the camera's pose in the odometry's child frame, `[x, y, z, qx, qy, qz, qw]`) is given as a
YAML list, e.g. camera_to_base:="[0.0, 0.0, 1.6, -0.5, 0.5, -0.5, 0.5]" for the demo camera;
'' keeps the posegraph_params_file's value. `prior_map_dirs` (a YAML list of saved maps) goes to
both nodes: vpr_node searches them, posegraph_node makes their sessions its map frame. Weights
are found as in vpr_node.launch.py.
Run in a real `ros2 launch` as docs/launch.md says; CI runs it with the stand-ins of
test/launch_standins.py (test/ros/test_launch_posegraph.py).
"""

from __future__ import annotations

import os

import yaml
from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction, Shutdown
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node


def _nodes(context) -> list[Node]:
    def arg(name: str) -> str:
        return LaunchConfiguration(name).perform(context)

    vpr_parameters: list = [arg("vpr_params_file")]
    if arg("weights"):  # only when given: '' would hide the parameter file's own `weights` entry
        vpr_parameters.append({"weights": arg("weights")})
    loops = arg("loop_closure")
    graph_parameters: list = [arg("posegraph_params_file"), {"loop_topic": loops + "/factor"}]
    if arg("camera_to_base"):
        pose = yaml.safe_load(arg("camera_to_base"))
        if not (isinstance(pose, list) and len(pose) == 7):
            raise ValueError(
                f"camera_to_base:={arg('camera_to_base')!r} is not a list of 7 numbers: give "
                'camera_to_base:="[x, y, z, qx, qy, qz, qw]"'
            )
        graph_parameters.append({"camera_to_base": [float(v) for v in pose]})
    if arg("prior_map_dirs"):  # both nodes: vpr_node searches them, the graph is anchored in them
        dirs = yaml.safe_load(arg("prior_map_dirs"))
        if not (isinstance(dirs, list) and dirs and all(isinstance(d, str) and d for d in dirs)):
            raise ValueError(
                f"prior_map_dirs:={arg('prior_map_dirs')!r} is not a list of folders: give "
                "prior_map_dirs:=\"['/maps/monday', '/maps/r2']\""
            )
        vpr_parameters.append({"prior_map_dirs": dirs})
        graph_parameters.append({"prior_map_dirs": dirs})
    return [
        Node(
            package="pair_vpr_ros",
            executable="vpr_node",
            name="vpr_node",
            output="screen",
            parameters=vpr_parameters,
            remappings=[("image", arg("image")), ("loop_closure", loops)],
            # one without the other is no use: a vpr_node that cannot start (no weights) would
            # leave a pose graph waiting for loops forever
            on_exit=Shutdown(reason="vpr_node exited"),
        ),
        Node(
            package="pair_vpr_ros",
            executable="posegraph_node",
            name="posegraph_node",
            output="screen",
            parameters=graph_parameters,
            remappings=[("odom", arg("odom"))],
            on_exit=Shutdown(reason="posegraph_node exited"),
        ),
    ]


def generate_launch_description() -> LaunchDescription:
    config = os.path.join(get_package_share_directory("pair_vpr_ros"), "config")
    arguments = [
        DeclareLaunchArgument(
            "weights",
            default_value="",
            description="Pair-VPR checkpoint (.pth); '' = the vpr_params_file's weights entry, "
            "else $PAIRVPR_WEIGHTS, else the one .pth in $XDG_DATA_HOME/pair_vpr_ros/",
        ),
        DeclareLaunchArgument("image", default_value="image", description="image topic"),
        DeclareLaunchArgument("odom", default_value="odom", description="odometry to correct"),
        DeclareLaunchArgument(
            "loop_closure",
            default_value="loop_closure",
            description="base name of vpr_node's outputs; the pose graph reads <it>/factor",
        ),
        DeclareLaunchArgument(
            "camera_to_base",
            default_value="",
            description="camera pose in the odometry's child frame, '[x, y, z, qx, qy, qz, "
            "qw]'; '' = the posegraph_params_file's",
        ),
        DeclareLaunchArgument(
            "prior_map_dirs",
            default_value="",
            description="saved maps for both nodes, '[/maps/a, /maps/b]': vpr_node searches "
            "them, posegraph_node takes their sessions as the map frame; '' = each params file's",
        ),
        DeclareLaunchArgument(
            "vpr_params_file",
            default_value=os.path.join(config, "vpr_node.yaml"),
            description="vpr_node parameters",
        ),
        DeclareLaunchArgument(
            "posegraph_params_file",
            default_value=os.path.join(config, "posegraph_node.yaml"),
            description="posegraph_node parameters",
        ),
    ]
    return LaunchDescription([*arguments, OpaqueFunction(function=_nodes)])
