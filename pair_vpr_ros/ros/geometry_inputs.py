"""The node's depth and intrinsics inputs, ROS-free (messages are duck-typed): buffered depth
images matched to frames by stamp, the latest valid CameraInfo, the parameter fallback.

Depth messages are kept raw (converted only for the frame that uses them). A frame waits up to
`depth_max_delay` s (wall clock) in the worker for its depth image (depth drivers often publish
after the colour image); without one stamped within `depth_tolerance` s of it, it goes on without
depth, counted as ``depth_unmatched``. A depth image that arrives later for such a frame is
counted as ``depth_late`` (so /diagnostics tells a slow depth driver from a missing one).
"""

from __future__ import annotations

import bisect
import threading
import time
from collections import deque
from typing import Any

from pair_vpr_ros.errors import ConfigError, GeometryInputError, ImageConversionError
from pair_vpr_ros.geometry.camera import CameraModel, camera_from_info, camera_from_params
from pair_vpr_ros.geometry.camera_notes import CAMERA_INFO_WAIT_S, camera_info_silence_note
from pair_vpr_ros.geometry.depth import depth_from_msg
from pair_vpr_ros.geometry.stereo import stereo_baseline
from pair_vpr_ros.images.convert import msg_to_rgb
from pair_vpr_ros.types import message_stamp


class _StampBuffer:
    """The last `size` messages in stamp order; `nearest` waits up to `wait` s for a later one.

    The stamps of the last `size` frames that found none are kept, so `add` can tell a message
    that came too late for its frame (under the same lock as `nearest`: no race)."""

    def __init__(self, size: int, tolerance: float) -> None:
        self.size, self.tolerance = size, tolerance
        self._stamps: list[float] = []
        self._msgs: list[Any] = []
        self._missed: deque[float] = deque(maxlen=size)
        self._cond = threading.Condition()

    def add(self, msg: Any) -> bool:
        """Keep `msg`; -> True when a frame already gave up waiting for it (late)."""
        with self._cond:
            stamp = message_stamp(msg)
            late = [s for s in self._missed if abs(s - stamp) <= self.tolerance]
            for s in late:
                self._missed.remove(s)
            i = bisect.bisect_right(self._stamps, stamp)
            self._stamps.insert(i, stamp)
            self._msgs.insert(i, msg)
            if len(self._stamps) > self.size:
                del self._stamps[0], self._msgs[0]
            self._cond.notify_all()
            return bool(late)

    def nearest(self, stamp: float, wait: float) -> Any | None:
        deadline = time.monotonic() + wait
        with self._cond:
            # Once a message at or after `stamp` is in, no later one can be nearer.
            while not (self._stamps and self._stamps[-1] >= stamp):
                left = deadline - time.monotonic()
                if left <= 0:
                    break
                self._cond.wait(left)
            i = bisect.bisect_left(self._stamps, stamp)
            near = [j for j in (i - 1, i) if 0 <= j < len(self._stamps)]
            best = min(near, key=lambda j: abs(self._stamps[j] - stamp), default=None)
            if best is None or abs(self._stamps[best] - stamp) > self.tolerance:
                self._missed.append(stamp)
                return None
            return self._msgs[best]


