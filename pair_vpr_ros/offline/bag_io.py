"""Reading camera frames (and optional poses) from rosbags; writing loop closures back to a bag.

Reads rosbag2 folders (mcap or sqlite3 storage), bare ``.mcap`` / ``.db3`` files and ROS 1 ``.bag``
files through rosbags' ``AnyReader``; types come from the definitions stored in the bag, with the
ROS 2 Jazzy typestore as fallback. Every failure becomes a ``BagError`` that names the bag and, for
a failure part-way through, the image message index and stamp where reading stopped.

Frame stamps are header stamps in float seconds (the time base LIO-SAM expects); a zero header
stamp falls back to the bag's receive time. Poses are matched to frames by nearest header stamp.
"""

from __future__ import annotations

import stat
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from functools import lru_cache, partial
from pathlib import Path
from typing import Any

import numpy as np
from rosbags.highlevel import AnyReader, AnyReaderError
from rosbags.rosbag1 import ReaderError as Ros1ReaderError
from rosbags.rosbag2 import ReaderError as Ros2ReaderError
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from pair_vpr_ros import loop_messages
from pair_vpr_ros.errors import BagError, ImageConversionError, OutputError
from pair_vpr_ros.imaging import MAX_PIXELS, msg_to_rgb
from pair_vpr_ros.types import Pose, PoseTrack, message_pose, message_stamp

IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
POSE_TYPES = (
    "nav_msgs/msg/Odometry",
    "geometry_msgs/msg/PoseStamped",
    "geometry_msgs/msg/PoseWithCovarianceStamped",
)
BAG_SUFFIXES = (".mcap", ".db3", ".bag")

_SPECIAL_FILES = (
    (stat.S_ISFIFO, "named pipe (FIFO)"),
    (stat.S_ISSOCK, "socket"),
    (stat.S_ISCHR, "character device"),
    (stat.S_ISBLK, "block device"),
    (stat.S_ISDIR, "folder"),
)
_METADATA_HINT = "the bag folder's metadata.yaml is damaged; `ros2 bag reindex` can rebuild it"
_OPEN_HINTS = {  # first match wins
    "File end magic is invalid": "the MCAP file is truncated or was never closed (recording "
    "interrupted?); the MCAP CLI's `mcap recover` can rebuild it",
    "File magic is invalid": "the file is not an MCAP / ROS 1 bag",
    "seems to be empty": "the file is empty",
    "files are missing": "a storage file that metadata.yaml lists is missing: copy the whole "
    "bag folder",
    "metadata": _METADATA_HINT,
    "YAML": _METADATA_HINT,
    "database": "the sqlite3 (.db3) file is corrupt, truncated or not a rosbag2 database",
    "Bag index looks damaged": "the ROS 1 bag is truncated or was never closed; `rosbag "
    "reindex` can rebuild its index",
    "Bag version": "not a ROS 1 bag (version 2.0)",
    "Rosbag2 version": "written by a rosbag2 newer than this rosbags release reads: upgrade "
    "rosbags (pip install -U rosbags)",
}


def _open_hint(text: str, path: Path) -> str:
    """What to do about an open failure whose message is `text`."""
    hint = next((h for key, h in _OPEN_HINTS.items() if key in text), None)
    if hint is None and "codec can't decode" in text:  # binary where text was expected
        hint = _METADATA_HINT if path.is_dir() else "the file is not a bag"
    return hint or "not a readable bag"


@lru_cache(maxsize=1)
def jazzy_typestore() -> Any:
    """The ROS 2 Jazzy typestore (fallback definitions and the types this package writes)."""
    return get_typestore(Stores.ROS2_JAZZY)


@dataclass(frozen=True)
class BagFrame:
    """One image message of the chosen topic.

    ``rgb`` is ``[H, W, 3]`` uint8, or None with ``error`` set when the message could not be
    deserialised or converted (the caller counts and skips it). ``cdr`` holds the message's CDR
    bytes only when requested (to copy images into an output bag).
    """

    index: int
    stamp: float
    log_time_ns: int
    frame_id: str
    rgb: np.ndarray | None
    pose: Pose | None
    error: str | None = None
    cdr: bytes | None = None


def _bag_name(reader: AnyReader) -> str:
    return ", ".join(str(p) for p in reader.paths)


