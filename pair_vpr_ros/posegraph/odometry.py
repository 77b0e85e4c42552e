"""The odometry history the pose graph keeps, to place a loop's stamp between graph nodes.

Messages are stored at most every ``period_s`` (decimated: 20 Hz is plenty for interpolating a
pose at a stamp), so memory grows with time driven, not with the odometry rate: 64 bytes per
stored message, about 4.6 MB per hour at the default 0.05 s.
"""

from __future__ import annotations

import gtsam
import numpy as np

from pair_vpr_ros.posegraph.transforms import interpolate, pose3


class OdometryHistory:
    """Growable ``stamps [M]`` float64 s and ``poses [M, 7]`` (x, y, z, qx, qy, qz, qw)."""

    def __init__(self, period_s: float = 0.05, max_gap_s: float = 1.0) -> None:
        self.period_s = period_s
        self.max_gap_s = max_gap_s
        self._stamps = np.zeros(1024)
        self._poses = np.zeros((1024, 7))
        self._size = 0
        self._last: tuple[float, tuple[float, ...]] | None = None  # newest message, stored or not

    def __len__(self) -> int:
        return self._size

    @property
    def stamps(self) -> np.ndarray:
        return self._stamps[: self._size]

    @property
    def poses(self) -> np.ndarray:
        return self._poses[: self._size]

    @property
    def latest_stamp(self) -> float | None:
        return None if self._last is None else self._last[0]

    def add(self, stamp: float, pose: tuple[float, ...]) -> None:
        """Keep ``pose`` at ``stamp`` (stamps must increase; the caller checks)."""
        previous = self._last
        self._last = (stamp, pose)
        stored = self._stamps[self._size - 1] if self._size else -np.inf
        gap = previous is not None and stamp - previous[0] > self.max_gap_s
        if gap and previous[0] > stored:
            self._append(*previous)  # keep both ends of a gap so the gap stays visible
        if stamp - stored >= self.period_s or gap:
            self._append(stamp, pose)

    def _append(self, stamp: float, pose: tuple[float, ...]) -> None:
        if self._size == len(self._stamps):
            self._stamps = np.concatenate([self._stamps, np.zeros_like(self._stamps)])
            self._poses = np.concatenate([self._poses, np.zeros_like(self._poses)])
        self._stamps[self._size] = stamp
        self._poses[self._size] = pose
        self._size += 1

    def pose_at(self, stamp: float, tolerance: float) -> gtsam.Pose3 | str:
        """Odometry pose at ``stamp`` (interpolated), or why there is none."""
        self._flush_last()
        stamps = self.stamps
        if self._size == 0:
            return "no odometry yet"
        if stamp < stamps[0] - tolerance:
            return f"stamp before the odometry history ({stamp:.3f} s < {stamps[0]:.3f} s)"
        if stamp > stamps[-1] + tolerance:
            return f"stamp after the newest odometry ({stamp:.3f} s > {stamps[-1]:.3f} s)"
        i = int(np.searchsorted(stamps, stamp))
        if i == 0 or i == self._size:
            return pose3(self._poses[min(i, self._size - 1)])
        t0, t1 = stamps[i - 1], stamps[i]
        if t1 - t0 > self.max_gap_s and min(stamp - t0, t1 - stamp) > tolerance:
            return f"stamp in an odometry gap ({stamp:.3f} s, between {t0:.3f} s and {t1:.3f} s)"
        return interpolate(
            pose3(self._poses[i - 1]), pose3(self._poses[i]), (stamp - t0) / (t1 - t0)
        )

    def _flush_last(self) -> None:
        """Store the newest message too, so lookups reach the very end of the history."""
        if self._last is not None and (self._size == 0 or self._last[0] > self.stamps[-1]):
            self._append(*self._last)
