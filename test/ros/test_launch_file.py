"""launch/vpr_node.launch.py, run with stand-ins for `launch` / `launch_ros` (not on PyPI).

The launch file is loaded from an install prefix laid out from setup.py's data_files (found
through the ament index, as `ros2 launch` finds it); the node it starts must be an installed
executable given the installed parameter file, and its ROS arguments must start the real
`VprNode` with the remapped topics and the weights the rules say."""

from __future__ import annotations

import re
import xml.etree.ElementTree as ET
from pathlib import Path

import launch_standins as ls
import pytest
import rclpy
from ament_index_python.packages import get_package_share_directory
from package_layout import PACKAGE, ROOT, console_scripts, install_prefix
from ros_cli import Graph, wait_for

from pair_vpr_ros.errors import ConfigError
from pair_vpr_ros.params.table import RANDOM_TINY, SPECS
from pair_vpr_ros.ros.node import VprNode

LAUNCH = "vpr_node.launch.py"


@pytest.fixture
def share(tmp_path, monkeypatch) -> Path:
    """The package's share folder in a fresh install prefix on AMENT_PREFIX_PATH."""
    prefix = install_prefix(tmp_path / "install" / PACKAGE)
    monkeypatch.setenv("AMENT_PREFIX_PATH", str(prefix))
    ls.installed(monkeypatch)
    return Path(get_package_share_directory(PACKAGE))


def launched(share: Path, **arguments: str) -> ls.Node:
    (node,) = ls.launch(ls.describe(share / "launch" / LAUNCH), arguments)
    return node


@pytest.fixture
def ros():
    """Start VprNode from ROS arguments (and a peer to see the graph); stopped afterwards."""
    rclpy.init()
    started: list[tuple[VprNode, Graph]] = []

    def start(args: list[str]) -> tuple[VprNode, Graph]:
        node = VprNode(cli_args=args, start_worker=False)
        started.append((node, Graph(node)))
        return started[-1]

    yield start
    for node, graph in started:
        graph.close()
        node.shutdown()
        node.destroy_node()
    rclpy.try_shutdown()


def test_node_action_names_what_setup_py_installs(share):
    node = launched(share)
    package = ET.parse(ROOT / "package.xml").getroot().findtext("name")
    assert node.package == package == PACKAGE
    assert console_scripts()[node.executable] == "pair_vpr_ros.ros.entry:vpr_node"
    assert node.name == "vpr_node"  # the services are /vpr_node/... (README, node.py)
    assert node.parameters == [str(share / "config" / "vpr_node.yaml")]  # no weights given
    params_file = Path(node.parameters[0])
    assert params_file.read_text() == (ROOT / "config" / "vpr_node.yaml").read_text()
    assert node.remappings == [
        (SPECS["image_topic"].default, "image"),
        ("loop_closure", "/lio_loop/loop_closure_detection"),
    ]


def test_its_arguments_start_the_node_with_the_remapped_topics(share, ros):
    node = launched(share, weights=RANDOM_TINY, image="/camera/image_raw")
    args = ls.ros_args(node)
    assert args == [
        "--ros-args", "-r", "__node:=vpr_node",
        "--params-file", str(share / "config" / "vpr_node.yaml"),
        "-p", f'weights:="{RANDOM_TINY}"',
        "-r", "image:=/camera/image_raw", "-r", "loop_closure:=/lio_loop/loop_closure_detection",
    ]  # fmt: skip
    vpr, graph = ros(args)
    assert vpr.get_parameter("weights").value == RANDOM_TINY
    wanted_pub = ("/lio_loop/loop_closure_detection", "std_msgs/msg/Float64MultiArray")
    wait_for(lambda: wanted_pub[0] in graph.topics()[0])
    published, subscribed = graph.topics()
    assert published[wanted_pub[0]] == [wanted_pub[1]]
    assert "/loop_closure" not in published
    assert subscribed == {"/camera/image_raw": ["sensor_msgs/msg/Image"]}


def test_without_weights_the_params_file_entry_stands(share, ros, tmp_path):
    mine = tmp_path / "robot.yaml"
    mine.write_text(f"/**:\n  ros__parameters:\n    weights: {RANDOM_TINY}\n    top_k: 3\n")
    node = launched(share, params_file=str(mine))
    assert node.parameters == [str(mine)]
    vpr, _ = ros(ls.ros_args(node))
    assert (vpr.get_parameter("weights").value, vpr.get_parameter("top_k").value) == (
        RANDOM_TINY, 3,
    )  # fmt: skip
    given = launched(share, params_file=str(mine), weights="/robot/other.pth")
    assert given.parameters == [str(mine), {"weights": "/robot/other.pth"}]


def test_usage_in_its_docstring_uses_declared_arguments(share):
    text = (share / "launch" / LAUNCH).read_text()
    usage = re.search(r"ros2 launch (\S+) (\S+)((?: +\\\n)?(?:\s+\w+:=\S+)+)", text)
    assert usage is not None, "the docstring shows no `ros2 launch` line"
    assert (usage.group(1), usage.group(2)) == (PACKAGE, LAUNCH)
    given = dict(re.findall(r"(\w+):=(\S+)", usage.group(3)))
    description = ls.describe(share / "launch" / LAUNCH)
    assert set(given) <= set(ls.declared(description))
    assert all(spec.description for spec in ls.declared(description).values())


def test_without_weights_anywhere_in_the_launch_the_node_resolves_them(share, ros, monkeypatch):
    monkeypatch.setenv("PAIRVPR_WEIGHTS", RANDOM_TINY)  # as a robot's environment sets it
    node = launched(share)
    vpr, _ = ros(ls.ros_args(node))
    assert vpr.get_parameter("weights").value == ""
    assert vpr.summary.startswith("model random-init:0|tiny|")


def test_sensor_topics_reach_the_node_and_relative_poses_follow_them(share):
    assert launched(share).parameters == [str(share / "config" / "vpr_node.yaml")]  # no odom
    node = launched(share, depth="/cam/depth", odom="/odom", robot_id="7")
    assert node.parameters[1:] == [
        {"depth_topic": "/cam/depth", "pose_topic": "/odom", "robot_id": "7",
         "relative_pose": True},
    ]  # fmt: skip


def test_text_arguments_arrive_as_text(share, ros, tmp_path):
    """Issue 48: robot_id:=7 or map_dir:=2024 through ros2 launch reach the node as strings
    (launch_ros would pass them on as numbers): map_dir 2024 is a folder, and robot_id 7 is
    refused by the identity rule, not by a parameter type error."""
    node = launched(share, weights=RANDOM_TINY, robot_id="r7", map_dir="2024")
    vpr, _ = ros(ls.ros_args(node))
    assert (vpr.get_parameter("robot_id").value, vpr.get_parameter("map_dir").value) == (
        "r7", "2024",
    )  # fmt: skip
    numeric = launched(share, weights=RANDOM_TINY, robot_id="7")
    with pytest.raises(ConfigError, match=r"^invalid parameters: robot_id '7' must be 1-64 "):
        ros(ls.ros_args(numeric))
