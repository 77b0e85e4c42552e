"""`posegraph_node` in-process: drifting odometry and loop_closure/factor messages in, a corrected
path, map->odom and corrected odometry out."""

from __future__ import annotations

import importlib
import os
import signal
import subprocess
import sys
import threading
import time
from collections import defaultdict

import drives
import numpy as np
import pytest
import rclpy
from geometry_msgs.msg import TransformStamped
from nav_msgs.msg import Odometry, Path
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile
from ros_cli import wait_for

from pair_vpr_ros.errors import ConfigError
from pair_vpr_ros.messages.factor import FACTOR_MSG_TYPES, factor_msg
from pair_vpr_ros.posegraph.simulate import ground_truth_loops
from pair_vpr_ros.posegraph.transforms import pose3
from pair_vpr_ros.ros import posegraph_node
from pair_vpr_ros.ros.posegraph_node import PoseGraphNode

CLASSES = {
    name: getattr(importlib.import_module(".".join(name.split("/")[:2])), name.split("/")[2])
    for name in FACTOR_MSG_TYPES
}


def odom_msg(stamp: float, pose) -> Odometry:
    msg = Odometry(child_frame_id="base_link")
    msg.header.frame_id = "odom"
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(round(stamp * 1e9), 10**9)
    p, q = msg.pose.pose.position, msg.pose.pose.orientation
    p.x, p.y, p.z, q.x, q.y, q.z, q.w = (float(v) for v in pose)
    return msg


@pytest.fixture
def ros():
    rclpy.init()
    yield
    rclpy.try_shutdown()


class Harness:
    def __init__(self, **overrides) -> None:
        values = {"odom_qos": "reliable", "path_period": 0.1, **overrides}
        self.node = PoseGraphNode(
            parameter_overrides=[Parameter(k, value=v) for k, v in values.items()]
        )
        self.peer = rclpy.create_node("peer")
        self.got: dict[str, list] = defaultdict(list)
        for topic, kind in (("corrected_path", Path), ("map_to_odom", TransformStamped),
                            ("corrected_odom", Odometry)):  # fmt: skip
            self.peer.create_subscription(kind, topic, self.got[topic].append, 100)
        self.odom = self.peer.create_publisher(Odometry, "odom", QoSProfile(depth=1000))
        self.loops = self.peer.create_publisher(Odometry, "loop_closure/factor", 100)
        self.executor = SingleThreadedExecutor()
        for node in (self.node, self.peer):
            self.executor.add_node(node)
        self.thread = threading.Thread(target=self.executor.spin, daemon=True)
        self.thread.start()
        wait_for(lambda: self.odom.get_subscription_count() >= 1)
        wait_for(lambda: self.loops.get_subscription_count() >= 1)

    def close(self) -> None:
        self.executor.shutdown()
        self.thread.join(5.0)
        self.node.destroy_node()
        self.peer.destroy_node()


