"""The content of the loop-closure messages, as plain Python (no ROS types).

The node fills rclpy messages and the bag writer fills rosbags messages from these functions, so
both publish identical data; the pose-graph tools decode them here too. One accepted
``LoopRecord`` gives up to four messages:

``loop_closure`` — ``std_msgs/Float64MultiArray``, the LIO-SAM / LVI-SAM pair
    ``data = [t_current, t_previous]``: exactly 2 float64, the query and match keyframes' image
    header stamps in seconds. ``layout`` is empty. LIO-SAM listens on
    ``lio_loop/loop_closure_detection``: remap this topic there. Every accepted loop, with or
    without a relative pose, whose match is older than the query (``t_previous < t_current``)
    and of the same robot and session; a loop to a keyframe stamped later (a map from another
    clock, a bag played again) or recorded by another robot or in another session (a prior
    map) has no pair message (``pair`` None): LIO-SAM would take it for a loop into its own
    trajectory at ``t_previous``.

``loop_closure/detail`` — ``std_msgs/Float64MultiArray``, every numeric field of the record,
    one value per field, labelled: ``DETAIL_LABELS`` = ``NUMERIC_FIELDS`` (query_id,
    query_stamp, match_id, match_stamp, pair_score, global_similarity, rank_before, rank_after,
    candidates, scored, inliers, inlier_ratio, accepted, pose_inliers, tx, ty, tz, qx, qy, qz,
    qw), then ``pose_status`` (0 no pose, 1 metric, 2 scale-free, 3 metric with the length from
    odometry), then the covariance ``cov_00`` .. ``cov_55`` (row, column in x, y, z, rx, ry, rz
    order; NaN without a pose), then four text fields carried by their labels, each
    ``<field>=<text>`` with the value NaN: ``query_robot``, ``query_session``, ``match_robot``,
    ``match_session`` (``detail_text``). After the covariance come ``query_camera`` and
    ``match_camera`` (a rig's camera indices, 0 for one camera) and after the identity the text
    label ``pose_frame=<frame>`` ("" unless the pose is between two rig bases).
    ``layout.dim`` has one ``MultiArrayDimension(label=<name>, size=1, stride=1)`` per value,
    ``layout.data_offset = 0``: look values up by label (``detail_to_dict``).

``loop_closure/json`` — ``std_msgs/String``, a JSON object with every ``LoopRecord`` field in
    order; booleans as JSON booleans, non-finite floats as ``null``, ``covariance`` a list of 36
    numbers or ``null``.

``loop_closure/factor`` — ``nav_msgs/Odometry``, one message per loop that has a relative pose:
    everything one between-factor needs (layout in ``messages.factor`` and docs/node.md).

``loop_closure/typed`` — ``pair_vpr_ros_interfaces/msg/LoopClosure`` (interfaces/ in this
    repository, docs/interfaces.md): the json record as one typed message, with both sides'
    robot and session and the relative pose as a ``geometry_msgs/PoseWithCovariance``;
    ``loop_closure_fields`` gives its values. Sent with detail and json.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from pair_vpr_ros.messages.factor import POSE_MSG_TYPES, LoopFactor, factor_from_record
from pair_vpr_ros.types import split_stamp

PAIR_TOPIC = "loop_closure"
DETAIL_TOPIC = "loop_closure/detail"
JSON_TOPIC = "loop_closure/json"
TYPED_TOPIC = "loop_closure/typed"
TYPED_TYPE = "pair_vpr_ros_interfaces/msg/LoopClosure"
TYPED_MSG_TYPES = (*POSE_MSG_TYPES, TYPED_TYPE)  # every message type `typed_msg` constructs
FLOAT64_ARRAY_TYPE = "std_msgs/msg/Float64MultiArray"
STRING_TYPE = "std_msgs/msg/String"

LOOP_RECORD_FIELDS = (
    "query_id",
    "query_stamp",
    "query_frame_id",
    "match_id",
    "match_stamp",
    "match_frame_id",
    "query_robot",
    "query_session",
    "match_robot",
    "match_session",
    "pair_score",
    "global_similarity",
    "rank_before",
    "rank_after",
    "candidates",
    "scored",
    "inliers",
    "inlier_ratio",
    "accepted",
    "reason",
    "pose_status",
    "pose_reason",
    "pose_inliers",
    "tx",
    "ty",
    "tz",
    "qx",
    "qy",
    "qz",
    "qw",
    "covariance",
    "query_camera",
    "match_camera",
    "pose_frame",
)
IDENTITY_FIELDS = ("query_robot", "query_session", "match_robot", "match_session")
TEXT_FIELDS = (
    "query_frame_id", "match_frame_id", *IDENTITY_FIELDS, "reason", "pose_status", "pose_reason",
    "pose_frame",
)  # fmt: skip
CAMERA_FIELDS = ("query_camera", "match_camera")  # numbers, after the covariance in detail
POSE_AXES = ("x", "y", "z", "rx", "ry", "rz")  # ROS PoseWithCovariance order
NUMERIC_FIELDS = tuple(
    f for f in LOOP_RECORD_FIELDS if f not in (*TEXT_FIELDS, "covariance", *CAMERA_FIELDS)
)
COVARIANCE_LABELS = tuple(f"cov_{r}{c}" for r in range(6) for c in range(6))
# new labels go last, so that a consumer indexing the old layout keeps working
DETAIL_LABELS = (*NUMERIC_FIELDS, "pose_status", *COVARIANCE_LABELS, *CAMERA_FIELDS)
POSE_STATUS_CODES = {"": 0, "metric": 1, "scale-free": 2, "metric-odometry": 3}


@dataclass(frozen=True)
class LoopMessages:
    """The messages of one loop closure, as plain data (``factor`` None: no relative pose)."""

    pair: list[float] | None  # None: the match is not older than the query
    detail_labels: tuple[str, ...]
    detail: list[float]
    json: str
    factor: LoopFactor | None = None


def identity(record: Any) -> dict[str, str]:
    """The record's robot and session of both sides ("" when it has none: the old format)."""
    return {name: str(getattr(record, name, "") or "") for name in IDENTITY_FIELDS}


