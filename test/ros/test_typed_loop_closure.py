"""`loop_closure/typed` (pair_vpr_ros_interfaces/LoopClosure) from a running `vpr_node`: a typed
subscriber gets every field of the loops the exact-match settings find, with and without a
relative pose (tiny random network, exact repeats as loops, see test_node.py), under the
resolved `loop_closure` name; a node process imports the package too."""

from __future__ import annotations

import json
import math
import os
import re
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest
import rclpy
from bag_fixtures import synthetic_images
from node_harness import wait_for
from std_msgs.msg import String
from test_node_geometry import GEOMETRY, run

from pair_vpr_ros.messages.factor import factor_from_msg
from pair_vpr_ros.messages.loop import JSON_TOPIC, POSE_STATUS_CODES, TYPED_TOPIC

ROOT = Path(__file__).resolve().parents[2]


def subscribe(h, msg_type, topic: str = TYPED_TOPIC) -> list:
    got: list = []
    h.peer.create_subscription(msg_type, topic, got.append, 50)
    wait_for(lambda: h.node.outputs.typed.get_subscription_count() >= 1)
    return got


def stamp(t) -> float:
    return t.sec + t.nanosec * 1e-9


def same_as_json(msg, record: dict) -> None:
    """Every field the json record has, equal in the typed message (NaN where it is null)."""
    for side in ("query", "match"):
        assert stamp(getattr(msg, f"{side}_stamp")) == record[f"{side}_stamp"]
        for name in ("id", "frame_id", "robot", "session"):
            assert getattr(msg, f"{side}_{name}") == record[f"{side}_{name}"]
    for name in ("pair_score", "global_similarity", "inlier_ratio"):
        value = getattr(msg, name)
        assert value == record[name] or (math.isnan(value) and record[name] is None), name
    for name in ("rank_before", "rank_after", "candidates", "scored", "inliers", "accepted",
                 "reason", "pose_reason", "pose_inliers"):  # fmt: skip
        assert getattr(msg, name) == record[name], name


def test_a_typed_subscriber_gets_every_field_of_each_loop(harness, typed_messages):
    h = harness(robot_id="rover_2", session_id="day1")
    got = subscribe(h, typed_messages.LoopClosure)
    records: list = []
    h.peer.create_subscription(String, JSON_TOPIC, records.append, 50)
    places = synthetic_images(4, size=32)
    h.publish([places[i] for i in (0, 1, 2, 3, 0, 2)])  # stamps 100 .. 105 s
    h.processed(6)
    wait_for(lambda: len(got) == 2 and len(records) == 2)
    msg = got[0]
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec, msg.header.frame_id) == (104, 0, "cam")
    assert [(m.query_id, m.match_id, m.query_stamp.sec, m.match_stamp.sec) for m in got] == [
        (4, 0, 104, 100),
        (5, 2, 105, 102),
    ]
    assert (msg.query_frame_id, msg.match_frame_id, msg.accepted, msg.reason) == (
        "cam", "cam", True, "",
    )  # fmt: skip
    assert (msg.rank_before, msg.rank_after, msg.candidates, msg.scored) == (1, 1, 1, 1)
    assert (msg.query_robot, msg.query_session, msg.match_robot, msg.match_session) == (
        "rover_2", "day1", "rover_2", "day1",
    )  # fmt: skip
    assert msg.pose_status == typed_messages.LoopClosure.POSE_NONE == 0
    assert (msg.pose_inliers, msg.inliers) == (-1, -1)
    pose = msg.relative_pose
    values = [pose.pose.position.x, pose.pose.orientation.w, *pose.covariance]
    assert len(pose.covariance) == 36 and all(math.isnan(v) for v in values)
    for m, r in zip(got, records, strict=True):
        same_as_json(m, json.loads(r.data))


def test_the_typed_pose_is_the_between_factor(harness, typed_messages):
    h = harness(**GEOMETRY)
    got = subscribe(h, typed_messages.LoopClosure)
    factors, records = run(h)  # places 0 1 2 0 with depth: one metric loop 103 s -> 100 s
    wait_for(lambda: len(got) == 1 and len(factors) == 1)
    msg, factor = got[0], factor_from_msg(factors[0])
    assert msg.pose_status == typed_messages.LoopClosure.POSE_METRIC
    assert msg.pose_inliers == factor.inliers >= 30
    p, q = msg.relative_pose.pose.position, msg.relative_pose.pose.orientation
    assert (p.x, p.y, p.z) == factor.translation
    assert (q.x, q.y, q.z, q.w) == factor.rotation
    assert tuple(msg.relative_pose.covariance) == factor.covariance
    assert msg.header.frame_id == factor.match_frame_id == "cam"
    same_as_json(msg, records[0])
    assert records[0]["pose_status"] == "metric"


