"""The re-rank latency budget (`rerank_budget_ms`), with a fake clock: each scored candidate
costs a fixed number of fake milliseconds, so no test depends on how fast this machine is."""

from __future__ import annotations

import math

import numpy as np
import pytest
from exact_match import EXACT_MATCH

from pair_vpr_ros.errors import ConfigError
from pair_vpr_ros.loops.detector import DetectorConfig, LoopDetector
from pair_vpr_ros.loops.frames import Frame
from pair_vpr_ros.loops.pipeline import LoopClosurePipeline
from pair_vpr_ros.loops.records import Candidate


class FakeClock:
    """A clock that only moves when a candidate is scored."""

    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def cands(n: int) -> list[Candidate]:
    return [Candidate(10 + i, float(i), "cam", 0.9 - 0.01 * i, i + 1) for i in range(n)]


def costly_scorer(clock: FakeClock, ms_per_candidate: float, scores: list[float], calls: list):
    """Scores candidate i as scores[i]; every call advances `clock` and is logged in `calls`."""

    def rerank(cs: list[Candidate]) -> np.ndarray:
        calls.append([c.rank_before for c in cs])
        clock.now += ms_per_candidate * len(cs) / 1e3
        return np.array([scores[c.rank_before - 1] for c in cs], dtype=np.float32)

    return rerank


def decide(
    budget_ms: float, n: int, ms_per_candidate: float, scores=None, step: int = 2, first: int = 1
):
    clock, calls = FakeClock(), []
    det = LoopDetector(DetectorConfig(rerank_budget_ms=budget_ms, top_k=n), clock=clock)
    scores = scores if scores is not None else [0.0] * n
    candidates = cands(n)
    rerank = costly_scorer(clock, ms_per_candidate, scores, calls)
    record = det.decide(1.0, "cam", candidates, rerank, step=step, first=first)
    return record, calls, candidates, clock


def test_no_budget_scores_every_candidate_in_one_call():
    record, calls, _, _ = decide(0.0, 10, 30.0)
    assert calls == [list(range(1, 11))]
    assert (record.candidates, record.scored) == (10, 10)


def test_budget_stops_before_the_step_that_would_overrun_it():
    # 30 ms each, steps 1 then 2: after 1 (30 ms) the next two fit (90 <= 100); after 3 (90 ms)
    # two more would end at 150 > 100, so scoring stops at 3 of 10.
    scores = [0.0, 1.0, 2.0, 0.0, 0.0, 9.0, 0.0, 0.0, 0.0, 0.0]
    record, calls, candidates, clock = decide(100.0, 10, 30.0, scores)
    assert calls == [[1], [2, 3]]
    assert (record.candidates, record.scored) == (10, 3)
    assert clock.now * 1e3 == pytest.approx(90.0)
    # the best of the scored three wins; candidate 6 (score 9) was never scored
    assert (record.match_id, record.rank_before, record.pair_score) == (12, 3, 2.0)
    assert [math.isnan(c.pair_score) for c in candidates] == [False] * 3 + [True] * 7


def test_budget_equal_to_the_predicted_cost_still_scores():
    # 25 ms each: 25 + 2 x 25 = 75 == budget -> scored; then 75 + 50 > 75 -> stop
    record, calls, _, _ = decide(75.0, 10, 25.0)
    assert calls == [[1], [2, 3]] and record.scored == 3


def test_budget_below_one_candidate_scores_the_global_best_only():
    record, calls, _, _ = decide(1.0, 10, 500.0, [0.0, 5.0] + [0.0] * 8)
    assert calls == [[1]]
    assert (record.scored, record.match_id, record.rank_before) == (1, 10, 1)


def test_large_budget_scores_all_in_steps():
    record, calls, _, _ = decide(1e5, 10, 30.0, step=4)
    assert calls == [[1], [2, 3, 4, 5], [6, 7, 8, 9], [10]]
    assert (record.candidates, record.scored) == (10, 10)


