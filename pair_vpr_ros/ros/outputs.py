"""The loop-closure outputs of `vpr_node`: one base topic and the topics under it.

`loop_closure` carries the LIO-SAM pair; `detail`, `json`, `factor`, `typed`, `markers` and
`image` live under whatever `loop_closure` resolves to, so one remap moves them all:
`-r loop_closure:=/lio_loop/loop_closure_detection` puts the pair where LIO-SAM listens and the
rest under `/lio_loop/loop_closure_detection/...`. A sub-topic can still be remapped on its own
by its resolved name (`-r /loop_closure/json:=/loops_json` without a base remap).
"""

from __future__ import annotations

import dataclasses
import importlib
from collections.abc import Iterable
from functools import cache

import numpy as np
from geometry_msgs.msg import Point
from nav_msgs.msg import Odometry
from rclpy.node import Node
from rclpy.type_support import check_for_type_support
from sensor_msgs.msg import Image
from std_msgs.msg import Float64MultiArray, MultiArrayDimension, String
from visualization_msgs.msg import Marker, MarkerArray

from pair_vpr_ros.loops.records import LoopRecord
from pair_vpr_ros.messages import loop as lm
from pair_vpr_ros.messages import loop_image
from pair_vpr_ros.messages.factor import FACTOR_MSG_TYPES, FACTOR_TOPIC, factor_msg
from pair_vpr_ros.types import Pose, split_stamp

try:  # built by `make setup` (scripts/build_interfaces.sh) or colcon in a ROS workspace
    from pair_vpr_ros_interfaces.msg import LoopClosure
except ImportError as err:  # the node runs without it: every other output stays on
    LoopClosure, TYPED_MISSING = None, str(err)
else:
    TYPED_MISSING = ""

MARKER_TOPIC = "loop_closure/markers"
SUBTOPICS = {  # output -> its topic relative to the base (loop_messages' names, base stripped)
    name: topic.removeprefix(lm.PAIR_TOPIC + "/")
    for name, topic in (
        ("detail", lm.DETAIL_TOPIC),
        ("json", lm.JSON_TOPIC),
        ("factor", FACTOR_TOPIC),
        ("typed", lm.TYPED_TOPIC),
        ("markers", MARKER_TOPIC),
        ("image", loop_image.IMAGE_TOPIC),
    )
}


def publish_while_up(node: Node, publisher, msg) -> bool:
    """Publish unless the node's context is shut down (a stop signal shuts it down at once,
    while a timer or the worker may still be about to publish): then drop `msg` quietly."""
    if not node.context.ok():
        return False
    try:
        publisher.publish(msg)
    except Exception:  # noqa: BLE001 - the context went down between the check and publish
        if node.context.ok():
            raise
        return False
    return True


def typed_unusable(classes: Iterable[type]) -> str:
    """'' when rclpy can publish every message class in `classes`, else why not. The Python
    package can import while its C type support cannot (a node started by another
    environment's `ros2 launch` that lacks this venv's lib/ in LD_LIBRARY_PATH): rclpy then
    raises UnsupportedTypeSupport or NoTypeSupportImportedException at `create_publisher`."""
    for cls in classes:
        try:
            check_for_type_support(cls)
        except Exception as err:  # noqa: BLE001 - any failure means typed off, never a crash
            return f"{type(err).__name__}: {err}".rstrip(": ")
    return ""


@cache
def message_classes(names: tuple[str, ...] = FACTOR_MSG_TYPES) -> dict[str, type]:
    """rclpy classes of the message types `names` (default: what `loop_messages.factor_msg`
    builds), by type name."""
    out = {}
    for name in names:
        package, kind, cls = name.split("/")
        out[name] = getattr(importlib.import_module(f"{package}.{kind}"), cls)
    return out


