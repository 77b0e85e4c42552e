"""ROS-free parts of the node: precision, frame queue, statistics (loading: test_weights)."""

from __future__ import annotations

import threading

import pytest
import torch

from pair_vpr_ros.ros.runtime import FrameQueue, NodeStats, precision_context


def test_bf16_autocasts_in_the_thread_that_enters_it():
    seen = []

    def run():
        with precision_context("cpu", "bf16"):
            seen.append(torch.is_autocast_enabled("cpu") and torch.get_autocast_dtype("cpu"))

    thread = threading.Thread(target=run)
    thread.start()
    thread.join()
    assert seen == [torch.bfloat16] and not torch.is_autocast_enabled("cpu")
    with precision_context("cpu", "fp32"):
        assert not torch.is_autocast_enabled("cpu")


def test_full_queue_drops_the_oldest():
    q = FrameQueue(2)
    assert [q.put(i) for i in range(5)] == [False, False, True, True, True]
    assert q.dropped == 3 and q.snapshot() == [3, 4] and len(q) == 2
    assert q.get(0.01) == 3 and q.get(0.01) == 4 and q.get(0.01) is None
    q.put(5)
    q.close()
    assert q.get(1.0) is None  # closed: the worker stops even with frames waiting


def test_stats_percentiles_and_problems():
    stats = NodeStats(window=4)
    assert stats.percentiles("encode") is None
    for ms in (100.0, 1.0, 2.0, 3.0, 4.0):  # the window keeps the last 4
        stats.add_ms("encode", ms)
    assert stats.percentiles("encode") == (2.5, pytest.approx(3.85), 4.0)
    assert dict(stats.latency_items())["encode_ms_max"] == "4.00"
    assert stats.problems() == ""
    stats.counts.dropped += 2
    assert stats.problems() == "2 frames dropped"
    stats.counts.received += 5
    stats.counts.invalid += 2
    stats.counts.errors += 1
    stats.counts.bad_poses += 3
    assert stats.problems() == "2 frames invalid, 1 frames failed, 3 poses invalid (NaN/inf)"
    assert stats.problems() == ""
    stats.counts.depth_unmatched += 3
    stats.counts.depth_late += 1
    assert stats.problems() == (
        "3 frames without depth, 1 depth images too late (depth_max_delay)"
    )
