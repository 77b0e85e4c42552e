"""The content of the loop-closure messages, as plain Python (no ROS types).

The node fills rclpy messages and the bag writer fills rosbags messages from these functions, so
both publish identical data. One accepted ``LoopRecord`` gives three messages:

``loop_closure`` — ``std_msgs/Float64MultiArray``, the LIO-SAM / LVI-SAM pair
    ``data = [t_current, t_previous]``: exactly 2 float64, the query and match keyframes' image
    header stamps in seconds. ``layout`` is empty. LIO-SAM listens on
    ``lio_loop/loop_closure_detection``: remap this topic there.

``loop_closure/detail`` — ``std_msgs/Float64MultiArray``, every numeric field of the record,
    one value per field, in this order::

        index  label              value
        0      query_id           query keyframe id in the place map
        1      query_stamp        query header stamp, s
        2      match_id           matched keyframe id
        3      match_stamp        matched header stamp, s
        4      pair_score         pair-classifier score (logit(q,c) + logit(c,q))
        5      global_similarity  global-descriptor similarity
        6      rank_before        rank by global similarity (1 = best)
        7      rank_after         rank after pair re-ranking (1 = best)
        8      inliers            geometric-verification inliers, -1 when not verified
        9      inlier_ratio       inliers / matches
        10     accepted           1.0 accepted, 0.0 rejected

    ``layout.dim`` has one ``MultiArrayDimension(label=<field>, size=1, stride=1)`` per value in
    the same order, ``layout.data_offset = 0``, so a consumer can look values up by label.
    The frame ids and the rejection reason are not numeric and appear only in the JSON.

``loop_closure/json`` — ``std_msgs/String``, a JSON object with every ``LoopRecord`` field
    (``query_id, query_stamp, query_frame_id, match_id, match_stamp, match_frame_id, pair_score,
    global_similarity, rank_before, rank_after, inliers, inlier_ratio, accepted, reason``);
    booleans as JSON booleans, non-finite floats as ``null``.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

PAIR_TOPIC = "loop_closure"
DETAIL_TOPIC = "loop_closure/detail"
JSON_TOPIC = "loop_closure/json"
FLOAT64_ARRAY_TYPE = "std_msgs/msg/Float64MultiArray"
STRING_TYPE = "std_msgs/msg/String"

LOOP_RECORD_FIELDS = (
    "query_id",
    "query_stamp",
    "query_frame_id",
    "match_id",
    "match_stamp",
    "match_frame_id",
    "pair_score",
    "global_similarity",
    "rank_before",
    "rank_after",
    "inliers",
    "inlier_ratio",
    "accepted",
    "reason",
)
TEXT_FIELDS = ("query_frame_id", "match_frame_id", "reason")
NUMERIC_FIELDS = tuple(f for f in LOOP_RECORD_FIELDS if f not in TEXT_FIELDS)


@dataclass(frozen=True)
class LoopMessages:
    """The three messages of one loop closure, as plain data."""

    pair: list[float]
    detail_labels: tuple[str, ...]
    detail: list[float]
    json: str


def pair_data(record: Any) -> list[float]:
    """``[t_current, t_previous]``: the query and match header stamps, s (LIO-SAM layout)."""
    return [float(record.query_stamp), float(record.match_stamp)]


def detail_data(record: Any) -> list[float]:
    """The numeric fields of ``record`` in ``NUMERIC_FIELDS`` order, booleans as 1.0 / 0.0."""
    return [float(getattr(record, name)) for name in NUMERIC_FIELDS]


def record_dict(record: Any) -> dict[str, Any]:
    """Every ``LoopRecord`` field in order, JSON-safe (non-finite floats become None)."""
    out: dict[str, Any] = {}
    for name in LOOP_RECORD_FIELDS:
        value = getattr(record, name)
        if isinstance(value, str) or value is None:
            pass
        elif isinstance(value, (bool, np.bool_)):
            value = bool(value)
        elif isinstance(value, (int, np.integer)):
            value = int(value)
        else:
            value = float(value)
            value = value if math.isfinite(value) else None
        out[name] = value
    return out


def record_json(record: Any) -> str:
    """The JSON string of ``record_dict(record)`` (the ``loop_closure/json`` payload)."""
    return json.dumps(record_dict(record), allow_nan=False)


def loop_messages(record: Any) -> LoopMessages:
    """All three payloads of one loop closure."""
    return LoopMessages(
        pair=pair_data(record),
        detail_labels=NUMERIC_FIELDS,
        detail=detail_data(record),
        json=record_json(record),
    )


def detail_to_dict(labels: list[str] | tuple[str, ...], data: Any) -> dict[str, float]:
    """Decode a detail message: ``{label: value}`` from its dimension labels and data."""
    if len(labels) != len(data):
        raise ValueError(f"detail message has {len(labels)} labels but {len(data)} values")
    return {label: float(value) for label, value in zip(labels, data, strict=True)}
