"""Several cameras from one bag (issue 49): a rig from repeated ``--topic`` or a rig file, each
camera's extrinsic from the file or from the bag's ``/tf_static``, and every camera's frames
(with its own depth, intrinsics and right image) merged by stamp into rig keyframes.

Repeated ``--topic``: one camera per topic, named by its namespace (``/rear_camera/image_raw``
-> ``rear_camera``); its camera_info and depth topics are the bag's only ones in that namespace
(the rest: none). A rig file names them (``loops.rig.rig_from_dict``). A camera without
``camera_to_base`` takes the pose of its images' frame id in the rig's base frame from
``/tf_static`` (tf2_msgs/TFMessage, chains composed); without either, the replay stops with a
clear error before any frame is read.
"""

from __future__ import annotations

import heapq
import re
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import yaml
from rosbags.highlevel import AnyReader

from pair_vpr_ros.errors import BagError, ConfigError
from pair_vpr_ros.loops.frames import Frame
from pair_vpr_ros.loops.rig import Rig, RigCamera, check_frame_ids, parse_rig, static_chain
from pair_vpr_ros.offline.bags import reader as bag_io
from pair_vpr_ros.offline.bags.geometry import CAMERA_INFO_TYPE, depth_topics, open_geometry
from pair_vpr_ros.offline.bags.sources import FrameCounts, bag_frames
from pair_vpr_ros.offline.bags.stereo import BagStereo

TF_STATIC = "/tf_static"
TF_TYPE = "tf2_msgs/msg/TFMessage"


def read_rig_file(path: str | Path) -> tuple[list[RigCamera], dict[str, Any]]:
    """A rig file (YAML) -> its cameras and settings (`parse_rig`; `resolve_rig` makes the
    Rig); ConfigError naming the file when it is missing or no rig."""
    path = Path(path).expanduser()
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as err:
        raise ConfigError(f"rig file {path} cannot be read: {err}") from err
    return parse_rig(data, f"rig file {path}")


def rig_from_topics(reader: AnyReader, topics: list[str]) -> list[RigCamera]:
    """One camera per image topic (repeated --topic); extrinsics are left to /tf_static."""
    infos = [n for n, i in sorted(reader.topics.items()) if i.msgtype == CAMERA_INFO_TYPE]
    depths, cams, names = depth_topics(reader), [], set()
    for topic in topics:
        space = topic.rpartition("/")[0]
        name = re.sub(r"\W", "_", space.strip("/")) or "camera"
        name = name if name[0].isalpha() else f"c{name}"
        while name in names:
            name += "_2"
        names.add(name)
        info = [t for t in infos if t.startswith(space + "/")]
        depth = [t for t in depths if t.startswith(space + "/") and t != topic]
        cams.append(RigCamera(name, image_topic=topic,
                              camera_info_topic=info[0] if len(info) == 1 else "",
                              depth_topic=depth[0] if len(depth) == 1 else ""))  # fmt: skip
    return cams


def first_frame_id(reader: AnyReader, topic: str) -> str:
    """The header frame id of a topic's first message ("" when it has none or does not read)."""
    for connection, _, raw in reader.messages(connections=reader.topics[topic].connections):
        try:
            return str(reader.deserialize(raw, connection.msgtype).header.frame_id)
        except Exception:  # noqa: BLE001 - an unreadable message: the frames say so later
            return ""
    return ""


def static_edges(reader: AnyReader) -> dict[str, tuple[str, tuple[float, ...]]]:
    """/tf_static of the bag: child frame -> (parent frame, pose of the child in the parent)."""
    info = reader.topics.get(TF_STATIC)
    edges: dict[str, tuple[str, tuple[float, ...]]] = {}
    if info is None or info.msgtype != TF_TYPE:
        return edges
    for connection, _, raw in reader.messages(connections=info.connections):
        try:
            msg = reader.deserialize(raw, connection.msgtype)
        except Exception:  # noqa: BLE001 - one unreadable message: the others may do
            continue
        for t in msg.transforms:
            p, q = t.transform.translation, t.transform.rotation
            edges[t.child_frame_id] = (t.header.frame_id, (p.x, p.y, p.z, q.x, q.y, q.z, q.w))
    return edges


