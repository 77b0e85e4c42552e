"""The node's frame intake: its subscriptions (images, depth, camera info, stereo, poses), the
image callback that converts and enqueues, and the worker that takes each queued frame through
the map thread (`MapControl`). A mixin of `VprNode` (ros/node.py)."""

from __future__ import annotations

import time
from functools import partial

from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
from nav_msgs.msg import Odometry
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from sensor_msgs.msg import CameraInfo, CompressedImage, Image

from pair_vpr_ros.errors import ImageConversionError
from pair_vpr_ros.geometry.camera_notes import demo_model_note
from pair_vpr_ros.images.convert import msg_to_rgb
from pair_vpr_ros.loops.frames import Frame, frame_due
from pair_vpr_ros.types import message_pose, message_stamp

SINGLE_CAMERA_TOPICS = (  # a rig's cameras have their own (ros/rig.py)
    "image_topic", "compressed_image_topic", "depth_topic", "camera_info_topic",
    "right_image_topic", "right_camera_info_topic",
)  # fmt: skip
POSE_TYPES = {
    "odometry": Odometry,
    "pose_stamped": PoseStamped,
    "pose_with_covariance_stamped": PoseWithCovarianceStamped,
}


class FrameIntake:
    """Subscriptions, their callbacks and the worker of `VprNode` (it supplies `values`,
    `frames`, `poses`, `stats`, `geometry_inputs`, `maps`, `fleet` and `_publish_loop`)."""

    def _make_subscriptions(self, v: dict) -> None:
        inputs = MutuallyExclusiveCallbackGroup()
        qos = qos_profile_sensor_data
        if v["qos"] == "reliable":
            qos = QoSProfile(
                depth=max(10, v["queue_size"]), reliability=ReliabilityPolicy.RELIABLE
            )
        if self.rig is not None:  # each camera its own topics (ros/rig.py); the poses below
            self._make_rig_subscriptions(v, qos)
            v = {**v, **dict.fromkeys(SINGLE_CAMERA_TOPICS, "")}
        for msg_type, name in (
            (Image, "image_topic"),
            (CompressedImage, "compressed_image_topic"),
        ):
            if v[name]:
                callback = partial(self._on_image, v[name])
                self.create_subscription(msg_type, v[name], callback, qos, callback_group=inputs)
        if v["depth_topic"]:
            self.create_subscription(
                Image, v["depth_topic"], self.geometry_inputs.on_depth, qos,
                callback_group=MutuallyExclusiveCallbackGroup(),
            )  # fmt: skip
        if v["camera_info_topic"]:
            self.create_subscription(
                CameraInfo, v["camera_info_topic"], self._on_camera_info, qos,
                callback_group=MutuallyExclusiveCallbackGroup(),
            )  # fmt: skip
        for msg_type, name, callback in (
            (Image, "right_image_topic", self.geometry_inputs.on_right),
            (CameraInfo, "right_camera_info_topic", self._on_right_camera_info),
        ):  # stereo: depth for keyframes from the rectified pair (geometry/stereo.py)
            if v[name]:
                group = MutuallyExclusiveCallbackGroup()
                self.create_subscription(msg_type, v[name], callback, qos, callback_group=group)
        if v["pose_topic"]:
            pose_type, group = POSE_TYPES[v["pose_type"]], MutuallyExclusiveCallbackGroup()
            self.create_subscription(
                pose_type, v["pose_topic"], self._on_pose, qos, callback_group=group
            )

    # ---- inputs ------------------------------------------------------------------------------
    def _on_image(self, topic: str, msg: Image | CompressedImage) -> None:
        self.stats.counts.received += 1
        stamp = message_stamp(msg, fallback=self.get_clock().now().nanoseconds / 1e9)
        if not frame_due(stamp, self._last_queued, self._min_interval):
            self.stats.counts.rate_limited += 1  # the pipeline would skip it: not queued
            return
        try:
            rgb = msg_to_rgb(msg, max_pixels=self.values["max_image_pixels"])
        except ImageConversionError as err:
            self.stats.counts.invalid += 1
            text = f"skipping a frame of {topic}: {err}"
            self.get_logger().warning(text, throttle_duration_sec=5.0)
            return
        self._last_queued = stamp
        frame = Frame(stamp=stamp, rgb=rgb, frame_id=msg.header.frame_id, source=topic)
        self._enqueue(frame)

    def _enqueue(self, item: Frame | list[Frame], what: str = "frame") -> None:
        """Queue a frame (or a rig keyframe) for the worker; a full queue drops its oldest."""
        if self.frames.put((item, time.monotonic())):
            self.stats.counts.dropped += 1
            self.get_logger().warning(
                f"frame queue full: dropping the oldest {what} (the model is slower than the "
                "camera; raise min_frame_interval or queue_size)",
                throttle_duration_sec=10.0,
            )

    def _on_right_camera_info(self, msg: CameraInfo) -> None:
        problem = self.geometry_inputs.on_right_camera_info(msg)
        if problem:
            self.get_logger().warning(problem, throttle_duration_sec=10.0)

    def _on_camera_info(self, msg: CameraInfo) -> None:
        problem = self.geometry_inputs.on_camera_info(msg)
        if problem:
            self.get_logger().warning(problem, throttle_duration_sec=10.0)

    def _on_pose(self, msg: Odometry | PoseStamped | PoseWithCovarianceStamped) -> None:
        stamp = message_stamp(msg)
        if not self.poses.add(stamp, message_pose(msg)):
            self.stats.counts.bad_poses += 1
            self.get_logger().warning(
                f"skipping a pose of {self.values['pose_topic']} at stamp {stamp:.3f} s: it "
                "holds NaN or infinite values (frames near it get no pose)",
                throttle_duration_sec=5.0,
            )

    # ---- worker ------------------------------------------------------------------------------
    def _work(self) -> None:
        while not self._stop.is_set():
            item = self.frames.get(timeout=0.2)
            if item is not None:
                self._process(*item)

    def _process(self, item: Frame | list[Frame], received: float) -> None:
        """One frame, or one rig keyframe (a list of frames, one per camera: ros/rig.py)."""
        frames = item if isinstance(item, list) else [item]
        for frame in frames:
            inputs = self._attach(frame)
        try:
            if isinstance(item, list):
                results = self.maps.process_group(frames)
            else:
                results = [self.maps.process(item)]
            for frame, (outcome, loops) in zip(frames, results, strict=True):
                self._report(frame, outcome, loops, received)
        except Exception as err:  # noqa: BLE001 - the worker must outlive any one frame
            if not self._stop.is_set():
                self.stats.counts.errors += len(frames)
                text = f"frame at {frames[0].stamp:.3f} s failed: {type(err).__name__}: {err}"
                self.get_logger().error(text, throttle_duration_sec=5.0)
        if inputs.enabled_depth and any(f.depth is None for f in frames):
            self.get_logger().warning(
                f"frame without depth: {inputs.last_problem}", throttle_duration_sec=10.0
            )

    def _attach(self, frame: Frame):
        """Give `frame` its pose, intrinsics, depth and right image -> its camera's inputs."""
        frame.pose = self.poses.nearest(frame.stamp, self.values["pose_tolerance"])
        rig = getattr(self, "rig", None)
        inputs = self.geometry_inputs if rig is None else self.rig_inputs[frame.camera_id]
        inputs.await_first_camera_info()
        frame.camera = inputs.camera_for(frame.rgb.shape[1], frame.rgb.shape[0])
        frame.depth = inputs.depth_for(frame.stamp)
        frame.right, frame.baseline = inputs.right_for(frame.stamp), inputs.baseline
        self._say_once(inputs.silence_note(time.monotonic()))
        if self._demo_note is None:  # the first frame: is the demo model on a real camera?
            self._demo_note = demo_model_note(self.pipeline.model.fingerprint, frame.rgb)
            self._say_once(self._demo_note)
        return inputs

    def _report(self, frame: Frame, outcome, loops, received: float) -> None:
        """Counts, latencies and the loops of one processed frame."""
        self.stats.counts.processed += 1
        if outcome.clock_jump_s:
            self.get_logger().warning(
                f"image stamps went back {outcome.clock_jump_s:.3f} s (to {frame.stamp:.3f} "
                "s): a bag played again or a clock reset; starting a new session (the map "
                "keeps its keyframes; loops only to keyframes stamped at least "
                "exclude_recent_s apart, and the pair topic only when the match is older)",
                throttle_duration_sec=10.0,
            )
        now_ms = self.get_clock().now().nanoseconds / 1e6
        self.stats.add_ms("latency", (time.monotonic() - received) * 1e3)
        self.stats.add_ms("stamp_age", now_ms - frame.stamp * 1e3)
        for key, ms in outcome.timings_ms.items():
            self.stats.add_ms(key, ms)
        if self.values["loop_image"]:
            self.pictures.keep(outcome, frame.rgb)
        for loop, match_pose in loops:  # accepted ones (one per map), else the best
            self._publish_loop(loop, frame.pose, match_pose)
            self._publish_loop_image(outcome, loop, frame.rgb)
        if self.fleet is not None:
            self.fleet.on_outcome(outcome)
