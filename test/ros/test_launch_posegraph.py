"""launch/vpr_posegraph.launch.py, run with stand-ins for `launch` / `launch_ros` (not on PyPI).

The two nodes it starts must be installed executables given the installed parameter files, and
their ROS arguments must start the real `VprNode` and `PoseGraphNode` so that the pose graph
subscribes to the very topic vpr_node publishes its between-factors on. (docs/launch.md says how
the file was also run in a real `ros2 launch`.)"""

from __future__ import annotations

import re
from pathlib import Path

import launch_standins as ls
import pytest
import rclpy
from ament_index_python.packages import get_package_share_directory
from package_layout import PACKAGE, console_scripts, install_prefix
from ros_cli import Graph, wait_for

from pair_vpr_ros.params.table import RANDOM_TINY
from pair_vpr_ros.ros.node import VprNode
from pair_vpr_ros.ros.posegraph_node import PoseGraphNode

LAUNCH = "vpr_posegraph.launch.py"
DEMO_CAMERA = "[0.0, 0.0, 1.6, -0.5, 0.5, -0.5, 0.5]"


@pytest.fixture
def share(tmp_path, monkeypatch) -> Path:
    prefix = install_prefix(tmp_path / "install" / PACKAGE)
    monkeypatch.setenv("AMENT_PREFIX_PATH", str(prefix))
    ls.installed(monkeypatch)
    return Path(get_package_share_directory(PACKAGE))


def launched(share: Path, **arguments: str) -> tuple[ls.Node, ls.Node]:
    vpr, graph = ls.launch(ls.describe(share / "launch" / LAUNCH), arguments)
    return vpr, graph


def test_both_nodes_are_installed_executables_with_installed_parameter_files(share):
    vpr, graph = launched(share)
    assert console_scripts()[vpr.executable] == "pair_vpr_ros.ros.entry:vpr_node"
    assert console_scripts()[graph.executable] == "pair_vpr_ros.ros.entry:posegraph_node"
    assert (vpr.package, graph.package) == (PACKAGE, PACKAGE)
    assert (vpr.name, graph.name) == ("vpr_node", "posegraph_node")
    # the odometry also gives vpr_node's keyframes their poses
    assert vpr.parameters == [str(share / "config" / "vpr_node.yaml"), {"pose_topic": "odom"}]
    assert graph.parameters == [
        str(share / "config" / "posegraph_node.yaml"),
        {"loop_topic": "loop_closure/factor"},
    ]
    assert vpr.remappings == [("image", "image"), ("loop_closure", "loop_closure")]
    assert graph.remappings == [("odom", "odom")]
    # either node ending ends the launch (a vpr_node without weights left the graph running)
    assert vpr.on_exit == ls.Shutdown("vpr_node exited")
    assert graph.on_exit == ls.Shutdown("posegraph_node exited")


def test_camera_to_base_and_weights_reach_the_nodes(share):
    vpr, graph = launched(share, weights="/robot/b.pth", camera_to_base=DEMO_CAMERA)
    assert vpr.parameters[1:] == [{"weights": "/robot/b.pth", "pose_topic": "odom"}]
    assert graph.parameters[2:] == [{"camera_to_base": [0.0, 0.0, 1.6, -0.5, 0.5, -0.5, 0.5]}]
    assert ls.ros_args(graph)[-4:-2] == ["-p", f"camera_to_base:={DEMO_CAMERA}"]


def test_prior_map_dirs_reach_both_nodes(share):
    vpr, graph = launched(share, prior_map_dirs="['/maps/monday', /maps/r2]")
    dirs = {"prior_map_dirs": ["/maps/monday", "/maps/r2"]}
    assert vpr.parameters[1:] == [{"pose_topic": "odom", **dirs}]
    assert graph.parameters[2:] == [dirs]
    for value in ("/maps/a", "[]", "[1]", "['']"):
        with pytest.raises(ValueError) as err:
            launched(share, prior_map_dirs=value)
        assert str(err.value) == (
            f"prior_map_dirs:={value!r} is not a list of folders: give "
            "prior_map_dirs:=\"['/maps/monday', '/maps/r2']\""
        )


