"""The whole loop-closing back end in one process: images + depth + camera_info into `vpr_node`,
drifting odometry into `posegraph_node`, and the corrected path ends where the robot truly is
(tiny random network, an exact repeat of the first image as the loop, see test_node.py)."""

from __future__ import annotations

import math

import numpy as np
from bag_fixtures import textured
from nav_msgs.msg import Odometry, Path
from node_harness import image_msg, wait_for
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile
from sensor_msgs.msg import CameraInfo, Image
from test_node_geometry import GEOMETRY, depth_msg, info_msg
from test_posegraph_node import odom_msg

from pair_vpr_ros.demo.odometry import OdometryNoise, drifting_odometry
from pair_vpr_ros.posegraph.transforms import planar_pose7
from pair_vpr_ros.ros.posegraph_node import PoseGraphNode


def square_lap() -> tuple[np.ndarray, np.ndarray]:
    """10 Hz stamps from 100.0 s and planar poses [N, 3] of one 4 m x 4 m lap, then 0.5 s parked
    at the start (places 0 1 2 3 at the corners at 100..103 s, back at place 0 at 104 s)."""
    stamps = 100.0 + np.arange(46) / 10.0
    corners = np.array([(0, 0), (4, 0), (4, 4), (0, 4), (0, 0)], float)
    s = np.minimum(stamps - 100.0, 4.0)
    k = np.minimum(s.astype(int), 3)
    xy = corners[k] + (corners[k + 1] - corners[k]) * (s - k)[:, None]
    yaw = np.where(s >= 4.0, 0.0, k * math.pi / 2)
    return stamps, np.column_stack([xy, yaw])


def test_images_depth_and_drifting_odometry_give_a_corrected_path(harness):
    h = harness(**GEOMETRY)
    graph_node = PoseGraphNode(parameter_overrides=[
        Parameter("odom_qos", value="reliable"), Parameter("path_period", value=0.1),
        Parameter("node_spacing_m", value=0.5),
    ])  # fmt: skip
    h.executor.add_node(graph_node)
    peer = h.peer
    paths: list[Path] = []
    peer.create_subscription(Path, "corrected_path", paths.append, 10)
    odom = peer.create_publisher(Odometry, "odom", QoSProfile(depth=100))
    info = peer.create_publisher(CameraInfo, "camera_info", 10)
    depth = peer.create_publisher(Image, "depth", 10)
    wait_for(lambda: min(p.get_subscription_count() for p in (odom, info, depth)) >= 1)
    stamps, truth = square_lap()
    drifted = drifting_odometry(truth, 10.0, seed=0, noise=OdometryNoise(0.02, 1.0, 0.0, 0.0))
    for stamp, pose in zip(stamps, drifted, strict=True):
        odom.publish(odom_msg(stamp, planar_pose7(*pose)))
    wait_for(lambda: graph_node.graph.counts.odometry == len(stamps))
    info.publish(info_msg())
    wait_for(lambda: h.node.geometry_inputs.camera_info is not None)
    places = [textured(s) for s in range(4)]
    for i, place in enumerate([0, 1, 2, 3, 0]):
        depth.publish(depth_msg(100.0 + i))
        h.pub.publish(image_msg(places[place], 100.0 + i))
    wait_for(lambda: graph_node.graph.counts.loops_added == 1)
    nodes = graph_node.graph.counts.nodes

    def end_error() -> float:  # m from the start, where the path ends
        end = paths[-1].poses[-1].pose.position if paths else None
        return math.hypot(end.x, end.y) if end and len(paths[-1].poses) == nodes else math.inf

    assert np.hypot(*drifted[-1, :2]) > 0.15  # where the odometry ends up
    # The robot has stopped: the node goes on converging on its path timer (0.1 s here).
    wait_for(lambda: end_error() < 0.05, 10.0)
    graph_node.destroy_node()