def _check_regular(path: Path) -> None:
    """A FIFO, socket or device named like a bag would block the reader (or never end)."""
    if path.exists() and not path.is_file():
        mode = path.stat().st_mode
        kind = next((name for test, name in _SPECIAL_FILES if test(mode)), "not a regular file")
        raise BagError(
            f"{path} is a {kind}, not a regular file: reading it could block forever; copy the "
            "recording to a file (or rosbag2 folder) first"
        )


def _resolve(path: Path) -> Path:
    """Check ``path`` names something rosbags can open; a folder without metadata.yaml holding one
    storage file is read through that file."""
    if not path.exists():
        raise BagError(
            f"bag {path} does not exist: give a rosbag2 folder, a .mcap or .db3 file "
            "or a ROS 1 .bag"
        )
    if path.is_dir():
        storage = sorted(p for p in path.iterdir() if p.suffix in (".mcap", ".db3"))
        for part in [path / "metadata.yaml", *storage]:
            _check_regular(part)
        if (path / "metadata.yaml").exists():
            return path
        if len(storage) == 1:
            return storage[0]
        raise BagError(
            f"{path} is a folder without metadata.yaml and with {len(storage)} .mcap/.db3 files: "
            "give a rosbag2 folder or one storage file"
        )
    _check_regular(path)
    if path.suffix not in BAG_SUFFIXES:
        raise BagError(
            f"{path} is not a bag: expected a rosbag2 folder or a file ending in "
            f"{', '.join(BAG_SUFFIXES)}"
        )
    return path


@contextmanager
def open_bag(path: str | Path) -> Iterator[AnyReader]:
    """Open a bag for reading; any failure to open it is a ``BagError`` with a hint."""
    resolved = _resolve(Path(path))
    try:
        reader = AnyReader([resolved], default_typestore=jazzy_typestore())
        reader.open()
    except (AnyReaderError, Ros1ReaderError, Ros2ReaderError, OSError, ValueError) as err:
        text = " ".join(str(err).split()) or type(err).__name__  # one line (YAML errors)
        raise BagError(f"cannot open bag {path}: {text} ({_open_hint(text, resolved)})") from err
    try:
        yield reader
    finally:
        reader.close()


def topics_of_types(reader: AnyReader, msgtypes: tuple[str, ...]) -> dict[str, str]:
    """``{topic: msgtype}`` of the bag's topics whose type is one of ``msgtypes``."""
    return {
        name: info.msgtype
        for name, info in sorted(reader.topics.items())
        if info.msgtype in msgtypes
    }


def _describe(topics: dict[str, str]) -> str:
    return ", ".join(f"{name} ({msgtype})" for name, msgtype in topics.items()) or "none"


def choose_image_topic(reader: AnyReader, topic: str | None = None) -> str:
    """The image topic to replay: ``topic`` when given, else the bag's only image topic."""
    images = topics_of_types(reader, IMAGE_TYPES)
    if not images:
        every = {name: info.msgtype or "?" for name, info in sorted(reader.topics.items())}
        raise BagError(
            f"bag {_bag_name(reader)} has no sensor_msgs/msg/Image or CompressedImage topic "
            f"(topics: {_describe(every)})"
        )
    if topic is None:
        if len(images) > 1:  # a depth stream is not what we recognise places in
            from pair_vpr_ros.offline.bag_geometry import depth_topics

            images = {k: v for k, v in images.items() if k not in depth_topics(reader)} or images
        if len(images) > 1:
            raise BagError(
                f"bag {_bag_name(reader)} has {len(images)} image topics: {_describe(images)}; "
                "choose one with --topic"
            )
        topic = next(iter(images))
    elif topic not in images:
        raise BagError(
            f"topic {topic} is not an image topic of bag {_bag_name(reader)}; "
            f"image topics: {_describe(images)}"
        )
    if reader.topics[topic].msgcount == 0:
        raise BagError(f"image topic {topic} of bag {_bag_name(reader)} has no messages")
    return topic


def choose_pose_topic(reader: AnyReader, topic: str | None = None) -> str | None:
    """The pose topic: ``topic`` if given (checked), else the bag's only pose topic, else None."""
    poses = topics_of_types(reader, POSE_TYPES)
    if topic is None:
        return next(iter(poses)) if len(poses) == 1 else None
    if topic not in poses:
        raise BagError(
            f"topic {topic} is not a pose topic of bag {_bag_name(reader)} (Odometry, PoseStamped "
            f"or PoseWithCovarianceStamped); pose topics: {_describe(poses)}"
        )
    return topic