def same_session(record: Any) -> bool:
    """Are query and match of the same robot and session (so on one clock and trajectory)?"""
    who = identity(record)
    return (who["query_robot"], who["query_session"]) == (who["match_robot"], who["match_session"])


def pair_data(record: Any) -> list[float] | None:
    """``[t_current, t_previous]``: the query and match header stamps, s (LIO-SAM layout);
    None unless ``t_previous < t_current`` and both are of one robot and session."""
    current, previous = float(record.query_stamp), float(record.match_stamp)
    return [current, previous] if previous < current and same_session(record) else None


def covariance_values(record: Any) -> list[float]:
    """The record's 36 covariance values (row-major), or 36 NaN when it has no pose."""
    cov = tuple(getattr(record, "covariance", ()) or ())
    return [float(v) for v in cov] if len(cov) == 36 else [math.nan] * 36


def detail_data(record: Any) -> list[float]:
    """Values in ``detail_labels(record)`` order, booleans as 1.0 / 0.0; the identity
    fields (text in their labels) NaN."""
    values = [float(getattr(record, name)) for name in NUMERIC_FIELDS]
    values.append(float(POSE_STATUS_CODES.get(record.pose_status, 0)))
    values += covariance_values(record) + [float(cameras(record)[k]) for k in CAMERA_FIELDS]
    return values + [math.nan] * (len(IDENTITY_FIELDS) + 1)


def detail_labels(record: Any) -> tuple[str, ...]:
    """``DETAIL_LABELS``, then ``<field>=<text>`` for each of ``IDENTITY_FIELDS`` and for
    ``pose_frame``."""
    texts = {**identity(record), "pose_frame": pose_frame(record)}
    return (*DETAIL_LABELS, *(f"{k}={v}" for k, v in texts.items()))


def cameras(record: Any) -> dict[str, int]:
    """The record's rig cameras of both sides (0 when it has none: one camera, old records)."""
    return {name: int(getattr(record, name, 0) or 0) for name in CAMERA_FIELDS}


def pose_frame(record: Any) -> str:
    """The frame of a rig loop's base-to-base pose; "" for a pose between camera frames."""
    return str(getattr(record, "pose_frame", "") or "")


def _json_value(value: Any) -> Any:
    if isinstance(value, str) or value is None:
        return value
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    value = float(value)
    return value if math.isfinite(value) else None


def record_dict(record: Any) -> dict[str, Any]:
    """Every ``LoopRecord`` field in order, JSON-safe (non-finite floats become None; the
    covariance a list of 36, or None without a pose)."""
    out: dict[str, Any] = {}
    for name in LOOP_RECORD_FIELDS:
        if name == "covariance":
            cov = tuple(getattr(record, name) or ())
            out[name] = [_json_value(v) for v in cov] if len(cov) == 36 else None
        elif name in IDENTITY_FIELDS:
            out[name] = identity(record)[name]
        elif name in CAMERA_FIELDS:
            out[name] = cameras(record)[name]
        elif name == "pose_frame":
            out[name] = pose_frame(record)
        else:
            out[name] = _json_value(getattr(record, name))
    return out


def record_json(record: Any) -> str:
    """The JSON string of ``record_dict(record)`` (the ``loop_closure/json`` payload)."""
    return json.dumps(record_dict(record), allow_nan=False)