def test_odometry_and_loops_in_corrected_path_out(ros):
    stamps, truth, odometry, pairs = drives.drive()
    loops = ground_truth_loops(stamps, truth, pairs, np.random.default_rng(0),
                               camera_to_base=drives.CAMERA)  # fmt: skip
    h = Harness(camera_to_base=list(drives.CAMERA))
    try:
        k = 0
        for i, (stamp, pose) in enumerate(zip(stamps, odometry, strict=True)):
            if i % 25 == 0:  # let the node keep up, as with a real 10 Hz odometry
                wait_for(lambda i=i: h.node.graph.counts.odometry >= i)
            h.odom.publish(odom_msg(stamp, pose))
            while k < len(loops) and loops[k].query_stamp <= stamp:
                h.loops.publish(factor_msg(loops[k], CLASSES))
                k += 1
        wait_for(lambda: h.node.graph.counts.odometry == len(stamps))
        wait_for(lambda: h.node.graph.counts.loops_added == len(loops))
        nodes = h.node.graph.counts.nodes
        wait_for(
            lambda: h.got["corrected_path"] and len(h.got["corrected_path"][-1].poses) == nodes
        )
        wait_for(lambda: len(h.got["corrected_odom"]) == len(stamps))
    finally:
        h.close()
    path = h.got["corrected_path"][-1]
    assert path.header.frame_id == "map" and path.poses[-1].header.frame_id == "map"
    xy = np.array([(p.pose.position.x, p.pose.position.y) for p in path.poses])
    index = np.searchsorted(stamps, h.node.graph.node_stamps())
    before = np.sqrt(np.mean(np.sum((odometry[index, :2] - truth[index, :2]) ** 2, axis=1)))
    after = np.sqrt(np.mean(np.sum((xy - truth[index, :2]) ** 2, axis=1)))
    assert before > 5.0 and after < before / 10, (before, after)
    correction = h.got["map_to_odom"][-1]
    assert (correction.header.frame_id, correction.child_frame_id) == ("map", "odom")
    assert abs(correction.transform.translation.x) + abs(correction.transform.translation.y) > 1.0
    last = h.got["corrected_odom"][-1]
    assert (last.header.frame_id, last.child_frame_id) == ("map", "base_link")
    end = np.array([last.pose.pose.position.x, last.pose.pose.position.y])
    assert (
        np.linalg.norm(end - truth[-1, :2]) < np.linalg.norm(odometry[-1, :2] - truth[-1, :2]) / 5
    )


def test_bad_odometry_and_loop_messages_are_counted_not_fatal(ros):
    h = Harness()
    try:
        h.odom.publish(odom_msg(1.0, (0, 0, 0, 0, 0, 0, 1)))
        h.odom.publish(odom_msg(2.0, (float("nan"), 0, 0, 0, 0, 0, 1)))
        h.odom.publish(odom_msg(3.0, (1, 0, 0, 0, 0, 0, 1)))
        junk = Odometry()  # status code 0: not a factor message
        h.loops.publish(junk)
        wait_for(lambda: h.node.graph.counts.odometry == 2)
        wait_for(lambda: h.node.loops_undecodable == 1)
    finally:
        h.close()
    assert h.node.graph.counts.skipped == {"odometry: pose has NaN or infinite values": 1}


def test_bad_parameters_refuse_to_start(ros):
    with pytest.raises(ConfigError, match="camera_to_base must be a list of 7 numbers"):
        PoseGraphNode(parameter_overrides=[Parameter("camera_to_base", value=[0.0] * 6)])
    with pytest.raises(ConfigError, match="loop_kernel='l2' must be one of cauchy, huber, none"):
        PoseGraphNode(parameter_overrides=[Parameter("loop_kernel", value="l2")])


def test_a_parameter_file_with_a_key_twice_refuses_to_start(tmp_path, capfd):
    path = tmp_path / "posegraph.yaml"
    path.write_text("/**:\n  ros__parameters:\n    loop_kernel: cauchy\n    loop_kernel: huber\n")
    assert posegraph_node.main(["posegraph_node", "--ros-args", "--params-file", str(path)]) == 1
    assert (
        f"[posegraph_node]: cannot start: --params-file {path}: 'loop_kernel' is given twice "
        "(lines 3 and 4): keep one (YAML would use the last one without a word)"
    ) in capfd.readouterr().err
    missing = tmp_path / "nowhere.yaml"
    assert (
        posegraph_node.main(["posegraph_node", "--ros-args", "--params-file", str(missing)]) == 1
    )
    assert f"cannot start: --params-file {missing} does not exist" in capfd.readouterr().err


