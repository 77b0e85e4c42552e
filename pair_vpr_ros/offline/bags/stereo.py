"""The right image of a rectified stereo pair from a bag, attached to the replayed frames.

Each frame takes the right image whose header stamp is nearest to its own, within the depth
tolerance (else it goes on without, counted), and the baseline from the right camera's
``CameraInfo`` (P[0, 3] = -fx B; `geometry.stereo.stereo_baseline`). The pipeline turns the pair
into depth for keyframes (`KeyframeGeometry.extract`). The right topic is read by its own
message iterator in step with the images, so memory stays constant.
"""

from __future__ import annotations

from collections import Counter, deque
from collections.abc import Iterator
from typing import Any

import numpy as np
from rosbags.highlevel import AnyReader

from pair_vpr_ros.errors import BagError, GeometryInputError, ImageConversionError
from pair_vpr_ros.geometry.stereo import stereo_baseline
from pair_vpr_ros.images.convert import msg_to_rgb
from pair_vpr_ros.images.pixels import MAX_PIXELS
from pair_vpr_ros.offline.bags.geometry import CAMERA_INFO_TYPE, IMAGE_TYPE
from pair_vpr_ros.types import message_stamp


def _check_topic(reader: AnyReader, topic: str, msgtype: str, flag: str) -> None:
    found = [n for n, i in sorted(reader.topics.items()) if i.msgtype == msgtype]
    if topic not in found:
        raise BagError(f"{flag} {topic} is not a {msgtype} topic of the bag; such topics: "
                       f"{', '.join(found) or 'none'}")  # fmt: skip


class BagStereo:
    """Right images and the stereo baseline of `reader`, for frames in bag (time) order."""

    def __init__(
        self,
        reader: AnyReader,
        right_topic: str,
        right_info_topic: str | None,
        tolerance: float,
        counts: Counter[str],
        max_pixels: int = MAX_PIXELS,
    ) -> None:
        _check_topic(reader, right_topic, IMAGE_TYPE, "--right-topic")
        self.reader, self.tolerance, self.counts = reader, tolerance, counts
        self.max_pixels = max_pixels
        self.baseline = 0.0  # none: keyframes count it as stereo_invalid
        if right_info_topic:
            _check_topic(reader, right_info_topic, CAMERA_INFO_TYPE, "--right-camera-info-topic")
            self.baseline = self._read_baseline(right_info_topic)
        self._iter = reader.messages(connections=reader.topics[right_topic].connections)
        self._window: deque[tuple[float, Any]] = deque()

    def _read_baseline(self, topic: str) -> float:
        for connection, _, raw in self.reader.messages(
            connections=self.reader.topics[topic].connections
        ):
            try:
                return stereo_baseline(self.reader.deserialize(raw, connection.msgtype))
            except (GeometryInputError, Exception) as err:  # noqa: BLE001 - counted
                self.counts[f"right camera_info invalid: {str(err)[:80]}"] += 1
        return 0.0

    def right_at(self, stamp: float) -> np.ndarray | None:
        """RGB [H, W, 3] of the right image nearest to `stamp` within the tolerance."""
        while not self._window or self._window[-1][0] <= stamp + self.tolerance:
            item = next(self._iter, None)
            if item is None:
                break
            connection, log_time, raw = item
            try:
                msg = self.reader.deserialize(raw, connection.msgtype)
            except Exception:  # noqa: BLE001 - one corrupt message: counted
                self.counts["right image undecodable"] += 1
                continue
            self._window.append((message_stamp(msg, log_time / 1e9), msg))
        while self._window and self._window[0][0] < stamp - self.tolerance:
            self._window.popleft()
        best = min(self._window, key=lambda d: abs(d[0] - stamp), default=None)
        if best is None or abs(best[0] - stamp) > self.tolerance:
            self.counts["right image: none within the stamp tolerance"] += 1
            return None
        try:
            return msg_to_rgb(best[1], self.max_pixels)
        except ImageConversionError as err:
            self.counts[f"right image invalid: {str(err)[:80]}"] += 1
            return None


def attach_right(frames: Iterator[Any], stereo: BagStereo) -> Iterator[Any]:
    """Pipeline frames in bag order -> the same frames with the right image and baseline."""
    for frame in frames:
        frame.right = stereo.right_at(frame.stamp)
        frame.baseline = stereo.baseline
        yield frame


def with_right(frames: Iterator[Any], reader: AnyReader, options: Any, counts: Counter[str]):
    """`frames` with the right images of `options.right_topic` (a ``ReplayOptions``), or
    `frames` unchanged without one."""
    if not options.right_topic:
        return frames
    stereo = BagStereo(reader, options.right_topic, options.right_camera_info_topic,
                       options.depth_tolerance, counts, options.max_image_pixels)  # fmt: skip
    return attach_right(frames, stereo)