def csv_row(record: Any) -> list[Any]:
    """One CSV row in ``LOOP_RECORD_FIELDS`` order; the covariance is one cell of 36
    space-separated numbers (empty without a pose)."""
    row = []
    texts = {**identity(record), **cameras(record), "pose_frame": pose_frame(record)}
    for name in LOOP_RECORD_FIELDS:
        value = texts[name] if name in texts else getattr(record, name)
        if name == "covariance":
            value = " ".join(repr(float(v)) for v in value) if len(value) == 36 else ""
        row.append(value)
    return row


def loop_messages(record: Any) -> LoopMessages:
    """All payloads of one loop closure."""
    return LoopMessages(
        pair=pair_data(record),
        detail_labels=detail_labels(record),
        detail=detail_data(record),
        json=record_json(record),
        factor=factor_from_record(record),
    )


def detail_to_dict(labels: list[str] | tuple[str, ...], data: Any) -> dict[str, float]:
    """Decode a detail message: ``{label: value}`` of its numeric values from its dimension
    labels and data (the text fields: ``detail_text``)."""
    if len(labels) != len(data):
        raise ValueError(f"detail message has {len(labels)} labels but {len(data)} values")
    pairs = zip(labels, data, strict=True)
    return {label: float(value) for label, value in pairs if "=" not in label}


def detail_text(labels: list[str] | tuple[str, ...]) -> dict[str, str]:
    """The text fields of a detail message, ``{field: text}`` (the identity; {} from a node
    older than issue 22)."""
    return dict(label.split("=", 1) for label in labels if "=" in label)


def loop_closure_fields(record: Any) -> dict[str, Any]:
    """The ``loop_closure/typed`` message (``TYPED_TYPE``) as plain values, keyed by its field
    names: stamps as (sec, nanosec); ``header`` = {stamp: the query's, frame_id: the match's};
    ``pose_status`` its code (``POSE_STATUS_CODES``: 0 none, 1 metric, 2 scale-free, 3 metric
    from odometry); ``relative_pose`` = {position (x, y, z), orientation (x, y, z, w),
    covariance (36, row-major)}, all NaN without a pose."""
    out: dict[str, Any] = {
        "header": {
            "stamp": split_stamp(float(record.query_stamp)),
            "frame_id": pose_frame(record) or str(record.match_frame_id),
        }
    }
    out |= identity(record)  # query_robot, query_session, match_robot, match_session
    out |= cameras(record)  # query_camera, match_camera
    for side in ("query", "match"):
        out[f"{side}_stamp"] = split_stamp(float(getattr(record, f"{side}_stamp")))
        out[f"{side}_id"] = int(getattr(record, f"{side}_id"))
        out[f"{side}_frame_id"] = str(getattr(record, f"{side}_frame_id"))
    for name in ("pair_score", "global_similarity", "inlier_ratio"):
        out[name] = float(getattr(record, name))
    for name in ("rank_before", "rank_after", "candidates", "scored", "inliers", "pose_inliers"):
        out[name] = int(getattr(record, name))
    out |= {
        "accepted": bool(record.accepted),
        "reason": str(record.reason),
        "pose_status": POSE_STATUS_CODES.get(record.pose_status, 0),
        "pose_reason": str(record.pose_reason),
        "relative_pose": {
            "position": tuple(float(getattr(record, k)) for k in ("tx", "ty", "tz")),
            "orientation": tuple(float(getattr(record, k)) for k in ("qx", "qy", "qz", "qw")),
            "covariance": covariance_values(record),
        },
    }
    return out


def typed_msg(record: Any, types: dict[str, Any]) -> Any:
    """Build the ``loop_closure/typed`` message of ``record`` (``loop_closure_fields``) with the
    message classes in ``types`` (keys: ``TYPED_MSG_TYPES``; rclpy classes or a rosbags
    typestore's ``types``), as ``factor_msg`` does for the factor."""
    f = loop_closure_fields(record)
    time = types["builtin_interfaces/msg/Time"]
    header, pose = f.pop("header"), f.pop("relative_pose")
    for side in ("query", "match"):
        sec, nanosec = f[f"{side}_stamp"]
        f[f"{side}_stamp"] = time(sec=sec, nanosec=nanosec)
    sec, nanosec = header["stamp"]
    point, quat = types["geometry_msgs/msg/Point"], types["geometry_msgs/msg/Quaternion"]
    return types[TYPED_TYPE](
        header=types["std_msgs/msg/Header"](
            stamp=time(sec=sec, nanosec=nanosec), frame_id=header["frame_id"]
        ),
        relative_pose=types["geometry_msgs/msg/PoseWithCovariance"](
            pose=types["geometry_msgs/msg/Pose"](
                position=point(**dict(zip("xyz", pose["position"], strict=True))),
                orientation=quat(**dict(zip("xyzw", pose["orientation"], strict=True))),
            ),
            covariance=np.asarray(pose["covariance"], dtype=np.float64),
        ),
        **f,
    )
