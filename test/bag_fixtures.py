"""Bag writers for tests: rosbags (mcap / sqlite3 / ROS 1) and foxglove's mcap writer.

Every writer takes ``images = [(stamp_s, rgb [H, W, 3] uint8)]`` and
``poses = [(stamp_s, (x, y, z))]`` and stores log times equal to the header stamps.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import cv2
import numpy as np
from rosbags.rosbag1 import Writer as Ros1Writer
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

TS2 = get_typestore(Stores.ROS2_JAZZY)
TS1 = get_typestore(Stores.ROS1_NOETIC)
IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
ODOMETRY = "nav_msgs/msg/Odometry"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
POSE_COV = "geometry_msgs/msg/PoseWithCovarianceStamped"


def synthetic_images(n: int, size: int = 16, seed: int = 0) -> list[np.ndarray]:
    """``n`` distinct random RGB images ``[size, size, 3]`` uint8."""
    rng = np.random.default_rng(seed)
    return [rng.integers(0, 256, (size, size, 3), dtype=np.uint8) for _ in range(n)]


def textured(seed: int, height: int = 120, width: int = 160) -> np.ndarray:
    """RGB uint8 ``[height, width, 3]``: 80 random rectangles on grey, corners for features."""
    rng = np.random.default_rng(seed)
    img = np.full((height, width, 3), 90, np.uint8)
    for _ in range(80):
        x, y = (int(v) for v in rng.integers(0, (width, height)))
        w, h = (int(v) for v in rng.integers(4, 20, 2))
        cv2.rectangle(img, (x, y), (x + w, y + h), [int(c) for c in rng.integers(0, 256, 3)], -1)
    return img


def revisit_world() -> tuple[list, list]:
    """(images, poses) of a small loop: 10 places at 1 Hz, 20 m apart; revisits of places 0-4
    at t = 100..104 s; two new places at t = 105, 106 s far away. 32 px images."""
    imgs = synthetic_images(12, size=32)
    images = [(float(i), imgs[i]) for i in range(10)]
    poses = [(float(i), (20.0 * i, 0.0, 0.0)) for i in range(10)]
    images += [(100.0 + i, imgs[i]) for i in range(5)]
    poses += [(100.0 + i, (20.0 * i, 0.0, 0.0)) for i in range(5)]
    images += [(105.0, imgs[10]), (106.0, imgs[11])]
    poses += [(105.0, (500.0, 500.0, 0.0)), (106.0, (600.0, 500.0, 0.0))]
    return images, poses


def _ns(stamp: float) -> int:
    return int(round(stamp * 1e9))


def _header(ts, stamp: float, frame_id: str, ros1: bool = False):
    sec, nsec = divmod(_ns(stamp), 10**9)
    time = ts.types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec)
    if ros1:
        return ts.types["std_msgs/msg/Header"](seq=0, stamp=time, frame_id=frame_id)
    return ts.types["std_msgs/msg/Header"](stamp=time, frame_id=frame_id)


def image_msg(ts, stamp: float, rgb: np.ndarray, compressed: bool, ros1: bool = False, **over):
    """An Image (rgb8) or CompressedImage (png) message of ``rgb``; ``over`` overrides fields."""
    header = _header(ts, stamp, over.pop("frame_id", "cam"), ros1)
    if compressed:
        ok, png = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        assert ok
        fields = dict(header=header, format="png", data=png.reshape(-1))
        return ts.types[COMPRESSED](**{**fields, **over})
    h, w = rgb.shape[:2]
    fields = dict(
        header=header, height=h, width=w, encoding="rgb8", is_bigendian=0, step=3 * w,
        data=rgb.reshape(-1).copy(),
    )  # fmt: skip
    return ts.types[IMAGE](**{**fields, **over})


def pose_msg(ts, msgtype: str, stamp: float, xyz: tuple[float, float, float], ros1: bool = False):
    """An Odometry / PoseStamped / PoseWithCovarianceStamped at ``xyz`` with identity rotation."""
    g = "geometry_msgs/msg/"
    pose = ts.types[g + "Pose"](
        position=ts.types[g + "Point"](x=xyz[0], y=xyz[1], z=xyz[2]),
        orientation=ts.types[g + "Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
    )
    header = _header(ts, stamp, "map", ros1)
    cov = ts.types[g + "PoseWithCovariance"](pose=pose, covariance=np.zeros(36))
    if msgtype == POSE_STAMPED:
        return ts.types[msgtype](header=header, pose=pose)
    if msgtype == POSE_COV:
        return ts.types[msgtype](header=header, pose=cov)
    twist = ts.types[g + "TwistWithCovariance"](
        twist=ts.types[g + "Twist"](
            linear=ts.types[g + "Vector3"](x=0.0, y=0.0, z=0.0),
            angular=ts.types[g + "Vector3"](x=0.0, y=0.0, z=0.0),
        ),
        covariance=np.zeros(36),
    )
    return ts.types[ODOMETRY](header=header, child_frame_id="base", pose=cov, twist=twist)


def _plain(value):
    """A rosbags message as nested dicts, bytes and lists (what foxglove's encoder takes)."""
    if dataclasses.is_dataclass(value):
        return {f.name: _plain(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, np.ndarray):
        return value.tobytes() if value.dtype == np.uint8 else value.tolist()
    if isinstance(value, list):
        return [_plain(v) for v in value]
    return value


def _messages(ts, images, poses, compressed, pose_type, topic, pose_topic, ros1=False):
    out = [(topic, image_msg(ts, t, rgb, compressed, ros1), t) for t, rgb in images]
    out += [(pose_topic, pose_msg(ts, pose_type, t, xyz, ros1), t) for t, xyz in poses]
    return sorted(out, key=lambda item: item[2])


def write_rosbag2(
    path: Path,
    images: list,
    poses: list = (),
    storage: str = "mcap",
    compressed: bool = False,
    pose_type: str = ODOMETRY,
    topic: str = "/cam/image",
    pose_topic: str = "/odom",
    extra: list = (),
    empty: list = (),
    version: int = 9,
) -> Path:
    """A rosbag2 folder written by rosbags.

    ``extra = [(topic, msgtype, msg, stamp)]`` adds messages; ``empty = [(topic, msgtype)]`` adds
    topics without messages.
    """
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    items = _messages(TS2, images, poses, compressed, pose_type, topic, pose_topic)
    types = {topic: COMPRESSED if compressed else IMAGE} if images else {}
    types.update({pose_topic: pose_type} if poses else {})
    types.update({t: msgtype for t, msgtype in empty})
    types.update({t: msgtype for t, msgtype, _, _ in extra})
    items += [(t, m, s) for t, _, m, s in extra]
    with Writer(path, version=version, storage_plugin=plugin) as writer:
        conns = {t: writer.add_connection(t, mt, typestore=TS2) for t, mt in types.items()}
        for name, msg, stamp in sorted(items, key=lambda item: item[2]):
            writer.write(conns[name], _ns(stamp), TS2.serialize_cdr(msg, types[name]))
    return path


def write_foxglove(
    path: Path,
    images: list,
    poses: list = (),
    compressed: bool = True,
    pose_type: str = POSE_STAMPED,
    topic: str = "/cam/image/compressed",
    pose_topic: str = "/pose",
    chunk_size: int = 1024 * 1024,
) -> Path:
    """A bare .mcap written by foxglove's ``mcap_ros2.writer.Writer`` (zstd chunks)."""
    from mcap_ros2.writer import Writer as FoxgloveWriter

    types = {topic: COMPRESSED if compressed else IMAGE, pose_topic: pose_type}
    with open(path, "wb") as stream:
        writer = FoxgloveWriter(stream, chunk_size=chunk_size)
        schemas = {
            t: writer.register_msgdef(mt, TS2.generate_msgdef(mt, ros_version=2)[0])
            for t, mt in types.items()
        }
        for name, msg, stamp in _messages(
            TS2, images, poses, compressed, pose_type, topic, pose_topic
        ):
            writer.write_message(name, schemas[name], _plain(msg), log_time=_ns(stamp))
        writer.finish()
    return path


def corrupt_foxglove(path: Path, images: list) -> Path:
    """An uncompressed-image .mcap (small chunks) with 64 bytes flipped in its middle: readers
    fail part-way with a chunk checksum error, after the first frames."""
    write_foxglove(path, images, compressed=False, chunk_size=3000)
    data = bytearray(path.read_bytes())
    for k in range(len(data) // 2, len(data) // 2 + 64):
        data[k] ^= 0xFF
    path.write_bytes(bytes(data))
    return path


def write_ros1(
    path: Path,
    images: list,
    poses: list = (),
    pose_type: str = POSE_COV,
    topic: str = "/camera/image_raw",
    pose_topic: str = "/amcl_pose",
) -> Path:
    """A ROS 1 .bag written by rosbags (Image rgb8)."""
    types = {topic: IMAGE, pose_topic: pose_type}
    with Ros1Writer(path) as writer:
        conns = {t: writer.add_connection(t, mt, typestore=TS1) for t, mt in types.items()}
        for name, msg, stamp in _messages(
            TS1, images, poses, False, pose_type, topic, pose_topic, True
        ):
            writer.write(conns[name], _ns(stamp), TS1.serialize_ros1(msg, types[name]))
    return path