def test_the_typed_topic_follows_the_remapped_base(harness, typed_messages):
    h = harness(remap="/lio_loop/loop_closure_detection")
    assert h.node.outputs.topics["typed"] == "/lio_loop/loop_closure_detection/typed"
    got = subscribe(h, typed_messages.LoopClosure, "/lio_loop/loop_closure_detection/typed")
    places = synthetic_images(3, size=32)
    h.publish([places[i] for i in (0, 1, 2, 0)])
    h.processed(4)
    wait_for(lambda: len(got) == 1)
    assert (got[0].query_id, got[0].match_id) == (3, 0)
    # the default identity: robot "robot" (no namespace), session the start time, UTC
    session = h.node.identity.session
    assert re.fullmatch(r"\d{8}T\d{6}Z", session)
    assert (got[0].query_robot, got[0].query_session, got[0].match_robot) == (
        "robot", session, "robot",
    )  # fmt: skip


@pytest.mark.slow
def test_a_node_process_publishes_the_typed_topic(typed_messages):
    env = {**os.environ, "RCUTILS_LOGGING_BUFFERED_STREAM": "0", "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen(
        [sys.executable, "-m", "pair_vpr_ros.ros.node", "--ros-args", "-p",
         "weights:=random-tiny", "-r", "loop_closure:=/lio/loops"],
        cwd=ROOT, env=env, text=True, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
    )  # fmt: skip
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(proc.stdout), daemon=True)
    reader.start()
    rclpy.init()
    try:
        probe = rclpy.create_node("probe")
        want = ("/lio/loops/typed", ["pair_vpr_ros_interfaces/msg/LoopClosure"])
        wait_for(lambda: want in probe.get_topic_names_and_types() or proc.poll() is not None)
        assert proc.poll() is None, "".join(lines)
        probe.destroy_node()
    finally:
        rclpy.try_shutdown()
        proc.terminate()
        proc.wait(30.0)
        reader.join(10.0)
    assert "is off" not in "".join(lines)


def test_message_sizes_on_the_wire(typed_messages):
    from rclpy.serialization import serialize_message

    m = typed_messages
    ids = dict(robot="robot_a", session="20261125T155000Z", model=list(range(8)))
    desc = np.linspace(-1, 1, 512).astype("<f2")
    descriptor = m.KeyframeDescriptor(**ids, keyframe_id=12345, dim=512, descriptor=desc.tobytes())
    assert len(serialize_message(descriptor)) == 1100 <= 1536  # the fleet budget, 1.5 KB
    tokens = np.zeros((529, 768), "<f2")  # ViT-B at 322 px
    request = m.ScoreRequest(
        **ids, request_id=1, owner_robot="robot_b", owner_session="20261125T160000Z",
        query_id=7, candidate_ids=list(range(5)), global_similarities=[0.5] * 5,
        token_count=529, token_dim=768, dense_tokens=tokens.tobytes(),
    )  # fmt: skip
    assert len(serialize_message(request)) - tokens.nbytes == 196  # all but the tokens
    response = m.ScoreResponse(
        **ids, request_id=1, requester_robot="robot_b", requester_session="20261125T160000Z",
        query_id=7, match_id=3, pair_score=2.5, scored=5, accepted=True, pose_status=1,
    )  # fmt: skip
    assert len(serialize_message(response)) == 123
    assert len(serialize_message(m.LoopClosure())) == 524  # 516 + the two rig camera ids


def test_pose_status_codes_are_the_message_constants(typed_messages):
    """The node (loop_messages) and the fleet (ros/fleet.py) fill pose_status from
    POSE_STATUS_CODES: its values must be LoopClosure's POSE_* constants."""
    cls = typed_messages.LoopClosure
    assert POSE_STATUS_CODES == {
        "": cls.POSE_NONE,
        "metric": cls.POSE_METRIC,
        "scale-free": cls.POSE_SCALE_FREE,
        "metric-odometry": cls.POSE_METRIC_ODOMETRY,
    }
