"""Launch `vpr_node` and the reference pose graph `posegraph_node` together.

    ros2 launch pair_vpr_ros vpr_posegraph.launch.py weights:=/path/pairvpr-vitB.pth \\
        image:=/camera/image_raw depth:=/camera/depth/image_raw \\
        camera_info:=/camera/camera_info odom:=/odom

`posegraph_node` reads `vpr_node`'s between-factors (`<loop_closure>/factor`) and the odometry
`odom`, and publishes `corrected_path`, `map_to_odom` and `corrected_odom`. Factors need
relative poses: give `camera_info` (and `depth` for metric ones) or the camera_* parameters in
`params_file`. When either node exits (e.g. vpr_node finds no weights), the launch shuts the
other down. `camera_to_base` (the camera's pose in the odometry's child frame, `[x, y, z, qx,
qy, qz, qw]`) is given as a YAML list, e.g. camera_to_base:="[0.0, 0.0, 1.6, -0.5, 0.5, -0.5,
0.5]" for the demo camera; '' keeps the posegraph_params_file's value. `prior_map_dirs` (a YAML
list of saved maps) goes to both nodes: vpr_node searches them, posegraph_node makes their
sessions its map frame. The sensor topics, `robot_id`, `map_dir` and the weights are as in
vpr_node.launch.py; every argument is in pair_vpr_ros/ros/launch_table.py, which
`make demo-live` reads too (the demo through this very set-up).
Run in a real `ros2 launch` as docs/launch.md says; CI runs it with the stand-ins of
test/launch_standins.py (test/ros/test_launch_posegraph.py).
"""

from __future__ import annotations

from pair_vpr_ros.ros.launch_table import launch_description


def generate_launch_description():
    return launch_description("vpr_posegraph.launch.py")
