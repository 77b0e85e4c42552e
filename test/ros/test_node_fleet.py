"""vpr_node with an identity (robot_id, session_id) and prior maps (prior_map_dirs), issue 22."""

from __future__ import annotations

import json

import pytest
import rclpy
from bad_input import saved_map_digest
from bag_fixtures import synthetic_images
from nav_msgs.msg import Odometry
from node_harness import EXACT, stamp_msg
from rclpy.parameter import Parameter
from ros_cli import wait_for
from std_srvs.srv import Trigger

from pair_vpr_ros.errors import ConfigError
from pair_vpr_ros.messages.loop import detail_text
from pair_vpr_ros.ros.node import VprNode


@pytest.fixture(scope="module")
def places():
    return synthetic_images(6, size=32)


def test_identity_and_a_prior_map(harness, places, tmp_path):
    first = harness(robot_id="r3", session_id="mon", map_dir=str(tmp_path / "map"))
    first.publish([places[i] for i in (0, 1, 2, 3, 4, 0)])
    first.processed(6)
    wait_for(lambda: len(first.got["loop_closure/json"]) == 1)
    record = json.loads(first.got["loop_closure/json"][0].data)
    assert [record[k] for k in ("query_robot", "query_session", "match_robot")] == [
        "r3", "mon", "r3",
    ]  # fmt: skip
    assert first.call(Trigger, "save_map").success
    first.close()
    before = saved_map_digest(tmp_path / "map")

    second = harness(
        robot_id="r3", session_id="tue", prior_map_dirs=[str(tmp_path / "map")],
        map_dir=str(tmp_path / "map"),
    )  # fmt: skip
    assert second.node.summary.endswith("robot r3, session tue, 1 prior maps")
    info = json.loads(second.call(Trigger, "map_info").message)
    assert (info["robot"], info["session"], info["keyframes"]) == ("r3", "tue", 0)
    assert info["prior_maps"] == [
        {"dir": str(tmp_path / "map"), "keyframes": 6, "sessions": {"r3/mon": 6}}
    ]
    second.publish([places[1]])  # the same stamps as monday's place 1: found at once
    second.processed(1)
    wait_for(lambda: len(second.got["loop_closure/json"]) == 1)
    record = json.loads(second.got["loop_closure/json"][0].data)
    assert (record["match_id"], record["match_session"], record["query_session"]) == (
        1, "mon", "tue",
    )  # fmt: skip
    labels = [d.label for d in second.got["loop_closure/detail"][0].layout.dim]
    assert detail_text(labels)["match_session"] == "mon"
    assert second.got["loop_closure"] == []  # another session: no LIO-SAM pair
    for service in ("save_map", "load_map", "build_map"):
        refused = second.call(Trigger, service)
        assert not refused.success and "is a prior map (loaded read-only)" in refused.message
    assert saved_map_digest(tmp_path / "map") == before


def test_robot_id_defaults_to_the_namespace_and_a_missing_prior_map_stops_the_start(tmp_path):
    rclpy.init()
    try:
        values = {**EXACT, "session_id": "s1"}
        overrides = [Parameter(k, value=v) for k, v in values.items()]
        node = VprNode(namespace="/fleet/r9", parameter_overrides=overrides, start_worker=False)
        assert (node.identity.robot, node.identity.session) == ("fleet_r9", "s1")
        node.shutdown()
        node.destroy_node()
        missing = Parameter("prior_map_dirs", value=[str(tmp_path / "none")])
        with pytest.raises(ConfigError, match="prior map .*none does not exist or is not a"):
            VprNode(parameter_overrides=[*overrides, missing], start_worker=False)
    finally:
        rclpy.try_shutdown()


def odometry(h, stamps):
    """Publish an odometry message at each stamp (x = the stamp's offset) and wait for them."""
    odom = h.peer.create_publisher(Odometry, "odom", 50)
    wait_for(lambda: odom.get_subscription_count() >= 1)
    for x, t in enumerate(stamps):
        msg = stamp_msg(Odometry(), t, "map")
        msg.pose.pose.position.x, msg.pose.pose.orientation.w = float(x), 1.0
        odom.publish(msg)
    wait_for(lambda: len(h.node.poses) == len(stamps))


def test_a_keyframe_publishes_a_loop_into_each_map(harness, places, tmp_path):
    # loop_per_map (default): the live map and the prior map each give at most one loop
    first = harness(
        robot_id="r3", session_id="mon", map_dir=str(tmp_path / "map"), pose_topic="odom"
    )
    odometry(first, [100.0, 101.0, 102.0])
    first.publish([places[i] for i in (0, 1, 2)])
    first.processed(3)
    assert first.call(Trigger, "save_map").success
    first.close()
    second = harness(
        robot_id="r3", session_id="tue", prior_map_dirs=[str(tmp_path / "map")],
        pose_topic="odom",
    )  # fmt: skip
    odometry(second, [200.0 + i for i in range(5)])
    second.publish([places[i] for i in (0, 4, 5, 3, 0)], t0=200.0)
    second.processed(5)
    # t=200: monday's place 0; t=204: monday's and tuesday's own (4 s back: beyond the 2.5 s)
    wait_for(lambda: len(second.got["loop_closure/json"]) == 3)
    records = [json.loads(m.data) for m in second.got["loop_closure/json"]]
    assert [(r["query_id"], r["match_session"], r["match_id"]) for r in records] == [
        (0, "mon", 0), (4, "tue", 0), (4, "mon", 0),
    ]  # fmt: skip
    assert [list(m.data) for m in second.got["loop_closure"]] == [[204.0, 200.0]]  # LIO-SAM
    counts = second.node.stats.counts  # loops into other sessions: no pair, counted apart
    assert (counts.loops, counts.loops_unordered) == (1, 2)
    # a marker for each loop, each with an id of its own (both poses: from each keyframe's map)
    wait_for(lambda: len(second.got["loop_closure/markers"]) == 3)
    lines = [m.markers[0] for m in second.got["loop_closure/markers"]]
    assert [line.id for line in lines] == [1, 2, 3]
    assert [[(p.x, p.y) for p in line.points] for line in lines] == [
        [(0.0, 0.0), (0.0, 0.0)], [(4.0, 0.0), (0.0, 0.0)], [(4.0, 0.0), (0.0, 0.0)],
    ]  # fmt: skip