@pytest.mark.parametrize("value", ["[1.0, 2.0]", "0.5", "{x: 1}"])
def test_a_camera_to_base_that_is_no_seven_list_is_refused(share, value):
    with pytest.raises(ValueError) as err:
        launched(share, camera_to_base=value)
    assert str(err.value) == (
        f"camera_to_base:={value!r} is not a list of 7 numbers: give "
        'camera_to_base:="[x, y, z, qx, qy, qz, qw]"'
    )


def test_the_pose_graph_hears_the_factors_vpr_node_publishes(share):
    vpr_args, graph_args = (
        ls.ros_args(n)
        for n in launched(
            share, weights=RANDOM_TINY, image="/camera/image_raw", odom="/robot/odom",
            loop_closure="/lio_loop/loop_closure_detection", camera_to_base=DEMO_CAMERA,
        )
    )  # fmt: skip
    rclpy.init()
    vpr = pose_graph = graph = None
    try:
        vpr = VprNode(cli_args=vpr_args, start_worker=False)
        pose_graph = PoseGraphNode(cli_args=graph_args)
        graph = Graph(vpr)
        factor = "/lio_loop/loop_closure_detection/factor"
        wait_for(lambda: factor in graph.topics("posegraph_node")[1])
        wait_for(lambda: factor in graph.topics("vpr_node")[0])
        published = graph.topics("vpr_node")[0]
        subscribed = graph.topics("posegraph_node")[1]
        assert published[factor] == subscribed[factor] == ["nav_msgs/msg/Odometry"]
        assert subscribed == {
            factor: ["nav_msgs/msg/Odometry"], "/robot/odom": ["nav_msgs/msg/Odometry"],
        }  # fmt: skip
        assert graph.topics("vpr_node")[1] == {
            "/camera/image_raw": ["sensor_msgs/msg/Image"],
            "/robot/odom": ["nav_msgs/msg/Odometry"],
        }
        assert pose_graph.values["camera_to_base"] == (0.0, 0.0, 1.6, -0.5, 0.5, -0.5, 0.5)
    finally:
        if graph is not None:
            graph.close()
        if vpr is not None:
            vpr.shutdown()
            vpr.destroy_node()
        if pose_graph is not None:
            pose_graph.destroy_node()
        rclpy.try_shutdown()


def test_the_sensor_topics_reach_vpr_node_and_turn_relative_poses_on(share):
    vpr, _ = launched(
        share, image="/cam/rgb", depth="/cam/depth", camera_info="/cam/info", odom="/odom",
        right_image="/cam/right", right_camera_info="/cam/right_info", robot_id="r7",
        map_dir="/maps/r7", params_file="/robot/vpr.yaml",
    )  # fmt: skip
    assert vpr.parameters == [
        "/robot/vpr.yaml",
        {
            "depth_topic": "/cam/depth", "camera_info_topic": "/cam/info",
            "right_image_topic": "/cam/right", "right_camera_info_topic": "/cam/right_info",
            "pose_topic": "/odom", "robot_id": "r7", "map_dir": "/maps/r7", "relative_pose": True,
        },
    ]  # fmt: skip
    assert vpr.remappings == [("image", "/cam/rgb"), ("loop_closure", "loop_closure")]
    only_info = launched(share, camera_info="/cam/info")[0].parameters[1]
    assert only_info == {"camera_info_topic": "/cam/info", "pose_topic": "odom",
                         "relative_pose": True}  # fmt: skip


def test_usage_in_its_docstring_uses_declared_arguments(share):
    text = (share / "launch" / LAUNCH).read_text()
    usage = re.search(r"ros2 launch (\S+) (\S+)((?: +\\\n)?(?:\s+\w+:=\S+)+)", text)
    assert usage is not None and (usage.group(1), usage.group(2)) == (PACKAGE, LAUNCH)
    given = dict(re.findall(r"(\w+):=(\S+)", usage.group(3)))
    declared = ls.declared(ls.describe(share / "launch" / LAUNCH))
    assert given and set(given) <= set(declared)
    assert all(spec.description for spec in declared.values())
