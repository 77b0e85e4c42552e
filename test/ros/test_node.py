"""`vpr_node` in-process with pip rclpy and a tiny random network.

Random-init descriptors are nearly collinear, so the detector settings let only identical images
through (revisits are exact repeats), as in test_pipeline.py. A peer node publishes the inputs,
listens to every output and calls the services; both spin in one executor thread.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import rclpy
from bag_fixtures import synthetic_images, write_rosbag2
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
from nav_msgs.msg import Odometry
from node_harness import diagnostics, image_msg, stamp_msg, wait_for
from sensor_msgs.msg import CompressedImage
from std_srvs.srv import SetBool, Trigger

from pair_vpr_ros.errors import MapError
from pair_vpr_ros.messages.factor import LoopFactor, factor_from_msg, factor_msg
from pair_vpr_ros.messages.loop import DETAIL_LABELS, detail_to_dict
from pair_vpr_ros.params.table import PARAMS
from pair_vpr_ros.place_map import PlaceMap
from pair_vpr_ros.ros.node import VprNode
from pair_vpr_ros.ros.outputs import message_classes as _message_classes
from pair_vpr_ros.ros.parameters import read_value
from pair_vpr_ros.ros.runtime import diagnostic_values
from pair_vpr_ros.types import message_pose


def saved_keyframes(path: Path) -> int | None:
    try:
        with PlaceMap.load(path, read_only=True) as saved:
            return len(saved)
    except MapError:
        return None


@pytest.fixture(scope="module")
def places():
    return synthetic_images(6, size=32)


def test_revisit_gives_exactly_the_expected_loop_on_every_topic(harness, places):
    h = harness(pose_topic="odom")
    odom = h.peer.create_publisher(Odometry, "odom", 50)
    wait_for(lambda: odom.get_subscription_count() >= 1)
    for t in range(9):
        msg = stamp_msg(Odometry(), 100.0 + t, "map")
        msg.pose.pose.position.x, msg.pose.pose.orientation.w = float(t), 1.0
        odom.publish(msg)
    wait_for(lambda: len(h.node.poses) == 9)
    # place 5 repeats at once (a near-duplicate keyframe, no loop); 0 and 2 are revisited.
    h.publish([places[i] for i in (0, 1, 2, 3, 4, 5, 5, 0, 2)])
    h.processed(9)
    wait_for(lambda: len(h.got["loop_closure/markers"]) == 2)
    assert [list(m.data) for m in h.got["loop_closure"]] == [[107.0, 100.0], [108.0, 102.0]]
    details = [
        detail_to_dict([d.label for d in m.layout.dim], m.data)
        for m in h.got["loop_closure/detail"]
    ]
    assert [(d["query_id"], d["match_id"], d["accepted"]) for d in details] == [
        (6.0, 0.0, 1.0),
        (7.0, 2.0, 1.0),
    ]
    assert list(details[0]) == list(DETAIL_LABELS)
    records = [json.loads(m.data) for m in h.got["loop_closure/json"]]
    assert [(r["query_stamp"], r["match_stamp"], r["query_frame_id"]) for r in records] == [
        (107.0, 100.0, "cam"),
        (108.0, 102.0, "cam"),
    ]
    line = h.got["loop_closure/markers"][0].markers[0]
    assert [(p.x, p.y) for p in line.points] == [(7.0, 0.0), (0.0, 0.0)]
    assert line.header.frame_id == "map"
    wait_for(lambda: diagnostics(h).get("loops") == "2")
    values = diagnostics(h)
    assert (values["frames_received"], values["map_size"], values["frames_dropped"]) == (
        "9",
        "8",
        "0",
    )
    assert (values["frames_similar_to_keyframe"], values["frames_rate_limited"]) == ("1", "0")
    per_keyframe = h.node.maps.state.bytes_per_keyframe
    assert per_keyframe == h.node.pipeline.place_map.bytes_per_keyframe > 0
    assert (values["bytes_per_keyframe"], values["map_bytes"]) == (
        str(per_keyframe),
        str(8 * per_keyframe),
    )


def test_every_encoding_reaches_the_queue_as_the_same_rgb(harness, places):
    h = harness(start_worker=False, compressed_image_topic="image/compressed")
    rgb = places[0]
    grey = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    bayer = rgb[:, :, 1].copy()
    yuyv = np.random.default_rng(1).integers(0, 256, (32, 64), dtype=np.uint8)
    padded = np.zeros((32, 32 * 3 + 8), np.uint8)
    padded[:, : 32 * 3] = rgb.reshape(32, -1)
    sent = {
        1.0: (image_msg(rgb, 1.0), rgb),
        2.0: (image_msg(rgb, 2.0, encoding="bgr8", data=rgb[:, :, ::-1].tobytes()), rgb),
        3.0: (image_msg(rgb, 3.0, encoding="mono8", data=grey.tobytes()), np.dstack([grey] * 3)),
        4.0: (
            image_msg(rgb, 4.0, encoding="bayer_rggb8", data=bayer.tobytes()),
            cv2.cvtColor(bayer, cv2.COLOR_BayerRGGB2RGB),
        ),
        5.0: (
            image_msg(rgb, 5.0, encoding="yuyv", data=yuyv.tobytes()),
            cv2.cvtColor(yuyv.reshape(32, 32, 2), cv2.COLOR_YUV2RGB_YUY2),
        ),
        6.0: (image_msg(rgb, 6.0, data=padded.tobytes()), rgb),
    }
    for msg, _ in sent.values():
        h.pub.publish(msg)
    compressed = h.peer.create_publisher(CompressedImage, "image/compressed", 10)
    wait_for(lambda: compressed.get_subscription_count() >= 1)
    png = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))[1].tobytes()
    compressed.publish(stamp_msg(CompressedImage(format="png", data=png), 7.0))
    sent[7.0] = (None, rgb)
    wait_for(lambda: len(h.node.frames) == 7)
    frames = {frame.stamp: frame for frame, _ in h.node.frames.snapshot()}
    assert sorted(frames) == sorted(sent)
    for stamp, (_, expected) in sent.items():
        assert np.array_equal(frames[stamp].rgb, expected), stamp
    assert frames[7.0].source == "image/compressed" and frames[1.0].frame_id == "cam"


def test_malformed_frames_are_counted_and_skipped(harness, places):
    # best effort hears the reliable publisher; 32 x 32 images pass the pixel limit, 64 x 64 not
    h = harness(qos="sensor_data", max_image_pixels=2000)
    rgb = places[0]
    h.pub.publish(image_msg(rgb, 1.0, data=rgb.tobytes()[:-10]))  # short buffer
    h.pub.publish(image_msg(rgb, 2.0, encoding="jpeg2000"))
    h.pub.publish(image_msg(np.zeros((64, 64, 3), np.uint8), 2.5))
    h.publish([places[1]], t0=3.0)
    h.processed(1)
    wait_for(lambda: h.node.stats.counts.invalid == 3)
    assert h.node.stats.counts.received == 4 and h.node.maps.size() == 1
    wait_for(lambda: any(m.status[0].level == b"\x01" for m in h.got["/diagnostics"]))
    warned = next(m.status[0] for m in h.got["/diagnostics"] if m.status[0].level == b"\x01")
    assert "3 frames invalid" in warned.message


def test_non_finite_poses_are_counted_and_skipped(harness):
    h = harness(start_worker=False, pose_topic="odom")
    for i, x in enumerate((1.0, float("nan"), float("inf"), 4.0)):
        msg = stamp_msg(Odometry(), 10.0 + i)
        msg.pose.pose.position.x, msg.pose.pose.orientation.w = x, 1.0
        h.node._on_pose(msg)  # the subscription's callback, without the transport
    assert len(h.node.poses) == 2 and h.node.stats.counts.bad_poses == 2
    assert h.node.poses.nearest(11.0, 0.5) is None  # no pose rather than a NaN one
    assert h.node.stats.problems() == "2 poses invalid (NaN/inf)"


def test_full_queue_drops_the_oldest_frames(harness, places):
    h = harness(start_worker=False, queue_size=2)
    h.publish(places[:5], t0=10.0)
    counts = h.node.stats.counts  # `received` counts on entry, `dropped` after the queue
    wait_for(lambda: (counts.received, counts.dropped) == (5, 3))
    assert [frame.stamp for frame, _ in h.node.frames.snapshot()] == [13.0, 14.0]


def test_rate_limited_frames_never_enter_the_queue(harness, places):
    """min_frame_interval is applied before the queue: a camera faster than the keyframe rate
    fills it only with frames the pipeline will encode, so nothing is dropped."""
    h = harness(start_worker=False, queue_size=3, min_frame_interval=1.0)
    for i in range(9):  # 4 Hz for 2 s: stamps 10.0, 10.25, ..., 12.0
        h.pub.publish(image_msg(places[i % len(places)], 10.0 + 0.25 * i))
    counts = h.node.stats.counts
    wait_for(lambda: counts.received == 9)
    assert (counts.rate_limited, counts.dropped) == (6, 0)
    assert [frame.stamp for frame, _ in h.node.frames.snapshot()] == [10.0, 11.0, 12.0]
    assert h.set(min_frame_interval=0.0)[0].successful  # run-time change reaches the gate
    h.pub.publish(image_msg(places[0], 12.1))
    wait_for(lambda: counts.received == 10)
    assert (counts.rate_limited, counts.dropped) == (6, 1)
    values = diagnostic_values(h.node.values, h.node.stats, h.node.frames, h.node.maps)
    assert (values["frames_rate_limited"], values["frames_rate_limited_unqueued"]) == ("6", "6")


def test_services_switch_mode_save_load_and_clear(harness, places, tmp_path):
    h = harness()
    assert h.call(Trigger, "save_map").message == (
        "map_dir is not set: ros2 param set /vpr_node map_dir /path/to/map"
    )
    h.map_dir = tmp_path / "map"
    assert h.set(map_dir=str(h.map_dir))[0].successful
    h.publish(places[:4])
    h.processed(4)
    saved = h.call(Trigger, "save_map")
    assert (saved.success, saved.message) == (True, f"saved 4 keyframes to {tmp_path / 'map'}")
    assert h.call(Trigger, "clear_map").success and h.node.maps.size() == 0
    loaded = h.call(Trigger, "load_map")
    assert (loaded.success, loaded.message) == (
        True,
        f"loaded 4 keyframes from {tmp_path / 'map'}",
    )
    reply = h.call(SetBool, "set_localization", data=True)
    assert (reply.success, reply.message) == (True, "mode: localization")
    assert h.node.get_parameter("mode").value == "localization"
    h.publish([places[5], places[1]], t0=200.0)  # a new place and a revisit of place 1
    h.processed(6)
    assert h.node.maps.size() == 4
    wait_for(lambda: len(h.got["loop_closure"]) == 1)
    assert list(h.got["loop_closure"][0].data) == [201.0, 101.0]
    assert h.call(SetBool, "set_localization", data=False).message == "mode: mapping"
    assert h.node.pipeline.config.mode == "mapping"


def test_build_map_service_from_a_bag(harness, places, tmp_path):
    bag = write_rosbag2(
        tmp_path / "bag",
        [(50.0 + i, rgb) for i, rgb in enumerate(places[:3])],
        [(50.0 + i, (float(i), 0.0, 0.0)) for i in range(3)],
    )
    h = harness(map_dir=str(tmp_path / "map"), build_source=str(bag))
    reply = h.call(Trigger, "build_map")
    assert reply.success and reply.message.startswith(f"building a map from {bag}")
    assert h.node.maps.wait_build(60.0)
    assert h.node.maps.build_state.startswith(f"done: 3 keyframes from 3 images of {bag}")
    assert h.node.maps.size() == 3
    with PlaceMap.load(tmp_path / "map", read_only=True) as saved:
        assert saved.meta(2).pose == (2.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)
    h.publish([places[0]], t0=200.0)  # the live map is the built one: a revisit of keyframe 0
    wait_for(lambda: h.got["loop_closure"])
    assert list(h.got["loop_closure"][0].data) == [200.0, 50.0]
    assert h.set(build_source=str(tmp_path / "absent"))[0].successful
    failed = h.call(Trigger, "build_map")
    assert not failed.success and "does not exist" in failed.message


def test_out_of_range_parameters_are_refused_with_a_reason(harness):
    h = harness()
    results = (
        h.set(top_k=-3),
        h.set(preset="fast"),
        h.set(device="cuda"),
        h.set(rerank_budget_ms=-5.0),
    )
    assert [r[0].reason for r in results] == [
        "Parameter top_k out of range. Min: 0, Max: 1000, value: -3",
        "preset='fast' must be one of speed, performance",
        "Trying to set a read-only parameter: device.",
        "Parameter rerank_budget_ms out of range Min: 0.0, Max: 600000.0, value: -5.0",
    ]
    assert not any(r[0].successful for r in results)
    assert h.node.pipeline.config.top_k == 1
    assert h.set(top_k=7, exclude_recent_s=9.0, rerank_budget_ms=250.0)[0].successful
    config = h.node.pipeline.config
    assert (config.top_k, config.exclude_recent_s, config.rerank_budget_ms) == (7, 9.0, 250.0)


def test_config_file_loads_with_every_default(tmp_path):
    config = Path(__file__).resolve().parents[2] / "config" / "vpr_node.yaml"
    rclpy.init()
    try:
        args = ["--ros-args", "--params-file", str(config), "-p", "weights:=random-tiny"]
        node = VprNode(cli_args=args, start_worker=False)
        for spec in PARAMS:
            expected = "random-tiny" if spec.name == "weights" else spec.default
            # an empty string array stays unset in ROS (it cannot be typed): read_value's ()
            assert read_value(node, spec) == expected, spec.name
        assert "(torch, fp32, 1 CPU thread)" in node.summary  # num_threads 0: auto, light model
        node.shutdown()
        node.destroy_node()
    finally:
        rclpy.try_shutdown()


def test_autosave_then_load_on_start(harness, places, tmp_path):
    h = harness(map_dir=str(tmp_path / "map"), autosave_period=0.2)
    h.publish(places[:3])
    h.processed(3)
    wait_for(lambda: saved_keyframes(tmp_path / "map") == 3)  # the timer saved the map
    h.close()
    again = harness(map_dir=str(tmp_path / "map"), load_map_on_start=True)
    assert again.node.maps.size() == 3


def test_every_pose_type_gives_position_and_orientation():
    for msg in (Odometry(), PoseStamped(), PoseWithCovarianceStamped()):
        pose = msg.pose if isinstance(msg, PoseStamped) else msg.pose.pose
        pose.position.x, pose.position.z, pose.orientation.w = 1.0, 3.0, 1.0
        assert message_pose(msg) == (1.0, 0.0, 3.0, 0.0, 0.0, 0.0, 1.0), type(msg).__name__


def test_factor_message_with_rclpy_classes():
    factor = LoopFactor(
        query_stamp=1700000012.25, match_stamp=1700000001.5, query_frame_id="cam_q",
        match_frame_id="cam_m", translation=(0.5, -0.1, 2.0), rotation=(0.0, 0.6, 0.0, 0.8),
        covariance=tuple(np.eye(6).ravel() * 0.01), metric=True, inliers=88, query_id=4,
        match_id=1,
    )  # fmt: skip
    msg = factor_msg(factor, _message_classes())
    assert isinstance(msg, Odometry)
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (1700000012, 250000000)
    assert factor_from_msg(msg) == factor