@pytest.mark.slow
def test_process_stops_cleanly_and_refuses_bad_parameters():
    env = {**os.environ, "RCUTILS_LOGGING_BUFFERED_STREAM": "0", "PYTHONUNBUFFERED": "1"}
    node = [sys.executable, "-m", "pair_vpr_ros.ros.posegraph_node", "--ros-args"]
    bad = subprocess.run([*node, "-p", "loop_kernel:=l2"], env=env, capture_output=True,
                         text=True, timeout=60)  # fmt: skip
    errors = [line for line in bad.stderr.splitlines() if line.strip()]
    assert bad.returncode == 1 and len(errors) == 1 and "Traceback" not in bad.stderr
    assert errors[0].endswith(
        "[posegraph_node]: cannot start: invalid parameters: loop_kernel='l2' must be one of "
        "cauchy, huber, none"
    )
    mixed = subprocess.run([*node, "-p", "camera_to_base:=[0, 0, 1.6, -0.5, 0.5, -0.5, 0.5]"],
                           env=env, capture_output=True, text=True, timeout=60)  # fmt: skip
    assert mixed.returncode == 1 and "Traceback" not in mixed.stderr
    assert "\nerror: posegraph_node cannot start: failed to initialize rcl" in mixed.stderr
    assert "write camera_to_base:=[0.0, 0.0, 1.6" in mixed.stderr
    node += ["-p", "camera_to_base:=[0.0, 0.0, 1.6, -0.5, 0.5, -0.5, 0.5]"]
    proc = subprocess.Popen(node, env=env, text=True, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT)  # fmt: skip
    lines = []
    for line in proc.stdout:
        lines.append(line)
        if "ready:" in line:
            break
    time.sleep(0.3)
    proc.send_signal(signal.SIGINT)
    assert proc.wait(30.0) == 0, "".join(lines)
    assert "ready: odometry odom, loops loop_closure/factor" in "".join(lines)


def test_several_robots_one_graph_outputs_per_robot(ros):
    """trajectories = 'a/s1=/a/odom, b/s1=/b/odom': odometry of each on its topic, loops naming
    the robots in the factor message; b's outputs appear once it has joined a's frame."""
    import fleet_drives as fd

    from pair_vpr_ros.messages.factor import factor_from_msg

    a, b = fd.robot(0, seed=1), fd.robot(60, seed=2)
    rng = np.random.default_rng(0)
    loops = fd.loops(b, a, ("b", "s1"), ("a", "s1"), 60, rng, start=100)
    node = PoseGraphNode(parameter_overrides=[
        Parameter("trajectories", value="a/s1=/a/odom, b/s1=/b/odom"),
        Parameter("camera_to_base", value=list(drives.CAMERA)),
    ])  # fmt: skip
    try:
        out = node.outputs[("b", "s1")]
        assert (out.path.topic_name, out.map.topic_name, out.odom.topic_name) == (
            "/b/corrected_path", "/b/map_to_odom", "/b/corrected_odom"
        )  # fmt: skip
        k = 0
        for i, stamp in enumerate(a[0]):
            node._on_odom(odom_msg(stamp, a[2][i]), trajectory=("a", "s1"))
            node._on_odom(odom_msg(stamp, b[2][i]), trajectory=("b", "s1"))
            while k < len(loops) and loops[k].query_stamp <= stamp:
                assert node.add_loop(factor_from_msg(factor_msg(loops[k], CLASSES))) in (
                    "added", "waiting", "pending"
                )  # fmt: skip
                k += 1
        node.publish_path()
        assert node.graph.joined(("b", "s1")) and node.graph.counts.loops_added == len(loops)
        # b's own loop on /b/loop_closure/factor: no identity in the message, b's by its topic
        own = fd.loops(b, b, ("b", "s1"), ("b", "s1"), 0, rng, start=b[3], stop=b[3] + 1)[0]
        msg = factor_msg(own, CLASSES)
        assert msg.child_frame_id == "camera"
        node._on_loop(msg, owner=("b", "s1"))
        assert node.graph.loops[-1].factor.query_robot == "b"
        assert node.graph.counts.loops_added == len(loops) + 1
        assert fd.world_error(node.graph, ("b", "s1"), b, a) < 1.0
    finally:
        node.destroy_node()


