"""`vpr_node`: the ROS 2 loop-closure node, a thin shell over `LoopClosurePipeline`.

Run::

    ros2 run pair_vpr_ros vpr_node --ros-args --params-file config/vpr_node.yaml \\
        -p weights:=/path/pairvpr-vitB.pth -r image:=/camera/image_raw \\
        -r loop_closure:=/lio_loop/loop_closure_detection

Inputs: `image` (sensor_msgs/Image) and/or `compressed_image_topic` (CompressedImage), optional
`pose_topic` (Odometry, PoseStamped or PoseWithCovarianceStamped). The image callback only
converts and enqueues (a full queue drops its oldest frame); a worker thread takes each frame to
the map thread of `MapControl`, the one thread that runs the pipeline and its map services.

Outputs: `loop_closure` (Float64MultiArray `[t_current, t_previous]`, LIO-SAM), `.../detail`
(labelled Float64MultiArray), `.../json` (String), `.../typed` (pair_vpr_ros_interfaces/
LoopClosure, docs/interfaces.md), `.../factor` (Odometry, loops with a pose): `loop_messages`;
`loop_closure/markers` (MarkerArray, when both poses are known); `/diagnostics` (~1 Hz).

Services (paths come from the `map_dir` and `build_source` parameters)::

    ros2 service call /vpr_node/set_localization std_srvs/srv/SetBool "{data: true}"
    ros2 service call /vpr_node/set_localization std_srvs/srv/SetBool "{data: false}"
    ros2 param set /vpr_node map_dir /path/to/map
    ros2 service call /vpr_node/save_map std_srvs/srv/Trigger
    ros2 service call /vpr_node/load_map std_srvs/srv/Trigger
    ros2 service call /vpr_node/clear_map std_srvs/srv/Trigger
    ros2 param set /vpr_node build_source /path/to/bag_or_image_folder
    ros2 service call /vpr_node/build_map std_srvs/srv/Trigger
    ros2 service call /vpr_node/map_info std_srvs/srv/Trigger

`build_map` checks its source and `map_dir`, then returns; the build runs in the background,
saves to `map_dir` and then replaces the live map (`map_info` answers JSON with the build's
state; a failed build keeps `/diagnostics` at ERROR until one succeeds). Outputs other than
`loop_closure` live under its resolved name (`ros.outputs`). Entry point: `ros.entry`. Only
rclpy code lives here; the parameter table is `params`, the queue / statistics `ros.runtime`,
poses `types`, the map services `ros.maps`.
"""

from __future__ import annotations

if __name__ == "__main__":  # `python -m pair_vpr_ros.ros.node`: through the light entry point,
    # so that Ctrl-C while rclpy and torch import is a clean stop, as for `vpr_node` (ros.entry)
    import sys as _sys

    from pair_vpr_ros.ros.entry import vpr_node as _vpr_node

    _sys.exit(_vpr_node())

import json
import signal
import sys
import threading
import time
from functools import partial

import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
from nav_msgs.msg import Odometry
from rcl_interfaces.msg import SetParametersResult
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor
from rclpy.impl.implementation_singleton import rclpy_implementation
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from sensor_msgs.msg import CameraInfo, CompressedImage, Image
from std_srvs.srv import SetBool, Trigger

from pair_vpr_ros import params
from pair_vpr_ros.cli import EXIT_ERROR, EXIT_OK
from pair_vpr_ros.detector import LoopRecord
from pair_vpr_ros.devices import check_device
from pair_vpr_ros.errors import ConfigError, ImageConversionError, PairVPRError
from pair_vpr_ros.fleet import InterRobotLoop
from pair_vpr_ros.geometry.camera_notes import demo_model_note, fallback_intrinsics_note
from pair_vpr_ros.identity import resolve_identity
from pair_vpr_ros.imaging import msg_to_rgb
from pair_vpr_ros.pipeline import Frame, LoopClosurePipeline, frame_due
from pair_vpr_ros.prior_maps import open_prior_maps
from pair_vpr_ros.ros.fleet import FleetLink
from pair_vpr_ros.ros.geometry_inputs import GeometryInputs
from pair_vpr_ros.ros.maps import MapControl
from pair_vpr_ros.ros.outputs import MARKER_TOPIC, LoopOutputs, publish_while_up
from pair_vpr_ros.ros.parameters import declared_default, descriptor, read_value
from pair_vpr_ros.ros.runtime import (
    FrameQueue,
    NodeStats,
    diagnostic_values,
    precision_context,
)
from pair_vpr_ros.types import Pose, PoseTrack, message_pose, message_stamp
from pair_vpr_ros.weights import load_model

