"""`posegraph_node`: a loop-closing back end for any odometry, a thin shell over ``PoseGraph``.

Run next to `vpr_node`::

    ros2 run pair_vpr_ros posegraph_node --ros-args --params-file config/posegraph_node.yaml \\
        -r odom:=/your/odometry

Inputs: ``odom`` (``nav_msgs/Odometry`` of the robot base) and ``loop_closure/factor`` (vpr_node's
between-factor topic). Every odometry message goes into the graph (a node each
``node_spacing_m``); every loop is placed between the nodes at its two stamps and iSAM2 updates.

Outputs: ``corrected_path`` (``nav_msgs/Path`` of the optimised nodes in ``map_frame``, every
``path_period`` s), ``map_to_odom`` (``geometry_msgs/TransformStamped``, map -> odometry frame,
after each update: relay it to ``/tf`` to correct everything that lives in the odometry frame) and
``corrected_odom`` (``nav_msgs/Odometry``: each odometry message moved into ``map_frame``).
Several robot-sessions (``trajectories`` = ``a/day1=/a/odom, b/day1=/b/odom``): one odometry
subscription per robot-session, one graph; the loops name their robots and sessions (the factor
message's frame ids of a loop between two; a loop within one comes on its robot's
``/<robot>/<loop_topic>``). The first is the map frame; each robot's outputs go to
``<robot>/corrected_path``, ``<robot>/map_to_odom`` and ``<robot>/corrected_odom`` once it has
joined the map frame. Prior sessions (``prior_map_dirs``: saved maps' keyframe poses, one
trajectory per robot-session, ``posegraph.priors``) come before the live ones: the first is the
map frame, and a live robot's loops into their keyframes place it there (no outputs of their own).
Only rclpy code lives here; the graph is ``posegraph.graph``, its parameters ``posegraph.params``.
"""

from __future__ import annotations

import functools
import sys

import rclpy
from builtin_interfaces.msg import Time
from geometry_msgs.msg import Pose, PoseStamped, TransformStamped
from nav_msgs.msg import Odometry, Path
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import QoSProfile, qos_profile_sensor_data

from pair_vpr_ros.errors import ConfigError, PairVPRError
from pair_vpr_ros.messages.factor import LoopFactor, factor_from_msg
from pair_vpr_ros.params import posegraph as params
from pair_vpr_ros.params.check import check_value
from pair_vpr_ros.params.file import params_file_problem
from pair_vpr_ros.posegraph.loops import own
from pair_vpr_ros.posegraph.priors import graph_with_priors, read_prior_sessions
from pair_vpr_ros.posegraph.tracks import label
from pair_vpr_ros.posegraph.transforms import pose3, pose7
from pair_vpr_ros.ros.parameters import declared_default, descriptor, read_value
from pair_vpr_ros.types import message_pose, message_stamp, split_stamp


def _stamp_msg(seconds: float) -> Time:
    sec, nanosec = split_stamp(seconds)
    return Time(sec=sec, nanosec=nanosec)


def _pose_msg(pose: tuple[float, ...]) -> Pose:
    msg = Pose()
    p, q = msg.position, msg.orientation
    p.x, p.y, p.z, q.x, q.y, q.z, q.w = (float(v) for v in pose)
    return msg


