"""The fleet messages <-> the typed ROS messages of `pair_vpr_ros_interfaces`
(`KeyframeDescriptor`, `ScoreRequest`, `ScoreResponse`), field for field, duck-typed: the ROS
side passes the classes in, so this module imports no ROS package. A typed message that cannot
be a fleet message raises `FleetMessageError` like bad codec bytes do ("malformed", "wrong
size"); `messages.check` then applies the same checks to both."""

from __future__ import annotations

from array import array
from collections.abc import Mapping
from typing import Any

import numpy as np

from pair_vpr_ros.errors import FleetMessageError
from pair_vpr_ros.fleet.messages import (
    MAX_CANDIDATES,
    KeyframeDescriptor,
    Message,
    ScoreRequest,
    ScoreResponse,
)
from pair_vpr_ros.types import split_stamp


def to_typed(msg: Message, classes: Mapping[str, Any], codes: Mapping[str, int]) -> Any:
    """A fleet message -> its typed ROS message (`classes`: class name -> class)."""
    out = classes[type(msg).__name__]()
    out.robot, out.session = msg.robot, msg.session
    out.model = np.frombuffer(msg.model, np.uint8)
    if isinstance(msg, KeyframeDescriptor):
        desc = np.ascontiguousarray(msg.descriptor, "<f2")
        out.keyframe_id, out.dim = int(msg.keyframe_id), len(desc)
        _stamp(out.stamp, msg.stamp)
        out.descriptor = array("B", desc.tobytes())
    elif isinstance(msg, ScoreRequest):
        dense = np.ascontiguousarray(msg.dense, "<f2")
        out.request_id, out.owner_robot, out.owner_session = (
            msg.request_id, msg.owner_robot, msg.owner_session)  # fmt: skip
        out.query_id = int(msg.query_id)
        _stamp(out.query_stamp, msg.query_stamp)
        out.candidate_ids = array("q", msg.candidate_ids)
        out.global_similarities = array("f", msg.similarities)
        out.token_count, out.token_dim = dense.shape
        out.dense_tokens = array("B", dense.tobytes())
        out.features = array("B", msg.features)
    else:
        out.request_id = msg.request_id
        out.requester_robot, out.requester_session = msg.requester_robot, msg.requester_session
        out.query_id, out.match_id = int(msg.query_id), int(msg.match_id)
        _stamp(out.match_stamp, msg.match_stamp)
        out.pair_score, out.scored, out.accepted = msg.pair_score, msg.scored, msg.accepted
        out.pose_status = codes.get(msg.pose_status, codes[""])
    return out


def from_typed(ros: Any, codes: Mapping[str, int]) -> Message:
    """A typed ROS message -> the fleet message (FleetMessageError when it cannot be one)."""
    kind = type(ros).__name__
    if kind not in ("KeyframeDescriptor", "ScoreRequest", "ScoreResponse"):
        raise FleetMessageError("malformed", f"not a fleet message type: {kind}")
    model = bytes(np.asarray(ros.model, np.uint8))
    if kind == "KeyframeDescriptor":
        desc = _float16(ros.descriptor, int(ros.dim), "descriptor")
        return KeyframeDescriptor(ros.robot, ros.session, model, int(ros.keyframe_id),
                                  _seconds(ros.stamp), desc)  # fmt: skip
    if kind == "ScoreRequest":
        n, d = int(ros.token_count), int(ros.token_dim)
        if not 1 <= len(ros.candidate_ids) <= MAX_CANDIDATES:
            raise FleetMessageError("malformed", f"{len(ros.candidate_ids)} candidates")
        dense = _float16(ros.dense_tokens, n * d, "dense tokens").reshape(n, d)
        return ScoreRequest(ros.robot, ros.session, model, int(ros.request_id), ros.owner_robot,
                            ros.owner_session, int(ros.query_id), _seconds(ros.query_stamp),
                            [int(i) for i in ros.candidate_ids],
                            [float(x) for x in ros.global_similarities], dense,
                            bytes(ros.features))  # fmt: skip
    names = {code: status for status, code in codes.items()}
    return ScoreResponse(ros.robot, ros.session, model, int(ros.request_id),
                         ros.requester_robot, ros.requester_session, int(ros.query_id),
                         int(ros.match_id), _seconds(ros.match_stamp), float(ros.pair_score),
                         int(ros.scored), bool(ros.accepted),
                         names.get(int(ros.pose_status), ""))  # fmt: skip


def _float16(data: Any, count: int, what: str) -> np.ndarray:
    raw = bytes(data)
    if len(raw) != 2 * count:
        raise FleetMessageError("wrong size", f"{what}: {len(raw)} bytes for {count} float16")
    return np.frombuffer(raw, "<f2").copy()


def _stamp(time_msg: Any, seconds: float) -> None:
    time_msg.sec, time_msg.nanosec = split_stamp(seconds)


def _seconds(time_msg: Any) -> float:
    return time_msg.sec + time_msg.nanosec * 1e-9
