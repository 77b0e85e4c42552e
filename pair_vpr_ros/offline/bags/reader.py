"""Reading camera frames (and optional poses) from rosbags (the loop-closure writer: loop_writer).

Reads rosbag2 folders (mcap or sqlite3 storage), bare ``.mcap`` / ``.db3`` files and ROS 1 ``.bag``
files through rosbags' ``AnyReader``; types come from the definitions stored in the bag, with the
ROS 2 Jazzy typestore as fallback. Every failure becomes a ``BagError`` that names the bag and, for
a failure part-way through, the image message index and stamp where reading stopped.

Frame stamps are header stamps in float seconds (the time base LIO-SAM expects); a zero header
stamp falls back to the bag's receive time. Poses are matched to frames by nearest header stamp.

Opening a bag lives in ``opening`` and the loop-closure bag writer in ``loop_writer``.
"""

from __future__ import annotations

from collections.abc import Callable, Container, Iterator
from dataclasses import dataclass
from functools import partial
from typing import Any

import numpy as np
from rosbags.highlevel import AnyReader

from pair_vpr_ros.errors import BagError, ImageConversionError
from pair_vpr_ros.images.convert import msg_to_rgb
from pair_vpr_ros.images.pixels import MAX_PIXELS
from pair_vpr_ros.offline.bags.opening import jazzy_typestore
from pair_vpr_ros.types import Pose, PoseTrack, message_pose, message_stamp

IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
POSE_TYPES = (
    "nav_msgs/msg/Odometry",
    "geometry_msgs/msg/PoseStamped",
    "geometry_msgs/msg/PoseWithCovarianceStamped",
)


@dataclass(frozen=True)
class BagFrame:
    """One image message of the chosen topic.

    ``rgb`` is ``[H, W, 3]`` uint8, or None with ``error`` set when the message could not be
    deserialised or converted (the caller counts and skips it). ``cdr`` holds the message's CDR
    bytes only when requested (to copy images into an output bag).
    """

    index: int
    stamp: float
    log_time_ns: int
    frame_id: str
    rgb: np.ndarray | None
    pose: Pose | None
    error: str | None = None
    cdr: bytes | None = None


def _bag_name(reader: AnyReader) -> str:
    return ", ".join(str(p) for p in reader.paths)


def topics_of_types(reader: AnyReader, msgtypes: tuple[str, ...]) -> dict[str, str]:
    """``{topic: msgtype}`` of the bag's topics whose type is one of ``msgtypes``."""
    return {
        name: info.msgtype
        for name, info in sorted(reader.topics.items())
        if info.msgtype in msgtypes
    }


def _describe(topics: dict[str, str]) -> str:
    return ", ".join(f"{name} ({msgtype})" for name, msgtype in topics.items()) or "none"


def choose_image_topic(reader: AnyReader, topic: str | None = None, flag: str = "--topic") -> str:
    """The image topic to replay: ``topic`` when given, else the bag's only image topic (several:
    a BagError saying to choose one with ``flag``)."""
    images = topics_of_types(reader, IMAGE_TYPES)
    if not images:
        every = {name: info.msgtype or "?" for name, info in sorted(reader.topics.items())}
        raise BagError(
            f"bag {_bag_name(reader)} has no sensor_msgs/msg/Image or CompressedImage topic "
            f"(topics: {_describe(every)})"
        )
    if topic is None:
        if len(images) > 1:  # a depth stream is not what we recognise places in
            from pair_vpr_ros.offline.bags.geometry import depth_topics

            images = {k: v for k, v in images.items() if k not in depth_topics(reader)} or images
        if len(images) > 1:
            raise BagError(
                f"bag {_bag_name(reader)} has {len(images)} image topics: {_describe(images)}; "
                f"choose one with {flag}"
            )
        topic = next(iter(images))
    elif topic not in images:
        raise BagError(
            f"topic {topic} is not an image topic of bag {_bag_name(reader)}; "
            f"image topics: {_describe(images)}"
        )
    if reader.topics[topic].msgcount == 0:
        raise BagError(f"image topic {topic} of bag {_bag_name(reader)} has no messages")
    return topic


def choose_pose_topic(reader: AnyReader, topic: str | None = None) -> str | None:
    """The pose topic: ``topic`` if given (checked), else the bag's only pose topic, else None."""
    poses = topics_of_types(reader, POSE_TYPES)
    if topic is None:
        return next(iter(poses)) if len(poses) == 1 else None
    if topic not in poses:
        raise BagError(
            f"topic {topic} is not a pose topic of bag {_bag_name(reader)} (Odometry, PoseStamped "
            f"or PoseWithCovarianceStamped); pose topics: {_describe(poses)}"
        )
    return topic