class PoseGraphNode(Node):
    """Odometry + loop closures in, corrected path and map->odom out."""

    def __init__(self, **kwargs) -> None:
        super().__init__(params.NODE_NAME, **kwargs)
        for spec in params.PARAMS:
            self.declare_parameter(spec.name, declared_default(spec), descriptor(spec))
        v = {spec.name: read_value(self, spec) for spec in params.PARAMS}
        if not isinstance(v["camera_to_base"], tuple):
            v["camera_to_base"] = tuple(float(x) for x in v["camera_to_base"])
        reasons = [r for name, value in v.items() if (r := check_value(name, value, params.SPECS))]
        if reasons:
            raise ConfigError("invalid parameters: " + "; ".join(reasons))
        self.values = v
        entries = params.parse_trajectories(v["trajectories"], v["odom_topic"])
        robots = [robot for robot, _, _ in entries]
        if len(set(robots)) < len(robots):
            raise ConfigError("trajectories: a robot is given twice (a node follows one live "
                              "session per robot)")  # fmt: skip
        # Prior sessions first (the map frame), fed before any live message.
        priors = read_prior_sessions(v["prior_map_dirs"])
        live = [(r, s) for r, s, _ in entries]
        self.graph = graph_with_priors(params.posegraph_config(v), priors, live)
        for note in priors.notes:
            self.get_logger().info(note)
        for i, session in enumerate(priors.sessions):
            self.get_logger().info(
                f"prior session {label(session.trajectory)}{' (the map frame)' if i == 0 else ''}"
                f": {len(session.stamps)} keyframe poses"
            )
        if priors.skipped:
            self.get_logger().warning(f"prior keyframes skipped: {dict(priors.skipped)}")
        self.loops_received = 0
        self.loops_undecodable = 0  # what became of the others: graph.counts
        qos = qos_profile_sensor_data if v["odom_qos"] == "sensor_data" else QoSProfile(depth=50)
        self.outputs: dict[tuple[str, str], _Outputs] = {}
        for robot, session, topic in entries:
            trajectory = (robot, session)
            self.outputs[trajectory] = _Outputs(self, f"{robot}/" if robot else "",
                                                v["odom_frame"])  # fmt: skip
            callback = functools.partial(self._on_odom, trajectory=trajectory)
            self.create_subscription(Odometry, topic, callback, qos)
        # Reliable and deep: loops are rare and each one matters (vpr_node publishes reliably).
        reliable = QoSProfile(depth=100)
        if len(entries) == 1:
            self.create_subscription(Odometry, v["loop_topic"], self._on_loop, reliable)
        for robot, session, _ in entries if len(entries) > 1 else ():
            # Each robot's vpr_node publishes its loops in its namespace: a loop within one
            # robot-session carries no identity in the factor message, so it is this robot's.
            owned = functools.partial(self._on_loop, owner=(robot, session))
            topic = f"/{robot}/{v['loop_topic'].lstrip('/')}"
            self.create_subscription(Odometry, topic, owned, reliable)
        self.create_timer(v["path_period"], self.publish_path)

    def _on_loop(self, msg: Odometry, owner: tuple[str, str] | None = None) -> None:
        self.loops_received += 1
        try:
            factor = factor_from_msg(msg)
        except ValueError as err:
            self.loops_undecodable += 1
            self.get_logger().warning(f"loop message skipped: {err}", throttle_duration_sec=5.0)
            return
        self.add_loop(own(factor, owner) if owner else factor)

    # ---- inputs --------------------------------------------------------------------------------
    def _on_odom(self, msg: Odometry, trajectory: tuple[str, str] = ("", "")) -> None:
        now = self.get_clock().now().nanoseconds * 1e-9  # for a publisher that never stamps
        stamp, pose = message_stamp(msg, now), message_pose(msg)
        reason = self.graph.add_odometry(stamp, pose, trajectory)
        if reason is not None:
            self.get_logger().warning(f"odometry at {stamp:.3f} s skipped: {reason}",
                                      throttle_duration_sec=5.0)  # fmt: skip
            return
        out = self.outputs[trajectory]
        out.odom_frame = out.odom_frame or msg.header.frame_id
        if self.graph.update():
            self._publish_correction(stamp)
        if not self.graph.joined(trajectory):
            return  # not in the map frame yet: nothing to correct it with
        corrected = self.graph.map_to_odom(trajectory).compose(pose3(pose))
        moved = Odometry(header=msg.header, child_frame_id=msg.child_frame_id)
        moved.header.frame_id = self.values["map_frame"]
        moved.pose.pose = _pose_msg(pose7(corrected))
        moved.twist = msg.twist  # in the child frame: unchanged by the correction
        out.odom.publish(moved)

    def add_loop(self, loop: LoopFactor) -> str:
        """Feed one loop into the graph and update; returns the graph's answer."""
        result = self.graph.add_loop(loop)
        if result not in ("added", "pending"):
            self.get_logger().warning(
                f"loop {loop.match_stamp:.3f} s -> {loop.query_stamp:.3f} s skipped: {result}",
                throttle_duration_sec=2.0,
            )
        elif self.graph.update():
            self._publish_correction(loop.query_stamp)
        return result

    # ---- outputs -------------------------------------------------------------------------------
    def _publish_correction(self, stamp: float) -> None:
        """``map_to_odom`` of every trajectory in the map frame (the graph moves them all)."""
        for trajectory, out in self.outputs.items():
            if not self.graph.joined(trajectory) or not len(self.graph.node_stamps(trajectory)):
                continue
            msg = TransformStamped()
            msg.header.stamp = _stamp_msg(stamp)
            msg.header.frame_id = self.values["map_frame"]
            msg.child_frame_id = out.odom_frame or "odom"
            x, y, z, qx, qy, qz, qw = pose7(self.graph.map_to_odom(trajectory))
            t, r = msg.transform.translation, msg.transform.rotation
            t.x, t.y, t.z, r.x, r.y, r.z, r.w = x, y, z, qx, qy, qz, qw
            out.map.publish(msg)

    def publish_path(self) -> None:
        """Publish each joined trajectory's optimised nodes as its ``corrected_path`` (nothing
        before its first node); when the odometry has stopped, also go on converging after a
        loop."""
        newest = [s[-1] for t in self.outputs if len(s := self.graph.node_stamps(t))]
        if not newest:
            return
        if self.graph.update():
            self._publish_correction(float(max(newest)))
        for trajectory, out in self.outputs.items():
            stamps = self.graph.node_stamps(trajectory)
            if len(stamps) and self.graph.joined(trajectory):
                out.path.publish(self._path(stamps, self.graph.optimised_poses(trajectory)))

    def _path(self, stamps, poses) -> Path:
        path = Path()
        path.header.frame_id = self.values["map_frame"]
        path.header.stamp = _stamp_msg(float(stamps[-1]))
        for stamp, pose in zip(stamps, poses, strict=True):
            item = PoseStamped(pose=_pose_msg(tuple(pose)))
            item.header.frame_id = path.header.frame_id
            item.header.stamp = _stamp_msg(float(stamp))
            path.poses.append(item)
        return path