def test_a_fixed_chunk_back_end_scores_whole_chunks_from_the_first_call():
    # first=2 (a back end that pads every call to 2): the first call scores the two global
    # best; a budget below one call still gets that call, never a padded single candidate.
    _, calls, _, _ = decide(100.0, 10, 30.0, step=2, first=2)
    assert calls == [[1, 2]]  # 60 ms spent, the next pair predicts 120 > 100
    record, calls, _, _ = decide(1.0, 10, 500.0, [0.0, 5.0] + [0.0] * 8, step=2, first=2)
    assert calls == [[1, 2]] and (record.scored, record.rank_before) == (2, 2)
    _, calls, _, _ = decide(1.0, 1, 500.0, step=2, first=2)
    assert calls == [[1]]


def test_below_global_floor_scores_nothing():
    det = LoopDetector(DetectorConfig(global_floor=0.95, rerank_budget_ms=50.0))
    record = det.decide(1.0, "cam", cands(4), lambda cs: pytest.fail("must not re-rank"))
    assert (record.candidates, record.scored, record.reason) == (4, 0, "below global floor")


@pytest.mark.parametrize("bad", [-1.0, math.nan, math.inf, -math.inf])
def test_bad_budget_is_a_config_error(bad):
    with pytest.raises(ConfigError, match="rerank_budget_ms=.* must be a finite number >= 0"):
        DetectorConfig(rerank_budget_ms=bad)


def test_pipeline_counts_and_records_the_budget(tiny_model):
    """The pipeline scores through the detector's budget; with a fake clock charging 30 ms per
    candidate and a 100 ms budget, a query gets at most 3 candidates scored (1 + 2: 90 ms)."""
    rng = np.random.default_rng(3)
    places = [rng.integers(0, 256, (48, 64, 3), dtype=np.uint8) for _ in range(6)]
    config = DetectorConfig(**{**EXACT_MATCH, "top_k": 5, "rerank_budget_ms": 100.0})
    config = config.updated(global_floor=-1.0)  # every query with candidates is re-ranked
    pipe = LoopClosurePipeline(tiny_model, config, rerank_chunk=2)
    clock = FakeClock()
    pipe.detector.clock = clock
    score = pipe.pair_scores

    def charged(dense, ids):
        clock.now += 0.030 * len(ids)
        return score(dense, ids)

    pipe.pair_scores = charged
    frames = [Frame(float(t), places[p], "cam") for t, p in enumerate([0, 1, 2, 3, 4, 5, 0, 1])]
    out = list(pipe.process_many(frames, batch_size=1))
    scored = [(o.loop.candidates, o.loop.scored) for o in out if o.loop is not None]
    # eligible keyframes for queries 3..7: 1, 2, 3, 4, 5 (exclude 1 keyframe and 2.5 s)
    assert scored == [(1, 1), (2, 2), (3, 3), (4, 3), (5, 3)]
    assert pipe.counts.candidates_scored == 12 and pipe.counts.rerank_budget_cut == 2
    pipe.set_config(pipe.config.updated(rerank_budget_ms=0.0))  # run-time change: no budget
    more = list(pipe.process_many([Frame(8.0, places[2], "cam")], batch_size=1))
    assert (more[0].loop.candidates, more[0].loop.scored) == (5, 5)


def test_pipeline_steps_by_a_fixed_chunk_back_end(tiny_model, monkeypatch):
    """A back end with `chunk_size` (OpenVINO pads every call to it) is scored a whole chunk
    at a time from the first call, whatever `rerank_chunk` says."""
    rng = np.random.default_rng(3)
    places = [rng.integers(0, 256, (48, 64, 3), dtype=np.uint8) for _ in range(6)]
    config = DetectorConfig(**{**EXACT_MATCH, "top_k": 5, "rerank_budget_ms": 1e6})
    monkeypatch.setattr(tiny_model, "chunk_size", 3, raising=False)  # as OpenVINOModel has
    pipe = LoopClosurePipeline(tiny_model, config.updated(global_floor=-1.0), rerank_chunk=2)
    sizes = []
    score = pipe.pair_scores

    def logged(dense, ids):
        sizes.append(len(ids))
        return score(dense, ids)

    pipe.pair_scores = logged
    frames = [Frame(float(t), places[p], "cam") for t, p in enumerate([0, 1, 2, 3, 4, 5, 0])]
    out = list(pipe.process_many(frames, batch_size=1))
    assert (out[-1].loop.candidates, out[-1].loop.scored) == (4, 4)
    assert sizes[-2:] == [3, 1]  # the last query's 4 eligible keyframes, in chunks of 3
