"""A reference SLAM back end for the loop closures: GTSAM Pose3 graph of odometry + loops.

    graph = PoseGraph(PoseGraphConfig(camera_to_base=(0, 0, 1.6, -0.5, 0.5, -0.5, 0.5)))
    graph.add_odometry(stamp, (x, y, z, qx, qy, qz, qw))   # every odometry message
    graph.add_loop(factor)                                  # a messages.factor.LoopFactor
    graph.update()                                          # iSAM2
    graph.optimised_poses(), graph.map_to_odom()

ROS-free: ``posegraph_node`` (ros/) and ``pairvpr-posegraph`` (offline/) drive this same object.
"""

from __future__ import annotations

from pair_vpr_ros.posegraph.config import PoseGraphConfig
from pair_vpr_ros.posegraph.graph import PoseGraph

__all__ = ["PoseGraph", "PoseGraphConfig"]