class LoopOutputs:
    """The publishers of one node; `publish` sends one loop's messages."""

    def __init__(self, node: Node, depth: int = 10) -> None:
        self._node = node
        self.base = node.resolve_topic_name(lm.PAIR_TOPIC)
        topics = {name: f"{self.base}/{sub}" for name, sub in SUBTOPICS.items()}
        self.topics = {"pair": self.base, **topics}
        self.pair = node.create_publisher(Float64MultiArray, self.base, depth)
        self.detail = node.create_publisher(Float64MultiArray, topics["detail"], depth)
        self.json = node.create_publisher(String, topics["json"], depth)
        self.factor = node.create_publisher(Odometry, topics["factor"], depth)
        self.markers = node.create_publisher(MarkerArray, topics["markers"], depth)
        self.image = node.create_publisher(Image, topics["image"], depth)
        self.typed = None
        missing = TYPED_MISSING or typed_unusable([LoopClosure])
        if missing:
            node.get_logger().warning(
                f"{topics['typed']} is off: the message package pair_vpr_ros_interfaces "
                f"cannot be imported ({missing}); build it with `make setup` (pip "
                "install) or `colcon build` in your ROS workspace, and start the node from "
                "its environment (docs/interfaces.md). Every other loop-closure topic is on."
            )
        else:
            self.typed = node.create_publisher(LoopClosure, topics["typed"], depth)

    def publish(
        self,
        record: LoopRecord,
        poses: tuple[Pose | None, Pose | None],
        marker_frame_id: str,
        number: int,
        pair: bool = True,
    ) -> tuple[bool, str]:
        """Send `record` (accepted, or rejected with publish_rejected): pair (accepted and
        ordered; never with `pair` False: an inter-robot loop's stamps are two robots' clocks,
        which a single-robot back end like LIO-SAM must not see), detail, json, typed, factor
        (with a relative pose), markers (both poses known, in `marker_frame_id`, marker id
        `number`) -> (pair sent, what the log should say)."""
        content = lm.loop_messages(record)
        if not pair:
            content = dataclasses.replace(content, pair=None)
        detail = Float64MultiArray(data=content.detail)
        detail.layout.dim = [
            MultiArrayDimension(label=x, size=1, stride=1) for x in content.detail_labels
        ]
        note = ""
        if record.accepted and content.pair is not None:
            self._send(self.pair, Float64MultiArray(data=content.pair))
            note = (
                f"loop closure {content.pair}: keyframe {record.match_id}, "
                f"score {record.pair_score:.3f}"
            )
        elif record.accepted and not lm.same_session(record):
            note = (
                f"loop closure to keyframe {record.match_id} of robot {record.match_robot!r} "
                f"session {record.match_session!r} (another trajectory): published on "
                f"{self.topics['detail']} and json, not on {self.base}"
            )
        elif record.accepted:
            note = (
                f"loop closure to keyframe {record.match_id} stamped {record.match_stamp:.3f} s, "
                f"not before the query ({record.query_stamp:.3f} s; another clock or a replayed "
                f"bag): published on {self.topics['detail']} and json, not on {self.base}"
            )
        self._send(self.detail, detail)
        self._send(self.json, String(data=content.json))
        if self.typed is not None:
            self._send(self.typed, lm.typed_msg(record, message_classes(lm.TYPED_MSG_TYPES)))
        if record.accepted and content.factor is not None:
            self._send(self.factor, factor_msg(content.factor, message_classes()))
        if record.accepted and None not in poses:
            self._send(self.markers, loop_marker(record, *poses, marker_frame_id, number))
        return content.pair is not None, note

    def publish_image(self, record: LoopRecord, bgr: np.ndarray) -> None:
        """Send one loop image (`messages.loop_image.draw_loop`), stamped and framed as the
        loop's query image."""
        msg = Image(**loop_image.image_fields(bgr))
        msg.header.stamp.sec, msg.header.stamp.nanosec = split_stamp(record.query_stamp)
        msg.header.frame_id = record.query_frame_id
        self._send(self.image, msg)

    def _send(self, publisher, msg) -> None:
        publish_while_up(self._node, publisher, msg)

    def clear_markers(self) -> None:
        self._send(self.markers, MarkerArray(markers=[Marker(action=Marker.DELETEALL)]))


def loop_marker(record: LoopRecord, pose_a: Pose, pose_b: Pose, frame_id: str, number: int):
    """One green line between the two keyframes' positions (id: the loop's number)."""
    m = Marker(ns="loop_closures", id=number)
    m.header.frame_id = frame_id
    m.header.stamp.sec, m.header.stamp.nanosec = split_stamp(record.query_stamp)
    m.type, m.action = Marker.LINE_LIST, Marker.ADD
    m.pose.orientation.w, m.scale.x = 1.0, 0.1
    m.color.g, m.color.a = 1.0, 1.0
    m.points = [Point(x=p[0], y=p[1], z=p[2]) for p in (pose_a, pose_b)]
    return MarkerArray(markers=[m])
