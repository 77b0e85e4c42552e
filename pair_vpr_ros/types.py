"""Poses and stamps as the node, the replay, the map build and the place map share them (ROS-free).

Messages are read by duck typing (``msg.header.stamp``, ``msg.pose``), so rclpy messages and the
ones rosbags deserialises both work: ``nav_msgs/Odometry``, ``geometry_msgs/PoseStamped`` and
``geometry_msgs/PoseWithCovarianceStamped``.
"""

from __future__ import annotations

import bisect
import math
import threading
from typing import Any

Pose = tuple[float, float, float, float, float, float, float]
"""``(x, y, z, qx, qy, qz, qw)``: a position in metres and a unit quaternion, in the frame of the
pose topic (odometry or ground truth)."""


def message_stamp(msg: Any, fallback: float = 0.0) -> float:
    """``msg.header.stamp`` in seconds; a zero stamp (publisher never set it) gives ``fallback``
    (the node passes its receive time, the replay the bag's log time)."""
    stamp = msg.header.stamp
    if stamp.sec == 0 and stamp.nanosec == 0:
        return fallback
    return stamp.sec + stamp.nanosec / 1e9


def split_stamp(stamp: float) -> tuple[int, int]:
    """Seconds -> (sec, nanosec) of the nearest nanosecond."""
    sec = math.floor(stamp)
    nsec = round((stamp - sec) * 1e9)
    return (sec + 1, 0) if nsec >= 1_000_000_000 else (int(sec), int(nsec))


def message_pose(msg: Any) -> Pose:
    """The pose of an Odometry / PoseWithCovarianceStamped (``msg.pose.pose``) or a
    PoseStamped (``msg.pose``) message."""
    pose = msg.pose.pose if hasattr(msg.pose, "pose") else msg.pose
    p, q = pose.position, pose.orientation
    return (float(p.x), float(p.y), float(p.z), float(q.x), float(q.y), float(q.z), float(q.w))


class PoseTrack:
    """Poses sorted by stamp, with one nearest-by-stamp lookup.

    ``maxlen`` keeps only the poses with the newest stamps (the node's bounded buffer; None: keep
    all, as a bag's pose topic is read). Thread-safe: the node adds poses from its pose callback
    while its worker looks them up. Stamps may arrive out of order; equal stamps keep their
    arrival order. A pose with a NaN or infinite value (or stamp) is refused and counted in
    ``rejected`` (``first_rejected``: its stamp), so a frame near it gets no pose rather than a bad
    one.
    """

    def __init__(self, maxlen: int | None = None) -> None:
        self._maxlen = maxlen
        self._stamps: list[float] = []
        self._poses: list[Pose] = []
        self._lock = threading.Lock()
        self.rejected = 0
        self.first_rejected: float | None = None

    def add(self, stamp: float, pose: Pose) -> bool:
        """Insert ``pose`` at ``stamp`` seconds (dropping the oldest stamp beyond ``maxlen``);
        False (and counted) when the stamp or a pose value is not finite."""
        if not (math.isfinite(stamp) and all(math.isfinite(v) for v in pose)):
            with self._lock:
                self.rejected += 1
                if self.first_rejected is None:
                    self.first_rejected = stamp
            return False
        with self._lock:
            i = bisect.bisect_right(self._stamps, stamp)
            self._stamps.insert(i, stamp)
            self._poses.insert(i, pose)
            if self._maxlen is not None and len(self._stamps) > self._maxlen:
                del self._stamps[0], self._poses[0]
        return True

    def nearest(self, stamp: float, tolerance: float) -> Pose | None:
        """The pose closest in time to ``stamp`` (the earlier on a tie), or None when none lies
        within ``tolerance`` seconds."""
        with self._lock:
            i = bisect.bisect_left(self._stamps, stamp)
            near = [j for j in (i - 1, i) if 0 <= j < len(self._stamps)]
            if not near:
                return None
            best = min(near, key=lambda j: abs(self._stamps[j] - stamp))
            return self._poses[best] if abs(self._stamps[best] - stamp) <= tolerance else None

    def items(self) -> tuple[list[float], list[Pose]]:
        """Copies of every stamp (s, ascending) and its pose."""
        with self._lock:
            return list(self._stamps), list(self._poses)

    def __len__(self) -> int:
        return len(self._stamps)
