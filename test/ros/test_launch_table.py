"""ros.launch_table, the one table both launch files and `make demo-live` read: what each
argument gives the nodes, the demo's arguments, and docs that list every argument."""

from __future__ import annotations

import re
from pathlib import Path

from pair_vpr_ros.demo.live import demo_arguments
from pair_vpr_ros.ros.launch_table import LAUNCHES, defaults, node_setups, ros_args

ROOT = Path(__file__).resolve().parents[2]
POSEGRAPH = "vpr_posegraph.launch.py"


def test_the_demo_gives_relative_poses_and_the_graph_its_factors():
    vpr, graph = node_setups(POSEGRAPH, demo_arguments("/m.pth", "/p.yaml"))
    assert vpr.parameters == [
        "/p.yaml",
        {"weights": "/m.pth", "depth_topic": "/camera/depth/image_raw",
         "camera_info_topic": "/camera/camera_info", "pose_topic": "/odom",
         "relative_pose": True},
    ]  # fmt: skip
    assert vpr.remappings == [("image", "/camera/image_raw"), ("loop_closure", "loop_closure")]
    assert graph.parameters[1:] == [
        {"loop_topic": "loop_closure/factor"},
        {"camera_to_base": [0.0, 0.0, 1.6, -0.5, 0.5, -0.5, 0.5]},
    ]
    assert graph.remappings == [("odom", "/odom")]
    assert graph.parameters[0] == str(ROOT / "config" / "posegraph_node.yaml")


def test_ros_args_write_dicts_to_parameter_files_as_launch_ros_does(tmp_path):
    values = {**defaults("vpr_node.launch.py", "/share/config"), "robot_id": "7"}
    (setup,) = node_setups("vpr_node.launch.py", values)
    args = ros_args(setup, tmp_path)
    assert args == [
        "--ros-args", "-r", "__node:=vpr_node", "--params-file", "/share/config/vpr_node.yaml",
        "--params-file", str(tmp_path / "vpr_node_1.yaml"),
        "-r", "image:=image", "-r", "loop_closure:=/lio_loop/loop_closure_detection",
    ]  # fmt: skip
    # a string stays a string (robot "7"), where `-p robot_id:=7` would be an integer
    assert '"robot_id": "7"' in (tmp_path / "vpr_node_1.yaml").read_text()


def test_launch_md_lists_every_argument_of_both_files():
    text = (ROOT / "docs" / "launch.md").read_text()
    for launch, arguments in LAUNCHES.items():
        row = re.search(rf"^\| `{re.escape(launch)}` \|.*$", text, re.M)
        assert row is not None, launch
        assert {a.name for a in arguments} <= set(re.findall(r"`(\w+)`", row.group(0))), launch
