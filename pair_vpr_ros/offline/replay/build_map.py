"""Building a place map from a rosbag or an image folder (the node's `~/build_map` service).

ROS-free: the node runs `build_map` in a background thread with a second `LoopClosurePipeline`
over its own model, then saves the result and loads it into the live pipeline.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

from pair_vpr_ros.errors import ConfigError
from pair_vpr_ros.geometry.keyframes import GeometryConfig
from pair_vpr_ros.identity import Identity
from pair_vpr_ros.images.pixels import MAX_PIXELS
from pair_vpr_ros.loops.detector import DetectorConfig
from pair_vpr_ros.loops.pipeline import LoopClosurePipeline
from pair_vpr_ros.model import PairVPRModel
from pair_vpr_ros.offline.bags.sources import FrameCounts, source_frames
from pair_vpr_ros.place_map import IndexConfig


@dataclass
class BuildResult:
    """What one build read and kept; `counts.first_error` names the first unusable image."""

    source: str
    counts: FrameCounts = field(default_factory=FrameCounts)  # images read and skipped
    keyframes: int = 0
    loops: int = 0  # loop closures found while building
    seconds: float = 0.0
    cancelled: bool = False

    @property
    def frames(self) -> int:
        return self.counts.frames

    @property
    def skipped(self) -> int:
        return self.counts.skipped

    def line(self) -> str:
        """One line for `map_info` and the log; bad poses (and why the pose topic stopped) are
        named after it, since frames near them were mapped without a pose."""
        text = (
            f"{self.keyframes} keyframes from {self.frames} images of {self.source} "
            f"({self.skipped} skipped, {self.loops} loops, {self.seconds:.1f} s)"
        )
        return "; ".join([text, *self.counts.pose_warnings])


def build_map(
    model: PairVPRModel,
    config: DetectorConfig,
    source: str | Path,
    *,
    image_topic: str | None = None,
    image_period: float = 1.0,
    index: str | IndexConfig = "flat",
    stop: threading.Event | None = None,
    batch_size: int = 8,
    max_pixels: int = MAX_PIXELS,
    geometry: GeometryConfig | None = None,
    result: BuildResult | None = None,
    identity: Identity | None = None,
) -> tuple[LoopClosurePipeline, BuildResult]:
    """Map every frame of `source` in mapping mode -> (the pipeline holding the unsaved map,
    what was read). `stop` cancels between frames (`result.cancelled`). Raises `ConfigError`
    for a missing source or one without a usable image, `BagError` for an unreadable bag.
    `result`: filled in as the build goes (another thread may read its counts: progress).
    `identity`: robot and session of the keyframes (default: `Identity()`)."""
    result = result if result is not None else BuildResult(source=str(source))
    t0 = time.perf_counter()
    frames = source_frames(source, result.counts, image_topic, image_period, max_pixels)
    pipe = LoopClosurePipeline(
        model, config.updated(mode="mapping"), index=index, geometry=geometry, identity=identity
    )
    try:
        for outcome in pipe.process_many(frames, batch_size=batch_size):
            result.loops += sum(loop.accepted for loop in outcome.reported())
            if stop is not None and stop.is_set():
                result.cancelled = True
                break
        result.keyframes = len(pipe.place_map)
        if not result.cancelled and result.keyframes == 0:
            first = result.counts.first_error
            why = f" (first error: {first})" if first else ""
            raise ConfigError(f"build_source {source} gave no usable image{why}")
    except BaseException:
        pipe.close()
        raise
    result.seconds = time.perf_counter() - t0
    return pipe, result
