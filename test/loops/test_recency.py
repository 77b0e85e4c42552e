"""Recent-keyframe exclusion by stamp distance, and clock jumps backwards."""

from __future__ import annotations

import numpy as np
import pytest

from pair_vpr_ros.loops.recency import ClockWatch, StampBuffer, eligible_keyframes


def eligible(stamps, query, exclude_s=30.0, exclude_n=0):
    mask = eligible_keyframes(np.array(stamps, dtype=np.float64), query, exclude_s, exclude_n)
    return None if mask is None else np.flatnonzero(mask).tolist()


@pytest.mark.parametrize(
    "stamps,query,expected",
    [
        ([0.0, 1.0, 2.0, 50.0, 51.0], 60.0, [0, 1, 2]),  # newest 2 are within 30 s
        ([0.0, 1.0, 2.0], 10.0, None),  # everything recent
        ([0.0, 100.0, 101.0, 102.0], 103.0, [0]),
        ([], 5.0, None),
        # a bag played twice: the first pass near the query's stamp is excluded, by stamp,
        # though its ids are old; keyframes stamped long before or after it are not
        ([0.0, 40.0, 80.0, 120.0, 0.5, 40.5], 80.5, [0, 1, 3, 4, 5]),
        ([0.0, 40.0, 80.0, 0.2], 0.3, [1, 2]),
    ],
)
def test_recent_keyframes_are_excluded_by_stamp_distance(stamps, query, expected):
    assert eligible(stamps, query) == expected


def test_keyframe_gap_excludes_newest_ids_and_the_same_stamp_always():
    assert eligible([0.0, 1.0, 2.0, 3.0, 4.0], 100.0, exclude_s=0.0, exclude_n=3) == [0, 1]
    assert eligible([5.0, 6.0, 7.0, 8.0], 6.0, exclude_s=0.0, exclude_n=1) == [0, 2]


def test_stamp_buffer_grows_and_keeps_order():
    buf = StampBuffer([1.0, 2.0])
    for t in range(3000):
        buf.append(float(t))
    assert len(buf) == 3002 and buf.values[:3].tolist() == [1.0, 2.0, 0.0]
    assert buf.values[-1] == 2999.0


def test_clock_watch_tells_jumps_from_reordering():
    watch = ClockWatch(tolerance_s=1.0)
    assert [watch.check(t) for t in (10.0, 11.0, 10.5, 12.0)] == [0.0, 0.0, 0.0, 0.0]
    assert watch.check(2.0) == 10.0 and watch.newest == 2.0  # a new session starts at 2 s
    assert watch.check(3.0) == 0.0
    watch.reset()
    assert watch.check(0.0) == 0.0


def as_ids(result, n: int):
    """Eligible ids of a `StampBuffer.eligible` result (a prefix length, a mask or None)."""
    if result is None:
        return None
    return list(range(result)) if isinstance(result, int) else np.flatnonzero(result).tolist()


@pytest.mark.parametrize("exclude_s,exclude_n", [(30.0, 0), (2.5, 3), (0.0, 1), (0.0, 0)])
def test_sorted_stamps_give_the_same_keyframes_by_bisection(exclude_s, exclude_n):
    rng = np.random.default_rng(4)
    for trial in range(200):
        stamps = np.sort(rng.integers(0, 100, rng.integers(0, 30))).astype(np.float64)
        if trial % 2:  # a jump back: not sorted any more, the mask path
            stamps = np.concatenate([stamps, stamps[: len(stamps) // 2]])
        buf = StampBuffer(stamps[: len(stamps) // 3])
        for t in stamps[len(stamps) // 3 :]:
            buf.append(float(t))
        assert buf.sorted == bool(np.all(np.diff(stamps) >= 0))
        query = float(rng.integers(-10, 110))
        expected = eligible(stamps, query, exclude_s, exclude_n)
        assert as_ids(buf.eligible(query, exclude_s, exclude_n), len(stamps)) == expected


def test_a_live_run_gets_a_prefix_length_not_a_mask():
    buf = StampBuffer(float(t) for t in range(100))
    assert buf.eligible(100.0, 30.0, 10) == 71  # ids 0..70: stamps <= 70
    assert buf.eligible(10.0, 30.0, 0) is not None and not isinstance(
        buf.eligible(10.0, 30.0, 0), int
    )  # keyframes stamped after the query (another clock): a mask
