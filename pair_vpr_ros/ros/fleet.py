"""vpr_node's fleet exchange on ROS 2 topics (thin: the logic is `fleet.FleetExchange`).

    fleet_keyframes_topic (shared)      every robot's keyframe descriptors, ~1.1 KB each
    fleet_request_topic/<robot_id>      score requests to that robot (the query's dense tokens)
    fleet_response_topic (shared)       the owners' answers, ~100 bytes each

`fleet_messages` picks the message types: typed (`pair_vpr_ros_interfaces` KeyframeDescriptor,
ScoreRequest, ScoreResponse, converted by `fleet.typed`) or bytes (the fleet codec in
`std_msgs/UInt8MultiArray`); auto = typed when that package is installed. Bytes sent and
received are counted as serialized on the wire. Everything that touches the pipeline runs on
the map thread of `MapControl` (messages are handed over from the subscription callbacks).
"""

from __future__ import annotations

from array import array
from collections.abc import Callable
from concurrent.futures import Future
from functools import partial
from typing import Any

from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.exceptions import InvalidTopicNameException
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import serialize_message
from std_msgs.msg import UInt8MultiArray

from pair_vpr_ros.errors import ConfigError, FleetMessageError
from pair_vpr_ros.fleet import FleetExchange, InterRobotLoop, Outgoing
from pair_vpr_ros.fleet.typed import from_typed, to_typed
from pair_vpr_ros.identity import Identity
from pair_vpr_ros.loops.frames import FrameOutcome
from pair_vpr_ros.messages.loop import POSE_STATUS_CODES
from pair_vpr_ros.params.fleet import fleet_config
from pair_vpr_ros.ros.maps import MapControl
from pair_vpr_ros.ros.outputs import publish_while_up, typed_unusable

try:  # built by `make setup` (scripts/build_interfaces.sh) or colcon in a ROS workspace
    from pair_vpr_ros_interfaces import msg as typed_msgs
except ImportError as err:  # the bytes transport needs only std_msgs
    typed_msgs, TYPED_MISSING = None, str(err)
else:
    TYPED_MISSING = ""

# Descriptors are kept by their publisher (transient local) for robots that join or return
# later: the newest 1000 (~1.1 MB) reach a late subscriber; requests and responses are not kept.
DEPTH = {"keyframes": 1000, "request": 4, "response": 50}
TYPED = {"keyframes": "KeyframeDescriptor", "request": "ScoreRequest", "response": "ScoreResponse"}


def typed_problem() -> str:
    """'' when the fleet's typed messages can be published, else why not (the package does
    not import, or its C type support does not load)."""
    if typed_msgs is None:
        return TYPED_MISSING or "pair_vpr_ros_interfaces is not installed"
    return typed_unusable(getattr(typed_msgs, name) for name in TYPED.values())


def typed_wanted(choice: str, warn: Callable[[str], Any]) -> bool:
    """fleet_messages -> typed (True) or bytes; ConfigError for typed that cannot be used (a
    fleet must agree on one kind); auto -> bytes without the package, and with one warning
    when the package imports but its type support does not load."""
    if choice == "bytes":
        return False
    problem = typed_problem()
    if problem and choice == "typed":
        raise ConfigError(
            f"fleet_messages is typed but pair_vpr_ros_interfaces cannot be used ({problem}): "
            "`make setup` builds it and the node must start from its environment "
            "(docs/interfaces.md), or use fleet_messages bytes on every robot"
        )
    if problem and typed_msgs is not None:
        warn(
            f"fleet_messages auto: bytes, because pair_vpr_ros_interfaces cannot be used "
            f"({problem}); every robot of the fleet must use the same kind"
        )
    return not problem


