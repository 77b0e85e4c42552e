"""The loop image, ROS-free: query | match side by side, the verified inlier matches drawn
between them, and the decision written above (scores, inliers, pose or the reason it was
rejected). One drawing for every consumer: the node's ``loop_closure/image`` (sensor_msgs/Image,
bgr8), the replay's ``--write-bag`` (the same topic) and the report's per-loop images.

A keyframe without an image (a prior map's, another robot's, one no longer kept) is drawn as a
grey panel that says so, never left out, so the picture always shows which side is missing.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import cv2
import numpy as np

from pair_vpr_ros.images.thumbnails import MemoryThumbnails, Thumbnail
from pair_vpr_ros.loops.frames import FrameOutcome, match_candidate
from pair_vpr_ros.loops.records import Candidate

IMAGE_TOPIC = "loop_closure/image"
IMAGE_TYPE = "sensor_msgs/msg/Image"
PANEL_HEIGHT = 240  # px of each image in the drawing
MAX_LINES = 150  # inlier matches drawn at most (evenly picked): more hide the images
_BANNER, _GAP = 42, 4
_FONT = cv2.FONT_HERSHEY_SIMPLEX
_ACCEPTED, _REJECTED = (40, 120, 40), (40, 40, 150)  # banner colours, BGR
_PALETTE = [(80, 220, 80), (240, 200, 60), (60, 200, 240), (230, 110, 230), (90, 160, 255)]


def pose_sigmas(record: Any) -> tuple[float, float] | None:
    """(largest translation std in m, largest rotation std in degrees) of the record's pose
    covariance (x, y, z, rx, ry, rz order); None without a pose."""
    cov = record.covariance
    if not record.pose_status or len(cov) != 36:
        return None
    diag = np.sqrt(np.maximum(np.diag(np.asarray(cov, np.float64).reshape(6, 6)), 0.0))
    return float(diag[:3].max()), math.degrees(float(diag[3:].max()))


def decision_lines(record: Any) -> tuple[str, str]:
    """Two lines saying what was decided about `record` (a LoopRecord or its dict)."""
    verdict = "LOOP" if record.accepted else "REJECTED"
    score = "not scored" if not math.isfinite(record.pair_score) else f"{record.pair_score:.2f}"
    first = (
        f"{verdict} {record.query_id} -> {record.match_id}  pair {score}  "
        f"sim {record.global_similarity:.3f}  rank {record.rank_before}->{record.rank_after}"
    )
    inliers = f"{record.inliers} inliers" if record.inliers >= 0 else "not verified"
    if not record.accepted:
        return first, f"{record.reason} ({inliers})"
    sigmas = pose_sigmas(record)
    if sigmas is None:
        pose = f"no pose: {record.pose_reason}" if record.pose_reason else "no pose"
    else:
        t = math.sqrt(record.tx**2 + record.ty**2 + record.tz**2)
        pose = (
            f"pose {record.pose_status} |t| {t:.2f} m, sigma {sigmas[0]:.3f} m {sigmas[1]:.2f} deg"
        )
    return first, f"{inliers}, {pose}"


def _panel(image: Thumbnail | None, height: int, missing: str) -> tuple[np.ndarray, float]:
    """One side as BGR [height, w, 3] and its scale from original pixels; a grey panel with
    `missing` written on it when there is no image."""
    if image is None:
        panel = np.full((height, height * 4 // 3, 3), 90, np.uint8)
        for i, text in enumerate(missing.split("\n")):
            cv2.putText(panel, text, (8, height // 2 + 18 * i), _FONT, 0.45, (230, 230, 230), 1,
                        cv2.LINE_AA)  # fmt: skip
        return panel, 0.0
    h, w = image.rgb.shape[:2]
    factor = height / h
    size = (max(1, round(w * factor)), height)
    panel = cv2.resize(image.rgb, size, interpolation=cv2.INTER_AREA if factor < 1 else
                       cv2.INTER_LINEAR)  # fmt: skip
    return cv2.cvtColor(panel, cv2.COLOR_RGB2BGR), image.scale * factor


def draw_loop(
    record: Any,
    query: Thumbnail | None,
    match: Thumbnail | None,
    matches: np.ndarray | None = None,
    height: int = PANEL_HEIGHT,
) -> np.ndarray:
    """BGR uint8 [42 + height, w, 3]: `query` | `match` (None: no image), `matches` [I, 4]
    (query x, y, match x, y in original pixels: `FrameOutcome.matches`) drawn as lines, and
    `decision_lines(record)` above."""
    left, sq = _panel(query, height, f"no image of keyframe {record.query_id}")
    right, sm = _panel(match, height, f"no image of keyframe {record.match_id}\n(prior map, "
                       "other robot or not kept)")  # fmt: skip
    width = left.shape[1] + _GAP + right.shape[1]
    out = np.full((_BANNER + height, width, 3), 255, np.uint8)
    out[:_BANNER] = _ACCEPTED if record.accepted else _REJECTED
    out[_BANNER:, : left.shape[1]] = left
    x0 = left.shape[1] + _GAP
    out[_BANNER:, x0:] = right
    for i, text in enumerate(decision_lines(record)):
        cv2.putText(out, text, (6, 16 + 18 * i), _FONT, 0.42, (255, 255, 255), 1, cv2.LINE_AA)
    if matches is not None and len(matches) and sq > 0 and sm > 0:
        pick = np.linspace(0, len(matches) - 1, min(len(matches), MAX_LINES)).round().astype(int)
        for n, (xq, yq, xm, ym) in enumerate(np.asarray(matches, np.float64)[pick]):
            a = (round(xq * sq), _BANNER + round(yq * sq))
            b = (x0 + round(xm * sm), _BANNER + round(ym * sm))
            colour = _PALETTE[n % len(_PALETTE)]
            cv2.line(out, a, b, colour, 1, cv2.LINE_AA)
            cv2.circle(out, a, 2, colour, -1, cv2.LINE_AA)
            cv2.circle(out, b, 2, colour, -1, cv2.LINE_AA)
    return out


def image_fields(bgr: np.ndarray) -> dict[str, Any]:
    """The sensor_msgs/Image fields of a BGR uint8 [h, w, 3] image, header aside."""
    h, w = bgr.shape[:2]
    return dict(height=h, width=w, encoding="bgr8", is_bigendian=0, step=3 * w,
                data=np.ascontiguousarray(bgr).reshape(-1))  # fmt: skip


class LoopPictures:
    """Loop images of a running pipeline: the query image comes with its outcome, the match's
    from `images` (a candidate -> its image, e.g. the report's files), else from the keyframe
    images this object keeps in memory (`keep`, at most `max_bytes` of JPEG: the oldest go).
    Only keyframes of `identity` (robot, session) have images; others are drawn as missing."""

    def __init__(
        self,
        identity: tuple[str, str],
        max_bytes: int = 64 << 20,
        images: Callable[[Candidate], Thumbnail | None] | None = None,
        height: int = PANEL_HEIGHT,
    ) -> None:
        self.identity, self.height, self._images = identity, height, images
        self.memory = MemoryThumbnails(max_bytes) if images is None else None

    def keep(self, outcome: FrameOutcome, rgb: np.ndarray | None) -> None:
        """Keep a stored keyframe's image, for loops to it later."""
        if self.memory is not None and rgb is not None and outcome.keyframe_id is not None:
            self.memory.put(outcome.keyframe_id, outcome.stamp, rgb)

    def match_image(self, cand: Candidate | None) -> Thumbnail | None:
        if cand is None or cand.prior >= 0 or (cand.robot, cand.session) != self.identity:
            return None  # a prior map's or another robot's keyframe: no image here
        if self._images is not None:
            return self._images(cand)
        return self.memory.get(cand.id, cand.stamp)

    def draw(self, outcome: FrameOutcome, record: Any, rgb: np.ndarray | None) -> np.ndarray:
        """BGR uint8: `record` (a decision of `outcome`) drawn by `draw_loop`, query `rgb`."""
        match = self.match_image(match_candidate(outcome, record))
        query = Thumbnail(rgb, 1.0) if rgb is not None else None
        return draw_loop(record, query, match, outcome.matches.get(record.rank_before),
                         self.height)  # fmt: skip
