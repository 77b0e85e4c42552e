"""The peer store (other robots' descriptors, one index with owner rows) and the budget."""

from __future__ import annotations

import numpy as np

from pair_vpr_ros.fleet import KeyframeDescriptor, model_tag
from pair_vpr_ros.fleet.peers import PeerHit, PeerStore, Proposal, RequestBudget

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


def proposal(sim, query_id=0):
    return Proposal(sim, query_id, float(query_id), ("a", "s1"), [])


def test_first_selection_sends_at_once_while_the_period_budget_lasts():
    budget = RequestBudget(2, period_s=10.0, select="first")
    sent = [len(budget.offer(t, [proposal(0.9)])[0]) for t in (0.0, 1.0, 2.0, 9.9, 10.0, 10.5, 11)]
    assert sent == [1, 1, 0, 0, 1, 1, 0]
    assert budget.offer(3.0, [proposal(0.9)]) == ([proposal(0.9)], 0)  # clock back: new period
    assert RequestBudget(0, 1.0, "first").offer(0.0, [proposal(0.5)]) == ([], 1)


def test_best_selection_sends_a_period_s_most_similar_when_it_ends():
    budget = RequestBudget(2, period_s=10.0, select="best")
    assert budget.offer(0.0, [proposal(0.7, 0)]) == ([], 0)
    assert budget.offer(4.0, [proposal(0.9, 1), proposal(0.8, 2)]) == ([], 0)
    assert budget.offer(9.0, [proposal(0.95, 3)]) == ([], 0)
    # the period that began at 0 s ends: its 2 best of 4 go out, 2 cut; 0.6 opens the next
    assert budget.offer(10.0, [proposal(0.6, 4)]) == ([proposal(0.95, 3), proposal(0.9, 1)], 2)
    assert budget.flush() == ([proposal(0.6, 4)], 0)
    assert budget.offer(12.0, []) == ([], 0)
