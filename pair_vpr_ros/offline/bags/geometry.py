"""Depth images and camera intrinsics from a bag, attached to the replayed frames.

Depth: a ``sensor_msgs/Image`` topic in 16UC1 (mm) or 32FC1 (m), aligned with the colour image;
each frame takes the depth message whose header stamp is nearest to its own, if within
``tolerance`` s (else the frame goes on without depth, counted). The depth topic is read by a
second message iterator in step with the images, so memory stays constant. Intrinsics: the
bag's ``sensor_msgs/CameraInfo`` topic; each frame takes the latest valid one at its stamp.
"""

from __future__ import annotations

from collections import Counter, deque
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
from rosbags.highlevel import AnyReader

from pair_vpr_ros.errors import BagError, GeometryInputError
from pair_vpr_ros.geometry.camera import CameraModel, camera_from_info
from pair_vpr_ros.geometry.depth import DEPTH_SCALE, depth_from_msg
from pair_vpr_ros.types import message_stamp

IMAGE_TYPE = "sensor_msgs/msg/Image"
CAMERA_INFO_TYPE = "sensor_msgs/msg/CameraInfo"
NONE = "none"


def _first_encoding(reader: AnyReader, topic: str) -> str | None:
    for connection, _, raw in reader.messages(connections=reader.topics[topic].connections):
        try:
            return str(reader.deserialize(raw, connection.msgtype).encoding)
        except Exception:  # noqa: BLE001 - an unreadable first message: not a depth topic
            return None
    return None


def depth_topics(reader: AnyReader) -> list[str]:
    """Image topics whose first message has a depth encoding (16UC1, 32FC1, mono16)."""
    return [
        name
        for name, info in sorted(reader.topics.items())
        if info.msgtype == IMAGE_TYPE
        and (_first_encoding(reader, name) or "").strip().lower() in DEPTH_SCALE
    ]


def _choose(reader: AnyReader, topic: str | None, found: list[str], what: str, flag: str):
    """-> (topic or None, a note for the user)."""
    if topic == NONE:
        return None, ""
    if topic is not None:
        if topic not in found:
            raise BagError(
                f"{topic} is not a {what} topic of the bag; {what} topics: "
                f"{', '.join(found) or 'none'}"
            )
        return topic, ""
    if len(found) == 1:
        return found[0], f"{what}: {found[0]} (the bag's only {what} topic; {flag} to change)"
    if found:
        return None, f"no {what}: the bag has several {what} topics ({', '.join(found)}); " \
                     f"pick one with {flag}"  # fmt: skip
    return None, ""


def choose_depth_topic(reader: AnyReader, topic: str | None) -> tuple[str | None, str]:
    """``topic`` (checked), None/"none"; or the bag's only depth image topic -> (topic, note)."""
    return _choose(reader, topic, depth_topics(reader), "depth image", "--depth-topic")


def choose_camera_info_topic(reader: AnyReader, topic: str | None) -> tuple[str | None, str]:
    infos = [n for n, i in sorted(reader.topics.items()) if i.msgtype == CAMERA_INFO_TYPE]
    return _choose(reader, topic, infos, "camera_info", "--camera-info-topic")


@dataclass
class _Depth:
    stamp: float
    msg: Any


class BagGeometry:
    """Attaches depth and intrinsics from `reader` to frames given in bag (time) order."""

    def __init__(
        self,
        reader: AnyReader,
        depth_topic: str | None,
        info_topic: str | None,
        tolerance: float,
        counts: Counter[str],
    ) -> None:
        self.reader, self.tolerance, self.counts = reader, tolerance, counts
        self._cameras = self._read_cameras(info_topic) if info_topic else []
        self._depth_iter: Iterator | None = None
        if depth_topic:
            conns = reader.topics[depth_topic].connections
            self._depth_iter = reader.messages(connections=conns)
        self._window: deque[_Depth] = deque()

    def _read_cameras(self, topic: str) -> list[tuple[float, CameraModel]]:
        out, bad = [], Counter()
        for connection, log_time, raw in self.reader.messages(
            connections=self.reader.topics[topic].connections
        ):
            try:
                msg = self.reader.deserialize(raw, connection.msgtype)
                out.append((message_stamp(msg, log_time / 1e9), camera_from_info(msg)))
            except (GeometryInputError, Exception) as err:  # noqa: BLE001 - counted
                bad[str(err).split(":")[0]] += 1
        self.counts.update({f"camera_info invalid: {k}": v for k, v in bad.items()})
        return sorted(out, key=lambda item: item[0])

    def camera_at(self, stamp: float) -> CameraModel | None:
        """The latest camera model at `stamp` (the first one for frames before it)."""
        if not self._cameras:
            return None
        stamps = [s for s, _ in self._cameras]
        i = max(0, int(np.searchsorted(stamps, stamp, side="right")) - 1)
        return self._cameras[i][1]

    def depth_at(self, stamp: float) -> np.ndarray | None:
        """Depth [H, W] m of the depth message nearest to `stamp` within the tolerance."""
        if self._depth_iter is None:
            return None
        while not self._window or self._window[-1].stamp <= stamp + self.tolerance:
            item = next(self._depth_iter, None)
            if item is None:
                break
            connection, log_time, raw = item
            try:
                msg = self.reader.deserialize(raw, connection.msgtype)
            except Exception:  # noqa: BLE001 - one corrupt depth message: counted
                self.counts["depth undecodable"] += 1
                continue
            self._window.append(_Depth(message_stamp(msg, log_time / 1e9), msg))
        while self._window and self._window[0].stamp < stamp - self.tolerance:
            self._window.popleft()
        if not self._window:
            self.counts["depth: no message within the stamp tolerance"] += 1
            return None
        best = min(self._window, key=lambda d: abs(d.stamp - stamp))
        if abs(best.stamp - stamp) > self.tolerance:
            self.counts["depth: no message within the stamp tolerance"] += 1
            return None
        try:
            return depth_from_msg(best.msg)
        except GeometryInputError as err:
            self.counts[f"depth invalid: {str(err)[:80]}"] += 1
            return None


def open_geometry(
    reader: AnyReader,
    depth_topic: str | None,
    camera_info_topic: str | None,
    tolerance: float,
    counts: Counter[str],
) -> tuple[BagGeometry, str | None, str | None, list[str]]:
    """Pick the topics (None: auto, "none": off) -> (BagGeometry, depth topic, camera_info
    topic, notes for the user)."""
    depth, note_d = choose_depth_topic(reader, depth_topic)
    info, note_i = choose_camera_info_topic(reader, camera_info_topic)
    notes = [n for n in (note_d, note_i) if n]
    if depth and not info:
        notes.append("depth without camera_info: no relative poses (they need intrinsics)")
    geometry = BagGeometry(reader, depth, info, tolerance, counts)
    if info and not geometry._cameras:
        notes.append(f"camera_info topic {info} holds no valid CameraInfo (see the summary's "
                     "geometry_skips): no relative poses")  # fmt: skip
    return geometry, depth, info, notes


def attach(frames: Iterator[Any], geometry: BagGeometry) -> Iterator[Any]:
    """Pipeline frames in bag order -> the same frames with depth and camera set."""
    for frame in frames:
        frame.camera = geometry.camera_at(frame.stamp)
        frame.depth = geometry.depth_at(frame.stamp)
        yield frame
