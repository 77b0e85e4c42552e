"""types: the one Pose, the one pose track (bounded or not), stamp/pose readers of messages."""

from __future__ import annotations

import threading

import pytest
from rosbags.typesys import Stores, get_typestore

from pair_vpr_ros.types import PoseTrack, message_pose, message_stamp, split_stamp

TS = get_typestore(Stores.ROS2_JAZZY)


def _pose(x: float) -> tuple[float, ...]:
    return (x, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)


def _header(sec: int, nanosec: int):
    time = TS.types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec)
    return TS.types["std_msgs/msg/Header"](stamp=time, frame_id="odom")


def _geometry(x: float, y: float, z: float, w: float):
    point = TS.types["geometry_msgs/msg/Point"](x=x, y=y, z=z)
    quat = TS.types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=w)
    return TS.types["geometry_msgs/msg/Pose"](position=point, orientation=quat)


def test_nearest_within_tolerance():
    track = PoseTrack()
    for stamp in (1.0, 2.0, 3.0):
        track.add(stamp, _pose(stamp))
    assert len(track) == 3
    assert track.nearest(2.15, 0.2) == _pose(2.0)
    assert track.nearest(2.85, 0.2) == _pose(3.0)
    assert track.nearest(2.6, 0.2) is None  # 0.4 s from both neighbours
    assert track.nearest(0.5, 0.2) is None and track.nearest(3.3, 0.2) is None
    assert track.nearest(3.25, 0.25) == _pose(3.0)  # exactly at the tolerance
    assert PoseTrack().nearest(1.0, 5.0) is None


def test_ties_and_equal_stamps_keep_order():
    track = PoseTrack()
    for stamp, x in ((2.0, 20.0), (1.0, 10.0), (2.0, 21.0)):  # out of order, one stamp twice
        track.add(stamp, _pose(x))
    assert track.nearest(1.5, 1.0) == _pose(10.0)  # a tie: the earlier stamp
    assert track.nearest(2.0, 0.0) == _pose(20.0)  # equal stamps: the first one added


def test_maxlen_keeps_the_newest_stamps():
    track = PoseTrack(maxlen=3)
    for stamp in (2.0, 0.0, 1.0, 3.0):  # out of order: capacity 3 keeps stamps 1, 2, 3
        track.add(stamp, _pose(stamp))
    assert len(track) == 3
    assert track.nearest(1.4, 0.5) == _pose(1.0) and track.nearest(2.6, 0.5) == _pose(3.0)
    assert track.nearest(0.0, 0.2) is None
    assert track.nearest(4.0, 0.5) is None


def test_adds_and_lookups_from_threads():
    track, found = PoseTrack(maxlen=500), []

    def add(offset: int) -> None:
        for i in range(offset, 2000, 4):
            track.add(float(i), _pose(float(i)))

    def look() -> None:
        for _ in range(2000):
            pose = track.nearest(1000.0, 2000.0)
            found.append(pose is None or pose[0] == int(pose[0]))

    threads = [threading.Thread(target=add, args=(k,)) for k in range(4)]
    threads.append(threading.Thread(target=look))
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(track) == 500 and all(found)
    assert track.nearest(1499.6, 0.5) == _pose(1500.0)  # the newest 500 stamps: 1500..1999
    assert track.nearest(1498.0, 0.5) is None


def test_message_stamp():
    odom = TS.types["nav_msgs/msg/Odometry"]
    msg = odom(header=_header(12, 500_000_000), child_frame_id="base", pose=None, twist=None)
    assert message_stamp(msg) == 12.5
    assert message_stamp(msg, fallback=99.0) == 12.5
    msg = odom(header=_header(0, 0), child_frame_id="base", pose=None, twist=None)
    assert message_stamp(msg, fallback=99.0) == 99.0  # publisher never set the stamp
    assert message_stamp(msg) == 0.0
    assert message_stamp(odom(header=_header(3, 1), child_frame_id="", pose=None, twist=None)) == (
        3 + 1 / 1e9
    )


@pytest.mark.parametrize("kind", ["Odometry", "PoseStamped", "PoseWithCovarianceStamped"])
def test_message_pose_of_every_pose_type(kind):
    geometry = _geometry(1.0, 2.0, 3.0, 1.0)
    t = TS.types
    with_cov = t["geometry_msgs/msg/PoseWithCovariance"](pose=geometry, covariance=[0.0] * 36)
    msg = {
        "Odometry": lambda: t["nav_msgs/msg/Odometry"](
            header=_header(1, 0), child_frame_id="base", pose=with_cov, twist=None
        ),
        "PoseStamped": lambda: t["geometry_msgs/msg/PoseStamped"](
            header=_header(1, 0), pose=geometry
        ),
        "PoseWithCovarianceStamped": lambda: t["geometry_msgs/msg/PoseWithCovarianceStamped"](
            header=_header(1, 0), pose=with_cov
        ),
    }[kind]()
    pose = message_pose(msg)
    assert pose == (1.0, 2.0, 3.0, 0.0, 0.0, 0.0, 1.0)
    assert all(type(v) is float for v in pose)


def test_split_stamp_rounds_to_the_nearest_nanosecond():
    assert split_stamp(1700000001.5) == (1700000001, 500000000)
    assert split_stamp(12.9999999999) == (13, 0)
    assert split_stamp(0.0) == (0, 0)
