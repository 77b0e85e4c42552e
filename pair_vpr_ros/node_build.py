"""Building a place map from a rosbag or an image folder (the node's `~/build_map` service).

ROS-free: the node runs `build_map` in a background thread with a second `LoopClosurePipeline`
over its own model, then saves the result and loads it into the live pipeline.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2

from . import bag_io
from .detector import DetectorConfig
from .errors import ConfigError
from .model import PairVPR
from .pipeline import Frame, LoopClosurePipeline

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp")


@dataclass
class BuildResult:
    """What one build read and kept; `first_error` names the first unusable image."""

    source: str
    frames: int = 0  # images read
    skipped: int = 0  # images that could not be decoded or converted
    keyframes: int = 0
    loops: int = 0  # loop closures found while building
    seconds: float = 0.0
    cancelled: bool = False
    first_error: str = ""

    def line(self) -> str:
        return (
            f"{self.keyframes} keyframes from {self.frames} images of {self.source} "
            f"({self.skipped} skipped, {self.loops} loops, {self.seconds:.1f} s)"
        )


def folder_images(folder: Path) -> list[Path]:
    """The image files directly in `folder`, sorted by name."""
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)


def _folder_frames(files: list[Path], period: float, result: BuildResult) -> Iterator[Frame]:
    for i, path in enumerate(files):
        result.frames += 1
        bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if bgr is None:
            result.skipped += 1
            result.first_error = result.first_error or f"{path}: not a readable image"
            continue
        rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
        yield Frame(stamp=i * period, rgb=rgb, frame_id=path.stem, source=str(path))


def _bag_frames(path: Path, topic: str | None, result: BuildResult) -> Iterator[Frame]:
    with bag_io.open_bag(path) as reader:
        topic = bag_io.choose_image_topic(reader, topic)
        pose_topic = bag_io.choose_pose_topic(reader)
        poses = bag_io.read_poses(reader, pose_topic) if pose_topic else None
        for bf in bag_io.iter_frames(reader, topic, poses):
            result.frames += 1
            if bf.rgb is None:
                result.skipped += 1
                result.first_error = result.first_error or f"message {bf.index}: {bf.error}"
                continue
            yield Frame(bf.stamp, bf.rgb, bf.frame_id, bf.pose, f"{path}:{topic}")


def source_frames(
    source: str | Path, result: BuildResult, image_topic: str | None = None, period: float = 1.0
) -> Iterator[Frame]:
    """Frames of a bag (header stamps, poses when the bag has one pose topic) or of an image
    folder (stamps `i * period` s). Unusable images are counted in `result`, not raised."""
    path = Path(source).expanduser()
    if not str(source) or not path.exists():
        raise ConfigError(
            f"build_source {str(source)!r} does not exist: set it to a rosbag (folder, .mcap, "
            ".db3 or .bag) or an image folder"
        )
    if path.is_dir() and folder_images(path):
        return _folder_frames(folder_images(path), period, result)
    return _bag_frames(path, image_topic or None, result)


def build_map(
    model: PairVPR,
    config: DetectorConfig,
    source: str | Path,
    *,
    image_topic: str | None = None,
    image_period: float = 1.0,
    index: str = "flat",
    stop: threading.Event | None = None,
    batch_size: int = 8,
) -> tuple[LoopClosurePipeline, BuildResult]:
    """Map every frame of `source` in mapping mode -> (the pipeline holding the unsaved map,
    what was read). `stop` cancels between frames (`result.cancelled`). Raises `ConfigError`
    for a missing source or one without a usable image, `BagError` for an unreadable bag."""
    result = BuildResult(source=str(source))
    t0 = time.perf_counter()
    frames = source_frames(source, result, image_topic, image_period)
    pipe = LoopClosurePipeline(model, config.updated(mode="mapping"), index=index)
    try:
        for outcome in pipe.process_many(frames, batch_size=batch_size):
            result.loops += bool(outcome.loop and outcome.loop.accepted)
            if stop is not None and stop.is_set():
                result.cancelled = True
                break
        result.keyframes = len(pipe.place_map)
        if not result.cancelled and result.keyframes == 0:
            why = f" (first error: {result.first_error})" if result.first_error else ""
            raise ConfigError(f"build_source {source} gave no usable image{why}")
    except BaseException:
        pipe.close()
        raise
    result.seconds = time.perf_counter() - t0
    return pipe, result