__all__ = ["MARKER_TOPIC", "VprNode", "main"]
RCLError = rclpy_implementation.RCLError
POSE_TYPES = {
    "odometry": Odometry,
    "pose_stamped": PoseStamped,
    "pose_with_covariance_stamped": PoseWithCovarianceStamped,
}


class VprNode(Node):
    """Frames in, loop closures out. `start_worker=False` leaves frames queued (tests)."""

    def __init__(self, *, start_worker: bool = True, **kwargs) -> None:
        super().__init__("vpr_node", **kwargs)
        for spec in params.PARAMS:
            self.declare_parameter(spec.name, declared_default(spec), descriptor(spec))
        v = {spec.name: read_value(self, spec) for spec in params.PARAMS}
        reasons = [r for name, value in v.items() if (r := params.check_value(name, value))]
        if reasons:
            raise ConfigError("invalid parameters: " + "; ".join(reasons))
        self.values = v
        device = check_device(v["device"])
        model = load_model(
            v["weights"], device=device, precision=v["precision"], image_size=v["image_size"],
            explicit_name="parameter weights (-p weights:=PATH)", params_rule=False,
            backend=v["backend"], openvino_cache_dir=v["openvino_cache_dir"],
        )  # fmt: skip
        # OpenVINO runs its own precision; torch autocast would only wrap the glue around it.
        autocast = v["precision"] if v["backend"] == "torch" else "fp32"
        config, geometry = params.detector_config(v), params.geometry_config(v)
        self.identity = resolve_identity(v["robot_id"], v["session_id"], self.get_namespace())
        priors = open_prior_maps(v["prior_map_dirs"], model.fingerprint, self.identity)
        for note in priors.notes:
            self._log("info", note)
        self._prior_summary = priors.summary()
        self.maps = MapControl(
            lambda: LoopClosurePipeline(
                model, config, index=params.index_config(v), geometry=geometry,
                identity=self.identity, prior_maps=priors.maps,
            ),
            self._log,
            partial(precision_context, device, autocast),
        )  # fmt: skip
        self.frames = FrameQueue(v["queue_size"])
        # The frame-rate limit, applied before the queue as well (the image callback's own
        # state): frames the pipeline would skip never fill the queue while a keyframe runs.
        self._min_interval = config.min_frame_interval
        self._last_queued: float | None = None
        self.poses = PoseTrack(maxlen=v["pose_buffer_size"])
        self.stats = NodeStats()
        self.geometry_inputs = GeometryInputs(v, self.stats.counts)
        self._stop = threading.Event()
        self._closed = False
        if v["load_map_on_start"]:
            ok, message = self.maps.load_if_present(v["map_dir"])
            if not ok:
                self.maps.close()
                raise ConfigError(f"load_map_on_start: {message}")
            self._log("info", message)
        self._warn_settings(v)
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.add_post_set_parameters_callback(self._after_set_parameters)
        self._make_interfaces(v)
        self.fleet = None
        if v["fleet_enable"]:
            try:
                self.fleet = FleetLink(self, self.maps, v, self.identity, self._publish_fleet_loop)
            except ConfigError:
                self.maps.close()
                raise
        self._worker = threading.Thread(target=self._work, name="vpr_worker", daemon=True)
        if start_worker:
            self._worker.start()
        self.summary = (
            f"model {model.fingerprint} on {v['device']} ({v['backend']}, {v['precision']}), "
            f"{self.maps.size()} keyframes, mode {v['mode']}, robot {self.identity.robot}, "
            f"session {self.identity.session}, {len(priors.maps)} prior maps"
        )
        if self.fleet is not None:
            self.summary += f"; {self.fleet.summary}"

    @property
    def pipeline(self) -> LoopClosurePipeline:
        return self.maps.pipeline

    def _log(self, level: str, text: str) -> None:
        """Log `text` at "info" or "error" (rclpy loggers bind one severity per call site)."""
        if level == "error":
            self.get_logger().error(text)
        else:
            self.get_logger().info(text)

    def _make_interfaces(self, v: dict) -> None:
        inputs, services = MutuallyExclusiveCallbackGroup(), MutuallyExclusiveCallbackGroup()
        qos = qos_profile_sensor_data
        if v["qos"] == "reliable":
            qos = QoSProfile(
                depth=max(10, v["queue_size"]), reliability=ReliabilityPolicy.RELIABLE
            )
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
        self.outputs = LoopOutputs(self)
        self.pub_pair = self.outputs.pair
        self.pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        for srv_type, name, handler in (
            (SetBool, "~/set_localization", self._srv_localization),
            (Trigger, "~/save_map", self._trigger(lambda: self.maps.save(self.values["map_dir"]))),
            (Trigger, "~/load_map", self._trigger(lambda: self.maps.load(self.values["map_dir"]))),
            (Trigger, "~/clear_map", self._trigger(self._clear)),
            (Trigger, "~/build_map", self._trigger(self._start_build)),
            (Trigger, "~/map_info", self._trigger(self._map_info)),
        ):
            self.create_service(srv_type, name, handler, callback_group=services)
        diagnostics = MutuallyExclusiveCallbackGroup()
        self.create_timer(v["diagnostics_period"], self._publish_diagnostics, diagnostics)
        if v["autosave_period"] > 0:
            self.create_timer(v["autosave_period"], self._autosave, services)

    # ---- parameters --------------------------------------------------------------------------
    def _say_once(self, note: str) -> None:
        if note:
            self.get_logger().warning(note)

    def _warn_settings(self, v: dict) -> None:
        """Settings that are valid alone but do nothing together: say so at once."""
        self._demo_note: str | None = None
        self._say_once(fallback_intrinsics_note(v))
        if v["save_on_shutdown"] and not v["map_dir"]:
            self.get_logger().warning(
                "save_on_shutdown is true but map_dir is empty: nothing will be saved when the "
                "node stops; set map_dir (-p map_dir:=/path/to/map or ros2 param set)"
            )

    def _on_set_parameters(self, changed: list[Parameter]) -> SetParametersResult:
        reason = params.check_change(self.values, {p.name: p.value for p in changed})
        return SetParametersResult(successful=reason is None, reason=reason or "")

    def _after_set_parameters(self, changed: list[Parameter]) -> None:
        self.values = {**self.values, **{p.name: p.value for p in changed}}
        if any(p.name in ("save_on_shutdown", "map_dir") for p in changed):
            self._warn_settings(self.values)
        if any(p.name in params.DETECTOR_PARAMS for p in changed):
            config = params.detector_config(self.values)
            self.maps.set_config(config)
            self._min_interval = config.min_frame_interval

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
        if self.frames.put((frame, time.monotonic())):
            self.stats.counts.dropped += 1
            self.get_logger().warning(
                "frame queue full: dropping the oldest frame (the model is slower than the "
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

    def _process(self, frame: Frame, received: float) -> None:
        frame.pose = self.poses.nearest(frame.stamp, self.values["pose_tolerance"])
        inputs = self.geometry_inputs
        frame.camera = inputs.camera_for(frame.rgb.shape[1], frame.rgb.shape[0])
        frame.depth = inputs.depth_for(frame.stamp)
        frame.right, frame.baseline = inputs.right_for(frame.stamp), inputs.baseline
        self._say_once(inputs.silence_note(time.monotonic()))
        if self._demo_note is None:  # the first frame: is the demo model on a real camera?
            self._demo_note = demo_model_note(self.pipeline.model.fingerprint, frame.rgb)
            self._say_once(self._demo_note)
        if inputs.enabled_depth and frame.depth is None:
            self.get_logger().warning(
                f"frame without depth: {inputs.last_problem}", throttle_duration_sec=10.0
            )
        try:
            outcome, match_pose = self.maps.process(frame)
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
            if outcome.loop is not None:
                self._publish_loop(outcome.loop, frame.pose, match_pose)
            if self.fleet is not None:
                self.fleet.on_outcome(outcome)
        except Exception as err:  # noqa: BLE001 - the worker must outlive any one frame
            if not self._stop.is_set():
                self.stats.counts.errors += 1
                text = f"frame at {frame.stamp:.3f} s failed: {type(err).__name__}: {err}"
                self.get_logger().error(text, throttle_duration_sec=5.0)

    def _publish_loop(self, record: LoopRecord, pose: Pose | None, match_pose: Pose | None):
        if not (record.accepted or self.values["publish_rejected"]):
            return
        counts = self.stats.counts
        sent, note = self.outputs.publish(
            record, (pose, match_pose), self.values["marker_frame_id"], counts.loops + 1
        )
        if record.accepted and sent:
            counts.loops += 1
            self.get_logger().info(note)
        elif record.accepted:
            counts.loops_unordered += 1
            self.get_logger().warning(note, throttle_duration_sec=10.0)

    def _publish_fleet_loop(self, loop: InterRobotLoop) -> None:
        """An inter-robot loop this robot decided as owner: published like a loop, but never
        on the LIO-SAM pair topic (two robots' stamps)."""
        record = loop.record
        if not (record.accepted or self.values["publish_rejected"]):
            return
        self.outputs.publish(record, (None, None), self.values["marker_frame_id"], 0, pair=False)
        if record.accepted:
            self.get_logger().info(
                f"inter-robot loop: {loop.query_robot} keyframe {record.query_id} -> "
                f"{loop.match_robot} keyframe {record.match_id}, score {record.pair_score:.3f}"
            )

    # ---- diagnostics, autosave, services --------------------------------------------------------
    def diagnostic_values(self) -> dict[str, str]:
        """Everything `/diagnostics` reports, as strings."""
        return diagnostic_values(self.values, self.stats, self.frames, self.maps)

    def _publish_diagnostics(self) -> None:
        values = self.diagnostic_values()
        problems = self.stats.problems()
        level = DiagnosticStatus.WARN if problems else DiagnosticStatus.OK
        if self.maps.build.error:  # until the next successful build
            level, problems = (
                DiagnosticStatus.ERROR,
                "; ".join(x for x in (self.maps.build.error, problems) if x),
            )
        status = DiagnosticStatus(
            name="vpr_node: loop closure",
            hardware_id=self.values["device"],
            level=level,
            message=problems or f"{values['mode']}, {values['map_size']} keyframes",
            values=[KeyValue(key=k, value=x) for k, x in values.items()],
        )
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = self.get_clock().now().to_msg()
        publish_while_up(self, self.pub_diag, msg)

    def _autosave(self) -> None:
        result = self.maps.autosave(self.values["map_dir"])
        if result is not None:
            self._log("info" if result[0] else "error", f"autosave: {result[1]}")

    @staticmethod
    def _trigger(action):
        def handle(request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
            response.success, response.message = action()
            return response

        return handle

    def _srv_localization(self, request: SetBool.Request, response: SetBool.Response):
        mode = "localization" if request.data else "mapping"
        result = self.set_parameters([Parameter("mode", value=mode)])[0]
        response.success = result.successful
        response.message = f"mode: {mode}" if result.successful else result.reason
        return response

    def _map_info(self) -> tuple[bool, str]:
        """The live map and the last build as JSON (a script polls this after build_map)."""
        info = {
            "keyframes": self.maps.size(),
            "mode": self.maps.state.mode,
            "map_dir": self.values["map_dir"],
            "build": self.maps.build.to_dict(),
            "robot": self.identity.robot,
            "session": self.identity.session,
            "prior_maps": self._prior_summary,  # dir, keyframes, sessions (fixed at start-up)
        }
        if self.fleet is not None:
            info["fleet"] = self.fleet.state()
        return True, json.dumps(info)

    def _clear(self) -> tuple[bool, str]:
        result = self.maps.clear()
        self.outputs.clear_markers()
        return result

    def _start_build(self) -> tuple[bool, str]:
        v = self.values
        return self.maps.start_build(
            v["build_source"],
            v["map_dir"],
            params.detector_config(v),
            image_topic=v["build_image_topic"] or None,
            image_period=v["build_image_period"],
            index=params.index_config(v),
            max_pixels=v["max_image_pixels"],
            geometry=params.geometry_config(v),
            identity=self.identity,
        )

    def shutdown(self) -> None:
        """Stop the worker and any build, save when asked to, release the map (idempotent)."""
        if self._closed:
            return
        self._closed = True
        self._stop.set()
        self.frames.close()
        if self._worker.is_alive():
            self._worker.join(timeout=30.0)
        save_to = self.values["map_dir"] if self.values["save_on_shutdown"] else ""
        result = self.maps.close(save_to)
        if result is not None:  # not the node's logger: after SIGINT its /rosout is gone
            log = rclpy.logging.get_logger(f"{self.get_name()}.shutdown")
            (log.info if result[0] else log.error)(f"on shutdown: {result[1]}")


class _StopSignals:
    """The first SIGINT / SIGTERM stops the node; later ones must not break off its shutdown (and
    the map save): Ctrl-C under `ros2 launch` delivers SIGINT twice, the terminal's and the copy
    launch forwards, and launch follows up with SIGTERM. Installed before `rclpy.init`, whose
    handlers chain to it."""

    def __init__(self) -> None:
        self.received = False
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, self._handle)

    def _handle(self, signum, frame) -> None:
        if not self.received:
            self.received = True
            raise KeyboardInterrupt

    def ignore_until_exit(self) -> None:
        """After a stop signal: ignore the rest for good (Python resets its own handlers to the
        default, fatal action while the interpreter exits; SIG_IGN it keeps)."""
        if self.received:
            for sig in (signal.SIGINT, signal.SIGTERM):
                signal.signal(sig, signal.SIG_IGN)


def main(argv: list[str] | None = None) -> int:
    """`vpr_node` entry point: `EXIT_OK` on a clean stop (Ctrl-C and SIGTERM are how a node is
    stopped, so they are not `EXIT_INTERRUPTED`), `EXIT_ERROR` when it cannot start."""
    signals = _StopSignals()
    log = rclpy.logging.get_logger("vpr_node")
    problem = params.params_file_problem(sys.argv if argv is None else argv)
    if problem:
        log.error(f"cannot start: {problem}")
        return EXIT_ERROR
    try:
        rclpy.init(args=argv)
    except RCLError as err:  # rcl's argument and parameter-file parser
        log.error(f"cannot start: {str(err).splitlines()[0]}")
        return EXIT_ERROR
    executor = MultiThreadedExecutor(num_threads=4)  # before the slow start: see below
    node = None
    try:
        try:
            node = VprNode()
        except (PairVPRError, ParameterException) as err:
            log.error(f"cannot start: {err}")
            return EXIT_ERROR
        executor.add_node(node)
        node.get_logger().info(f"ready: {node.summary}")  # after `node` is set: see finally
        executor.spin()
        return EXIT_OK
    except (KeyboardInterrupt, ExternalShutdownException):
        return EXIT_OK
    except Exception:
        if not rclpy.ok():  # a signal during start-up shut the context down under us
            return EXIT_OK
        raise
    finally:
        executor.shutdown()
        if node is not None:
            node.shutdown()
            node.destroy_node()
        rclpy.try_shutdown()
        signals.ignore_until_exit()


if __name__ == "__main__":
    sys.exit(main())
