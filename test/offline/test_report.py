"""report: CSV / JSON contents, ground-truth labels and PR numbers on a hand-made case, plots."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from pair_vpr_ros.errors import ConfigError
from pair_vpr_ros.offline.report.folder import write_loops_csv, write_loops_json, write_report
from pair_vpr_ros.offline.report.loop_truth import (
    KeyframeInfo,
    evaluate_loops,
    is_true_loop,
    pr_curve,
    queries_with_true_match,
    true_match_mask,
)

try:
    from pair_vpr_ros.loops.records import LoopRecord
except ImportError:  # pragma: no cover - detector.py is written in parallel
    LoopRecord = None


def _record(query_id, match_id, pair_score, global_similarity, accepted, **over):
    fields = dict(
        query_id=query_id, query_stamp=10.0 * query_id, query_frame_id="cam", match_id=match_id,
        match_stamp=10.0 * match_id, match_frame_id="cam", pair_score=pair_score,
        global_similarity=global_similarity, rank_before=0, rank_after=0, candidates=4,
        scored=2, inliers=-1,
        inlier_ratio=0.0, accepted=accepted, reason="" if accepted else "below threshold",
    )  # fmt: skip
    fields.update(over)
    if LoopRecord is None:
        return type("LoopRecordStandIn", (), fields)()
    return LoopRecord(**fields)


def _pose(x, y, z=0.0):
    return (float(x), float(y), float(z), 0.0, 0.0, 0.0, 1.0)


# A hand-made world; exclusion window 5 s, radius 10 m.
KEYFRAMES = [
    KeyframeInfo(0, 0.0, _pose(0, 0)),
    KeyframeInfo(1, 10.0, _pose(50, 0)),
    KeyframeInfo(2, 20.0, _pose(100, 0)),
    KeyframeInfo(3, 30.0, _pose(3, 4)),  # 5 m from 0: true match 0
    KeyframeInfo(4, 40.0, _pose(52, 0)),  # 2 m from 1: true match 1
    KeyframeInfo(5, 50.0, _pose(200, 0)),  # alone
    KeyframeInfo(6, 52.0, _pose(201, 0)),  # 1 m from 5 but only 2 s later: no true match
    KeyframeInfo(7, 60.0, _pose(100, 8)),  # 8 m from 2: true match 2
    KeyframeInfo(8, 70.0, None),  # no pose
]
RECORDS = [
    _record(3, 0, 5.0, 0.9, True),  # true
    _record(4, 2, 4.0, 0.95, True),  # false (48 m)
    _record(5, 1, 3.0, 0.5, False),  # false
    _record(6, 5, 1.0, 0.7, False),  # false (inside the exclusion window)
    _record(7, 2, 2.0, 0.8, False),  # true
    _record(8, 0, 4.5, 0.6, True),  # unlabelled
]
GLOBAL_TOP1 = [
    _record(3, 0, 0.0, 0.9, False),  # true
    _record(4, 2, 0.0, 0.95, False),  # false
    _record(5, 1, 0.0, 0.5, False),  # false
    _record(6, 5, 0.0, 0.7, False),  # false
    _record(7, 2, 0.0, 0.8, False),  # true
    _record(8, 1, 0.0, 0.6, False),  # unlabelled
]
GT = {"gt_radius": 10.0, "exclusion_s": 5.0}


def test_true_match_rule():
    kf = {k.id: k for k in KEYFRAMES}
    assert is_true_loop(kf[3], kf[0], **GT) is True
    assert is_true_loop(kf[0], kf[3], **GT) is False  # the match must be earlier in the map
    assert is_true_loop(kf[6], kf[5], **GT) is False
    assert is_true_loop(kf[6], kf[5], gt_radius=10.0, exclusion_s=2.0) is True  # >= window
    assert is_true_loop(kf[4], kf[1], gt_radius=1.9, exclusion_s=5.0) is False
    assert is_true_loop(kf[8], kf[0], **GT) is None
    assert is_true_loop(None, kf[0], **GT) is None
    assert queries_with_true_match(KEYFRAMES, **GT) == {3, 4, 7}
    assert queries_with_true_match(KEYFRAMES, tile=2, chunk=3, **GT) == {3, 4, 7}


@pytest.mark.parametrize("seed", range(6))
def test_true_match_sweep_equals_brute_force(seed):
    """The x-sweep with small tiles finds exactly the queries a full pairwise check finds."""
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 300))
    xyz = rng.integers(0, 20, (n, 3)) * rng.choice([0.5, 1.0, 3.0])  # ties at the radius
    ids, stamps = rng.permutation(n), np.sort(rng.random(n) * 50)
    kfs = [
        KeyframeInfo(int(ids[i]), float(stamps[i]), (*xyz[i], 0, 0, 0, 1) if i % 7 else None)
        for i in range(n)
    ]
    gt = {"gt_radius": float(rng.choice([0.0, 1.0, 5.0])), "exclusion_s": float(seed % 2 * 5)}
    posed = [k for k in kfs if k.pose is not None]
    expected = {q.id for q in posed if any(is_true_loop(q, m, **gt) for m in posed)}
    tile, chunk = int(rng.integers(1, 40)), int(rng.integers(1, 60))
    assert queries_with_true_match(kfs, tile=tile, chunk=chunk, **gt) == expected


@pytest.mark.parametrize(
    ("gt", "message"),
    [
        ({"gt_radius": -5.0}, "gt_radius must be a finite number >= 0, got -5.0"),
        ({"gt_radius": float("nan")}, "gt_radius must be a finite number >= 0, got nan"),
        ({"exclusion_s": float("inf")}, "exclusion_s must be a finite number >= 0, got inf"),
    ],
)
def test_bad_ground_truth_settings(gt, message):
    with pytest.raises(ConfigError, match=re.escape(message)):
        evaluate_loops(RECORDS, KEYFRAMES, **{**GT, **gt})


def test_precision_recall_exact():
    ev = evaluate_loops(RECORDS, KEYFRAMES, global_records=GLOBAL_TOP1, **GT)
    assert ev.labels == [True, False, False, False, True, None]
    assert (ev.positives, ev.accepted, ev.true_accepted) == (3, 3, 1)
    assert (ev.false_accepted, ev.unlabelled_accepted) == (1, 1)
    assert ev.precision == 0.5
    assert ev.recall == pytest.approx(1 / 3, abs=1e-15)

    curve = ev.reranked
    assert curve.thresholds.tolist() == [5.0, 4.0, 3.0, 2.0, 1.0]
    np.testing.assert_allclose(curve.precision, [1, 1 / 2, 1 / 3, 1 / 2, 2 / 5], rtol=1e-15)
    np.testing.assert_allclose(curve.recall, [1 / 3, 1 / 3, 1 / 3, 2 / 3, 2 / 3], rtol=1e-15)
    assert curve.average_precision() == pytest.approx(0.5, abs=1e-15)
    assert curve.recall_at_full_precision() == pytest.approx(1 / 3, abs=1e-15)
    f1, threshold = curve.best_f1()
    assert (f1, threshold) == (pytest.approx(4 / 7, abs=1e-15), 2.0)

    glob = ev.global_only
    assert glob.thresholds.tolist() == [0.95, 0.9, 0.8, 0.7, 0.5]
    np.testing.assert_allclose(glob.precision, [0, 1 / 2, 2 / 3, 1 / 2, 2 / 5], rtol=1e-15)
    np.testing.assert_allclose(glob.recall, [0, 1 / 3, 2 / 3, 2 / 3, 2 / 3], rtol=1e-15)
    assert glob.average_precision() == pytest.approx(7 / 18, abs=1e-15)
    assert glob.recall_at_full_precision() == 0.0
    assert glob.recall_at_precision(0.6) == pytest.approx(2 / 3, abs=1e-15)
    assert glob.recall_at_precision(0.9) == 0.0
    assert glob.operating_point(0.6) == (0.8, pytest.approx(2 / 3), pytest.approx(2 / 3))
    assert glob.operating_point(0.9) is None
    # the last threshold >= the one asked for; none above the highest score
    assert glob.at_threshold(0.85) == (pytest.approx(1 / 2), pytest.approx(1 / 3))
    assert glob.at_threshold(0.5) == (pytest.approx(2 / 5), pytest.approx(2 / 3))
    assert glob.at_threshold(0.96) is None
    assert glob.best_f1() == (pytest.approx(2 / 3, abs=1e-15), 0.8)

    summary = ev.to_dict()
    assert summary["positives"] == 3 and summary["precision"] == 0.5
    assert summary["global_only"]["average_precision"] == pytest.approx(7 / 18, abs=1e-15)
    assert summary["reranked"]["recall_at_90_precision"] == pytest.approx(1 / 3, abs=1e-15)
    json.dumps(summary, allow_nan=False)


def test_queries_the_map_did_not_store_are_labelled_by_stamp():
    """map_growth places: a represented query (query_id -1, stored=False, id = keyframes
    stored before it) is a query with true matches among those, never a match itself."""
    kfs = [
        KeyframeInfo(0, 0.0, _pose(0, 0)),
        KeyframeInfo(1, 10.0, _pose(50, 0)),
        KeyframeInfo(2, 20.0, _pose(1, 0), stored=False),  # near 0, stored after 0 and 1
        KeyframeInfo(2, 30.0, _pose(51, 0)),  # the next stored one: the same id
        KeyframeInfo(3, 40.0, _pose(2, 0)),  # near 0 and near the represented one at 20 s
        KeyframeInfo(1, 45.0, _pose(300, 0), stored=False),  # alone
    ]
    assert true_match_mask(kfs, **GT).tolist() == [False, False, True, True, True, False]
    assert queries_with_true_match(kfs, **GT) == {2, 3}  # stored ids only
    records = [
        _record(-1, 0, 5.0, 0.9, True, query_stamp=20.0),  # true: 1 m from keyframe 0
        _record(-1, 1, 4.0, 0.9, True, query_stamp=45.0),  # false: 250 m away
        _record(3, 0, 3.0, 0.9, True),  # true (its query stamp is 30 here: looked up by id)
        _record(-1, 0, 2.0, 0.9, True, query_stamp=99.0),  # a stamp no keyframe has
    ]
    ev = evaluate_loops(records, kfs, **GT)
    assert ev.labels == [True, False, True, None]
    assert ev.positives == 3 and ev.true_accepted == 2 and ev.false_accepted == 1
    represented = KeyframeInfo(2, 20.0, _pose(1, 0), stored=False)
    assert is_true_loop(kfs[4], represented, **GT) is False  # never a match


def test_reranked_curve_scores_by_the_detector_s_re_rank_score():
    # weight 10: re-rank scores 14, 13.5, 8, 8, 10, 10.5 -> the true loop of query 7 (10.0)
    # now ranks above the false one of query 5 (8.0), as the detector would accept them
    ev = evaluate_loops(RECORDS, KEYFRAMES, global_weight=10.0, **GT)
    assert ev.reranked.thresholds.tolist() == [14.0, 13.5, 10.0, 8.0]
    np.testing.assert_allclose(ev.reranked.precision, [1, 1 / 2, 2 / 3, 2 / 5], rtol=1e-15)
    assert ev.labels == evaluate_loops(RECORDS, KEYFRAMES, **GT).labels


def test_pr_curve_ties_and_empty():
    curve = pr_curve([1.0, 0.5, 1.0], [True, True, False], positives=2)
    assert curve.thresholds.tolist() == [1.0, 0.5]
    assert curve.precision.tolist() == [0.5, pytest.approx(2 / 3, abs=1e-15)]
    assert curve.recall.tolist() == [0.5, 1.0]
    nan = pr_curve([float("nan"), 0.5], [True, True], positives=2)
    assert nan.thresholds.tolist() == [0.5] and nan.recall.tolist() == [0.5]
    empty = pr_curve([], [], positives=0)
    assert len(empty.thresholds) == 0 and empty.average_precision() == 0.0
    assert empty.best_f1() == (0.0, None)
    assert pr_curve([2.0], [True], positives=0).recall.tolist() == [0.0]


def test_no_positives_and_no_accepted_give_none():
    ev = evaluate_loops([RECORDS[2]], KEYFRAMES[:3], **GT)
    assert ev.positives == 0 and ev.precision is None and ev.recall is None


CSV_TEXT = (
    "query_id,query_stamp,query_frame_id,match_id,match_stamp,match_frame_id,query_robot,"
    "query_session,match_robot,match_session,pair_score,"
    "global_similarity,rank_before,rank_after,candidates,scored,inliers,inlier_ratio,accepted,"
    "reason,"
    "pose_status,pose_reason,pose_inliers,tx,ty,tz,qx,qy,qz,qw,covariance,query_camera,"
    "match_camera,pose_frame\r\n"
    "3,30.0,cam,0,0.0,cam,,,,,5.0,0.9,0,0,4,2,-1,0.0,True,,,,-1,nan,nan,nan,nan,nan,nan,nan,,0,0,"
    "\r\n"
    "5,50.0,cam,1,10.0,cam,,,,,3.0,0.5,0,0,4,2,-1,0.0,False,below threshold,,,-1,nan,nan,nan,"
    "nan,nan,nan,nan,,0,0,\r\n"
)
NO_IDENTITY = dict(query_robot="", query_session="", match_robot="", match_session="")
NO_POSE = dict(  # and one camera's rig fields
    query_camera=0,
    match_camera=0,
    pose_frame="",
    pose_status="",
    pose_reason="",
    pose_inliers=-1,
    tx=None,
    ty=None,
    tz=None,
    qx=None,
    qy=None,
    qz=None,
    qw=None,
    covariance=None,
)


def test_csv_and_json_contents(tmp_path):
    records = [RECORDS[0], RECORDS[2]]
    write_loops_csv(records, tmp_path / "loops.csv")
    assert (tmp_path / "loops.csv").read_bytes().decode() == CSV_TEXT
    write_loops_json(records, tmp_path / "loops.json")
    assert json.loads((tmp_path / "loops.json").read_text()) == [
        {
            "query_id": 3, "query_stamp": 30.0, "query_frame_id": "cam", "match_id": 0,
            "match_stamp": 0.0, "match_frame_id": "cam", **NO_IDENTITY, "pair_score": 5.0,
            "global_similarity": 0.9, "rank_before": 0, "rank_after": 0, "candidates": 4,
            "scored": 2, "inliers": -1,
            "inlier_ratio": 0.0, "accepted": True, "reason": "", **NO_POSE,
        },
        {
            "query_id": 5, "query_stamp": 50.0, "query_frame_id": "cam", "match_id": 1,
            "match_stamp": 10.0, "match_frame_id": "cam", **NO_IDENTITY, "pair_score": 3.0,
            "global_similarity": 0.5, "rank_before": 0, "rank_after": 0, "candidates": 4,
            "scored": 2, "inliers": -1,
            "inlier_ratio": 0.0, "accepted": False, "reason": "below threshold", **NO_POSE,
        },
    ]  # fmt: skip


def test_write_report_with_and_without_poses(tmp_path):
    positions = np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 0.0]])
    ev = write_report(
        tmp_path / "a", RECORDS, KEYFRAMES, positions, global_records=GLOBAL_TOP1, **GT
    )
    assert ev.true_accepted == 1
    for name in ("loops.csv", "loops.json", "pr_curve.png", "trajectory.png"):
        data = (tmp_path / "a" / name).read_bytes()
        assert len(data) > 0
    assert (tmp_path / "a" / "pr_curve.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    no_pose = [KeyframeInfo(k.id, k.stamp, None) for k in KEYFRAMES]
    assert write_report(tmp_path / "b", RECORDS, no_pose, **GT) is None
    assert sorted(p.name for p in (tmp_path / "b").iterdir()) == ["loops.csv", "loops.json"]


def test_plot_titles_name_the_ground_truth(tmp_path, monkeypatch):
    from matplotlib.figure import Figure

    titles = {}

    def record(fig, path, **kwargs):
        titles[Path(path).name] = fig.axes[0].get_title()

    monkeypatch.setattr(Figure, "savefig", record)
    positions = np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 0.0]])
    write_report(tmp_path, RECORDS, KEYFRAMES, positions, source="/ground_truth", **GT)
    assert titles == {
        "pr_curve.png": "loop closures, 3 queries with a true match\nground truth: /ground_truth",
        "trajectory.png": "path and loops, ground truth: /ground_truth",
    }
    write_report(tmp_path, RECORDS, KEYFRAMES, positions, **GT)
    assert titles["trajectory.png"] == ""  # no source given, none claimed