class FleetLink:
    """Topics <-> one `FleetExchange` around the node's live pipeline."""

    def __init__(
        self,
        node: Node,
        maps: MapControl,
        values: dict[str, Any],
        identity: Identity,
        on_loop: Callable[[InterRobotLoop], None],
    ) -> None:
        robot, session = identity.robot, identity.session  # the identity rule makes topic tokens
        config = fleet_config(values, robot, session)
        self.typed = typed_wanted(values["fleet_messages"], node.get_logger().warning)
        if self.typed:
            self._classes = {name: getattr(typed_msgs, name) for name in TYPED.values()}
            self._codes = POSE_STATUS_CODES  # = LoopClosure.POSE_* (test_typed_loop_closure)
        self._node, self._maps, self._on_loop = node, maps, on_loop
        self.exchange = maps.call(lambda: FleetExchange(maps.pipeline, config, self._send))
        self._qos = {k: QoSProfile(depth=d, reliability=ReliabilityPolicy.RELIABLE)
                     for k, d in DEPTH.items()}  # fmt: skip
        self._qos["keyframes"].durability = DurabilityPolicy.TRANSIENT_LOCAL
        self._request_topic = values["fleet_request_topic"].rstrip("/")
        self._pubs = {
            "keyframes": self._publisher(values["fleet_keyframes_topic"], "keyframes"),
            "response": self._publisher(values["fleet_response_topic"], "response"),
        }
        self._owners: dict[str, Any] = {}  # owner robot -> its request publisher
        group = MutuallyExclusiveCallbackGroup()
        for channel, topic in (
            ("keyframes", values["fleet_keyframes_topic"]),
            ("request", f"{self._request_topic}/{robot}"),
            ("response", values["fleet_response_topic"]),
        ):
            node.create_subscription(self._type(channel), topic, partial(self._heard, channel),
                                     self._qos[channel], callback_group=group)  # fmt: skip
        node.create_timer(1.0, self._tick)
        kind = "typed" if self.typed else "bytes"
        self.summary = f"fleet exchange on as robot {robot!r}, session {session!r} ({kind})"

    def on_outcome(self, outcome: FrameOutcome) -> None:
        """After a frame: publish a new keyframe's descriptor and requests (map thread)."""
        if outcome.keyframe_id is not None:
            self._maps.call(self._on_map_thread, self.exchange.on_keyframe, outcome)

    def state(self) -> dict:
        """The exchange's counts and bytes (copied on the map thread)."""
        return self._maps.call(self.exchange.summary)

    def _tick(self) -> None:
        future = self._maps.submit(self._on_map_thread, self.exchange.tick)
        future.add_done_callback(self._tick_done)

    def _tick_done(self, future: Future) -> None:
        """A timer tick's error is logged and counted (it would vanish in the Future); this
        runs on the map thread, which completed the Future."""
        err = future.exception()
        if err is not None:
            self.exchange.counts.skipped["tick failed"] += 1
            self._node.get_logger().error(f"fleet exchange tick failed: {err}")

    def _type(self, channel: str) -> type:
        return self._classes[TYPED[channel]] if self.typed else UInt8MultiArray

    def _on_map_thread(self, fn: Callable, *args: Any) -> Any:
        self.exchange.pipe = self._maps.pipeline  # a loaded or built map replaces it
        return fn(*args)

    def _heard(self, channel: str, msg: Any) -> None:
        self._maps.submit(self._receive, channel, msg)

    def _receive(self, channel: str, msg: Any) -> None:
        ex = self.exchange
        if self.typed:
            size = len(serialize_message(msg))
            try:
                loop = self._on_map_thread(ex.handle, channel, from_typed(msg, self._codes), size)
            except FleetMessageError as err:
                ex.reject(channel, size, err.reason)
                return
        else:
            data = msg.data.tobytes() if hasattr(msg.data, "tobytes") else bytes(msg.data)
            loop = self._on_map_thread(ex.receive, channel, data)
        if loop is not None:
            self._on_loop(loop)

    def _publisher(self, topic: str, channel: str):
        return self._node.create_publisher(self._type(channel), topic, self._qos[channel])

    def _send(self, out: Outgoing) -> int:
        """Publish one message -> its serialized size in bytes."""
        if out.channel == "request":
            pub = self._owners.get(out.target)
            if pub is None:
                topic = f"{self._request_topic}/{out.target}"
                try:
                    pub = self._publisher(topic, "request")
                except InvalidTopicNameException as err:  # counted by the exchange
                    raise FleetMessageError("bad name", f"owner {out.target!r}: {err}") from err
                self._owners[out.target] = pub
        else:
            pub = self._pubs[out.channel]
        if self.typed:
            msg = to_typed(out.message, self._classes, self._codes)
        else:
            msg = UInt8MultiArray(data=array("B", out.data))
        publish_while_up(self._node, pub, msg)
        return len(serialize_message(msg))
