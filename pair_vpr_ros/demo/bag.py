"""Write the demo drive as a rosbag2 (MCAP storage), the topics a robot would record:

``/camera/image_raw`` (rgb8, or mono8 for a grey camera; or ``/compressed``),
``/camera/camera_info`` (pinhole, no distortion),
``/camera/depth/image_raw``: depth aligned with the colour pixels (16UC1 millimetres, 0 = none;
``demo.depth``), unless ``depth=False``,
``/odom``: drifting odometry of ``base_link`` in ``odom`` (see ``demo.odometry``), and
``/ground_truth``: the true pose of ``base_link`` in ``map``, both ``nav_msgs/Odometry``. The
camera sits ``Camera.height_m`` above ``base_link``, looking along its x axis
(``camera.CAMERA_TO_BASE``); the image frame ``camera`` is an optical frame (x right, y down,
z forward). With ``rear=True`` also the rear camera's ``/rear_camera/...`` topics and both
cameras' poses on ``/tf_static`` (``demo.rig``).
"""

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

from pair_vpr_ros.demo import rig
from pair_vpr_ros.demo.camera import Camera, camera_to_base
from pair_vpr_ros.demo.depth import depth_to_mm, render_depth
from pair_vpr_ros.demo.odometry import OdometryNoise, drifting_odometry
from pair_vpr_ros.demo.render import render_frame
from pair_vpr_ros.demo.world import World, WorldConfig, generate_world
from pair_vpr_ros.errors import BagError

IMAGE_TOPIC = "/camera/image_raw"
COMPRESSED_TOPIC = "/camera/image_raw/compressed"
CAMERA_INFO_TOPIC = "/camera/camera_info"
DEPTH_TOPIC = "/camera/depth/image_raw"
ODOM_TOPIC = "/odom"
GROUND_TRUTH_TOPIC = "/ground_truth"
CAMERA_FRAME = "camera"
MAP_FRAME = "map"
ODOM_FRAME = "odom"
BASE_FRAME = "base_link"
ODOMETRY_TYPE = "nav_msgs/msg/Odometry"
TF_TYPE = "tf2_msgs/msg/TFMessage"
JPEG_QUALITY = 90


def write_demo_bag(
    path: str | Path,
    seed: int = 7,
    frames: int = WorldConfig.frames,
    compressed: bool = False,
    size: tuple[int, int] = (320, 240),
    force: bool = False,
    odometry: OdometryNoise | None = None,
    depth: bool = True,
    mono: bool = False,
) -> Path:
    """Generate the world for `seed`; write its drive to `path` (`.mcap` file or bag folder)."""
    world = generate_world(seed, frames=frames, width=size[0], height=size[1])
    return write_world_bag(
        world, path, compressed=compressed, force=force, odometry=odometry, depth=depth, mono=mono
    )


def write_world_bag(
    world: World,
    path: str | Path,
    compressed: bool = False,
    force: bool = False,
    progress: bool = False,
    odometry: OdometryNoise | None = None,
    depth: bool = True,
    mono: bool = False,
    local_odometry: bool = False,
    rear: bool = False,
) -> Path:
    """Write every frame of `world` to `path` and return it.

    A path ending in `.mcap` becomes one MCAP file; any other path becomes a rosbag2 folder
    (metadata.yaml plus `<name>.mcap`). Both read back with `rosbags.highlevel.AnyReader`. The bag
    is written next to `path` first and moved into place, so a failure leaves no partial bag.
    `progress` shows a tqdm bar; `odometry` sets how `/odom` drifts (default `OdometryNoise()`);
    `depth=False` leaves out the depth topic (40 ms a frame to render, 150 KB at 320x240);
    `mono=True` writes what a grey camera gives: mono8 images (grey JPEGs if `compressed`), the
    BT.601 luma of the rendered colours. `local_odometry=True`: `/odom` starts at the origin of
    its own frame, as a robot's does (else at the true start pose: odom = map at start).
    `rear=True`: the rear camera's topics and /tf_static too (``demo.rig``).
    """
    path = Path(path)
    odometry = odometry or OdometryNoise()
    odometry.validate()
    _check_room(path, force)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", dir=path.parent))
    try:
        folder = tmp / (path.stem if _is_file(path) else path.name)
        _write(world, folder, compressed, progress, odometry, depth, mono, local_odometry, rear)
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