def read_poses(reader: AnyReader, topic: str) -> tuple[PoseTrack, str | None]:
    """All poses of ``topic`` by header stamp, and why reading stopped part-way (None when it did
    not; the poses before that point are kept). Poses with NaN / inf values are left out and
    counted in ``track.rejected`` (see ``bad_poses_warning``)."""
    track, error = PoseTrack(), None
    messages = reader.messages(connections=reader.topics[topic].connections)
    while True:
        try:
            connection, log_time, raw = next(messages)
            msg = reader.deserialize(raw, connection.msgtype)
        except StopIteration:
            break
        except Exception as err:  # noqa: BLE001 - any reader/deserialiser failure ends the pass
            error = (
                f"reading pose topic {topic} of bag {_bag_name(reader)} stopped after "
                f"{len(track)} messages: {err}"
            )
            break
        track.add(message_stamp(msg, log_time / 1e9), message_pose(msg))
    return track, error


def bad_poses_warning(track: PoseTrack, topic: str) -> str | None:
    """The warning for the poses ``read_poses`` left out (None when none was)."""
    if not track.rejected:
        return None
    return (
        f"{track.rejected} poses of {topic} hold NaN or infinite values and were skipped (the "
        f"first at stamp {track.first_rejected:.3f} s); frames near them have no pose"
    )


def iter_frames(
    reader: AnyReader,
    topic: str,
    poses: PoseTrack | None = None,
    pose_tolerance: float = 0.2,
    max_frames: int | None = None,
    keep_cdr: bool = False,
    convert: Callable[[Any], np.ndarray] | None = None,
    max_pixels: int = MAX_PIXELS,
) -> Iterator[BagFrame]:
    """Yield the image messages of ``topic`` in bag order as ``BagFrame`` s.

    Messages that do not deserialise or convert come back with ``rgb=None`` and ``error`` set.
    A failure of the reader itself raises ``BagError`` saying where it stopped; frames yielded
    before it are valid. ``convert`` defaults to ``imaging.msg_to_rgb`` with ``max_pixels``.
    """
    if convert is None:
        convert = partial(msg_to_rgb, max_pixels=max_pixels)

    def decode(connection: Any, log_time: int, raw: bytes, index: int) -> BagFrame:
        try:
            msg = reader.deserialize(raw, connection.msgtype)
        except Exception as err:  # noqa: BLE001 - one corrupt message is a counted skip
            error = f"cannot deserialise: {err}"
            return BagFrame(index, log_time / 1e9, log_time, "", None, None, error)
        stamp = message_stamp(msg, log_time / 1e9)
        pose = poses.nearest(stamp, pose_tolerance) if poses is not None else None
        cdr = None
        if keep_cdr:  # ROS 1 payloads are re-serialised as ROS 2 CDR
            cdr = bytes(raw) if reader.is2 else _jazzy_cdr(msg, connection.msgtype)
        try:
            rgb, error = convert(msg), None
        except ImageConversionError as err:
            rgb, error = None, str(err)
        return BagFrame(index, stamp, log_time, msg.header.frame_id, rgb, pose, error, cdr)

    messages = reader.messages(connections=reader.topics[topic].connections)
    index, last_stamp = 0, None
    while max_frames is None or index < max_frames:
        try:
            connection, log_time, raw = next(messages)
        except StopIteration:
            return
        except Exception as err:  # noqa: BLE001 - any reader failure is a bag problem
            where = (
                "before the first message" if last_stamp is None else f"stamp {last_stamp:.3f} s"
            )
            raise BagError(
                f"reading {topic} of bag {_bag_name(reader)} stopped at image message {index} "
                f"(after {where}): {err}"
            ) from err
        frame = decode(connection, log_time, raw, index)
        yield frame
        last_stamp, index = frame.stamp, index + 1


def _jazzy_cdr(msg: Any, msgtype: str) -> bytes:
    return bytes(jazzy_typestore().serialize_cdr(msg, msgtype))


