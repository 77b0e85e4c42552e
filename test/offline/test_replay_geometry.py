"""Replays with depth and camera_info: relative poses in the outputs, topic discovery, and bad
depth / intrinsics as counted skips (tiny random model; revisits are exact repeats)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from bag_fixtures import TS2, _header, textured, write_rosbag2
from rosbags.highlevel import AnyReader

from pair_vpr_ros.errors import BagError
from pair_vpr_ros.loops.detector import DetectorConfig
from pair_vpr_ros.messages.factor import FACTOR_TOPIC, factor_from_msg
from pair_vpr_ros.offline.replay.options import ReplayOptions
from pair_vpr_ros.offline.replay.run import replay_bag

CONFIG = DetectorConfig(
    top_k=1, score_threshold=-1e9, keyframe_max_similarity=1.0, exclude_recent_s=3.5,
    exclude_recent_keyframes=0, global_floor=0.99999,
)  # fmt: skip
H, W = 120, 160
INFO = "sensor_msgs/msg/CameraInfo"
DEPTH_TOPIC, INFO_TOPIC = "/cam/depth", "/cam/camera_info"


@pytest.fixture
def model(tiny_model):
    return tiny_model


def depth_msg(stamp: float, mm: np.ndarray):
    h, w = mm.shape
    return TS2.types["sensor_msgs/msg/Image"](
        header=_header(TS2, stamp, "cam"), height=h, width=w, encoding="16UC1", is_bigendian=0,
        step=2 * w, data=mm.astype("<u2").view(np.uint8).reshape(-1),
    )  # fmt: skip


def info_msg(stamp: float, f: float = 100.0):
    roi = TS2.types["sensor_msgs/msg/RegionOfInterest"](
        x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
    )
    return TS2.types[INFO](
        header=_header(TS2, stamp, "cam"), height=H, width=W, distortion_model="plumb_bob",
        d=np.zeros(5), k=np.array([f, 0, 79.5, 0, f, 59.5, 0, 0, 1.0]), r=np.eye(3).ravel(),
        p=np.array([f, 0, 79.5, 0, 0, f, 59.5, 0, 0, 0, 1.0, 0]), binning_x=0, binning_y=0,
        roi=roi,
    )  # fmt: skip


def write_bag(path, depth_shift=0.0, depth_shape=(H, W), focal=100.0, depth_topics=1):
    """Places 0-2 at t=0..2, revisits of 0 and 1 at t=4, 5; depth 4 m; one camera_info."""
    imgs = [textured(s) for s in range(3)]
    order = [0, 1, 2, 0, 1]
    stamps = [0.0, 1.0, 2.0, 4.0, 5.0]
    images = [(t, imgs[p]) for t, p in zip(stamps, order, strict=True)]
    mm = np.full(depth_shape, 4000, np.uint16)
    extra = [(INFO_TOPIC, INFO, info_msg(0.0, focal), 0.0)]
    for k in range(depth_topics):
        topic = DEPTH_TOPIC if k == 0 else f"{DEPTH_TOPIC}{k}"
        extra += [(topic, "sensor_msgs/msg/Image", depth_msg(t + depth_shift, mm), t + 0.001)
                  for t in stamps]  # fmt: skip
    return write_rosbag2(path, images, extra=extra)


def replay(tmp_path, bag, model, **kw):
    return replay_bag(
        bag,
        tmp_path / "out",
        ReplayOptions(progress=False, overwrite=True, **kw),
        model=model,
        config=CONFIG,
    )


def test_depth_and_camera_info_give_metric_poses_in_every_output(tmp_path, model):
    s = replay(tmp_path, write_bag(tmp_path / "bag"), model, write_bag=True)
    assert (s.topic, s.depth_topic, s.camera_info_topic) == ("/cam/image", DEPTH_TOPIC, INFO_TOPIC)
    assert s.notes[:2] == [  # then the pose topics' notes (test_replay_pose_topics.py)
        f"depth image: {DEPTH_TOPIC} (the bag's only depth image topic; --depth-topic to change)",
        f"camera_info: {INFO_TOPIC} (the bag's only camera_info topic; --camera-info-topic to "
        "change)",
    ]
    assert s.loops == 2 and s.geometry_skips == {} and s.pipeline_counts["pose_metric"] == 2
    loops = [r for r in json.loads((tmp_path / "out" / "loops.json").read_text()) if r["accepted"]]
    assert [(r["pose_status"], r["match_id"]) for r in loops] == [("metric", 0), ("metric", 1)]
    assert all(abs(r["tx"]) < 1e-3 and len(r["covariance"]) == 36 for r in loops)
    with AnyReader([tmp_path / "out" / "bag"]) as reader:
        factors = [
            factor_from_msg(reader.deserialize(raw, c.msgtype))
            for c, _, raw in reader.messages()
            if c.topic == "/" + FACTOR_TOPIC
        ]
    assert [(f.query_stamp, f.match_stamp, f.metric) for f in factors] == [
        (4.0, 0.0, True), (5.0, 1.0, True),
    ]  # fmt: skip


@pytest.mark.parametrize(
    ("kw", "bag_kw", "reason", "skips"),
    [
        (dict(camera_info_topic="none"), {}, "no intrinsics for the query keyframe", {}),
        (dict(depth_topic="none"), {}, "degenerate motion", {}),
        ({}, dict(depth_shift=0.5), "degenerate motion",
         {"depth: no message within the stamp tolerance": 5}),
        ({}, dict(focal=0.0), "no intrinsics for the query keyframe",
         {"camera_info invalid: camera model 160x120": 1}),
    ],
)  # fmt: skip
def test_missing_or_bad_geometry_inputs_are_reasons_and_counted_skips(
    tmp_path, model, kw, bag_kw, reason, skips
):
    s = replay(tmp_path, write_bag(tmp_path / "bag", **bag_kw), model, **kw)
    assert s.loops == 2 and s.geometry_skips == skips  # the loops themselves are unaffected
    loops = [r for r in json.loads((tmp_path / "out" / "loops.json").read_text()) if r["accepted"]]
    assert all(r["pose_status"] == "" and r["pose_reason"].startswith(reason) for r in loops)


def test_depth_of_another_size_is_dropped_and_counted(tmp_path, model):
    s = replay(tmp_path, write_bag(tmp_path / "bag", depth_shape=(60, 80)), model)
    assert s.pipeline_counts["depth_wrong_size"] == 5 and s.pipeline_counts["pose_none"] == 2


def test_several_depth_topics_need_a_choice(tmp_path, model):
    bag = write_bag(tmp_path / "bag", depth_topics=2)
    s = replay(tmp_path, bag, model)
    assert s.depth_topic is None and s.notes[0] == (
        f"no depth image: the bag has several depth image topics ({DEPTH_TOPIC}, "
        f"{DEPTH_TOPIC}1); pick one with --depth-topic"
    )
    s = replay(tmp_path, bag, model, depth_topic=f"{DEPTH_TOPIC}1")
    assert s.depth_topic == f"{DEPTH_TOPIC}1" and s.pipeline_counts["pose_metric"] == 2
    with pytest.raises(BagError, match="/cam/image is not a depth image topic of the bag"):
        replay(tmp_path, bag, model, depth_topic="/cam/image")
