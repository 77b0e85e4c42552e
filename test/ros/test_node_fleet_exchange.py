"""Two vpr_nodes (robots "a" and "b", by namespace) exchanging over ROS 2 topics on this
machine: b revisits a place a saw, a (the owner) scores b's request and publishes the
inter-robot loop on its detail / json topics, never on the LIO-SAM pair topic."""

from __future__ import annotations

import json
import threading

import numpy as np
import pytest
import rclpy
from node_harness import EXACT, image_msg
from rclpy.executors import MultiThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile
from ros_cli import wait_for
from sensor_msgs.msg import Image
from std_msgs.msg import Float64MultiArray, String

from pair_vpr_ros.ros.node import VprNode

FLEET = dict(EXACT, fleet_enable=True, relative_pose=False, keyframe_max_similarity=0.99999,
             fleet_period=1.0)  # fmt: skip


def robot(ns: str, **overrides) -> VprNode:
    values = {**FLEET, **overrides}
    return VprNode(
        parameter_overrides=[Parameter(k, value=v) for k, v in values.items()],
        cli_args=["--ros-args", "-r", f"__ns:=/{ns}"],
    )


@pytest.fixture
def ros():
    rclpy.init()
    nodes: list = []
    executor = MultiThreadedExecutor(num_threads=6)
    yield nodes, executor
    executor.shutdown()
    for node in nodes:
        if isinstance(node, VprNode):
            node.shutdown()
        node.destroy_node()
    rclpy.try_shutdown()


@pytest.mark.parametrize("messages", ["typed", "bytes"])
def test_two_robots_close_a_loop_between_them_over_topics(ros, messages):
    if messages == "typed":
        pytest.importorskip("pair_vpr_ros_interfaces.msg")
    nodes, executor = ros
    a, b = robot("a", fleet_messages=messages), robot("b", fleet_messages=messages)
    assert a.fleet.typed == (messages == "typed")
    peer = rclpy.create_node("peer")
    nodes += [a, b, peer]
    got: dict[str, list] = {"json": [], "pair": []}
    peer.create_subscription(String, "/a/loop_closure/json", got["json"].append, 10)
    peer.create_subscription(Float64MultiArray, "/a/loop_closure", got["pair"].append, 10)
    pubs = {ns: peer.create_publisher(Image, f"/{ns}/image", QoSProfile(depth=50)) for ns in "ab"}
    for node in nodes:
        executor.add_node(node)
    threading.Thread(target=executor.spin, daemon=True).start()
    wait_for(lambda: all(p.get_subscription_count() >= 1 for p in pubs.values()))
    wait_for(lambda: a.fleet._pubs["keyframes"].get_subscription_count() >= 2)
    rng = np.random.default_rng(5)
    places = [rng.integers(0, 256, (48, 64, 3), dtype=np.uint8) for _ in range(4)]
    for i in range(3):
        pubs["a"].publish(image_msg(places[i], 100.0 + i))
    wait_for(lambda: len(b.fleet.exchange.store) >= 3)
    pubs["b"].publish(image_msg(places[3], 200.0))
    pubs["b"].publish(image_msg(places[1], 201.0))
    wait_for(lambda: got["json"], timeout=60.0)
    record = json.loads(got["json"][0].data)
    assert (record["query_id"], record["match_id"], record["accepted"]) == (1, 1, True)
    assert (record["query_stamp"], record["match_stamp"]) == (201.0, 101.0)
    assert got["pair"] == []  # two robots' clocks: not for LIO-SAM
    ex_b = b.fleet.exchange
    wait_for(lambda: ex_b.counts.loops_confirmed == 1)
    assert a.fleet.exchange.counts.loops_accepted == 1
    assert dict(ex_b.counts.skipped) == {} and ex_b.counts.sent["request"] == 1
    # bytes counted as serialized: the codec's, or CDR's for the typed message (+ overhead)
    n, d = a.pipeline.model.num_patches, a.pipeline.model.config.embed_dim
    assert n * d * 2 < ex_b.counts.sent_bytes["request"] < n * d * 2 + 400
    assert 1024 < ex_b.counts.sent_bytes["keyframes"] / ex_b.counts.sent["keyframes"] < 1536
    info = a.fleet.state()
    assert info["keyframes"] == 3 and info["peer_keyframes"] == {f"b/{ex_b.config.session}": 2}
