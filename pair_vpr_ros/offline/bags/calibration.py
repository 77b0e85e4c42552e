"""int8 calibration images from the robot's own recording: a rosbag's image topic or a folder.

Static int8 (backend openvino, precision int8) fixes each activation's range from a few sample
images. By default they are synthetic scenes (`model/calibration.py`); the parameter
``openvino_calibration`` (replay: ``--openvino-calibration``) names a bag or an image folder of
the robot's own camera instead, so the ranges are those of the images the node will see. The
images are picked evenly over the recording (`evenly_spaced`), decoded as the node decodes
frames (`images.convert`, with its ``max_image_pixels`` limit) and preprocessed as the
network's input.
An unusable image is skipped and counted; fewer than 2 usable ones is a ``ConfigError``.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
from torch import Tensor

from pair_vpr_ros.errors import ConfigError, ImageConversionError
from pair_vpr_ros.images.encoded import file_to_rgb
from pair_vpr_ros.images.pixels import MAX_PIXELS
from pair_vpr_ros.model import preprocess_batch
from pair_vpr_ros.model.calibration import CALIBRATION_IMAGES
from pair_vpr_ros.offline.bags import reader as bag_io
from pair_vpr_ros.offline.bags.opening import open_bag
from pair_vpr_ros.offline.bags.sources import FrameCounts, bag_frames, check_source, folder_images

PARAM = "openvino_calibration"
SYNTHETIC = " (or '' for synthetic scenes)"
TOPIC_FLAG = "openvino_calibration_topic (replay: --openvino-calibration-topic)"
MIN_IMAGES = 2  # what `OpenVINOModel` accepts


def evenly_spaced(total: int, count: int) -> list[int]:
    """`count` indices spread evenly over ``range(total)``, the first and last included (the
    nearest index to each of `count` equal steps); every index when ``total <= count``."""
    if total <= count:
        return list(range(total))
    if count == 1:
        return [0]
    steps = count - 1
    return [(2 * i * (total - 1) + steps) // (2 * steps) for i in range(count)]


def check_calibration_source(source: str | Path) -> Path:
    """The path of calibration source `source` (cheap: callers check before loading weights);
    ConfigError when it does not exist or is a folder with neither images nor a bag."""
    return check_source(source, PARAM, SYNTHETIC)


def _folder_rgb(path: Path, count: int, counts: FrameCounts, max_pixels: int) -> list:
    files = folder_images(path)
    out = []
    for i in evenly_spaced(len(files), count):
        counts.frames += 1
        try:
            out.append(file_to_rgb(files[i], max_pixels))
        except ImageConversionError as err:  # the message names the file
            counts.skip(str(err))
    return out


def _bag_rgb(
    path: Path, count: int, counts: FrameCounts, max_pixels: int, topic: str | None
) -> tuple[list[np.ndarray], str]:
    with open_bag(path) as reader:
        topic = bag_io.choose_image_topic(reader, topic, TOPIC_FLAG)
        picks = set(evenly_spaced(reader.topics[topic].msgcount, count))
        frames = bag_io.iter_frames(reader, topic, max_pixels=max_pixels, indices=picks)
        return [frame.rgb for frame, _ in bag_frames(frames, counts, f"{path}:{topic}")], topic


def calibration_images(
    source: str | Path,
    size: int,
    count: int = CALIBRATION_IMAGES,
    topic: str | None = None,
    max_pixels: int = MAX_PIXELS,
    counts: FrameCounts | None = None,
) -> Tensor:
    """`count` images picked evenly from a bag's image topic (``topic``, else its only one) or an
    image folder (sorted by name), preprocessed for the network -> float32 [B,3,size,size],
    B <= count. Unusable images (also those over ``max_pixels``) are skipped and counted in
    `counts`, as is a bag that stops part-way. ConfigError: a missing or empty source, or fewer
    than 2 usable images; BagError: a bag that does not open or lacks the topic."""
    path = check_calibration_source(source)
    counts = FrameCounts() if counts is None else counts
    if path.is_dir() and folder_images(path):
        rgb, where = _folder_rgb(path, count, counts, max_pixels), f"folder {path}"
    else:
        rgb, topic = _bag_rgb(path, count, counts, max_pixels, topic)
        where = f"topic {topic} of bag {path}"
    if len(rgb) < MIN_IMAGES:
        why = "; ".join(w for w in (counts.first_error, counts.error) if w)
        raise ConfigError(
            f"{PARAM}: {len(rgb)} usable image(s) of {counts.frames} picked from {where}"
            f"{f' ({why})' if why else ''}; int8 calibration needs at least {MIN_IMAGES}: give a "
            f"bag or folder with more readable camera images{SYNTHETIC}"
        )
    return preprocess_batch(rgb, size)


def skipped_note(counts: FrameCounts, source: str | Path) -> str | None:
    """What to tell the user about images `calibration_images` could not use (None: none)."""
    if not counts.skipped and counts.error is None:
        return None
    parts = []
    if counts.skipped:
        parts.append(
            f"{counts.skipped} of {counts.frames} picked images skipped (first: "
            f"{counts.first_error})"
        )
    if counts.error is not None:
        parts.append(f"reading stopped part-way: {counts.error}")
    return f"{PARAM} {source}: " + "; ".join(parts) + "; calibrated on the others"


def calibration_loader(
    source: str | Path,
    topic: str | None = None,
    max_pixels: int = MAX_PIXELS,
    warn: Callable[[str], None] | None = None,
    count: int = CALIBRATION_IMAGES,
) -> Callable[[int], Tensor] | None:
    """What ``weights.load_model(openvino_calibration=...)`` takes: image size -> the images of
    `calibration_images` [B,3,S,S] (skips reported through `warn`); None for source '' (the
    synthetic scenes). The source is checked here, before any weights are loaded."""
    if not str(source):
        return None
    check_calibration_source(source)

    def load(size: int) -> Tensor:
        counts = FrameCounts()
        images = calibration_images(source, size, count, topic or None, max_pixels, counts)
        note = skipped_note(counts, source)
        if note is not None and warn is not None:
            warn(note)
        return images

    return load
