"""Launch `vpr_node` with the installed config/vpr_node.yaml.

    ros2 launch pair_vpr_ros vpr_node.launch.py weights:=/path/pairvpr-vitB.pth \\
        image:=/camera/image_raw camera_info:=/camera/camera_info odom:=/odom \\
        loop_closure:=/lio_loop/loop_closure_detection

The sensor topics (`image`, `depth`, `camera_info`, `odom`, `right_image`,
`right_camera_info`), `robot_id` and `map_dir` go to the node; a camera_info or depth topic
turns relative poses on. Every argument and what it gives the node is in one table,
pair_vpr_ros/ros/launch_table.py, which `make demo-live` reads too. Without `weights:=` the
node finds its checkpoint as everywhere else: the `weights` entry of `params_file`, else
$PAIRVPR_WEIGHTS, else the one .pth in $XDG_DATA_HOME/pair_vpr_ros/.
Not run in CI (`launch` / `launch_ros` are not on PyPI): test/ros/test_launch_file.py runs it
with stand-ins for them and checks what it would start against what setup.py installs.
"""

from __future__ import annotations

from pair_vpr_ros.ros.launch_table import launch_description


def generate_launch_description():
    return launch_description("vpr_node.launch.py")
