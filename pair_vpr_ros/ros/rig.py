"""`vpr_node` with several cameras (issue 49): each camera's parameters (``<name>.image_topic``,
..., ``<name>.camera_to_base``; params/rig.py), extrinsics from the parameters or from
/tf_static, each camera's subscriptions and depth / intrinsics, and the rig keyframes they form
(`loops.rig_frames.RigAssembler`: a camera that is late or silent is counted, never waited for
beyond ``rig_max_delay``). A mixin of `VprNode` (ros/node.py); with ``cameras`` empty none of
this runs and the node is the single-camera node it was."""

from __future__ import annotations

import threading
import time
from dataclasses import replace
from functools import partial
from typing import Any

from rcl_interfaces.msg import ParameterDescriptor
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CameraInfo, CompressedImage, Image

from pair_vpr_ros.errors import ConfigError, ImageConversionError
from pair_vpr_ros.images.convert import msg_to_rgb
from pair_vpr_ros.loops.frames import Frame, frame_due
from pair_vpr_ros.loops.rig import Rig, static_chain
from pair_vpr_ros.loops.rig_frames import RigAssembler
from pair_vpr_ros.params.rig import (
    CAMERA_PARAMS,
    CAMERA_TO_BASE,
    CAMERA_TO_BASE_HELP,
    camera_defaults,
    rig_cameras,
    rig_settings,
)
from pair_vpr_ros.ros.geometry_inputs import GeometryInputs
from pair_vpr_ros.types import message_stamp

POLL_S = 0.05  # how often the rig's late groups are looked at


def declare_rig(node: Node, v: dict) -> Rig | None:
    """Declare each camera's parameters and build the rig (None: no `cameras`); cameras without
    camera_to_base get it from /tf_static within ``rig_tf_wait`` s. ConfigError otherwise."""
    names = list(v["cameras"])
    if not names:
        return None
    values: dict[str, Any] = {}
    for name in names:
        for key, default in camera_defaults(name).items():
            text = CAMERA_PARAMS[key.split(".", 1)[1]][1]
            node.declare_parameter(key, default, ParameterDescriptor(description=text,
                                                                     read_only=True))  # fmt: skip
            values[key] = node.get_parameter(key).value
        key = f"{name}.{CAMERA_TO_BASE}"
        node.declare_parameter(key, Parameter.Type.DOUBLE_ARRAY,
                               ParameterDescriptor(description=CAMERA_TO_BASE_HELP,
                                                   read_only=True))  # fmt: skip
        values[key] = tuple(node.get_parameter_or(key, Parameter(key, value=[])).value or ())
    cams, settings = rig_cameras(names, values), rig_settings(v)
    unknown = [c for c in cams if c.camera_to_base is None]
    if unknown and len(cams) > 1:
        found = static_extrinsics(node, [c.frame_id for c in unknown], settings["base_frame"],
                                  v["rig_tf_wait"])  # fmt: skip
        cams = [replace(c, camera_to_base=found.get(c.frame_id)) if c.camera_to_base is None
                else c for c in cams]  # fmt: skip
    try:
        return Rig(tuple(cams), **settings)
    except ConfigError as err:
        raise ConfigError(f"{err} ({tf_note(cams)})") from err


def tf_note(cams) -> str:
    """Why /tf_static could not help (appended to a rig's error)."""
    try:
        import tf2_msgs.msg  # noqa: F401
    except ImportError:
        return "tf2_msgs is not installed (not on PyPI; a ROS install has it): give camera_to_base"
    blind = [c.name for c in cams if c.camera_to_base is None and not c.frame_id]
    if blind:
        return f"set {', '.join(f'{n}.frame_id' for n in blind)} to look them up in /tf_static"
    return "/tf_static gave no transform within rig_tf_wait s"