def resolve_rig(
    reader: AnyReader, cameras: list[RigCamera], settings: dict[str, Any], where: str
) -> tuple[Rig, list[str]]:
    """Check every camera's topics and frame id; give each camera without an extrinsic the one
    /tf_static has for its images' frame id. -> (the rig, notes); BagError / ConfigError."""
    notes, edges, frame_ids = [], None, {}
    base = settings.get("base_frame", Rig.base_frame)
    topics = [cam.image_topic for cam in cameras]
    for cam in cameras:
        if not cam.image_topic or topics.count(cam.image_topic) > 1:
            raise ConfigError(f"{where}: rig camera {cam.name!r} needs an image_topic of its "
                              f"own (got {cam.image_topic!r})")  # fmt: skip
        bag_io.choose_image_topic(reader, cam.image_topic)  # an image topic of the bag
        frame_ids[cam.name] = cam.frame_id or first_frame_id(reader, cam.image_topic)
    try:
        check_frame_ids({k: v for k, v in frame_ids.items() if v})
    except ConfigError as err:
        raise ConfigError(f"{where}: {err}") from err
    cams = []
    for cam in cameras:
        if cam.camera_to_base is None:
            edges = static_edges(reader) if edges is None else edges
            pose = static_chain(edges, base, frame_ids[cam.name]) if edges else None
            if pose is None:
                raise ConfigError(
                    f"rig camera {cam.name!r} has no extrinsic: its camera_to_base is not in the "
                    f"rig file and {TF_STATIC} of the bag has no transform from {base!r}"
                    f" to its frame {frame_ids[cam.name]!r}: give camera_to_base in a rig file "
                    "(--rig)"
                )
            notes.append(f"rig camera {cam.name}: camera_to_base from {TF_STATIC} "
                         f"({base} -> {frame_ids[cam.name]})")  # fmt: skip
            cam = replace(cam, camera_to_base=pose)
        cams.append(replace(cam, frame_id=frame_ids[cam.name]))
    try:
        rig = Rig(tuple(cams), **settings)
    except ConfigError as err:
        raise ConfigError(f"{where}: {err}") from err
    check_topics(reader, rig)
    return rig, notes


def camera_frames(
    reader: AnyReader, rig: Rig, index: int, poses: Any, options: Any, counts: FrameCounts,
    source: str,
) -> Iterator[tuple[Frame, bag_io.BagFrame]]:  # fmt: skip
    """Camera `index`'s usable frames (its depth, intrinsics, right image) and the messages
    they came from, in bag order."""
    cam = rig.cameras[index]
    read = bag_io.iter_frames(reader, cam.image_topic, poses, options.pose_tolerance,
                              options.max_frames, max_pixels=options.max_image_pixels)  # fmt: skip
    geometry = open_geometry(reader, cam.depth_topic or "none", cam.camera_info_topic or "none",
                             options.depth_tolerance, counts.geometry_skips)[0]  # fmt: skip
    stereo = None
    if cam.right_topic:
        stereo = BagStereo(reader, cam.right_topic, cam.right_camera_info_topic or None,
                           options.depth_tolerance, counts.geometry_skips,
                           options.max_image_pixels)  # fmt: skip
    for frame, bf in bag_frames(read, counts, f"{source}:{cam.image_topic}"):
        frame.camera_id = index
        frame.camera, frame.depth = geometry.camera_at(frame.stamp), geometry.depth_at(frame.stamp)
        if stereo is not None:
            frame.right, frame.baseline = stereo.right_at(frame.stamp), stereo.baseline
        yield frame, bf


def merged(streams: list[Iterator[tuple[Frame, Any]]]) -> Iterator[tuple[Frame, Any]]:
    """Every camera's (frame, message) stream, merged by stamp (then camera)."""
    return heapq.merge(*streams, key=lambda pair: (pair[0].stamp, pair[0].camera_id))


def check_topics(reader: AnyReader, rig: Rig) -> None:
    """BagError when a camera's camera_info or depth topic is not in the bag."""
    for cam in rig.cameras:
        for what, topic in (("camera_info_topic", cam.camera_info_topic),
                            ("depth_topic", cam.depth_topic)):  # fmt: skip
            if topic and topic not in reader.topics:
                raise BagError(f"rig camera {cam.name!r}: its {what} {topic} is not in the bag "
                               f"(topics: {', '.join(sorted(reader.topics))})")  # fmt: skip
