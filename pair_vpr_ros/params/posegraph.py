"""The parameters of `posegraph_node`, ROS-free: one table, mirrored in config/posegraph_node.yaml.

The graph settings carry the names of ``PoseGraphConfig``'s fields, so ``pairvpr-posegraph
--params-file`` reads the same file the node does. All are read-only: the graph is built with them.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

from pair_vpr_ros.errors import ConfigError
from pair_vpr_ros.identity import name_problem
from pair_vpr_ros.params.file import yaml_text
from pair_vpr_ros.params.table import RO, ParamSpec, _p
from pair_vpr_ros.posegraph.config import KERNELS, PoseGraphConfig

NODE_NAME = "posegraph_node"
_D = PoseGraphConfig()

PARAMS: tuple[ParamSpec, ...] = (
    # ---- topics and frames
    _p("odom_topic", "odom", "nav_msgs/Odometry input: the odometry to correct", **RO),
    _p("loop_topic", "loop_closure/factor", "loop between-factor input (vpr_node's output)", **RO),
    _p("odom_qos", "sensor_data", "odometry QoS: sensor_data (best effort, hears every "
       "publisher) or reliable", choices=("sensor_data", "reliable"), **RO),
    _p("trajectories", "", "several robot-sessions: comma-separated ROBOT/SESSION=ODOM_TOPIC "
       "(e.g. 'a/day1=/a/odom, b/day1=/b/odom'), the first one the map frame (after any "
       "prior_map_dirs sessions), each robot's loops "
       "on /ROBOT/<loop_topic>; SESSION may be empty (any session of that robot); '' = one robot "
       "on odom_topic and loop_topic", **RO),
    _p("prior_map_dirs", (), "saved place maps (e.g. vpr_node's prior_map_dirs) whose "
       "keyframe poses become one trajectory per robot-session, loaded before any message: "
       "the first one's first session is the map frame, the live trajectories join it by their "
       "loops into those keyframes", strings=True, **RO),
    _p("map_frame", "map", "frame of the corrected path and parent of map_to_odom", **RO),
    _p("odom_frame", "", "child frame of map_to_odom ('' = the odometry's header.frame_id)", **RO),
    _p("path_period", 1.0, "seconds between corrected_path messages (the whole path each time)",
       0.05, 3600.0, **RO),
    # ---- graph (PoseGraphConfig)
    _p("node_spacing_m", _D.node_spacing_m, "a new graph node after this much travel (m) ...",
       0.01, 1000.0, **RO),
    _p("node_spacing_deg", _D.node_spacing_deg, "... or this much turning (deg)",
       0.1, 180.0, **RO),
    _p("odom_sigma_m", _D.odom_sigma_m, "odometry factor translation sigma (m): floor ...",
       1e-6, 100.0, **RO),
    _p("odom_sigma_per_m", _D.odom_sigma_per_m, "... plus this per metre between the nodes",
       0.0, 10.0, **RO),
    _p("odom_sigma_deg", _D.odom_sigma_deg, "odometry factor rotation sigma (deg): floor ...",
       1e-6, 180.0, **RO),
    _p("odom_sigma_deg_per_m", _D.odom_sigma_deg_per_m, "... plus this per metre",
       0.0, 180.0, **RO),
    _p("loop_kernel", _D.loop_kernel, "robust kernel on loop factors (false loops lose their "
       "weight)", choices=KERNELS, **RO),
    _p("loop_kernel_width", _D.loop_kernel_width, "kernel width, in sigmas of the loop's own "
       "covariance", 0.01, 1000.0, **RO),
    _p("innovation_kernel", _D.innovation_kernel, "widen each loop's kernel by the graph's own "
       "uncertainty about its two nodes: a lone loop after a large drift is followed, but early "
       "false loops get in too", **RO),
    _p("camera_to_base", _D.camera_to_base, "pose of the loops' camera frame in the odometry's "
       "child (base) frame: [x, y, z, qx, qy, qz, qw]; the demo: [0, 0, 1.6, -0.5, 0.5, -0.5, "
       "0.5] (optical frame 1.6 m above base_link)", **RO),
    _p("stamp_tolerance_s", _D.stamp_tolerance_s, "a loop stamp may lie this far (s) outside "
       "the odometry", 0.0, 60.0, **RO),
    _p("max_odom_gap_s", _D.max_odom_gap_s, "odometry messages further apart (s) form a gap "
       "(counted; no loop is placed inside one)", 0.001, 3600.0, **RO),
    _p("history_period_s", _D.history_period_s, "odometry kept for placing loop stamps, at most "
       "every this many seconds", 0.0, 10.0, **RO),
    _p("relinearize_threshold", _D.relinearize_threshold, "iSAM2 relinearisation threshold",
       1e-6, 10.0, **RO),
    _p("join_min_loops", _D.join_min_loops, "several robot-sessions: one joins the map frame "
       "once this many of its loops to joined ones agree on its place (1 = at its first loop)",
       1, 100, **RO),
    _p("join_tolerance_m", _D.join_tolerance_m, "two loops agree when the poses they give one "
       "node differ by at most this (m) ...", 0.01, 1000.0, **RO),
    _p("join_tolerance_deg", _D.join_tolerance_deg, "... and this (deg) ...", 0.01, 180.0, **RO),
    _p("join_tolerance_per_m", _D.join_tolerance_per_m, "... widened by this fraction of the "
       "odometry travelled between the two loops", 0.0, 10.0, **RO),
    _p("loop_iterations", _D.loop_iterations, "iSAM2 iterations after a loop, one per later "
       "odometry message or path_period (the robust kernel converges even when the robot stops)",
       0, 100, **RO),
)  # fmt: skip

SPECS: dict[str, ParamSpec] = {p.name: p for p in PARAMS}
GRAPH_PARAMS = tuple(f.name for f in dataclasses.fields(PoseGraphConfig))
HEADER = (
    "# posegraph_node parameters (defaults). Start with:",
    "#   ros2 run pair_vpr_ros posegraph_node --ros-args \\",
    "#       --params-file config/posegraph_node.yaml -r odom:=/your/odometry",
    "# All are read-only (start-up only). pairvpr-posegraph --params-file reads this file too.",
)


def parse_trajectories(text: str, odom_topic: str) -> list[tuple[str, str, str]]:
    """``trajectories`` -> [(robot, session, odometry topic)]; '' -> one robot on
    ``odom_topic``. ``ConfigError`` names a malformed or repeated entry."""
    if not text.strip():
        return [("", "", odom_topic)]
    out: list[tuple[str, str, str]] = []
    for entry in (e.strip() for e in text.split(",")):
        ident, sep, topic = entry.partition("=")
        robot, _, session = ident.strip().partition("/")
        robot, session, topic = robot.strip(), session.strip(), topic.strip()
        if not sep or not robot or not topic or "/" in session:
            raise ConfigError(
                f"trajectories: {entry!r} is not ROBOT/SESSION=ODOM_TOPIC (e.g. 'a/day1=/a/odom')"
            )
        for what, name in (("robot", robot), ("session", session)):
            problem = name_problem(f"trajectories: {what} id", name) if name else None
            if problem:
                raise ConfigError(problem)
        if any((robot, session) == (r, s) for r, s, _ in out):
            raise ConfigError(f"trajectories: robot-session {robot}/{session} is given twice")
        if any(topic == t for _, _, t in out):
            raise ConfigError(f"trajectories: odometry topic {topic} is given twice")
        out.append((robot, session, topic))
    return out


def defaults() -> dict[str, Any]:
    return {p.name: p.default for p in PARAMS}


def posegraph_config(values: Mapping[str, Any]) -> PoseGraphConfig:
    """The ``PoseGraphConfig`` of a parameter set (missing names keep their defaults)."""
    settings = {name: values[name] for name in GRAPH_PARAMS if name in values}
    if "camera_to_base" in settings:
        settings["camera_to_base"] = tuple(float(v) for v in settings["camera_to_base"])
    return PoseGraphConfig(**settings)


def posegraph_yaml_text() -> str:
    """``config/posegraph_node.yaml``."""
    return yaml_text(PARAMS, HEADER)
