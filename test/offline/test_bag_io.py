"""offline.bags.reader: frames and poses from bags of every writer; every bad input's message."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from bag_fixtures import (
    COMPRESSED,
    IMAGE,
    ODOMETRY,
    POSE_COV,
    POSE_STAMPED,
    TS2,
    image_msg,
    pose_msg,
    synthetic_images,
    write_foxglove,
    write_ros1,
    write_rosbag2,
)
from rosbags.highlevel import AnyReader

from pair_vpr_ros.errors import BagError
from pair_vpr_ros.loops.records import LoopRecord
from pair_vpr_ros.messages import loop as loop_messages
from pair_vpr_ros.messages.factor import factor_from_msg, factor_from_record
from pair_vpr_ros.offline.bags.loop_writer import LoopBagWriter
from pair_vpr_ros.offline.bags.opening import open_bag
from pair_vpr_ros.offline.bags.reader import (
    choose_image_topic,
    choose_pose_topic,
    iter_frames,
    read_poses,
)

STAMPS = [100.0, 100.5, 101.0, 101.5]


def _images(n: int = 4):
    return list(zip(STAMPS[:n], synthetic_images(n), strict=True))


def _poses():
    # pose stamps 0.05 s after each frame except the last frame (no pose within 0.2 s)
    return [(t + 0.05, (float(i), 2.0 * i, 0.5)) for i, t in enumerate(STAMPS[:3])]


def _read(path: Path, topic: str | None = None, pose_topic: str | None = None, **kw):
    with open_bag(path) as reader:
        topic = choose_image_topic(reader, topic)
        pose_topic = choose_pose_topic(reader, pose_topic)
        poses, error = read_poses(reader, pose_topic) if pose_topic else (None, None)
        return list(iter_frames(reader, topic, poses, **kw)), (pose_topic, poses, error)


def _check_frames(frames, images, expect_poses: bool) -> None:
    assert [f.index for f in frames] == list(range(len(images)))
    assert [f.stamp for f in frames] == pytest.approx([t for t, _ in images], abs=1e-9)
    for frame, (_, rgb) in zip(frames, images, strict=True):
        assert frame.error is None
        np.testing.assert_array_equal(frame.rgb, rgb)
        assert frame.frame_id == "cam"
    if expect_poses:
        assert [f.pose for f in frames] == [
            (0.0, 0.0, 0.5, 0.0, 0.0, 0.0, 1.0),
            (1.0, 2.0, 0.5, 0.0, 0.0, 0.0, 1.0),
            (2.0, 4.0, 0.5, 0.0, 0.0, 0.0, 1.0),
            None,
        ]


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
@pytest.mark.parametrize("compressed", [False, True])
def test_rosbags_writer_folder_and_bare_file(tmp_path, storage, compressed):
    images = _images()
    bag = write_rosbag2(tmp_path / "bag", images, _poses(), storage, compressed)
    frames, poses = _read(bag)
    _check_frames(frames, images, expect_poses=True)
    assert poses[0] == "/odom" and len(poses[1]) == 3 and poses[2] is None
    bare = next(bag.glob("*.mcap" if storage == "mcap" else "*.db3"))
    _check_frames(_read(bare)[0], images, expect_poses=True)


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_version_8_metadata(tmp_path, storage):
    images = _images()
    bag = write_rosbag2(tmp_path / "bag", images, _poses(), storage, version=8)
    _check_frames(_read(bag)[0], images, expect_poses=True)


@pytest.mark.parametrize("pose_type", [POSE_STAMPED, ODOMETRY, POSE_COV])
def test_foxglove_writer(tmp_path, pose_type):
    images = _images()
    path = write_foxglove(tmp_path / "fox.mcap", images, _poses(), pose_type=pose_type)
    frames, poses = _read(path)
    _check_frames(frames, images, expect_poses=True)
    assert poses[0] == "/pose"


def test_ros1_bag(tmp_path):
    images = _images()
    frames, _ = _read(write_ros1(tmp_path / "old.bag", images, _poses()), keep_cdr=True)
    _check_frames(frames, images, expect_poses=True)
    # ROS 1 payloads are re-serialised as ROS 2 CDR for the output bag
    msg = TS2.deserialize_cdr(frames[1].cdr, IMAGE)
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec, msg.encoding) == (
        100,
        5 * 10**8,
        "rgb8",
    )


def test_folder_without_metadata_reads_its_storage_file(tmp_path):
    bag = write_rosbag2(tmp_path / "bag", _images(2))
    (bag / "metadata.yaml").unlink()
    assert len(_read(bag)[0]) == 2


def test_max_frames_and_cdr_copy(tmp_path):
    bag = write_rosbag2(tmp_path / "bag", _images())
    frames, _ = _read(bag, max_frames=2, keep_cdr=True)
    assert [f.index for f in frames] == [0, 1]
    assert TS2.deserialize_cdr(frames[0].cdr, IMAGE).width == 16
    assert frames[0].log_time_ns == 100 * 10**9


def test_zero_header_stamp_falls_back_to_log_time(tmp_path):
    msg = image_msg(TS2, 0.0, synthetic_images(1)[0], compressed=False)
    bag = write_rosbag2(tmp_path / "bag", [], extra=[("/cam/raw", IMAGE, msg, 7.25)])
    (frame,), _ = _read(bag)
    assert frame.stamp == 7.25


def test_bad_image_is_a_counted_skip(tmp_path):
    rgb = synthetic_images(1)[0]
    bad = image_msg(TS2, 5.0, rgb, compressed=False, encoding="no_such_encoding")
    good = image_msg(TS2, 6.0, rgb, compressed=False)
    extra = [("/cam", IMAGE, bad, 5.0), ("/cam", IMAGE, good, 6.0)]
    frames, _ = _read(write_rosbag2(tmp_path / "bag", [], extra=extra))
    assert frames[0].rgb is None and "no_such_encoding" in frames[0].error
    assert frames[0].stamp == 5.0
    assert frames[1].error is None and frames[1].stamp == 6.0


def _two_topic_bag(tmp_path: Path) -> Path:
    msg = image_msg(TS2, 1.0, synthetic_images(1)[0], compressed=True)
    return write_rosbag2(
        tmp_path / "bag", _images(2), extra=[("/b/compressed", COMPRESSED, msg, 1.0)]
    )


def test_several_image_topics_need_topic(tmp_path):
    bag = _two_topic_bag(tmp_path)
    with open_bag(bag) as reader:
        with pytest.raises(
            BagError,
            match=r"has 2 image topics: /b/compressed \(sensor_msgs/msg/CompressedImage\), "
            r"/cam/image \(sensor_msgs/msg/Image\); choose one with --topic",
        ):
            choose_image_topic(reader)
        assert choose_image_topic(reader, "/b/compressed") == "/b/compressed"
        with pytest.raises(
            BagError,
            match=r"topic /nope is not an image topic of bag .*image topics: /b/compressed",
        ):
            choose_image_topic(reader, "/nope")


def test_pose_topic_selection(tmp_path):
    pose = pose_msg(TS2, POSE_STAMPED, 1.0, (0.0, 0.0, 0.0))
    bag = write_rosbag2(
        tmp_path / "bag", _images(2), _poses(), extra=[("/p2", POSE_STAMPED, pose, 1.0)]
    )
    with open_bag(bag) as reader:
        assert choose_pose_topic(reader) is None  # two pose topics: none chosen silently
        assert choose_pose_topic(reader, "/p2") == "/p2"
        with pytest.raises(
            BagError, match=r"topic /cam/image is not a pose topic .*/odom, /p2|/odom"
        ):
            choose_pose_topic(reader, "/cam/image")


def test_bag_without_images(tmp_path):
    bag = write_rosbag2(tmp_path / "bag", [], _poses())
    with (
        open_bag(bag) as reader,
        pytest.raises(
            BagError,
            match=r"has no sensor_msgs/msg/Image or CompressedImage topic \(topics: /odom ",
        ),
    ):
        choose_image_topic(reader)


def test_image_topic_without_messages(tmp_path):
    bag = write_rosbag2(tmp_path / "bag", [], _poses(), empty=[("/cam/image", IMAGE)])
    with (
        open_bag(bag) as reader,
        pytest.raises(BagError, match="image topic /cam/image of bag .* has no messages"),
    ):
        choose_image_topic(reader)


@pytest.mark.parametrize(
    ("name", "content", "message"),
    [
        ("missing.mcap", None, r"bag .*missing.mcap does not exist: give a rosbag2 folder"),
        ("notes.txt", b"hello", r"notes.txt is not a bag: expected a rosbag2 folder or a file "),
        ("garbage.mcap", b"hello world" * 50, r"File magic is invalid\. \(the file is not an MC"),
        ("empty.mcap", b"", r"seems to be empty\. \(the file is empty\)"),
        ("empty.bag", b"", r"seems to be empty\. \(the file is empty\)"),
        ("garbage.db3", b"hello world" * 50, r"file is not a database \(the sqlite3"),
    ],
)
def test_bad_files(tmp_path, name, content, message):
    path = tmp_path / name
    if content is not None:
        path.write_bytes(content)
    with pytest.raises(BagError, match=message), open_bag(path):
        pass


def test_truncated_mcap(tmp_path):
    bag = write_rosbag2(tmp_path / "bag", _images())
    storage = next(bag.glob("*.mcap"))
    storage.write_bytes(storage.read_bytes()[: storage.stat().st_size // 2])
    with pytest.raises(BagError, match=r"cannot open bag .*File end magic is invalid.*truncated"):
        with open_bag(bag):
            pass


def test_failure_mid_bag_says_where(tmp_path):
    images = [(10.0 + i, rgb) for i, rgb in enumerate(synthetic_images(12, size=64))]
    path = write_foxglove(tmp_path / "f.mcap", images, compressed=False, chunk_size=20000)
    data = bytearray(path.read_bytes())
    for k in range(len(data) // 2, len(data) // 2 + 64):  # corrupt one chunk in the middle
        data[k] ^= 0xFF
    path.write_bytes(bytes(data))
    got = []
    with open_bag(path) as reader, pytest.raises(BagError) as info:
        for frame in iter_frames(reader, choose_image_topic(reader)):
            got.append(frame)
    assert 0 < len(got) < 12
    assert all(f.error is None for f in got)
    expected = (
        f"stopped at image message {len(got)} (after stamp {got[-1].stamp:.3f} s): "
        "Chunk checksum mismatch."
    )
    assert expected in str(info.value)


def test_loop_bag_writer_round_trip(tmp_path):
    cov = tuple(float(v) for v in np.eye(6).ravel() * 0.01)
    pose = dict(
        pose_status="metric", pose_inliers=40, tx=1.0, ty=0.0, tz=0.5, qx=0.0, qy=0.0, qz=0.0,
        qw=1.0, covariance=cov,
    )  # fmt: skip
    record = LoopRecord(
        query_id=7, query_stamp=120.25, query_frame_id="cam", match_id=2, match_stamp=101.5,
        match_frame_id="cam", pair_score=3.5, global_similarity=0.875, rank_before=1,
        rank_after=0, candidates=6, scored=3, inliers=-1, inlier_ratio=0.0, accepted=True,
        reason="", **pose,
    )  # fmt: skip
    no_pose = replace(record, query_stamp=121.25, pose_status="", covariance=(), tx=math.nan)
    cdr = bytes(TS2.serialize_cdr(image_msg(TS2, 120.25, synthetic_images(1)[0], False), IMAGE))
    out = tmp_path / "out_bag"
    with LoopBagWriter(out, image_topic="/cam", image_msgtype=IMAGE) as writer:
        writer.write_image(cdr, 120_250_000_000)
        writer.write_loop(record, 120_250_000_000)
        writer.write_loop(no_pose, 121_250_000_000)  # no relative pose: no factor message
        later = replace(no_pose, match_stamp=130.0)  # the match stamped after the query:
        writer.write_loop(later, 122_250_000_000)  # no LIO-SAM pair (issue 17)
    with AnyReader([out]) as reader:
        got: dict = {}
        for c, t, raw in reader.messages():
            got.setdefault(c.topic, []).append((c.msgtype, t, reader.deserialize(raw, c.msgtype)))
    assert {k: len(v) for k, v in got.items()} == {
        "/cam": 1, "/loop_closure": 2, "/loop_closure/detail": 3, "/loop_closure/json": 3,
        "/loop_closure/factor": 1, "/loop_closure/typed": 3,
    }  # fmt: skip
    got = {k: v[0] for k, v in got.items()}
    typed_type, _, typed = got["/loop_closure/typed"]  # as the node publishes it
    assert typed_type == loop_messages.TYPED_TYPE == "pair_vpr_ros_interfaces/msg/LoopClosure"
    assert (typed.header.stamp.sec, typed.header.stamp.nanosec) == (120, 250_000_000)
    assert (typed.header.frame_id, typed.match_stamp.sec, typed.match_stamp.nanosec) == (
        "cam", 101, 500_000_000,
    )  # fmt: skip
    assert (typed.query_id, typed.match_id, typed.pair_score, typed.accepted) == (7, 2, 3.5, True)
    assert (typed.pose_status, typed.pose_inliers) == (typed.POSE_METRIC, 40)
    position = typed.relative_pose.pose.position
    assert (position.x, position.y, position.z, typed.relative_pose.pose.orientation.w) == (
        1.0, 0.0, 0.5, 1.0,
    )  # fmt: skip
    assert typed.relative_pose.covariance.tolist() == list(cov)
    assert {t for _, t, _ in got.values()} == {120_250_000_000}
    pair = got["/loop_closure"][2]
    assert pair.data.tolist() == [120.25, 101.5] and pair.layout.dim == []
    detail = got["/loop_closure/detail"][2]
    labels = [d.label for d in detail.layout.dim]
    unnamed = [f"{k}=" for k in loop_messages.IDENTITY_FIELDS]  # a record without identity
    assert labels == [*loop_messages.DETAIL_LABELS, *unnamed, "pose_frame="]
    assert {(d.size, d.stride) for d in detail.layout.dim} == {(1, 1)}
    values = loop_messages.detail_to_dict(labels, detail.data)
    assert {k: values[k] for k in loop_messages.NUMERIC_FIELDS} == {
        "query_id": 7.0, "query_stamp": 120.25, "match_id": 2.0, "match_stamp": 101.5,
        "pair_score": 3.5, "global_similarity": 0.875, "rank_before": 1.0, "rank_after": 0.0,
        "candidates": 6.0, "scored": 3.0, "inliers": -1.0, "inlier_ratio": 0.0, "accepted": 1.0,
        "pose_inliers": 40.0, "tx": 1.0, "ty": 0.0, "tz": 0.5, "qx": 0.0, "qy": 0.0, "qz": 0.0,
        "qw": 1.0,
    }  # fmt: skip
    assert values["pose_status"] == 1.0 and values["cov_33"] == 0.01
    factor_type, _, factor = got["/loop_closure/factor"]
    assert factor_type == "nav_msgs/msg/Odometry"
    assert factor_from_msg(factor) == factor_from_record(record)
    assert got["/loop_closure/json"][0] == "std_msgs/msg/String"
    assert got["/loop_closure/json"][2].data == loop_messages.record_json(record)
    assert got["/cam"][2].header.stamp.sec == 120
    with pytest.raises(BagError, match="output bag .*out_bag exists already"):
        LoopBagWriter(out)
