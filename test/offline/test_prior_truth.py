"""offline.report.prior_truth: loops into prior maps labelled where the bag's ground truth covers
the prior keyframes (the map was built from this recording), reported apart from live loops."""

from __future__ import annotations

from pair_vpr_ros.loops.records import LoopRecord
from pair_vpr_ros.offline.report.loop_truth import KeyframeInfo
from pair_vpr_ros.offline.report.prior_truth import evaluate_prior_loops, prior_positions
from pair_vpr_ros.place_map import KeyframeMeta
from pair_vpr_ros.types import PoseTrack

Q = (0.0, 0.0, 0.0, 1.0)


def track(points: dict[float, float]) -> PoseTrack:
    """Poses at x = points[stamp] on the x axis."""
    out = PoseTrack()
    for stamp, x in points.items():
        out.add(stamp, (x, 0.0, 0.0, *Q))
    return out


def meta(i: int, stamp: float, x: float, source: str = "drive.mcap") -> KeyframeMeta:
    pose = (x, 0.0, 0.0, *Q)
    return KeyframeMeta(i, stamp, "cam", pose, f"{source}#{i}", robot="r1", session="mon")


def loop(query: int, match: int, session: str = "mon", accepted: bool = True) -> LoopRecord:
    return LoopRecord(
        query, 0.0, "cam", match, 0.0, "cam", query_robot="r1", query_session="tue",
        match_robot="r1", match_session=session, pair_score=1.0, global_similarity=0.9,
        rank_before=1, rank_after=1, accepted=accepted,
    )  # fmt: skip


def test_prior_keyframes_of_this_recording_get_its_ground_truth():
    truth = track({1.0: 100.0, 2.0: 200.0, 3.0: 300.0})
    odometry = track({1.0: 1.0, 2.0: 2.0, 3.0: 3.0})
    metas = [
        meta(0, 1.0, 1.0),  # this bag: odometry as stored
        meta(1, 2.0, 2.5),  # the same name but another recording: its odometry differs
        meta(2, 3.0, 3.0, source="other.mcap"),  # another bag
        meta(3, 9.0, 9.0),  # a stamp the ground truth does not have
    ]
    covered = prior_positions(metas, "drive.mcap", truth, odometry, tolerance=0.1)
    assert covered == {("r1", "mon", 0): (100.0, 0.0, 0.0, *Q)}
    assert prior_positions(metas, "drive.mcap", None, odometry, 0.1) == {}
    assert len(prior_positions(metas, "drive.mcap", truth, None, 0.1)) == 2  # no odometry


def test_prior_loops_true_false_unlabelled_and_recall():
    prior = {("r1", "mon", 0): (0.0, 0.0, 0.0, *Q), ("r1", "mon", 1): (50.0, 0.0, 0.0, *Q)}
    live = [KeyframeInfo(i, float(i), (5.0 * i, 0.0, 0.0, *Q)) for i in range(4)]
    records = [
        loop(0, 0),  # 0 m: true
        loop(1, 1),  # 45 m: false
        loop(2, 7),  # a prior keyframe without ground truth: unlabelled
        loop(3, 0, accepted=False),  # not accepted: not counted
        loop(3, 2, session="tue"),  # the live map: not a prior-map loop
    ]
    ev = evaluate_prior_loops(records, live, prior, prior_keyframes=8, gt_radius=10.0)
    assert (ev.accepted, ev.true_accepted, ev.false_accepted, ev.unlabelled_accepted) == (
        3,
        1,
        1,
        1,
    )
    assert (ev.covered, ev.prior_keyframes, ev.positives, ev.true_queries) == (2, 8, 3, 1)
    assert ev.precision == 0.5 and ev.recall == 1 / 3
    assert ev.to_dict()["recall"] == 1 / 3
    empty = evaluate_prior_loops(records, live, {}, 8)
    assert (empty.precision, empty.recall, empty.unlabelled_accepted) == (None, None, 3)
