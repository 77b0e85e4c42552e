"""`vpr_node` with depth and camera_info: the between-factor topic carries a metric pose; bad
intrinsics or depth are counted and give a reason, never a pose (tiny random network, exact
repeats as loops, see test_node.py)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from bag_fixtures import textured
from nav_msgs.msg import Odometry
from node_harness import image_msg, stamp_msg, wait_for
from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import String

from pair_vpr_ros.errors import ConfigError
from pair_vpr_ros.messages.factor import FACTOR_TOPIC, factor_from_msg
from pair_vpr_ros.messages.loop import JSON_TOPIC

H, W = 120, 160


def depth_msg(t: float, shape=(H, W), mm: int = 4000) -> Image:
    data = np.full(shape, mm, "<u2").tobytes()
    msg = Image(height=shape[0], width=shape[1], encoding="16UC1", step=2 * shape[1], data=data)
    return stamp_msg(msg, t)


def info_msg(f: float = 100.0) -> CameraInfo:
    msg = CameraInfo(width=W, height=H, distortion_model="plumb_bob", d=[0.0] * 5)
    msg.k = [f, 0.0, 79.5, 0.0, f, 59.5, 0.0, 0.0, 1.0]
    return stamp_msg(msg, 0.0)


def run(h, depth_shift=0.0, depth_shape=(H, W), focal=100.0) -> tuple[list, list]:
    """Publish camera_info, then places 0 1 2 0 with depth -> (factors, json records)."""
    peer = h.peer
    factors, records = [], []
    peer.create_subscription(Odometry, FACTOR_TOPIC, factors.append, 10)
    peer.create_subscription(String, JSON_TOPIC, records.append, 10)
    info = peer.create_publisher(CameraInfo, "camera_info", 10)
    depth = peer.create_publisher(Image, "depth", 10)
    wait_for(lambda: info.get_subscription_count() >= 1 and depth.get_subscription_count() >= 1)
    info.publish(info_msg(focal))
    wait_for(lambda: h.node.geometry_inputs.camera_info is not None or focal <= 0, 5.0)
    places = [textured(s) for s in range(3)]
    for i, p in enumerate([0, 1, 2, 0]):
        depth.publish(depth_msg(100.0 + i + depth_shift, depth_shape))
        h.pub.publish(image_msg(places[p], 100.0 + i))
    h.processed(4)
    wait_for(lambda: len(records) >= 1)
    return factors, [json.loads(r.data) for r in records]


GEOMETRY = dict(depth_topic="depth", camera_info_topic="camera_info", exclude_recent_s=2.5)


def test_images_depth_and_camera_info_give_a_metric_between_factor(harness):
    h = harness(**GEOMETRY)
    factors, records = run(h)
    wait_for(lambda: len(factors) == 1)
    f = factor_from_msg(factors[0])
    assert (f.query_stamp, f.match_stamp, f.query_frame_id, f.match_frame_id) == (
        103.0, 100.0, "cam", "cam",
    )  # fmt: skip
    assert f.metric and f.inliers >= 30 and np.linalg.norm(f.translation) < 1e-3
    assert np.all(np.isfinite(f.covariance)) and f.covariance[0] > 0
    assert records[0]["pose_status"] == "metric" and records[0]["accepted"] is True
    assert h.node.stats.counts.depth_unmatched == 0


@pytest.mark.parametrize(
    ("bad", "count", "reason"),
    [
        (dict(focal=0.0), "camera_info_invalid", "no intrinsics for the query keyframe"),
        (dict(depth_shift=0.5), "depth_unmatched", "degenerate motion"),
        (dict(depth_shape=(60, 80)), None, "degenerate motion"),
    ],
)
def test_bad_intrinsics_or_depth_are_counted_and_give_no_pose(harness, bad, count, reason):
    h = harness(**GEOMETRY)
    factors, records = run(h, **bad)
    assert records[0]["accepted"] and records[0]["pose_status"] == ""
    assert records[0]["pose_reason"].startswith(reason), records[0]["pose_reason"]
    assert factors == []
    if count:
        assert getattr(h.node.stats.counts, count) >= 1
    else:
        assert h.node.maps.state.counts.depth_wrong_size == 4


def test_fallback_intrinsics_parameters_are_checked_at_start(harness):
    with pytest.raises(ConfigError, match="camera_\\* parameters: .*'plumb_bob' takes 4 or 5"):
        harness(camera_fx=100.0, camera_distortion_model="plumb_bob", camera_distortion="0.1,0.2")