def static_extrinsics(node: Node, frames: list[str], base: str, wait: float) -> dict[str, Any]:
    """The poses of `frames` in `base` from /tf_static (tf2_msgs/TFMessage), heard for up to
    `wait` s; {} when tf2_msgs is not installed."""
    try:
        from tf2_msgs.msg import TFMessage
    except ImportError:
        return {}
    edges: dict[str, tuple[str, tuple[float, ...]]] = {}

    def heard(msg: Any) -> None:
        for t in msg.transforms:
            p, q = t.transform.translation, t.transform.rotation
            edges[t.child_frame_id] = (t.header.frame_id, (p.x, p.y, p.z, q.x, q.y, q.z, q.w))

    qos = QoSProfile(depth=100, durability=DurabilityPolicy.TRANSIENT_LOCAL,
                     reliability=ReliabilityPolicy.RELIABLE)  # fmt: skip
    sub = node.create_subscription(TFMessage, "/tf_static", heard, qos)
    found: dict[str, Any] = {}
    deadline = time.monotonic() + wait
    try:
        import rclpy

        while time.monotonic() < deadline and len(found) < len([f for f in frames if f]):
            rclpy.spin_once(node, timeout_sec=0.1)
            found = {f: p for f in frames if f and (p := static_chain(edges, base, f))}
    finally:
        node.destroy_subscription(sub)
    return found


class RigIntake:
    """The rig's subscriptions and rig keyframes of `VprNode` (it supplies `rig`, `values`,
    `stats`, `frames`, `_min_interval`, `_last_queued` and the worker)."""

    def _make_rig_subscriptions(self, v: dict, qos: Any) -> None:
        buffer = 30 + v["queue_size"]
        self.rig_inputs = [GeometryInputs(
            {**v, "depth_topic": c.depth_topic, "camera_info_topic": c.camera_info_topic,
             "right_image_topic": c.right_topic,
             "right_camera_info_topic": c.right_camera_info_topic},
            self.stats.counts, buffer_size=buffer) for c in self.rig.cameras]  # fmt: skip
        self.assembler = RigAssembler(self.rig)
        self._rig_lock = threading.Lock()
        for k, (cam, inputs) in enumerate(zip(self.rig.cameras, self.rig_inputs, strict=True)):
            group = MutuallyExclusiveCallbackGroup()
            subs = [(Image, cam.image_topic, partial(self._on_rig_image, k))]
            subs += [
                (CameraInfo, cam.camera_info_topic, inputs.on_camera_info),
                (Image, cam.depth_topic, inputs.on_depth),
                (Image, cam.right_topic, inputs.on_right),
                (CameraInfo, cam.right_camera_info_topic, inputs.on_right_camera_info),
            ]
            for msg_type, topic, callback in subs:
                if topic:
                    self.create_subscription(msg_type, topic, callback, qos, callback_group=group)
        self.create_timer(POLL_S, self._poll_rig, MutuallyExclusiveCallbackGroup())

    def _on_rig_image(self, camera: int, msg: Image | CompressedImage) -> None:
        self.stats.counts.received += 1
        stamp = message_stamp(msg, fallback=self.get_clock().now().nanoseconds / 1e9)
        try:
            rgb = msg_to_rgb(msg, max_pixels=self.values["max_image_pixels"])
        except ImageConversionError as err:
            self.stats.counts.invalid += 1
            name = self.rig.name(camera)
            self.get_logger().warning(f"skipping a frame of camera {name}: {err}",
                                      throttle_duration_sec=5.0)  # fmt: skip
            return
        frame = Frame(stamp, rgb, msg.header.frame_id, source=self.rig.cameras[camera].image_topic,
                      camera_id=camera)  # fmt: skip
        with self._rig_lock:
            groups = self.assembler.add(frame)
        self._queue_groups(groups)

    def _poll_rig(self) -> None:
        with self._rig_lock:
            groups = self.assembler.poll()
        self._queue_groups(groups)

    def _queue_groups(self, groups: list[list[Frame]]) -> None:
        """Rig keyframes into the worker's queue (the frame-rate limit applied per group)."""
        for group in groups:
            if not frame_due(group[0].stamp, self._last_queued, self._min_interval):
                self.stats.counts.rate_limited += len(group)
                continue
            self._last_queued = group[0].stamp
            self._enqueue(group, "rig keyframe")  # ros/intake.py

    def rig_diagnostics(self) -> dict[str, str]:
        """The rig's counts for /diagnostics ({} without a rig)."""
        if getattr(self, "rig", None) is None:
            return {}
        c = self.assembler.counts
        out = {"rig_keyframes": str(c.keyframes), "rig_incomplete": str(c.incomplete),
               "rig_frame_id_clash": str(c.frame_id_clash)}  # fmt: skip
        for name in self.rig.names:
            out[f"rig_{name}_missing"] = str(c.missing.get(name, 0))
            out[f"rig_{name}_late"] = str(c.late.get(name, 0))
            out[f"rig_{name}_apart"] = str(c.apart.get(name, 0))
        return out