class _Outputs:
    """One robot-session's publishers (``prefix``: '' for a single robot, else ``robot/``) and
    the frame of its odometry."""

    def __init__(self, node: Node, prefix: str, odom_frame: str) -> None:
        self.path = node.create_publisher(Path, f"{prefix}corrected_path", 1)
        self.map = node.create_publisher(TransformStamped, f"{prefix}map_to_odom", 10)
        self.odom = node.create_publisher(Odometry, f"{prefix}corrected_odom", 10)
        self.odom_frame = odom_frame


def main(argv: list[str] | None = None) -> int:
    """`posegraph_node` entry point: 0 on a clean stop (Ctrl-C, SIGTERM), 1 if it cannot start."""
    problem = params_file_problem(sys.argv if argv is None else argv)
    if problem:  # a missing file or a key given twice (rcl would keep the last without a word)
        rclpy.logging.get_logger(params.NODE_NAME).error(f"cannot start: {problem}")
        return 1
    try:
        rclpy.init(args=argv)
    except Exception as err:  # noqa: BLE001 - rcl's argument parser raises its own RCLError
        print(
            f"error: {params.NODE_NAME} cannot start: {err} (list parameters need one type: "
            "write camera_to_base:=[0.0, 0.0, 1.6, -0.5, 0.5, -0.5, 0.5])",
            file=sys.stderr,
        )
        return 1
    executor = SingleThreadedExecutor()
    node = None
    try:
        try:
            node = PoseGraphNode()
        except (PairVPRError, ParameterException) as err:
            rclpy.logging.get_logger(params.NODE_NAME).error(f"cannot start: {err}")
            return 1
        executor.add_node(node)
        node.get_logger().info(
            f"ready: odometry {node.values['odom_topic']}, loops {node.values['loop_topic']}"
        )
        executor.spin()
        return 0
    except (KeyboardInterrupt, ExternalShutdownException):
        return 0
    finally:
        executor.shutdown()
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":
    sys.exit(main())
