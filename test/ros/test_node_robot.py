"""`vpr_node` under what a robot does every day (issue 17): a bag played again or a clock reset
(stamps going back), and `loop_closure` remapped for LIO-SAM (every output follows it). In one
process: the node and a peer publishing and listening (`node_harness`)."""

from __future__ import annotations

import json

import pytest
from bag_fixtures import synthetic_images
from node_harness import diagnostics, wait_for


@pytest.fixture(scope="module")
def places():
    return synthetic_images(6, size=32)


def test_stamps_going_back_never_publish_a_pair_with_t_current_not_after_t_previous(
    harness, places
):
    h = harness()
    everything = [places[i] for i in range(6)]
    h.publish(everything, t0=100.0)
    h.publish(everything, t0=100.0)  # the bag played again: the same images at the same stamps
    h.publish(everything[:2], t0=50.0)  # a clock reset to before the first pass
    h.publish(everything[2:4], t0=200.0)  # time moves on: revisits of the first pass
    h.processed(16)
    wait_for(
        lambda: (
            diagnostics(h).get("loops") == "2"
            and diagnostics(h).get("loops_unordered") == "2"
            and diagnostics(h).get("clock_jumps") == "2"
        )
    )
    pairs = [list(m.data) for m in h.got["loop_closure"]]
    assert all(current > previous for current, previous in pairs), pairs
    assert pairs == [[200.0, 102.0], [201.0, 103.0]]
    # the loops after the reset (into the first pass's "future") are on detail and json only
    wait_for(lambda: len(h.got["loop_closure/json"]) == 4)
    records = [json.loads(m.data) for m in h.got["loop_closure/json"]]
    assert [(r["query_stamp"], r["match_stamp"]) for r in records] == [
        (50.0, 100.0), (51.0, 101.0), (200.0, 102.0), (201.0, 103.0)
    ]  # fmt: skip
    assert h.node.stats.counts.errors == 0


def test_every_output_follows_a_remapped_loop_closure(harness, places):
    base = "/lio_loop/loop_closure_detection"
    h = harness(remap=base)
    h.publish([places[i] for i in (0, 1, 2, 0)], t0=100.0)
    h.processed(4)
    wait_for(lambda: len(h.got["loop_closure"]) == 1 and len(h.got["loop_closure/json"]) == 1)
    assert list(h.got["loop_closure"][0].data) == [103.0, 100.0]
    assert len(h.got["loop_closure/detail"]) == 1
    expected = {base, *(f"{base}/{s}" for s in ("detail", "json", "factor", "markers"))}

    def published() -> dict[str, list[str]]:
        return dict(h.peer.get_publisher_names_and_types_by_node("vpr_node", "/"))

    wait_for(lambda: expected <= set(published()))  # the graph is discovered, not instant
    assert {t for t in published() if "loop" in t} == expected
    assert published()[base] == ["std_msgs/msg/Float64MultiArray"]
