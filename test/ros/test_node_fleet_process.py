"""Two vpr_node processes (robots "a" and "b" by namespace) exchange over localhost: b's
revisit of a place a saw becomes an inter-robot loop that a publishes."""

from __future__ import annotations

import json
import os
import time

import numpy as np
import pytest
import rclpy
import test_node_process
from node_harness import image_msg
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import Image
from std_msgs.msg import String, UInt8MultiArray
from std_srvs.srv import Trigger
from test_node_process import start

from pair_vpr_ros.fleet import decode

pytestmark = pytest.mark.slow  # two node processes

PARAMS = dict(weights="random-tiny", global_floor=0.99999, score_threshold=-1e6,
              keyframe_max_similarity=0.99999, exclude_recent_s=2.5, exclude_recent_keyframes=1,
              top_k=1, min_frame_interval=0.0, qos="reliable", queue_size=50,
              relative_pose=False, fleet_enable=True, fleet_messages="bytes",
              fleet_period=1.0)  # fmt: skip


def node_args(ns: str) -> list[str]:
    args = ["-r", f"__ns:=/{ns}"]
    for k, v in PARAMS.items():
        args += ["-p", f"{k}:={str(v).lower() if isinstance(v, bool) else v}"]
    return args


def test_two_node_processes_find_a_loop_between_them(monkeypatch):
    # the processes must share this test's ROS_DOMAIN_ID (set per test by conftest)
    monkeypatch.setattr(test_node_process, "ENV", {**test_node_process.ENV, **os.environ})
    procs = [start(*node_args(ns)) for ns in "ab"]
    rclpy.init()
    peer = rclpy.create_node("fleet_peer")
    try:
        got, heard = [], []
        peer.create_subscription(String, "/a/loop_closure/json", got.append, 10)
        qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)

        def on_descriptor(msg: UInt8MultiArray) -> None:
            heard.append(decode(bytes(msg.data)).robot)

        peer.create_subscription(UInt8MultiArray, "/fleet/keyframes", on_descriptor, qos)
        pubs = {ns: peer.create_publisher(Image, f"/{ns}/image", QoSProfile(depth=50))
                for ns in "ab"}  # fmt: skip

        def spin_until(cond, timeout=60.0):
            end = time.monotonic() + timeout
            while not cond() and time.monotonic() < end:
                rclpy.spin_once(peer, timeout_sec=0.1)
            return cond()

        assert spin_until(lambda: all(p.get_subscription_count() >= 1 for p in pubs.values()))
        rng = np.random.default_rng(5)
        places = [rng.integers(0, 256, (48, 64, 3), dtype=np.uint8) for _ in range(4)]
        for i in range(3):
            pubs["a"].publish(image_msg(places[i], 100.0 + i))
        assert spin_until(lambda: heard.count("a") >= 3)
        # b has them in its peer store (map_info), not only on the wire, before it revisits
        client = peer.create_client(Trigger, "/b/vpr_node/map_info")
        assert client.wait_for_service(timeout_sec=30.0)

        def b_holds_a() -> bool:
            future = client.call_async(Trigger.Request())
            spin_until(future.done, timeout=10.0)
            info = json.loads(future.result().message) if future.done() else {}
            held = info.get("fleet", {}).get("peer_keyframes", {})
            return sum(n for owner, n in held.items() if owner.startswith("a/")) >= 3

        assert spin_until(b_holds_a)
        pubs["b"].publish(image_msg(places[3], 200.0))
        pubs["b"].publish(image_msg(places[1], 201.0))
        assert spin_until(lambda: got), "".join(x for _, _, ls in procs for x in ls)
        record = json.loads(got[0].data)
        assert (record["query_id"], record["match_id"], record["accepted"]) == (1, 1, True)
        assert (record["query_stamp"], record["match_stamp"]) == (201.0, 101.0)
    finally:
        peer.destroy_node()
        rclpy.try_shutdown()
        for proc, reader, lines in procs:
            proc.terminate()
            assert proc.wait(30.0) == 0, "".join(lines)
            reader.join(10.0)
    out = "".join(line for _, _, lines in procs for line in lines)
    assert "fleet exchange on as robot 'a'" in out and "Traceback" not in out
    assert "inter-robot loop: b keyframe 1 -> a keyframe 1" in out
