"""`loop_per_map`: a keyframe closes at most one loop into each map it is searched in (its live
map and each prior map), so a robot's later session finds its own first session even where
another robot's keyframe of the place is as similar. Hand-built maps in tmp_path; the tiny
random network with exact repeats as the only loops (exact_match.py)."""

from __future__ import annotations

import numpy as np
import pytest
from exact_match import EXACT_MATCH

from pair_vpr_ros.identity import Identity
from pair_vpr_ros.loops.detector import DetectorConfig
from pair_vpr_ros.loops.frames import Frame
from pair_vpr_ros.loops.pipeline import LoopClosurePipeline
from pair_vpr_ros.messages.loop import pair_data
from pair_vpr_ros.place_map import PlaceMap

PER_MAP = DetectorConfig(**EXACT_MATCH)  # loop_per_map: the default
MERGED = PER_MAP.updated(loop_per_map=False)


@pytest.fixture(scope="module")
def places():
    rng = np.random.default_rng(3)
    return [rng.integers(0, 256, (48, 64, 3), dtype=np.uint8) for _ in range(6)]


def frames(places, order, t0):
    return [Frame(t0 + i, places[p], "cam") for i, p in enumerate(order)]


@pytest.fixture()
def priors(tiny_model, places, tmp_path):
    """Saved maps: robot a's day1 (places 0, 1, 2) and robot b's day1 (places 2, 3, 0)."""
    dirs = []
    for robot, order in (("a", [0, 1, 2]), ("b", [2, 3, 0])):
        pipe = LoopClosurePipeline(tiny_model, MERGED, identity=Identity(robot, "day1"))
        list(pipe.process_many(frames(places, order, t0=0.0)))
        dirs.append(pipe.save_map(tmp_path / robot))
        pipe.close()
    return dirs


def live(tiny_model, config, dirs):
    maps = [PlaceMap.load(d, read_only=True) for d in dirs]
    return LoopClosurePipeline(tiny_model, config, identity=Identity("a", "day2"), prior_maps=maps)


def matches(outcome):
    """(robot, session, id) of each accepted loop the outcome reports."""
    return [(r.match_robot, r.match_session, r.match_id) for r in outcome.reported() if r.accepted]


def test_a_keyframe_gets_a_loop_into_each_matching_map(tiny_model, places, priors):
    pipe = live(tiny_model, PER_MAP, priors)
    # t=100: place 0 (in both prior maps), place 1 (a's only), place 4 (nowhere), then place 0
    # again at t=104, now also in the live map (4 s ago: outside exclude_recent_s 2.5)
    out = list(pipe.process_many(frames(places, [0, 1, 4, 5, 0], t0=100.0)))
    assert [matches(o) for o in out] == [
        [("a", "day1", 0), ("b", "day1", 2)],
        [("a", "day1", 1)],
        [],
        [],
        [("a", "day2", 0), ("a", "day1", 0), ("b", "day1", 2)],
    ]
    # one decision per map searched: the live map from t=103 (t=100 is then 3 s back, beyond
    # exclude_recent_s 2.5); places 4 and 5 are in no map (each best below the global floor)
    assert [len(o.loops) for o in out] == [2, 2, 2, 3, 3]
    assert out[1].loop.match_robot == "a" and out[1].reported() == [out[1].loop]
    assert out[2].loop.reason == "below global floor" and len(out[2].reported()) == 1
    assert [r.query_id for r in out[4].loops] == [4, 4, 4]
    # LIO-SAM's pair only for the loop within the live robot-session
    assert [pair_data(r) for r in out[4].loops] == [[104.0, 100.0], None, None]
    assert (pipe.counts.loops, pipe.counts.rejected, pipe.counts.keyframes) == (6, 2, 5)
    # rank_before counts over all maps' candidates: each names one candidate of the keyframe
    assert sorted(c.rank_before for c in out[4].candidates) == [1, 2, 3]
    pipe.close()


def test_one_loop_per_keyframe_without_loop_per_map(tiny_model, places, priors):
    pipe = live(tiny_model, MERGED, priors)
    out = list(pipe.process_many(frames(places, [0, 1, 4, 5, 0], t0=100.0)))
    # one top-1 of all maps: equally similar exact repeats, the live map first, then priors
    assert [matches(o) for o in out] == [
        [("a", "day1", 0)], [("a", "day1", 1)], [], [], [("a", "day2", 0)],
    ]  # fmt: skip
    assert all(o.loops == [] for o in out) and pipe.counts.loops == 3
    pipe.close()


def test_without_prior_maps_both_settings_decide_alike(tiny_model, places):
    order = [0, 1, 2, 3, 0, 2, 5, 1]
    got = []
    for config in (PER_MAP, MERGED):
        pipe = LoopClosurePipeline(tiny_model, config)
        out = list(pipe.process_many(frames(places, order, t0=0.0)))
        got.append(([r.to_dict() for o in out for r in o.reported()], pipe.counts))
        assert all(o.loops == [] for o in out)
        pipe.close()
    assert got[0] == got[1]
    assert [(r["query_id"], r["match_id"]) for r in got[0][0] if r["accepted"]] == [
        (4, 0), (5, 2), (7, 1),
    ]  # fmt: skip


def test_temporal_consistency_counts_per_map(tiny_model, places, priors):
    # two agreeing queries needed, counted per map: each map's two matches agree (ids within
    # 5 of each other in that map), so the second query closes a loop into each
    config = PER_MAP.updated(temporal_consistency=2, temporal_tolerance=5)
    pipe = live(tiny_model, config, priors)
    out = list(pipe.process_many(frames(places, [0, 2], t0=100.0)))
    assert matches(out[0]) == []
    assert matches(out[1]) == [("a", "day1", 2), ("b", "day1", 0)]
    pipe.close()
