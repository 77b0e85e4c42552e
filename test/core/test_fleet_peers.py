"""The peer store (other robots' descriptors, one index with owner rows) and the budget."""

from __future__ import annotations

import numpy as np

from pair_vpr_ros.fleet import KeyframeDescriptor, model_tag
from pair_vpr_ros.fleet.peers import PeerHit, PeerStore, RequestBudget

TAG = model_tag("m")


def unit(v):
    v = np.asarray(v, np.float32)
    return (v / np.linalg.norm(v)).astype(np.float16)


def add(store, robot, session, kf_id, vec):
    store.add(KeyframeDescriptor(robot, session, TAG, kf_id, float(kf_id), unit(vec)))


def test_search_groups_hits_by_owner_and_applies_the_floor():
    store = PeerStore("me", 4, TAG)
    add(store, "a", "s1", 0, [1, 0, 0, 0])
    add(store, "b", "s1", 0, [1, 0.1, 0, 0])
    add(store, "a", "s1", 1, [1, 0.3, 0, 0])
    add(store, "a", "s2", 0, [0, 1, 0, 0])
    hits = store.search(unit([1, 0, 0, 0]).astype(np.float32), k=4, floor=0.9)
    assert list(hits) == [("a", "s1"), ("b", "s1")]  # the best hit's owner first
    assert [h.keyframe_id for h in hits[("a", "s1")]] == [0, 1]
    first = hits[("a", "s1")][0]
    assert first == PeerHit("a", "s1", 0, 0.0, first.similarity)
    assert abs(first.similarity - 1.0) < 1e-3
    assert store.owners() == {"a/s1": 2, "a/s2": 1, "b/s1": 1}
    assert store.search(unit([0, 0, 1, 0]).astype(np.float32), k=4, floor=0.5) == {}


def test_missing_counts_gaps_per_robot_session():
    store = PeerStore("me", 4, TAG)
    for kf_id in (0, 3):
        add(store, "a", "s1", kf_id, [1, kf_id, 0, 0])
    add(store, "b", "s1", 1, [0, 1, 0, 0])
    assert store.missing() == 2 + 1


def test_budget_per_period():
    budget = RequestBudget(2, period_s=10.0)
    assert [budget.take(t) for t in (0.0, 1.0, 2.0, 9.9, 10.0, 10.5, 11.0)] == [
        True, True, False, False, True, True, False,
    ]  # fmt: skip
    assert budget.take(3.0)  # the clock went back (a new session): a new period
    assert not RequestBudget(0, 1.0).take(0.0)
