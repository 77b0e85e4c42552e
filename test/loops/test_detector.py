"""Decision logic, with hand-made candidates and scores (no network)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from pair_vpr_ros.errors import ConfigError
from pair_vpr_ros.loops.detector import DetectorConfig, LoopDetector, preset
from pair_vpr_ros.loops.records import Candidate, rank_by_pair_score


def cands(*sims):
    return [
        Candidate(
            id=10 + i, stamp=float(i), frame_id="cam", global_similarity=s, rank_before=i + 1
        )
        for i, s in enumerate(sims)
    ]


def scorer(*scores):
    return lambda cs: np.array(scores[: len(cs)], dtype=np.float32)


def test_rerank_picks_best_pair_score_and_keeps_global_rank():
    det = LoopDetector(DetectorConfig(score_threshold=1.0))
    found = [replace(c, robot="b", session="s2") for c in cands(0.9, 0.8, 0.7)]
    rec = det.decide(100.0, "cam", found, scorer(0.5, 3.0, 2.0), query_identity=("a", "s1"))
    fields = rec.to_dict()
    assert math.isnan(fields.pop("inlier_ratio"))
    pose = {k: fields.pop(k) for k in ("tx", "ty", "tz", "qx", "qy", "qz", "qw")}
    assert all(math.isnan(v) for v in pose.values())  # no relative pose from the detector
    assert fields == dict(
        query_id=-1,
        query_stamp=100.0,
        query_frame_id="cam",
        match_id=11,
        match_stamp=1.0,
        match_frame_id="cam",
        query_robot="a",
        query_session="s1",
        match_robot="b",
        match_session="s2",
        pair_score=3.0,
        global_similarity=0.8,
        rank_before=2,
        rank_after=1,
        candidates=3,
        scored=3,
        inliers=-1,
        accepted=True,
        reason="",
        pose_status="",
        pose_reason="",
        pose_inliers=-1,
        covariance=(),
        query_camera=0,
        match_camera=0,
        pose_frame="",
    )


def test_rank_by_pair_score_orders_best_first_and_keeps_global_order_on_ties():
    ranked = rank_by_pair_score(cands(0.9, 0.8, 0.7, 0.6), np.array([1.0, 2.0, 1.0, 2.0]))
    assert [(c.id, c.pair_score, c.rank_before) for c in ranked] == [
        (11, 2.0, 2),
        (13, 2.0, 4),
        (10, 1.0, 1),
        (12, 1.0, 3),
    ]
    with pytest.raises(ValueError):
        rank_by_pair_score(cands(0.9, 0.8), np.array([1.0]))  # one score per candidate


def test_global_weight_adds_the_similarity_to_the_pair_score():
    # pair scores 1.0 / 1.5 / 0.2 at similarities 0.9 / 0.5 / 0.8: the pair score alone picks
    # the second; with weight 2 the re-rank scores are 2.8 / 2.5 / 1.8 and the first wins
    ranked = rank_by_pair_score(cands(0.9, 0.5, 0.8), np.array([1.0, 1.5, 0.2]), 2.0)
    assert [c.id for c in ranked] == [10, 11, 12]
    assert [c.rerank_score(2.0) for c in ranked] == pytest.approx([2.8, 2.5, 1.8])
    assert [c.id for c in rank_by_pair_score(cands(0.9, 0.5, 0.8), np.array([1.0, 1.5, 0.2]))] == [
        11,
        10,
        12,
    ]
    config = DetectorConfig(global_weight=2.0, score_threshold=2.7)
    rec = LoopDetector(config).decide(1.0, "c", cands(0.9, 0.5, 0.8), scorer(1.0, 1.5, 0.2))
    # the record keeps the pair score itself; the threshold compared 2.8
    assert (rec.accepted, rec.match_id, rec.pair_score, rec.rank_before) == (True, 10, 1.0, 1)
    config = config.updated(score_threshold=2.9)
    rec = LoopDetector(config).decide(1.0, "c", cands(0.9, 0.5, 0.8), scorer(1.0, 1.5, 0.2))
    assert (rec.accepted, rec.reason, rec.match_id) == (False, "score below threshold", 10)


def test_global_weight_ranks_the_scored_part_under_a_budget():
    ticks = iter([0.0, 0.0, 0.010, 0.030])  # 10 ms a call: the third would end at 45 ms > 25
    config = DetectorConfig(global_weight=10.0, rerank_budget_ms=25.0)
    det = LoopDetector(config, clock=lambda: next(ticks))
    rec = det.decide(1.0, "c", cands(0.9, 0.8, 0.1), scorer(0.0, 0.5, 9.0), step=1)
    # re-rank scores of the scored two: 9.0 and 8.5 (the pair score alone would pick the 2nd)
    assert (rec.scored, rec.match_id) == (2, 10)


def test_below_threshold_is_rejected_with_reason():
    rec = LoopDetector(DetectorConfig(score_threshold=5.0)).decide(
        1.0, "cam", cands(0.9, 0.8), scorer(1.0, 4.0)
    )
    assert (rec.accepted, rec.reason, rec.match_id, rec.pair_score) == (
        False,
        "score below threshold",
        11,
        4.0,
    )


def test_global_floor_skips_reranking():
    def never(_):
        raise AssertionError("re-ranking must not run below the floor")

    rec = LoopDetector(DetectorConfig(global_floor=0.95)).decide(1.0, "c", cands(0.9), never)
    assert (rec.accepted, rec.reason, rec.match_id) == (False, "below global floor", 10)
    assert math.isnan(rec.pair_score)


def test_no_candidates_gives_no_record():
    assert LoopDetector().decide(1.0, "c", [], scorer()) is None


def test_temporal_consistency_needs_agreeing_consecutive_queries():
    det = LoopDetector(DetectorConfig(temporal_consistency=3, temporal_tolerance=2))
    reasons = []
    for match in (50, 51, 90, 91, 92, 93):
        cs = [Candidate(match, 0.0, "c", 0.9, 1)]
        rec = det.decide(1.0, "c", cs, scorer(1.0))
        reasons.append(rec.reason or "accepted")
    assert reasons == [
        "awaiting temporal consistency (1/3)",
        "awaiting temporal consistency (2/3)",
        "awaiting temporal consistency (1/3)",
        "awaiting temporal consistency (2/3)",
        "accepted",
        "accepted",
    ]


def test_temporal_consistency_agrees_only_within_one_map_robot_and_session():
    det = LoopDetector(DetectorConfig(temporal_consistency=2, temporal_tolerance=2))
    reasons = []
    for match, robot, session, prior in (
        (50, "a", "s1", -1),
        (51, "b", "s1", -1),  # close id, other robot: ids say nothing about place
        (52, "b", "s2", -1),  # other session
        (53, "b", "s2", 0),  # same names, but a prior map's id space
        (54, "b", "s2", 0),
    ):
        cs = [Candidate(match, 0.0, "c", 0.9, 1, robot=robot, session=session, prior=prior)]
        reasons.append(det.decide(1.0, "c", cs, scorer(1.0)).reason or "accepted")
    assert reasons == ["awaiting temporal consistency (1/2)"] * 4 + ["accepted"]


def follow(det, ids_scores, robot="a", session="s1", verify=None):
    """One query whose candidates are (id, pair score) in global order: (match, rank, reason)."""
    cs = [Candidate(i, 0.0, "c", 0.5, r + 1, robot=robot, session=session)
          for r, (i, _) in enumerate(ids_scores)]  # fmt: skip
    rec = det.decide(1.0, "c", cs, scorer(*(s for _, s in ids_scores)), verify=verify)
    return rec.match_id, rec.rank_after, rec.reason or "accepted"


def test_sequence_margin_accepts_a_weaker_candidate_that_continues_the_last_loop():
    config = DetectorConfig(score_threshold=10.0, sequence_margin=4.0, temporal_tolerance=2,
                            geometric_verification=True)  # fmt: skip
    det = LoopDetector(config)
    ok = lambda _c: (40, 0.6)  # noqa: E731
    assert follow(det, [(50, 12.0)], verify=ok) == (50, 1, "accepted")
    # best is 90 (below threshold), 52 continues the loop to 50 at 7 >= 10 - 4: accepted
    assert follow(det, [(90, 9.0), (52, 7.0)], verify=ok) == (52, 2, "accepted")
    # 55 is 3 ids from 52 (> tolerance 2); 53 scores 5.9 < 6: neither is followed
    assert follow(det, [(55, 9.0), (53, 5.9)], verify=ok) == (55, 1, "score below threshold")
    # that query ended the sequence: 54 (1 id from 53, 2 from 52) is not followed now
    assert follow(det, [(54, 9.5)], verify=ok) == (54, 1, "score below threshold")


def test_sequence_margin_keeps_verification_and_the_group():
    det = LoopDetector(DetectorConfig(score_threshold=10.0, sequence_margin=4.0,
                                      geometric_verification=True, min_inliers=20))  # fmt: skip
    assert follow(det, [(50, 12.0)], verify=lambda _c: (40, 0.6))[2] == "accepted"
    # a follower still needs its inliers; a failed one ends the sequence
    assert follow(det, [(51, 8.0)], verify=lambda _c: (12, 0.3)) == (
        51, 1, "geometric verification failed (12 inliers)")  # fmt: skip
    assert follow(det, [(52, 8.0)], verify=lambda _c: (40, 0.6))[2] == "score below threshold"
    assert follow(det, [(60, 12.0)], verify=lambda _c: (40, 0.6))[2] == "accepted"
    # close id, other session: ids say nothing about place
    assert follow(det, [(61, 8.0)], session="s2")[2] == "score below threshold"
    # the pipeline ends a sequence whose last loop got no relative pose
    assert follow(det, [(62, 12.0)])[2] == "accepted"
    det.end_sequence(None)
    assert follow(det, [(63, 8.0)])[2] == "score below threshold"
    # the margin 0 (default) follows nothing
    det = LoopDetector(DetectorConfig(score_threshold=10.0))
    follow(det, [(50, 12.0)])
    assert follow(det, [(51, 9.99)])[2] == "score below threshold"


def test_geometric_verification_gate():
    det = LoopDetector(DetectorConfig(geometric_verification=True, min_inliers=20))
    rec = det.decide(1.0, "c", cands(0.9), scorer(1.0), verify=lambda _id: (12, 0.3))
    assert (rec.accepted, rec.inliers, rec.reason) == (
        False,
        12,
        "geometric verification failed (12 inliers)",
    )
    rec = det.decide(1.0, "c", cands(0.9), scorer(1.0), verify=lambda _id: (40, 0.6))
    assert (rec.accepted, rec.inliers, rec.inlier_ratio) == (True, 40, 0.6)


def test_keyframe_selection_by_similarity():
    det = LoopDetector(DetectorConfig(keyframe_max_similarity=0.9))
    assert det.is_new_keyframe(None) and det.is_new_keyframe(0.89)
    assert not det.is_new_keyframe(0.9)


@pytest.mark.parametrize(
    "changes,message",
    [
        (dict(top_k=0), "detector top_k=0 must be >= 1"),
        (dict(mode="slam"), "detector mode='slam' must be one of ('mapping', 'localization')"),
        (dict(score_threshold=float("nan")), "detector score_threshold=nan must be a finite"),
        (dict(temporal_consistency=0), "temporal_consistency=0 must be >= 1"),
        (dict(global_weight=-1.0), "detector global_weight=-1.0 must be a finite number >= 0"),
        (dict(loop_per_map="no"), "detector loop_per_map='no' must be true or false"),
        (dict(rerank_cascade=1), "detector rerank_cascade=1 must be true or false"),
        (dict(learned_floor="yes"), "detector learned_floor='yes' must be true or false"),
        (dict(global_weight=float("inf")), "detector global_weight=inf must be a finite number"),
        (dict(sequence_margin=-1.0), "detector sequence_margin=-1.0 must be a finite number >= 0"),
        (dict(sequence_margin=float("nan")), "detector sequence_margin=nan must be a finite"),
    ],
)
def test_bad_config_is_refused(changes, message):
    with pytest.raises(ConfigError, match=message.replace("(", r"\(").replace(")", r"\)")):
        DetectorConfig(**changes)


def test_presets():
    assert preset("performance").top_k == 100
    assert preset("speed", top_k=5).top_k == 5
    with pytest.raises(ConfigError, match="unknown preset 'fast': choose one of speed, perf"):
        preset("fast")


def test_verification_without_features_rejects():
    det = LoopDetector(DetectorConfig(geometric_verification=True))
    rec = det.decide(1.0, "c", cands(0.9), scorer(1.0), verify=lambda _id: (-1, float("nan")))
    assert (rec.accepted, rec.reason) == (
        False,
        "geometric verification impossible (no features for the match)",
    )