def read_poses(reader: AnyReader, topic: str) -> tuple[PoseTrack, str | None]:
    """All poses of ``topic`` by header stamp, and why reading stopped part-way (None when it did
    not; the poses before that point are kept). Poses with NaN / inf values are left out and
    counted in ``track.rejected`` (see ``bad_poses_warning``)."""
    track, error = PoseTrack(), None
    messages = reader.messages(connections=reader.topics[topic].connections)
    while True:
        try:
            connection, log_time, raw = next(messages)
            msg = reader.deserialize(raw, connection.msgtype)
        except StopIteration:
            break
        except Exception as err:  # noqa: BLE001 - any reader/deserialiser failure ends the pass
            error = (
                f"reading pose topic {topic} of bag {_bag_name(reader)} stopped after "
                f"{len(track)} messages: {err}"
            )
            break
        track.add(message_stamp(msg, log_time / 1e9), message_pose(msg))
    return track, error


def bad_poses_warning(track: PoseTrack, topic: str) -> str | None:
    """The warning for the poses ``read_poses`` left out (None when none was)."""
    if not track.rejected:
        return None
    return (
        f"{track.rejected} poses of {topic} hold NaN or infinite values and were skipped (the "
        f"first at stamp {track.first_rejected:.3f} s); frames near them have no pose"
    )


def iter_frames(
    reader: AnyReader,
    topic: str,
    poses: PoseTrack | None = None,
    pose_tolerance: float = 0.2,
    max_frames: int | None = None,
    keep_cdr: bool = False,
    convert: Callable[[Any], np.ndarray] | None = None,
    max_pixels: int = MAX_PIXELS,
    indices: Container[int] | None = None,
) -> Iterator[BagFrame]:
    """Yield the image messages of ``topic`` in bag order as ``BagFrame`` s.

    Messages that do not deserialise or convert come back with ``rgb=None`` and ``error`` set.
    A failure of the reader itself raises ``BagError`` saying where it stopped; frames yielded
    before it are valid. ``convert`` defaults to ``images.convert.msg_to_rgb`` with ``max_pixels``.
    ``indices``: only the messages of these indices are decoded and yielded (the others are read
    past undecoded; ``max_frames`` still counts every message).
    """
    if convert is None:
        convert = partial(msg_to_rgb, max_pixels=max_pixels)

    def decode(connection: Any, log_time: int, raw: bytes, index: int) -> BagFrame:
        try:
            msg = reader.deserialize(raw, connection.msgtype)
        except Exception as err:  # noqa: BLE001 - one corrupt message is a counted skip
            error = f"cannot deserialise: {err}"
            return BagFrame(index, log_time / 1e9, log_time, "", None, None, error)
        stamp = message_stamp(msg, log_time / 1e9)
        pose = poses.nearest(stamp, pose_tolerance) if poses is not None else None
        cdr = None
        if keep_cdr:  # ROS 1 payloads are re-serialised as ROS 2 CDR
            cdr = bytes(raw) if reader.is2 else _jazzy_cdr(msg, connection.msgtype)
        try:
            rgb, error = convert(msg), None
        except ImageConversionError as err:
            rgb, error = None, str(err)
        return BagFrame(index, stamp, log_time, msg.header.frame_id, rgb, pose, error, cdr)

    messages = reader.messages(connections=reader.topics[topic].connections)
    index, last_stamp = 0, None
    while max_frames is None or index < max_frames:
        try:
            connection, log_time, raw = next(messages)
        except StopIteration:
            return
        except Exception as err:  # noqa: BLE001 - any reader failure is a bag problem
            where = (
                "before the first message" if last_stamp is None else f"stamp {last_stamp:.3f} s"
            )
            raise BagError(
                f"reading {topic} of bag {_bag_name(reader)} stopped at image message {index} "
                f"(after {where}): {err}"
            ) from err
        if indices is not None and index not in indices:
            last_stamp, index = log_time / 1e9, index + 1
            continue
        frame = decode(connection, log_time, raw, index)
        yield frame
        last_stamp, index = frame.stamp, index + 1


def _jazzy_cdr(msg: Any, msgtype: str) -> bytes:
    return bytes(jazzy_typestore().serialize_cdr(msg, msgtype))