class GeometryInputs:
    """Depth buffer + camera model for `vpr_node`; `counts` (the node's `NodeCounts`) collects
    the input problems."""

    def __init__(
        self,
        values: dict,
        counts: Any,
        buffer_size: int = 30,
    ) -> None:
        self.enabled_depth = bool(values["depth_topic"])
        self.tolerance = float(values["depth_tolerance"])
        self.wait = float(values["depth_max_delay"])
        self.counts, self.size = counts, buffer_size
        self.values = values
        self._depth = _StampBuffer(buffer_size, self.tolerance)
        self._right = _StampBuffer(buffer_size, self.tolerance)  # stereo: right images (rectified)
        self.baseline = 0.0  # stereo: from the right camera_info
        self.camera_info: CameraModel | None = None
        self.last_problem = ""
        self._first_frame: float | None = None
        self._silence_said = False
        self._info_seen = threading.Event()  # the first usable CameraInfo arrived
        self._info_waited = False  # ... or one frame waited for it in vain: never again
        try:
            self.camera_for(640, 480)  # the fallback parameters make a valid model
        except (GeometryInputError, ValueError) as err:
            raise ConfigError(f"camera_* parameters: {err}") from err

    # ---- callbacks (executor threads) ----------------------------------------------------
    def on_depth(self, msg: Any) -> None:
        if self._depth.add(msg):
            self.counts.depth_late += 1

    def on_right(self, msg: Any) -> None:
        self._right.add(msg)

    def on_right_camera_info(self, msg: Any) -> str | None:
        """Keep the stereo baseline of the right camera's `msg`; -> the problem (counted)."""
        try:
            self.baseline = stereo_baseline(msg)
        except GeometryInputError as err:
            self.counts.camera_info_invalid += 1
            self.last_problem = str(err)
            return self.last_problem
        return None

    def on_camera_info(self, msg: Any) -> str | None:
        """Keep the intrinsics of `msg`; -> the problem when it is unusable (counted)."""
        try:
            self.camera_info = camera_from_info(msg)
            self._info_seen.set()
        except GeometryInputError as err:
            self.counts.camera_info_invalid += 1
            self.last_problem = f"camera_info unusable: {err}"
            return self.last_problem
        return None

    # ---- worker ---------------------------------------------------------------------------
    def await_first_camera_info(self) -> None:
        """With a camera_info topic and none heard yet: wait up to `wait` s for the first one,
        once. A driver (or a bag player) sends it next to the first image, and its callback may
        run just after the worker took that image: without the wait the first keyframe has no
        intrinsics and no loop to it gets a relative pose. A silent topic costs one wait."""
        done = self._info_waited or self._info_seen.is_set()
        if self.values["camera_info_topic"] and not done:
            self._info_waited = not self._info_seen.wait(self.wait)

    def camera_for(self, width: int, height: int) -> CameraModel | None:
        """The CameraInfo intrinsics, else the intrinsics parameters (for this image size),
        else None."""
        if self.camera_info is not None:
            return self.camera_info
        v = self.values
        if v["camera_fx"] <= 0:
            return None
        d = [float(x) for x in v["camera_distortion"].replace(",", " ").split()]
        cx = v["camera_cx"] if v["camera_cx"] >= 0 else (width - 1) / 2
        cy = v["camera_cy"] if v["camera_cy"] >= 0 else (height - 1) / 2
        fy = v["camera_fy"] if v["camera_fy"] > 0 else v["camera_fx"]
        model = v["camera_distortion_model"]
        return camera_from_params(width, height, v["camera_fx"], fy, cx, cy, model, d)

    def depth_for(self, stamp: float) -> Any | None:
        """Depth [H, W] m for a frame at `stamp`, or None (counted when depth is expected)."""
        if not self.enabled_depth:
            return None
        msg = self._depth.nearest(stamp, self.wait)
        if msg is None:
            self.counts.depth_unmatched += 1
            self.last_problem = (
                f"no depth image stamped within depth_tolerance {self.tolerance} s of the image "
                f"({stamp:.3f}) arrived within depth_max_delay {self.wait} s (diagnostics "
                "depth_late counts the ones that came later)"
            )
            return None
        try:
            return depth_from_msg(msg)
        except GeometryInputError as err:
            self.counts.depth_invalid += 1
            self.last_problem = str(err)
            return None

    def right_for(self, stamp: float) -> Any | None:
        """RGB [H, W, 3] of the right image nearest to `stamp` (stereo), or None (counted)."""
        if not self.values.get("right_image_topic"):
            return None
        msg = self._right.nearest(stamp, self.wait)
        try:
            return None if msg is None else msg_to_rgb(msg)
        except ImageConversionError as err:
            self.last_problem = f"right image: {err}"
            return None

    def silence_note(self, now: float) -> str:
        """Once, when camera_info_topic is set and no valid CameraInfo came within
        CAMERA_INFO_WAIT_S s of the first frame: what to check; else ""."""
        topic = self.values["camera_info_topic"]
        if self._first_frame is None:
            self._first_frame = now
        if self._silence_said or not topic or self.camera_info is not None:
            return ""
        if now - self._first_frame < CAMERA_INFO_WAIT_S:
            return ""
        self._silence_said = True
        fallback = self.values["camera_fx"] > 0
        return camera_info_silence_note(topic, now - self._first_frame, fallback)
