"""Two robots' pipelines exchanging in one process (no ROS) over `LocalBus`, with the tiny
random network: only exact repeats pass the global floor (exact_match.py), so a place robot b
sees that robot a saw before is the one inter-robot loop."""

from __future__ import annotations

import numpy as np
import pytest
from exact_match import EXACT_MATCH

from pair_vpr_ros.fleet import Faults, FleetConfig, FleetExchange, LocalBus
from pair_vpr_ros.identity import Identity
from pair_vpr_ros.loops.detector import DetectorConfig
from pair_vpr_ros.loops.frames import Frame
from pair_vpr_ros.loops.pipeline import LoopClosurePipeline
from pair_vpr_ros.loops.scoring import map_pair_scores

SESSION = "20261125T160000Z"


@pytest.fixture(scope="module")
def places():
    rng = np.random.default_rng(7)
    return [rng.integers(0, 256, (48, 64, 3), dtype=np.uint8) for _ in range(8)]


def robot(model, bus, name, clock, **fleet):
    """Robot `name` on `bus`; requests go out at once ("first") unless `fleet` says."""
    who = Identity(name, SESSION)
    pipe = LoopClosurePipeline(model, DetectorConfig(**EXACT_MATCH), identity=who)
    config = FleetConfig(robot=name, session=SESSION, **{"select": "first", **fleet})
    ex = FleetExchange(pipe, config, bus.sender(name), clock=lambda: clock[0], first_request_id=0)
    bus.join(ex)
    return ex


def drive(bus, plan, places, clock):
    """plan: [(robot exchange, place, stamp)] in stamp order -> loops decided."""
    loops = []
    for ex, place, stamp in plan:
        clock[0] = stamp
        outcome = ex.pipe.process(Frame(stamp, places[place], frame_id="cam"))
        ex.on_keyframe(outcome)
        loops += bus.deliver()
    return loops


def test_two_robots_find_the_place_they_share(tiny_model, places):
    bus, clock = LocalBus(), [0.0]
    a, b = robot(tiny_model, bus, "a", clock), robot(tiny_model, bus, "b", clock)
    plan = [(a, 0, 0.0), (b, 4, 0.5), (a, 1, 1.0), (b, 5, 1.5), (a, 2, 2.0), (b, 6, 2.5),
            (b, 1, 3.5), (a, 3, 4.0)]  # fmt: skip
    loops = drive(bus, plan, places, clock)
    assert len(loops) == 1
    loop = loops[0]
    rec = loop.record
    assert (loop.query_robot, loop.match_robot) == ("b", "a")
    assert (loop.query_session, loop.match_session) == (SESSION, SESSION)
    assert (rec.query_id, rec.query_stamp, rec.match_id, rec.match_stamp) == (3, 3.5, 1, 1.0)
    assert rec.accepted and rec.reason == "" and rec.candidates == rec.scored == 1
    assert np.isfinite(rec.pair_score)
    # b asked a (the owner) once; a scored it and answered; b counted the confirmation
    assert (b.counts.sent["request"], a.counts.sent["response"]) == (1, 1)
    assert (a.counts.loops_accepted, b.counts.loops_confirmed, b.pending) == (1, 1, 0)
    # each heard the other's 4 descriptors, and its own 4 back (ignored, not skipped)
    assert len(a.store) == len(b.store) == 4
    assert a.counts.ignored == 4 + 1 and b.counts.ignored == 4  # a also ignores b's response
    assert not a.counts.skipped and not b.counts.skipped
    s = b.summary()
    assert s["descriptor_bytes_per_keyframe"] == b.counts.sent_bytes["keyframes"] / 4
    assert s["descriptor_bytes_per_keyframe"] <= 1536
    n, d = tiny_model.num_patches, tiny_model.config.embed_dim
    assert b.counts.sent_bytes["request"] > n * d * 2  # the query's dense tokens travelled


def test_budget_bounds_requests_per_period(tiny_model, places):
    bus, clock = LocalBus(), [0.0]
    a = robot(tiny_model, bus, "a", clock)
    b = robot(tiny_model, bus, "b", clock, budget=1, period_s=10.0)
    plan = [(a, 0, 0.0), (a, 1, 1.0), (a, 2, 2.0), (b, 0, 5.0), (b, 1, 6.0), (b, 2, 16.0)]
    loops = drive(bus, plan, places, clock)
    # b's second request falls in the period of its first: cut; the third is in a new period
    assert [(x.record.query_id, x.record.match_id) for x in loops] == [(0, 0), (2, 2)]
    assert (b.counts.sent["request"], b.counts.budget_cut) == (2, 1)


