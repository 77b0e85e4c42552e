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
`.../image` (Image bgr8: query | match, inlier matches, scores; `messages.loop_image`);
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
poses `types`, the map services `ros.maps`. `VprNode` is built from the node's parameter handling
(`ros.parameters`), its frame intake and worker (`ros.intake`) and its services and diagnostics
(`ros.services`); this module keeps its start-up, loop publishing, shutdown and `main`.
"""

from __future__ import annotations

if __name__ == "__main__":  # `python -m pair_vpr_ros.ros.node`: through the light entry point,
    # so that Ctrl-C while rclpy and torch import is a clean stop, as for `vpr_node` (ros.entry)
    import sys as _sys

    from pair_vpr_ros.ros.entry import vpr_node as _vpr_node

    _sys.exit(_vpr_node())

import signal
import sys
import threading
from functools import partial

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor
from rclpy.impl.implementation_singleton import rclpy_implementation
from rclpy.node import Node

from pair_vpr_ros import params
from pair_vpr_ros.cli import EXIT_ERROR, EXIT_OK
from pair_vpr_ros.errors import ConfigError, PairVPRError
from pair_vpr_ros.fleet import InterRobotLoop
from pair_vpr_ros.identity import resolve_identity
from pair_vpr_ros.loops.frames import FrameOutcome
from pair_vpr_ros.loops.pipeline import LoopClosurePipeline
from pair_vpr_ros.loops.prior_maps import open_prior_maps
from pair_vpr_ros.loops.records import LoopRecord
from pair_vpr_ros.messages.loop_image import LoopPictures
from pair_vpr_ros.model.devices import check_device
from pair_vpr_ros.model.threads import applied_threads
from pair_vpr_ros.offline.bags.calibration import calibration_loader
from pair_vpr_ros.ros.fleet import FleetLink
from pair_vpr_ros.ros.geometry_inputs import GeometryInputs
from pair_vpr_ros.ros.intake import FrameIntake
from pair_vpr_ros.ros.maps import MapControl
from pair_vpr_ros.ros.outputs import MARKER_TOPIC, LoopOutputs
from pair_vpr_ros.ros.parameters import ParameterHandling, declare_all
from pair_vpr_ros.ros.rig import RigIntake, declare_rig
from pair_vpr_ros.ros.runtime import FrameQueue, NodeStats, precision_context
from pair_vpr_ros.ros.services import NodeServices
from pair_vpr_ros.types import Pose, PoseTrack
from pair_vpr_ros.weights import load_model

__all__ = ["MARKER_TOPIC", "VprNode", "main"]
RCLError = rclpy_implementation.RCLError


class VprNode(ParameterHandling, RigIntake, FrameIntake, NodeServices, Node):
    """Frames in, loop closures out. `start_worker=False` leaves frames queued (tests)."""

    def __init__(self, *, start_worker: bool = True, **kwargs) -> None:
        super().__init__("vpr_node", **kwargs)
        v = declare_all(self)
        self.values = v
        self.rig = declare_rig(self, v)  # None: one camera (ros/rig.py)
        device = check_device(v["device"])
        calibration = calibration_loader(
            v["openvino_calibration"], v["openvino_calibration_topic"], v["max_image_pixels"],
            self.get_logger().warning,
        )  # fmt: skip
        model = load_model(
            v["weights"], device=device, precision=v["precision"], image_size=v["image_size"],
            explicit_name="parameter weights (-p weights:=PATH)", params_rule=False,
            backend=v["backend"], openvino_cache_dir=v["openvino_cache_dir"],
            openvino_calibration=calibration, num_threads=v["num_threads"],
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
                identity=self.identity, prior_maps=priors.maps, rig=self.rig,
            ),
            self._log,
            partial(precision_context, device, autocast),
        )  # fmt: skip
        self.frames = FrameQueue(v["queue_size"])
        # keyframe images for loop_closure/image's match side (kept while loop_image is on)
        who = (self.identity.robot, self.identity.session)
        self.pictures = LoopPictures(who, v["loop_image_memory_mb"] << 20)
        # The frame-rate limit, applied before the queue as well (the image callback's own
        # state): frames the pipeline would skip never fill the queue while a keyframe runs.
        self._min_interval = config.min_frame_interval
        self._last_queued: float | None = None
        self.poses = PoseTrack(maxlen=v["pose_buffer_size"])
        self.stats = NodeStats()
        # depth (and right) images are looked up when the worker takes the frame: keep them for
        # every frame the queue can hold, else a frame queued behind many others loses its depth
        self.geometry_inputs = GeometryInputs(
            v, self.stats.counts, buffer_size=30 + v["queue_size"]
        )
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
        threads = applied_threads()
        self.summary = (
            f"model {model.fingerprint} on {v['device']} ({v['backend']}, {v['precision']}, "
            f"{threads} CPU thread{'s' * (threads != 1)}), "
            f"{self.maps.size()} keyframes, mode {v['mode']}, robot {self.identity.robot}, "
            f"session {self.identity.session}, {len(priors.maps)} prior maps"
        )
        if self.fleet is not None:
            self.summary += f"; {self.fleet.summary}"
        if self.rig is not None:
            cams = ", ".join(f"{c.name} ({c.image_topic})" for c in self.rig.cameras)
            self.summary += f"; rig of {cams}, loops in {self.rig.base_frame}"

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
        self._make_subscriptions(v)
        self.outputs = LoopOutputs(self)
        self.pub_pair = self.outputs.pair
        self.pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self._make_services(v)

    def _publish_loop(self, record: LoopRecord, pose: Pose | None, match_pose: Pose | None):
        if not (record.accepted or self.values["publish_rejected"]):
            return
        counts = self.stats.counts
        number = counts.loops + counts.loops_unordered + 1  # a marker id of its own per loop
        sent, note = self.outputs.publish(
            record, (pose, match_pose), self.values["marker_frame_id"], number
        )
        if record.accepted and sent:
            counts.loops += 1
            self.get_logger().info(note)
        elif record.accepted:
            counts.loops_unordered += 1
            self.get_logger().warning(note, throttle_duration_sec=10.0)

    def _publish_loop_image(self, outcome: FrameOutcome, record: LoopRecord, rgb) -> None:
        """`loop_closure/image` of an accepted loop (a rejected one with loop_image_rejected)."""
        v = self.values
        if v["loop_image"] and (record.accepted or v["loop_image_rejected"]):
            self.outputs.publish_image(record, self.pictures.draw(outcome, record, rgb))

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
