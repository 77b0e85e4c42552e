"""messages.loop: the plain-data content of the node's loop-closure messages."""

from __future__ import annotations

import json
import math
from types import SimpleNamespace

import numpy as np
import pytest

from pair_vpr_ros.messages import loop as lm


def _record(**over):
    fields = dict(
        query_id=12, query_stamp=1700000123.456789, query_frame_id="cam_front", match_id=3,
        match_stamp=1700000001.25, match_frame_id="cam_front", pair_score=2.75,
        global_similarity=0.8125, rank_before=2, rank_after=0, candidates=10, scored=3, inliers=-1,
        inlier_ratio=float("nan"), accepted=True, reason="", pose_status="", pose_reason="",
        pose_inliers=-1, tx=NAN, ty=NAN, tz=NAN, qx=NAN, qy=NAN, qz=NAN, qw=NAN, covariance=(),
    )  # fmt: skip
    return SimpleNamespace(**{**fields, **over})


NAN = float("nan")
COV = tuple(float(i) for i in range(36))


def _posed(**over):
    """An accepted record with a metric pose."""
    pose = dict(
        pose_status="metric", pose_inliers=57, tx=1.5, ty=-0.25, tz=3.0, qx=0.0, qy=0.6,
        qz=0.0, qw=0.8, covariance=COV,
    )  # fmt: skip
    return _record(**{**pose, **over})


def test_pair_is_exactly_two_stamps():
    assert lm.pair_data(_record()) == [1700000123.456789, 1700000001.25]


@pytest.mark.parametrize("match_stamp", [1700000123.456789, 1700000200.0])
def test_no_pair_unless_the_match_is_older(match_stamp):
    record = _record(match_stamp=match_stamp)  # same stamp, or a later one (another clock)
    assert lm.pair_data(record) is None and lm.loop_messages(record).pair is None


def test_detail_layout_and_values():
    assert lm.NUMERIC_FIELDS == (
        "query_id", "query_stamp", "match_id", "match_stamp", "pair_score", "global_similarity",
        "rank_before", "rank_after", "candidates", "scored", "inliers", "inlier_ratio",
        "accepted", "pose_inliers",
        "tx", "ty", "tz", "qx", "qy", "qz", "qw",
    )  # fmt: skip
    assert lm.DETAIL_LABELS[21:24] == ("pose_status", "cov_00", "cov_01")
    assert lm.DETAIL_LABELS[57] == "cov_55" and len(lm.DETAIL_LABELS) == 22 + 36 + 2
    assert lm.DETAIL_LABELS[58:] == ("query_camera", "match_camera")  # last: old indices hold
    data = lm.detail_data(_record(accepted=False, inlier_ratio=0.5))
    assert data[:14] == [
        12.0, 1700000123.456789, 3.0, 1700000001.25, 2.75, 0.8125, 2.0, 0.0, 10.0, 3.0, -1.0,
        0.5, 0.0, -1.0,
    ]  # fmt: skip
    assert all(math.isnan(v) for v in data[14:21] + data[22:58]) and data[21] == 0.0
    assert data[58:60] == [0.0, 0.0]  # one camera
    labels = lm.detail_labels(_record())
    assert lm.detail_to_dict(labels, data)["accepted"] == 0.0
    posed = lm.detail_to_dict(labels, lm.detail_data(_posed()))
    assert (posed["pose_status"], posed["pose_inliers"], posed["tz"]) == (1.0, 57.0, 3.0)
    assert (posed["cov_00"], posed["cov_12"], posed["cov_55"]) == (0.0, 8.0, 35.0)
    scale_free = lm.detail_to_dict(labels, lm.detail_data(_posed(pose_status="scale-free")))
    assert scale_free["pose_status"] == 2.0
    rig = lm.detail_to_dict(labels, lm.detail_data(_record(query_camera=1, match_camera=2)))
    assert (rig["query_camera"], rig["match_camera"]) == (1.0, 2.0)
    with pytest.raises(ValueError, match="detail message has 65 labels but 2 values"):
        lm.detail_to_dict(labels, [1.0, 2.0])


IDENTITY = dict(query_robot="r1", query_session="s2", match_robot="r0", match_session="s1")


def test_detail_carries_both_sides_identity_in_its_labels():
    record = _record(**IDENTITY)
    labels, data = lm.detail_labels(record), lm.detail_data(record)
    assert labels[:60] == lm.DETAIL_LABELS and len(data) == 65
    assert labels[60:] == (
        "query_robot=r1", "query_session=s2", "match_robot=r0", "match_session=s1",
        "pose_frame=",
    )  # fmt: skip
    assert all(math.isnan(v) for v in data[60:])
    assert lm.detail_text(labels) == {**IDENTITY, "pose_frame": ""}
    assert "query_robot=r1" not in lm.detail_to_dict(labels, data)  # numbers only
    assert lm.detail_text(lm.DETAIL_LABELS) == {}  # a detail message from an older node


def test_json_and_csv_carry_both_sides_identity_after_match_frame_id():
    record = _record(**IDENTITY)
    decoded = json.loads(lm.record_json(record))
    assert list(decoded)[5:10] == ["match_frame_id", *IDENTITY]
    assert {k: decoded[k] for k in IDENTITY} == IDENTITY
    assert lm.csv_row(record)[6:10] == list(IDENTITY.values())
    assert json.loads(lm.record_json(_record()))["query_robot"] == ""  # old duck-typed records