def test_a_robot_twice_refuses_to_start(ros):
    with pytest.raises(ConfigError, match="trajectories: a robot is given twice"):
        PoseGraphNode(parameter_overrides=[
            Parameter("trajectories", value="a/s1=/a/odom, a/s2=/a2/odom")
        ])  # fmt: skip


def test_prior_map_sessions_are_the_map_frame_a_live_robot_relocalises_into(ros, tmp_path):
    """prior_map_dirs: the saved map's robot-session (a/day1, its keyframe poses) is the map
    frame; the single live robot's loops into its keyframes are added, not skipped, and its
    corrected odometry lands in a/day1's frame."""
    import fleet_drives as fd
    from map_fixtures import prior_drive_map

    from pair_vpr_ros.messages.factor import factor_from_msg

    a, b = fd.robot(0, seed=1, laps=1), fd.robot(60, seed=2, laps=1)
    A, B = ("a", "day1"), ("b", "s1")
    loops = fd.loops(b, a, B, A, 60, np.random.default_rng(0), every=5)
    prior = prior_drive_map(tmp_path / "a_day1", a, without_pose={7})
    node = PoseGraphNode(parameter_overrides=[
        Parameter("prior_map_dirs", value=[prior]),
        Parameter("camera_to_base", value=list(drives.CAMERA)),
    ])  # fmt: skip
    try:
        assert [t.trajectory for t in node.graph.tracks] == [A, ("", "")]
        assert list(node.outputs) == [("", "")]  # no outputs of a prior session
        assert node.graph.counts.skipped == {"prior keyframe: no pose": 1}
        k = 0
        for stamp, pose in zip(b[0], b[2], strict=True):
            node._on_odom(odom_msg(stamp, pose))
            while k < len(loops) and loops[k].query_stamp <= stamp:
                msg = factor_msg(loops[k], CLASSES)
                assert "@b@s1" in msg.child_frame_id and "@a@day1" in msg.header.frame_id
                assert node.add_loop(factor_from_msg(msg)) in ("added", "waiting")
                k += 1
        node.publish_path()
        assert node.graph.counts.loops_added == len(loops)
        assert node.graph.counts.skipped == {"prior keyframe: no pose": 1}
        assert node.graph.joined(("", ""))
        assert fd.world_error(node.graph, ("", ""), b, a) < 1.0
        # corrected odometry at the last stamp, in the prior frame: map_to_odom * odometry
        end = node.graph.map_to_odom(("", "")).compose(pose3(b[2][-1])).translation()[:2]
        truth = pose3(a[1][0]).inverse().compose(pose3(b[1][-1])).translation()[:2]
        assert np.linalg.norm(end - truth) < 1.0 < np.linalg.norm(b[2][-1][:2] - truth)
    finally:
        node.destroy_node()


def test_a_prior_session_given_live_or_a_missing_map_refuses_to_start(ros, tmp_path, capfd):
    import fleet_drives as fd
    from map_fixtures import prior_drive_map

    prior = prior_drive_map(tmp_path / "a_day1", fd.robot(0, seed=1, laps=1))
    with pytest.raises(ConfigError, match="trajectories: robot-session a/day1 is a prior session"):
        PoseGraphNode(parameter_overrides=[
            Parameter("prior_map_dirs", value=[prior]),
            Parameter("trajectories", value="a/day1=/a/odom"),
        ])  # fmt: skip
    rclpy.try_shutdown()
    missing = tmp_path / "nowhere"
    argv = ["posegraph_node", "--ros-args", "-p", f"prior_map_dirs:=['{missing}']"]
    assert posegraph_node.main(argv) == 1
    assert (
        f"[posegraph_node]: cannot start: prior_map_dirs: {missing} does not exist or is not a "
        "folder: give the folder of a saved place map (vpr_node's save_map, a replay's map/)"
    ) in capfd.readouterr().err
