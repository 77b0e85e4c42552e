"""Write the demo drive as a rosbag2 (MCAP storage): camera images plus ground-truth odometry."""

from __future__ import annotations

import math
import shutil
import tempfile
from pathlib import Path

import cv2
import numpy as np
from rosbags.rosbag2 import StoragePlugin, Writer, WriterError
from rosbags.typesys import Stores, get_typestore
from tqdm import tqdm

from pair_vpr_ros.demo.render import render_frame
from pair_vpr_ros.demo.world import World, WorldConfig, generate_world
from pair_vpr_ros.errors import BagError

IMAGE_TOPIC = "/camera/image_raw"
COMPRESSED_TOPIC = "/camera/image_raw/compressed"
ODOM_TOPIC = "/odom"
CAMERA_FRAME = "camera"
MAP_FRAME = "map"
BASE_FRAME = "base_link"
JPEG_QUALITY = 90


def write_demo_bag(
    path: str | Path,
    seed: int = 7,
    frames: int = WorldConfig.frames,
    compressed: bool = False,
    size: tuple[int, int] = (320, 240),
    force: bool = False,
) -> Path:
    """Generate the world for `seed`; write its drive to `path` (`.mcap` file or bag folder)."""
    world = generate_world(seed, frames=frames, width=size[0], height=size[1])
    return write_world_bag(world, path, compressed=compressed, force=force)


def write_world_bag(
    world: World,
    path: str | Path,
    compressed: bool = False,
    force: bool = False,
    progress: bool = False,
) -> Path:
    """Write every frame of `world` to `path` and return it.

    A path ending in `.mcap` becomes one MCAP file; any other path becomes a rosbag2 folder
    (metadata.yaml plus `<name>.mcap`). Both read back with `rosbags.highlevel.AnyReader`. The bag
    is written next to `path` first and moved into place, so a failure leaves no partial bag.
    `progress` shows a tqdm bar.
    """
    path = Path(path)
    _check_room(path, force)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", dir=path.parent))
    try:
        folder = tmp / (path.stem if _is_file(path) else path.name)
        _write(world, folder, compressed, progress)
        _remove(path)  # only now: a failed write keeps the old output
        (folder / f"{folder.name}.mcap" if _is_file(path) else folder).replace(path)
    except (OSError, WriterError) as err:
        raise BagError(f"cannot write demo bag {path}: {err}") from err
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return path


def _is_file(path: Path) -> bool:
    """Whether `path` names a single MCAP file rather than a bag folder."""
    return path.suffix.lower() == ".mcap"


def _check_room(path: Path, force: bool) -> None:
    """Refuse an existing output unless `force`; even then refuse a folder that is not a bag."""
    if not path.exists() and not path.is_symlink():
        return
    if not force:
        raise BagError(f"output {path} already exists; pass --force (force=True) to overwrite it")
    is_dir = path.is_dir() and not path.is_symlink()
    if is_dir and any(path.iterdir()) and not (path / "metadata.yaml").is_file():
        raise BagError(
            f"refusing to overwrite {path}: it is a non-empty folder but not a rosbag2 bag "
            "(no metadata.yaml); choose another output path"
        )


def _remove(path: Path) -> None:
    """Delete an old output that `_check_room` allowed to be replaced."""
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    elif path.exists() or path.is_symlink():
        path.unlink()


def _write(world: World, folder: Path, compressed: bool, progress: bool) -> None:
    """Serialise images and odometry of every frame with identical header stamps and log times."""
    ts = get_typestore(Stores.ROS2_JAZZY)
    t = ts.types
    image_type = "sensor_msgs/msg/CompressedImage" if compressed else "sensor_msgs/msg/Image"
    with Writer(folder, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        image_conn = writer.add_connection(
            COMPRESSED_TOPIC if compressed else IMAGE_TOPIC, image_type, typestore=ts
        )
        odom_conn = writer.add_connection(ODOM_TOPIC, "nav_msgs/msg/Odometry", typestore=ts)
        for i in tqdm(range(world.num_frames), desc="frames", unit="frame", disable=not progress):
            stamp_ns = int(world.stamps_ns[i])
            stamp = t["builtin_interfaces/msg/Time"](
                sec=stamp_ns // 1_000_000_000, nanosec=stamp_ns % 1_000_000_000
            )
            rgb = render_frame(world, i)
            image = _image_msg(t, stamp, rgb, compressed)
            writer.write(image_conn, stamp_ns, ts.serialize_cdr(image, image_type))
            odom = _odom_msg(t, stamp, world, i)
            writer.write(odom_conn, stamp_ns, ts.serialize_cdr(odom, "nav_msgs/msg/Odometry"))


def _image_msg(t: dict, stamp: object, rgb: np.ndarray, compressed: bool) -> object:
    """sensor_msgs Image (rgb8) or CompressedImage (jpeg) of `rgb` [H, W, 3] uint8."""
    header = t["std_msgs/msg/Header"](stamp=stamp, frame_id=CAMERA_FRAME)
    if compressed:
        ok, buf = cv2.imencode(".jpg", rgb[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
        assert ok, "JPEG encoding of a uint8 image cannot fail"
        return t["sensor_msgs/msg/CompressedImage"](header=header, format="jpeg", data=buf.ravel())
    h, w = rgb.shape[:2]
    return t["sensor_msgs/msg/Image"](
        header=header,
        height=h,
        width=w,
        encoding="rgb8",
        is_bigendian=0,
        step=3 * w,
        data=np.ascontiguousarray(rgb).reshape(-1),
    )


def _odom_msg(t: dict, stamp: object, world: World, i: int) -> object:
    """nav_msgs Odometry: ground-truth pose (yaw as quaternion), velocity in base_link."""
    x, y, yaw = (float(v) for v in world.poses[i])
    # Finite differences over the step after frame i (the step before it for the last frame).
    j = min(i + 1, world.num_frames - 1)
    k = max(j - 1, 0)
    dt = max(j - k, 1) / world.config.rate_hz
    vx, vy = (world.poses[j, :2] - world.poses[k, :2]) / dt
    yaw_rate = math.remainder(float(world.poses[j, 2] - world.poses[k, 2]), math.tau) / dt
    c, s = math.cos(yaw), math.sin(yaw)
    pose = t["geometry_msgs/msg/Pose"](
        position=t["geometry_msgs/msg/Point"](x=x, y=y, z=0.0),
        orientation=t["geometry_msgs/msg/Quaternion"](
            x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2)
        ),
    )
    vec = t["geometry_msgs/msg/Vector3"]
    twist = t["geometry_msgs/msg/Twist"](
        linear=vec(x=float(c * vx + s * vy), y=float(c * vy - s * vx), z=0.0),
        angular=vec(x=0.0, y=0.0, z=yaw_rate),
    )
    return t["nav_msgs/msg/Odometry"](
        header=t["std_msgs/msg/Header"](stamp=stamp, frame_id=MAP_FRAME),
        child_frame_id=BASE_FRAME,
        pose=t["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
        twist=t["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=np.zeros(36)),
    )
