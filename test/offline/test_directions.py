"""Recall split by the way a revisit was driven (issue 49): out along a street, back the other
way, out again; a rig keyframe's cameras count as one instant."""

from __future__ import annotations

import math

import pytest

from pair_vpr_ros.loops.records import LoopRecord
from pair_vpr_ros.offline.report.directions import direction_recall
from pair_vpr_ros.offline.report.loop_truth import KeyframeInfo


def _pose(x: float, yaw: float) -> tuple[float, ...]:
    return (x, 0.0, 0.0, 0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))


def _drive(cameras: int = 1) -> list[KeyframeInfo]:
    """Out (x 0..90, east), back (90..0, west), out again: a keyframe a second, 10 m apart."""
    legs = [(x, 0.0) for x in range(0, 100, 10)] + [(x, math.pi) for x in range(90, -10, -10)]
    legs += [(x, 0.0) for x in range(0, 100, 10)]
    return [KeyframeInfo(cameras * t + c, float(t), _pose(x, yaw))
            for t, (x, yaw) in enumerate(legs) for c in range(cameras)]  # fmt: skip


def _loop(query: KeyframeInfo, match: KeyframeInfo) -> LoopRecord:
    scores = dict(pair_score=1, global_similarity=1, rank_before=1, rank_after=1, accepted=True)
    return LoopRecord(query.id, query.stamp, "c", match.id, match.stamp, "c", **scores)


@pytest.mark.parametrize("cameras", [1, 2])
def test_revisits_driven_back_are_counted_apart_from_those_driven_the_same_way(cameras):
    kf = _drive(cameras)
    by_stamp = {k.stamp: k for k in reversed(kf)}  # the first camera's keyframe of each stamp
    # back: instants 10-19 (x 90..0) revisit 0-9 the other way; 20-29 the same way as 0-9
    loops = [_loop(by_stamp[float(t)], by_stamp[float(19 - t)]) for t in (12, 13)]
    loops += [_loop(kf[cameras * t + cameras - 1], by_stamp[float(t - 20)]) for t in range(20, 28)]
    loops.append(_loop(by_stamp[14.0], by_stamp[1.0]))  # 40 m off: false, found nothing
    out = direction_recall(loops, kf, gt_radius=5.0, exclusion_s=3.0, tolerance=0.5)
    assert out["opposite"] == {"positives": 9, "found": 2, "recall": 2 / 9}
    assert out["same"] == {"positives": 10, "found": 8, "recall": 0.8}


def test_no_posed_keyframe_gives_no_figures():
    assert direction_recall([], [KeyframeInfo(0, 0.0, None)], 5.0, 3.0) is None
