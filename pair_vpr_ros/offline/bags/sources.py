"""Pipeline frames from a rosbag or an image folder, counting what cannot be used.

The replay (``offline.replay``) and the map build (``offline.build_map``, the node's
``~/build_map``) read frames through here, so both skip and count an unusable image the same way:
a message that does not deserialise or convert, a file that is not a readable image.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

from pair_vpr_ros.errors import BagError, ConfigError, ImageConversionError
from pair_vpr_ros.images.encoded import IMAGE_SUFFIXES, file_to_rgb
from pair_vpr_ros.images.pixels import MAX_PIXELS
from pair_vpr_ros.loops.frames import Frame
from pair_vpr_ros.offline.bags import reader as bag_io
from pair_vpr_ros.offline.bags.geometry import attach, open_geometry
from pair_vpr_ros.offline.bags.opening import open_bag
from pair_vpr_ros.offline.bags.reader import BagFrame

DEPTH_TOLERANCE = 0.02  # s between an image and its depth image when building a map


@dataclass
class FrameCounts:
    """What a source gave: ``frames`` images read (messages or files), ``skipped`` unusable ones
    counted by ``reasons``, ``first_error`` the first unusable one and where it was, ``error`` why
    reading stopped part-way (None when it did not; the frames before it are valid)."""

    frames: int = 0
    skipped: int = 0
    reasons: Counter[str] = field(default_factory=Counter)
    first_error: str = ""
    error: str | None = None
    # Usable frames whose stamp is earlier than (backwards) or equal to (repeated) the previous
    # usable frame's: reported, since the detector's time windows compare stamps.
    backwards: int = 0
    repeated: int = 0
    first_backwards: str = ""
    last_stamp: float | None = None
    geometry_skips: Counter[str] = field(default_factory=Counter)  # depth / camera_info problems
    # Pose messages left out (NaN / inf values) and why the pose topic was not read to its end:
    # the frames near them have no pose (`bag_io.bad_poses_warning`).
    bad_poses: int = 0
    pose_warnings: list[str] = field(default_factory=list)

    def skip(self, reason: str, where: str = "") -> None:
        self.skipped += 1
        self.reasons[reason] += 1
        self.first_error = self.first_error or (f"{where}: {reason}" if where else reason)

    def stamp(self, stamp: float, where: str) -> None:
        """Note the stamp of the next usable frame (counts stamps that do not increase)."""
        last, self.last_stamp = self.last_stamp, stamp
        if last is None or stamp > last:
            return
        if stamp == last:
            self.repeated += 1
            return
        self.backwards += 1
        self.first_backwards = self.first_backwards or f"{where}: {stamp:.3f} s after {last:.3f} s"

    def stamp_warnings(self, topic: str) -> list[str]:
        """What to tell the user about stamps that do not increase ([] when they all do)."""
        used = self.frames - self.skipped
        advice = (
            "a step back of more than 1 s starts a new session (clock_jumps), and a frame only "
            "matches keyframes stamped at least exclude_recent_s from it, before or after; "
            "unless the recording was played twice, check the camera driver's stamps"
        )
        if used > 1 and self.repeated == used - 1:
            return [
                f"all {used} image stamps of {topic} are identical ({self.last_stamp:.3f} s): "
                "no frame can match another (keyframes at a frame's own stamp never do); check "
                "the camera driver's stamps"
            ]
        out = []
        if self.backwards:
            out.append(
                f"{self.backwards} image stamps of {topic} go back in time (first at "
                f"{self.first_backwards}): " + advice
            )
        if self.repeated:
            out.append(f"{self.repeated} image stamps of {topic} repeat the previous one")
        return out


def bag_frames(
    frames: Iterable[BagFrame], counts: FrameCounts, source: str
) -> Iterator[tuple[Frame, BagFrame]]:
    """The usable frames of ``bag_io.iter_frames`` as pipeline frames (``source#index``), each
    with the ``BagFrame`` it came from. A ``BagError`` part-way ends the frames quietly, kept in
    ``counts.error``, so the pipeline still flushes the frames it holds."""
    try:
        for bf in frames:
            counts.frames += 1
            if bf.rgb is None:
                counts.skip(bf.error or "unknown", f"message {bf.index}")
                continue
            counts.stamp(bf.stamp, f"message {bf.index}")
            yield Frame(bf.stamp, bf.rgb, bf.frame_id, bf.pose, f"{source}#{bf.index}"), bf
    except BagError as err:
        counts.error = str(err)


def folder_images(folder: Path) -> list[Path]:
    """The image files directly in ``folder`` (``IMAGE_SUFFIXES``), sorted by name."""
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)


def folder_frames(
    files: Iterable[Path], counts: FrameCounts, period: float, max_pixels: int = MAX_PIXELS
) -> Iterator[Frame]:
    """Image files as frames stamped ``i * period`` s (frame id: the file's stem), decoded by
    ``images.encoded.file_to_rgb`` (its size limit ``max_pixels`` and 16-bit scaling)."""
    for i, path in enumerate(files):
        counts.frames += 1
        try:
            rgb = file_to_rgb(path, max_pixels)
        except ImageConversionError as err:  # the message names the file
            counts.skip(str(err))
            continue
        yield Frame(stamp=i * period, rgb=rgb, frame_id=path.stem, source=str(path))


def _bag_source(
    path: Path, topic: str | None, counts: FrameCounts, max_pixels: int, pose_topic: str | None
) -> Iterator[Frame]:
    with open_bag(path) as reader:
        topic = bag_io.choose_image_topic(reader, topic)
        pose_topic = bag_io.choose_pose_topic(reader, pose_topic)
        poses = None
        if pose_topic:
            poses, error = bag_io.read_poses(reader, pose_topic)
            counts.bad_poses = poses.rejected
            bad = bag_io.bad_poses_warning(poses, pose_topic)
            counts.pose_warnings += [w for w in (error, bad) if w]
        read = bag_io.iter_frames(reader, topic, poses, max_pixels=max_pixels)
        # Depth and intrinsics when the bag has one topic of each (poses need them later).
        geometry = open_geometry(reader, None, None, DEPTH_TOLERANCE, counts.geometry_skips)[0]
        usable = (frame for frame, _ in bag_frames(read, counts, f"{path}:{topic}"))
        yield from attach(usable, geometry)
    if counts.error is not None:
        raise BagError(counts.error)


def source_frames(
    source: str | Path,
    counts: FrameCounts,
    image_topic: str | None = None,
    period: float = 1.0,
    max_pixels: int = MAX_PIXELS,
    pose_topic: str | None = None,
) -> Iterator[Frame]:
    """Frames of a bag (header stamps; poses of ``pose_topic``, else of the bag's only pose
    topic) or of an image folder (stamps ``i * period`` s). Unusable images (also those over
    ``max_pixels``) are counted in ``counts``; a missing source is a ``ConfigError``, an
    unreadable bag (also part-way) a ``BagError``."""
    path = check_source(source)
    if path.is_dir() and folder_images(path):
        return folder_frames(folder_images(path), counts, period, max_pixels)
    return _bag_source(path, image_topic or None, counts, max_pixels, pose_topic)


def check_source(source: str | Path, name: str = "build_source", otherwise: str = "") -> Path:
    """The path of a source (parameter ``name``) that exists and may hold frames (ConfigError
    otherwise: a missing path, or a folder with neither images nor a bag in it; ``otherwise``
    ends the advice, e.g. "or '' for ...")."""
    path = Path(source).expanduser()
    kinds = (
        f"a rosbag (folder, .mcap, .db3 or .bag) or an image folder ({', '.join(IMAGE_SUFFIXES)})"
        + otherwise
    )
    if not str(source) or not path.exists():
        raise ConfigError(f"{name} {str(source)!r} does not exist: set it to {kinds}")
    if path.is_dir() and not folder_images(path):
        bag_files = [
            p for p in path.iterdir() if p.name == "metadata.yaml" or p.suffix in (".mcap", ".db3")
        ]
        if not bag_files:
            raise ConfigError(
                f"{name} {path} is a folder with neither images nor a rosbag2 "
                f"(metadata.yaml or a .mcap/.db3 file) in it: set it to {kinds}"
            )
    return path