def _write(
    world: World,
    folder: Path,
    compressed: bool,
    progress: bool,
    noise: OdometryNoise,
    depth: bool,
    mono: bool = False,
    local_odometry: bool = False,
    rear: bool = False,
) -> None:
    """Serialise every frame's messages with identical header stamps and log times."""
    ts = get_typestore(Stores.ROS2_JAZZY)
    t = ts.types
    image_type = "sensor_msgs/msg/CompressedImage" if compressed else "sensor_msgs/msg/Image"
    info_type = "sensor_msgs/msg/CameraInfo"
    odometry = drifting_odometry(world.poses, world.config.rate_hz, world.seed, noise)
    if local_odometry:
        odometry = _from_start(odometry)
    cam = Camera(world.config.width, world.config.height)
    with Writer(folder, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        image_topic = COMPRESSED_TOPIC if compressed else IMAGE_TOPIC
        conns = {
            image_topic: writer.add_connection(image_topic, image_type, typestore=ts),
            CAMERA_INFO_TOPIC: writer.add_connection(CAMERA_INFO_TOPIC, info_type, typestore=ts),
            ODOM_TOPIC: writer.add_connection(ODOM_TOPIC, ODOMETRY_TYPE, typestore=ts),
            GROUND_TRUTH_TOPIC: writer.add_connection(
                GROUND_TRUTH_TOPIC, ODOMETRY_TYPE, typestore=ts
            ),
        }
        if depth:
            conns[DEPTH_TOPIC] = writer.add_connection(
                DEPTH_TOPIC, "sensor_msgs/msg/Image", typestore=ts
            )
        rear_topics = [(rig.REAR_IMAGE_TOPIC, image_type), (rig.REAR_CAMERA_INFO_TOPIC, info_type)]
        rear_topics += [(rig.REAR_DEPTH_TOPIC, "sensor_msgs/msg/Image")] if depth else []
        for topic, msgtype in [*rear_topics, (rig.TF_STATIC_TOPIC, TF_TYPE)] if rear else []:
            conns[topic] = writer.add_connection(topic, msgtype, typestore=ts)
        rate = world.config.rate_hz
        for i in tqdm(range(world.num_frames), desc="frames", unit="frame", disable=not progress):
            stamp_ns = int(world.stamps_ns[i])
            stamp = t["builtin_interfaces/msg/Time"](
                sec=stamp_ns // 1_000_000_000, nanosec=stamp_ns % 1_000_000_000
            )
            messages = (
                (image_topic, _image_msg(t, stamp, render_frame(world, i), compressed, mono)),
                (CAMERA_INFO_TOPIC, _camera_info_msg(t, stamp, cam)),
                (ODOM_TOPIC, _odom_msg(t, stamp, odometry, i, rate, ODOM_FRAME)),
                (GROUND_TRUTH_TOPIC, _odom_msg(t, stamp, world.poses, i, rate, MAP_FRAME)),
            )
            if depth:
                metres = render_depth(world.layout, world.poses[i], cam, world.occluders_of(i))
                messages += ((DEPTH_TOPIC, _depth_msg(t, stamp, depth_to_mm(metres))),)
            if rear:
                messages += _rear_messages(t, stamp, world, i, cam, compressed, mono, depth)
            for topic, msg in messages:
                writer.write(conns[topic], stamp_ns, ts.serialize_cdr(msg, msg.__msgtype__))


def _rear_messages(t, stamp, world, i, cam, compressed, mono, depth) -> tuple:
    """The rear camera's messages of frame `i` (/tf_static once, with the first frame)."""
    frame = rig.REAR_FRAME
    out = (
        (rig.REAR_IMAGE_TOPIC, _image_msg(t, stamp, rig.render_rear(world, i), compressed, mono,
                                          frame)),
        (rig.REAR_CAMERA_INFO_TOPIC, _camera_info_msg(t, stamp, cam, frame)),
    )  # fmt: skip
    if depth:
        out += ((rig.REAR_DEPTH_TOPIC, _depth_msg(t, stamp, depth_to_mm(rig.rear_depth(world, i)),
                                                  frame)),)  # fmt: skip
    if i == 0:
        poses = {CAMERA_FRAME: camera_to_base(cam), frame: rig.rear_to_base(cam)}
        out += ((rig.TF_STATIC_TOPIC, rig.tf_static_msg(t, stamp, poses)),)
    return out


def _from_start(poses: np.ndarray) -> np.ndarray:
    """Planar poses ``[N, 3]`` (x, y, yaw) in the frame of the first one."""
    x0, y0, yaw0 = poses[0]
    c, s = math.cos(yaw0), math.sin(yaw0)
    dx, dy = poses[:, 0] - x0, poses[:, 1] - y0
    yaw = np.angle(np.exp(1j * (poses[:, 2] - yaw0)))
    return np.stack([c * dx + s * dy, -s * dx + c * dy, yaw], axis=1)


def _depth_msg(t: dict, stamp: object, mm: np.ndarray, frame: str = CAMERA_FRAME) -> object:
    """sensor_msgs Image, 16UC1 millimetres [H, W] uint16, little-endian."""
    h, w = mm.shape
    return t["sensor_msgs/msg/Image"](
        header=t["std_msgs/msg/Header"](stamp=stamp, frame_id=frame),
        height=h,
        width=w,
        encoding="16UC1",
        is_bigendian=0,
        step=2 * w,
        data=np.ascontiguousarray(mm, dtype="<u2").view(np.uint8).reshape(-1),
    )


def _camera_info_msg(t: dict, stamp: object, cam: Camera, frame: str = CAMERA_FRAME) -> object:
    """sensor_msgs CameraInfo of the demo camera: pinhole, square pixels, no distortion."""
    f, cx, cy = cam.f, cam.cx, cam.cy
    return t["sensor_msgs/msg/CameraInfo"](
        header=t["std_msgs/msg/Header"](stamp=stamp, frame_id=frame),
        height=cam.height,
        width=cam.width,
        distortion_model="plumb_bob",
        d=np.zeros(5),
        k=np.array([f, 0.0, cx, 0.0, f, cy, 0.0, 0.0, 1.0]),
        r=np.eye(3).reshape(-1),
        p=np.array([f, 0.0, cx, 0.0, 0.0, f, cy, 0.0, 0.0, 0.0, 1.0, 0.0]),
        binning_x=0,
        binning_y=0,
        roi=t["sensor_msgs/msg/RegionOfInterest"](
            x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
        ),
    )


def _image_msg(
    t: dict, stamp: object, rgb: np.ndarray, compressed: bool, mono: bool = False,
    frame: str = CAMERA_FRAME,
) -> object:  # fmt: skip
    """sensor_msgs Image (rgb8, or mono8 with `mono`) or CompressedImage (jpeg) of `rgb`
    [H, W, 3] uint8."""
    header = t["std_msgs/msg/Header"](stamp=stamp, frame_id=frame)
    pixels = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY) if mono else rgb[..., ::-1]  # grey or BGR
    if compressed:
        ok, buf = cv2.imencode(".jpg", pixels, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
        assert ok, "JPEG encoding of a uint8 image cannot fail"
        return t["sensor_msgs/msg/CompressedImage"](header=header, format="jpeg", data=buf.ravel())
    h, w = rgb.shape[:2]
    return t["sensor_msgs/msg/Image"](
        header=header,
        height=h,
        width=w,
        encoding="mono8" if mono else "rgb8",
        is_bigendian=0,
        step=(1 if mono else 3) * w,
        data=np.ascontiguousarray(pixels if mono else rgb).reshape(-1),
    )


def _odom_msg(
    t: dict, stamp: object, poses: np.ndarray, i: int, rate_hz: float, frame_id: str
) -> object:
    """nav_msgs Odometry of `base_link` at planar pose `poses[i]` (x, y, yaw) in `frame_id`,
    with the velocity (in base_link) of the step after frame i (before it, for the last)."""
    x, y, yaw = (float(v) for v in poses[i])
    j = min(i + 1, len(poses) - 1)
    k = max(j - 1, 0)
    dt = max(j - k, 1) / rate_hz
    vx, vy = (poses[j, :2] - poses[k, :2]) / dt
    yaw_rate = math.remainder(float(poses[j, 2] - poses[k, 2]), math.tau) / dt
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
        header=t["std_msgs/msg/Header"](stamp=stamp, frame_id=frame_id),
        child_frame_id=BASE_FRAME,
        pose=t["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
        twist=t["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=np.zeros(36)),
    )