def test_budget_zero_sends_descriptors_only(tiny_model, places):
    bus, clock = LocalBus(), [0.0]
    a = robot(tiny_model, bus, "a", clock)
    b = robot(tiny_model, bus, "b", clock, budget=0)
    assert drive(bus, [(a, 0, 0.0), (b, 0, 1.0)], places, clock) == []
    assert (b.counts.sent["keyframes"], b.counts.sent["request"], b.counts.budget_cut) == (1, 0, 1)


def test_an_owner_that_left_times_out_and_both_carry_on(tiny_model, places):
    bus, clock = LocalBus(), [0.0]
    a = robot(tiny_model, bus, "a", clock)
    b = robot(tiny_model, bus, "b", clock, timeout_s=5.0)
    drive(bus, [(a, 0, 0.0), (a, 1, 1.0), (a, 2, 2.0)], places, clock)
    bus.leave("a")
    assert drive(bus, [(b, 0, 3.0)], places, clock) == []  # request lost with a
    assert b.pending == 1
    drive(bus, [(b, 4, 9.0)], places, clock)  # 6 s later: counted as timed out
    assert (b.pending, b.counts.timeouts) == (0, 1)
    bus.join(a)  # a comes back; its keyframe made while away never reached b
    loops = drive(bus, [(a, 5, 10.0), (b, 1, 11.0)], places, clock)
    assert [(x.record.query_id, x.record.match_id) for x in loops] == [(2, 1)]
    assert b.counts.loops_confirmed == 1


def test_faulty_network_counts_and_never_crashes(tiny_model, places):
    bus, clock = LocalBus(Faults(drop=0.2, duplicate=0.3, reorder=0.3, corrupt=0.2, seed=3)), [0.0]
    a = robot(tiny_model, bus, "a", clock)
    b = robot(tiny_model, bus, "b", clock)
    plan = [(a if i % 2 else b, i % 8, float(i)) for i in range(40)]
    loops = drive(bus, plan, places, clock)
    skipped = a.counts.skipped + b.counts.skipped
    assert skipped["corrupt"] > 0 and skipped["duplicate"] > 0
    assert set(skipped) <= {"corrupt", "duplicate", "late", "unknown request", "malformed"}
    assert bus.dropped > 0
    assert a.store.reordered + b.store.reordered > 0
    assert all(x.record.accepted for x in loops)
    assert a.store.missing() + b.store.missing() > 0


def test_owner_scores_exactly_as_a_local_re_ranking_would(tiny_model, places):
    """The owner's score for a request equals the pair score of the same two keyframes'
    tokens, as the requester would compute with both maps at hand (float16 on the wire loses
    nothing: the map stores float16)."""
    bus, clock = LocalBus(), [0.0]
    config = dict(EXACT_MATCH, global_floor=-1.0, top_k=3)
    a = robot(tiny_model, bus, "a", clock, top_k=3)
    b = robot(tiny_model, bus, "b", clock, top_k=3)
    a.pipe.set_config(DetectorConfig(**config))
    b.pipe.set_config(DetectorConfig(**config))
    loops = drive(bus, [(a, 0, 0.0), (a, 1, 1.0), (a, 2, 2.0), (b, 3, 3.0)], places, clock)
    assert len(loops) == 1
    rec = loops[0].record
    assert (rec.candidates, rec.scored) == (3, 3)
    query = b.pipe.place_map.get_dense([0])[0]
    expected = map_pair_scores(tiny_model, a.pipe.place_map, query, [0, 1, 2])
    assert rec.pair_score == pytest.approx(float(expected.max()), abs=1e-6)
    assert rec.match_id == int(np.argmax(expected))


def test_best_selection_sends_the_period_s_best_candidates_when_it_ends(tiny_model, places):
    bus, clock = LocalBus(), [0.0]
    a = robot(tiny_model, bus, "a", clock)
    b = robot(tiny_model, bus, "b", clock, budget=1, period_s=10.0, select="best", top_k=1)
    config = DetectorConfig(**dict(EXACT_MATCH, global_floor=-1.0))
    b.pipe.set_config(config)
    # every pair passes the floor: b's keyframes at 5 s and 6 s both propose; the exact
    # repeat (place 1, similarity ~1) wins the period's one request
    plan = [(a, 0, 0.0), (a, 1, 1.0), (b, 4, 5.0), (b, 1, 6.0)]
    assert drive(bus, plan, places, clock) == []  # held until the period ends
    assert b.counts.sent["request"] == 0
    clock[0] = 15.0
    assert b.tick() == 1
    loops = bus.deliver()
    assert [(x.record.query_id, x.record.match_id) for x in loops] == [(1, 1)]
    assert (b.counts.budget_cut, b.counts.sent["request"]) == (1, 1)