@pytest.mark.parametrize(
    "other", [dict(match_robot="r0"), dict(match_session="s1"), dict(query_robot="x")]
)
def test_no_pair_for_a_match_of_another_robot_or_session(other):
    same = dict(query_robot="r1", query_session="s2", match_robot="r1", match_session="s2")
    assert lm.pair_data(_record(**same)) == [1700000123.456789, 1700000001.25]
    assert lm.pair_data(_record(**{**same, **other})) is None


def test_json_has_every_field_in_order():
    record = _record(pair_score=np.float32(2.5), accepted=np.bool_(True), query_id=np.int64(12))
    decoded = json.loads(lm.record_json(record))
    assert list(decoded) == list(lm.LOOP_RECORD_FIELDS)
    assert decoded["query_id"] == 12 and decoded["pair_score"] == 2.5
    assert (decoded["candidates"], decoded["scored"]) == (10, 3)
    assert decoded["accepted"] is True and decoded["inlier_ratio"] is None
    assert decoded["query_frame_id"] == "cam_front" and decoded["reason"] == ""
    assert decoded["covariance"] is None and decoded["tx"] is None
    posed = json.loads(lm.record_json(_posed()))
    assert posed["covariance"] == list(COV) and posed["qy"] == 0.6
    assert posed["pose_status"] == "metric" and posed["pose_inliers"] == 57


def test_csv_row_puts_the_covariance_in_one_cell():
    row = lm.csv_row(_posed())
    assert len(row) == len(lm.LOOP_RECORD_FIELDS)
    cell = lm.LOOP_RECORD_FIELDS.index("covariance")
    assert row[cell].split() == [repr(v) for v in COV]
    assert lm.csv_row(_record())[cell] == ""
    assert row[cell + 1 :] == [0, 0, ""]  # query_camera, match_camera, pose_frame: one camera


def test_loop_messages_bundle():
    msgs = lm.loop_messages(_record())
    assert msgs.pair == lm.pair_data(_record())
    assert msgs.detail_labels[:60] == lm.DETAIL_LABELS and len(msgs.detail) == 65
    assert json.loads(msgs.json)["match_id"] == 3
    assert msgs.factor is None  # no pose, no factor
    assert lm.loop_messages(_posed()).factor == lm.factor_from_record(_posed())


def test_field_order_matches_loop_record():
    from pair_vpr_ros.loops.records import LoopRecord

    assert list(lm.LOOP_RECORD_FIELDS) == LoopRecord.field_names()


def test_typed_fields_of_a_loop_without_a_pose():
    fields = lm.loop_closure_fields(_record(inliers=41, inlier_ratio=0.625))
    pose = fields.pop("relative_pose")
    assert fields == {
        "header": {"stamp": (1700000123, 456789017), "frame_id": "cam_front"},
        "query_stamp": (1700000123, 456789017), "query_id": 12, "query_frame_id": "cam_front",
        "query_robot": "", "query_session": "",
        "match_stamp": (1700000001, 250000000), "match_id": 3, "match_frame_id": "cam_front",
        "match_robot": "", "match_session": "",
        "pair_score": 2.75, "global_similarity": 0.8125, "inlier_ratio": 0.625,
        "rank_before": 2, "rank_after": 0, "candidates": 10, "scored": 3, "inliers": 41,
        "pose_inliers": -1, "accepted": True, "reason": "", "pose_status": 0, "pose_reason": "",
        "query_camera": 0, "match_camera": 0,
    }  # fmt: skip
    assert all(math.isnan(v) for v in (*pose["position"], *pose["orientation"]))
    assert len(pose["covariance"]) == 36 and all(math.isnan(v) for v in pose["covariance"])


@pytest.mark.parametrize(
    ("status", "code"),
    [("metric", 1), ("scale-free", 2), ("metric-odometry", 3), ("", 0), ("unheard-of", 0)],
)
def test_typed_fields_carry_the_pose_and_its_status_code(status, code):
    fields = lm.loop_closure_fields(_posed(pose_status=status, accepted=False, reason="low"))
    assert (fields["pose_status"], fields["pose_inliers"]) == (code, 57)
    assert (fields["accepted"], fields["reason"]) == (False, "low")
    assert fields["relative_pose"] == {
        "position": (1.5, -0.25, 3.0),
        "orientation": (0.0, 0.6, 0.0, 0.8),
        "covariance": list(COV),
    }


def test_typed_fields_types_fit_the_message():
    # numpy scalars from the pipeline become the Python types rclpy's setters accept
    record = _record(query_id=np.int64(7), rank_before=np.int32(1), pair_score=np.float32(0.5),
                     accepted=np.bool_(True))  # fmt: skip
    fields = lm.loop_closure_fields(record)
    assert [type(fields[k]) for k in ("query_id", "rank_before", "pair_score", "accepted")] == [
        int, int, float, bool,
    ]  # fmt: skip


def test_typed_fields_name_both_sides_robot_and_session():
    fields = lm.loop_closure_fields(_record(**IDENTITY))
    assert [fields[k] for k in lm.IDENTITY_FIELDS] == ["r1", "s2", "r0", "s1"]
