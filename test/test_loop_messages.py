"""loop_messages: the plain-data content of the node's loop-closure messages."""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pytest

from pair_vpr_ros import loop_messages as lm


def _record(**over):
    fields = dict(
        query_id=12, query_stamp=1700000123.456789, query_frame_id="cam_front", match_id=3,
        match_stamp=1700000001.25, match_frame_id="cam_front", pair_score=2.75,
        global_similarity=0.8125, rank_before=2, rank_after=0, inliers=-1,
        inlier_ratio=float("nan"), accepted=True, reason="",
    )  # fmt: skip
    return SimpleNamespace(**{**fields, **over})


def test_pair_is_exactly_two_stamps():
    assert lm.pair_data(_record()) == [1700000123.456789, 1700000001.25]


def test_detail_layout_and_values():
    assert lm.NUMERIC_FIELDS == (
        "query_id", "query_stamp", "match_id", "match_stamp", "pair_score", "global_similarity",
        "rank_before", "rank_after", "inliers", "inlier_ratio", "accepted",
    )  # fmt: skip
    data = lm.detail_data(_record(accepted=False, inlier_ratio=0.5))
    assert data == [
        12.0, 1700000123.456789, 3.0, 1700000001.25, 2.75, 0.8125, 2.0, 0.0, -1.0, 0.5, 0.0,
    ]  # fmt: skip
    assert lm.detail_to_dict(lm.NUMERIC_FIELDS, data)["accepted"] == 0.0
    with pytest.raises(ValueError, match="detail message has 11 labels but 2 values"):
        lm.detail_to_dict(lm.NUMERIC_FIELDS, [1.0, 2.0])


def test_json_has_every_field_in_order():
    record = _record(pair_score=np.float32(2.5), accepted=np.bool_(True), query_id=np.int64(12))
    decoded = json.loads(lm.record_json(record))
    assert list(decoded) == list(lm.LOOP_RECORD_FIELDS)
    assert decoded["query_id"] == 12 and decoded["pair_score"] == 2.5
    assert decoded["accepted"] is True and decoded["inlier_ratio"] is None
    assert decoded["query_frame_id"] == "cam_front" and decoded["reason"] == ""


def test_loop_messages_bundle():
    msgs = lm.loop_messages(_record())
    assert msgs.pair == lm.pair_data(_record())
    assert msgs.detail_labels == lm.NUMERIC_FIELDS and len(msgs.detail) == 11
    assert json.loads(msgs.json)["match_id"] == 3


def test_field_order_matches_loop_record():
    from pair_vpr_ros.detector import LoopRecord

    assert list(lm.LOOP_RECORD_FIELDS) == LoopRecord.field_names()