class LoopBagWriter:
    """Write loop closures (and optionally the replayed images) to a new rosbag2 folder (mcap).

    Loop messages are the node's (``loop_messages``) on ``/loop_closure``,
    ``/loop_closure/detail``, ``/loop_closure/json`` and (loops with a relative pose)
    ``/loop_closure/factor``, each written at the receive time of its query image so the output
    plays in step with the source bag. Use as a context manager; ``path`` must not exist.
    """

    def __init__(
        self, path: str | Path, image_topic: str | None = None, image_msgtype: str = ""
    ) -> None:
        self.path = Path(path)
        if self.path.exists():
            raise BagError(f"output bag {self.path} exists already: remove it or write elsewhere")
        self._ts = jazzy_typestore()
        self._writer = Writer(self.path, version=9, storage_plugin=StoragePlugin.MCAP)
        self._image_topic, self._image_msgtype = image_topic, image_msgtype
        self._connections: dict[str, Any] = {}

    def __enter__(self) -> LoopBagWriter:
        try:
            self._writer.open()
        except OSError as err:
            raise BagError(f"cannot create output bag {self.path}: {err}") from err
        ts = self._ts
        float_array, string = loop_messages.FLOAT64_ARRAY_TYPE, loop_messages.STRING_TYPE
        for topic, msgtype in (
            (loop_messages.PAIR_TOPIC, float_array),
            (loop_messages.DETAIL_TOPIC, float_array),
            (loop_messages.JSON_TOPIC, string),
            (loop_messages.FACTOR_TOPIC, loop_messages.FACTOR_TYPE),
        ):
            self._connections[topic] = self._writer.add_connection(
                "/" + topic, msgtype, typestore=ts
            )
        if self._image_topic is not None:
            self._connections["image"] = self._writer.add_connection(
                self._image_topic, self._image_msgtype, typestore=ts
            )
        return self

    def __exit__(self, *exc: object) -> None:
        try:
            self._writer.close()
        except OSError as err:
            if exc[0] is None:  # do not hide the error that ended the block
                raise self._failed(err) from err

    def _failed(self, err: OSError) -> OutputError:
        return OutputError(
            f"writing the output bag {self.path} failed ({err.strerror or err}); free disk "
            "space or write elsewhere"
        )

    def _write(self, connection: Any, log_time_ns: int, cdr: bytes) -> None:
        try:
            self._writer.write(connection, log_time_ns, cdr)
        except OSError as err:
            raise self._failed(err) from err

    def write_image(self, cdr: bytes, log_time_ns: int) -> None:
        """Copy one image message (CDR bytes) at its original receive time."""
        self._write(self._connections["image"], log_time_ns, cdr)

    def write_loop(self, record: Any, log_time_ns: int) -> None:
        """Write the messages of one loop closure at ``log_time_ns``."""
        ts, content = self._ts, loop_messages.loop_messages(record)
        array, layout, dim = (
            ts.types["std_msgs/msg/Float64MultiArray"],
            ts.types["std_msgs/msg/MultiArrayLayout"],
            ts.types["std_msgs/msg/MultiArrayDimension"],
        )
        detail = array(
            layout=layout(
                dim=[dim(label=label, size=1, stride=1) for label in content.detail_labels],
                data_offset=0,
            ),
            data=np.asarray(content.detail, dtype=np.float64),
        )
        text = ts.types["std_msgs/msg/String"](data=content.json)
        msgs = []
        if content.pair is not None:  # None: the match is not older (loop_messages.pair_data)
            pair = array(layout=layout(dim=[], data_offset=0), data=np.asarray(content.pair))
            msgs.append((loop_messages.PAIR_TOPIC, pair))
        msgs += [
            (loop_messages.DETAIL_TOPIC, detail),
            (loop_messages.JSON_TOPIC, text),
        ]
        if content.factor is not None:
            msgs.append(
                (loop_messages.FACTOR_TOPIC, loop_messages.factor_msg(content.factor, ts.types))
            )
        for topic, msg in msgs:
            cdr = ts.serialize_cdr(msg, msg.__msgtype__)
            self._write(self._connections[topic], log_time_ns, cdr)


def check_bag_path(path: str | Path) -> Path:
    """The storage path of bag ``path``, or BagError (what is wrong, what to give) when it is
    none; cheap, so a tool checks it before slow work such as finding and loading weights."""
    return _resolve(Path(path))
