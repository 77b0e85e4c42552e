"""The re-rank cascade (`rerank_cascade`, loops/cascade.py) with fake scorers: the decision is
full scoring's wherever its bounds hold, from fewer decoder passes; what it left unscored is
explicit on each candidate; a young cascade scores everything; the budget still applies."""

from __future__ import annotations

import math

import numpy as np
import pytest

from pair_vpr_ros.loops import cascade as cascade_module
from pair_vpr_ros.loops import floor as floor_module
from pair_vpr_ros.loops.cascade import MIN_PAIRS, CascadeStats
from pair_vpr_ros.loops.detector import DetectorConfig, LoopDetector
from pair_vpr_ros.loops.records import Candidate


class Logits:
    """Fake one-direction scorer: candidate `rank_before` r has logit(q,c) qc[r-1] and logit(c,q)
    cq[r-1]; every call is logged as (first image, ranks) and costs `ms` fake ms a pair."""

    def __init__(self, qc, cq, ms: float = 0.0) -> None:
        self.qc, self.cq, self.ms, self.calls, self.now = qc, cq, ms, [], 0.0

    def __call__(self, cands: list[Candidate], first: str) -> np.ndarray:
        self.calls.append((first, [c.rank_before for c in cands]))
        self.now += self.ms * len(cands) / 1e3
        table = self.cq if first == "candidate" else self.qc
        return np.array([table[c.rank_before - 1] for c in cands], dtype=np.float32)

    def both(self, cands: list[Candidate]) -> np.ndarray:  # full scoring, for comparison
        return np.array([np.float32(self.qc[c.rank_before - 1]) + np.float32(
            self.cq[c.rank_before - 1]) for c in cands], dtype=np.float32)  # fmt: skip


def cands(sims) -> list[Candidate]:
    return [Candidate(100 + i, float(i), "cam", s, i + 1) for i, s in enumerate(sims)]


def ready(spread: float, top: float) -> CascadeStats:
    return CascadeStats(pairs=MIN_PAIRS, spread=spread, top=top)


def detector(stats: CascadeStats | None = None, **config) -> LoopDetector:
    det = LoopDetector(DetectorConfig(rerank_cascade=True, **config))
    if stats is not None:
        det.cascade.stats = stats
    return det


def test_a_young_cascade_scores_every_candidate_both_ways_in_global_order():
    scorer = Logits([1.0, 4.0, 2.0], [1.5, 3.0, 2.5])
    det = detector(score_threshold=5.0)
    record = det.decide(1.0, "cam", cands([0.9, 0.8, 0.7]), scorer.both, step=1, one_way=scorer)
    assert scorer.calls == [("query", [1]), ("candidate", [1]), ("query", [2]),
                            ("candidate", [2]), ("query", [3]), ("candidate", [3])]  # fmt: skip
    assert (record.match_id, record.pair_score, record.accepted) == (101, 7.0, True)
    assert (record.scored, det.last_passes) == (3, 6)
    assert det.cascade.stats.pairs == 3 and det.cascade.stats.spread == 1.0


def test_the_second_direction_only_where_it_can_change_the_decision():
    # weight 10: re-rank score = pair + 10 x similarity. Bounds: spread 1, top 8.
    sims = [0.9, 0.85, 0.5, 0.2]
    qc, cq = [3.5, 3.0, 0.5, 3.0], [3.0, 2.5, 4.0, 3.5]  # the query first: qc first
    scorer = Logits(qc, cq)
    det = detector(ready(1.0, 8.0), score_threshold=10.0, global_weight=10.0)
    candidates = cands(sims)
    record = det.decide(1.0, "cam", candidates, scorer.both, one_way=scorer)
    # global best both ways: 6.5 + 9 = 15.5. Candidate 2, unscored: 8 + 1 + 8.5 = 17.5 ->
    # one way (3.0): 6 + 1 + 8.5 = 15.5 >= 15.5 -> second way: 5.5 + 8.5 = 14. Candidate 3,
    # unscored 9 + 5 = 14 < 15.5; candidate 4: 9 + 2 = 11: never scored.
    assert scorer.calls == [("query", [1]), ("candidate", [1]), ("query", [2]),
                            ("candidate", [2])]  # fmt: skip
    assert (record.match_id, record.pair_score, record.accepted) == (100, 6.5, True)
    assert (record.scored, det.last_passes) == (2, 4)
    assert [c.directions for c in candidates] == [2, 2, 0, 0]
    assert math.isnan(candidates[2].pair_score) and math.isnan(candidates[2].logit_qc)
    assert (candidates[1].logit_qc, candidates[1].logit_cq) == (3.0, 2.5)


def test_a_candidate_left_one_way_says_so():
    scorer = Logits([3.0, -8.0], [3.0, -9.0])
    det = detector(ready(1.0, 6.0), score_threshold=0.0)
    candidates = cands([0.9, 0.89])
    det.decide(1.0, "cam", candidates, scorer.both, one_way=scorer)
    # candidate 2: unscored bound 7 >= 6 -> one way: -16 + 1 < 6: stops there
    assert [c.directions for c in candidates] == [2, 1]
    assert candidates[1].logit_qc == -8.0 and math.isnan(candidates[1].logit_cq)
    assert math.isnan(candidates[1].pair_score) and det.last_passes == 3


def test_nothing_can_reach_the_threshold_scores_the_global_best_alone():
    scorer = Logits([1.0] * 5, [1.0] * 5)
    det = detector(ready(2.0, 5.0), score_threshold=50.0)
    record = det.decide(1.0, "cam", cands([0.5] * 5), scorer.both, one_way=scorer)
    assert (record.accepted, record.reason, record.scored) == (False, "score below threshold", 1)
    assert det.last_passes == 2 and not det.last_cut


def test_a_candidate_continuing_the_sequence_is_scored_down_to_the_margin_floor():
    # threshold 10, margin 6: the previous keyframe's loop went to id 200; a candidate within
    # temporal_tolerance of it is accepted at >= 4
    config = dict(score_threshold=10.0, sequence_margin=6.0, temporal_tolerance=2)
    det = detector(ready(0.5, 9.0), **config)
    first = Logits([6.0], [6.0])
    det.decide(1.0, "cam", [Candidate(200, 0.0, "cam", 0.9, 1)], first.both, one_way=first)
    candidates = [Candidate(150, 0.0, "cam", 0.9, 1), Candidate(201, 0.0, "cam", 0.8, 2)]
    scorer = Logits([1.0, 2.5], [1.0, 2.0])
    record = det.decide(2.0, "cam", candidates, scorer.both, one_way=scorer)
    assert (record.match_id, record.accepted, record.pair_score) == (201, True, 4.5)
    # without the sequence the second candidate (bound 9.5 < 10) is never scored
    det = detector(ready(0.5, 9.0), **config)
    candidates = [Candidate(150, 0.0, "cam", 0.9, 1), Candidate(201, 0.0, "cam", 0.8, 2)]
    record = det.decide(2.0, "cam", candidates, scorer.both, one_way=scorer)
    assert (record.match_id, record.accepted, candidates[1].directions) == (150, False, 0)


def test_the_budget_stops_the_cascade_and_settles_the_best_one_way_candidate():
    # 30 ms a pass, 100 ms: the global best (2 passes, 60 ms), one more first direction
    # (90 ms); the next (120 ms) would overrun. Then the one-way candidate whose estimate
    # (2 x 5 = 10) beats the best full score (2) gets its second direction.
    scorer = Logits([1.0, 5.0, 0.0, 5.0], [1.0, 0.0, 5.0, 0.0], ms=30.0)
    det = detector(ready(3.0, 12.0), score_threshold=0.0, rerank_budget_ms=100.0)
    det.clock = lambda: scorer.now
    candidates = cands([0.5] * 4)
    record = det.decide(1.0, "cam", candidates, scorer.both, step=1, one_way=scorer)
    assert scorer.calls == [("query", [1]), ("candidate", [1]), ("query", [2]),
                            ("candidate", [2])]  # fmt: skip
    assert det.last_cut and det.last_passes == 4
    assert (record.match_id, record.pair_score, record.scored) == (101, 5.0, 2)


@pytest.mark.parametrize("first", ["candidate", "query"])
def test_with_bounds_that_hold_every_decision_is_full_scorings(first, monkeypatch):
    """Random keyframes (10 candidates, sims and logits drawn like the demo model's): with the
    spread and top the data really has, the cascade decides as full scoring does."""
    monkeypatch.setattr(cascade_module, "FIRST", first)
    monkeypatch.setattr(cascade_module, "SECOND", "query" if first == "candidate" else "candidate")
    rng = np.random.default_rng(7)
    queries = []
    for _ in range(150):
        sims = np.sort(rng.uniform(0.3, 0.9, 10))[::-1]
        base = 60 * (sims - 0.6) + rng.normal(0, 4, 10)
        qc, cq = base + rng.normal(0, 1.5, 10), base + rng.normal(0, 1.5, 10)
        queries.append((sims, qc.astype(np.float32), cq.astype(np.float32)))
    spread = max(float(np.abs(q - c).max()) for _, q, c in queries)
    top = max(float((q + c).max()) for _, q, c in queries)
    config = dict(score_threshold=64.0, global_weight=100.0, sequence_margin=24.0)
    full, cas = LoopDetector(DetectorConfig(**config)), detector(ready(spread, top), **config)
    passes = 0
    for t, (sims, qc, cq) in enumerate(queries):
        scorer = Logits(qc, cq)
        want = full.decide(float(t), "cam", cands(sims), scorer.both)
        got = cas.decide(float(t), "cam", cands(sims), scorer.both, step=1, one_way=scorer)
        assert (got.match_id, got.accepted) == (want.match_id, want.accepted) or (
            not want.accepted and not got.accepted
        ), t
        if want.accepted:
            assert got.pair_score == want.pair_score
        passes += cas.last_passes
    assert passes < 0.5 * 2 * 10 * len(queries)


def test_the_learned_floor_skips_nothing_while_the_map_is_young(monkeypatch):
    monkeypatch.setattr(floor_module, "MIN_LOOPS", 3)
    det = detector(ready(1.0, 5.0), score_threshold=0.0)
    scorer = Logits([2.0] * 3, [2.0] * 3)
    for t, sim in enumerate([0.8, 0.7, 0.9]):  # three accepted loops: the floor is learned
        assert det.floor.value() is None
        det.decide(float(t), "cam", cands([sim, 0.1, 0.1]), scorer.both, one_way=scorer)
    assert det.floor.loops == 3
    assert det.floor.value() == pytest.approx(np.quantile([0.8, 0.7, 0.9], 0.01) - 0.05)
    record = det.decide(5.0, "cam", cands([0.6, 0.5]), lambda c: pytest.fail("re-ranked"),
                        one_way=lambda c, f: pytest.fail("re-ranked"))  # fmt: skip
    assert (record.scored, record.accepted, det.last_skipped, det.last_passes) == (
        0,
        False,
        True,
        0,
    )
    assert record.reason == "below learned global floor (0.652)" and math.isnan(record.pair_score)
    # off with learned_floor false, and without the cascade (today's behaviour)
    for config in (dict(learned_floor=False), dict(rerank_cascade=False)):
        det.set_config(det.config.updated(**config))
        assert det.decide(6.0, "cam", cands([0.6]), scorer.both, one_way=scorer).scored == 1
    det.reset_map()  # a new, loaded or cleared map is young again
    assert det.floor.value() is None and det.floor.loops == 0


def test_a_broken_pass_never_wins_and_never_hangs():
    """A model that returns NaN (damaged weights): the pass counts as scored, at -inf."""
    scorer = Logits([float("nan")] * 3, [float("nan")] * 3)
    det = detector(ready(1.0, 5.0), score_threshold=-100.0)
    candidates = cands([0.9, 0.8, 0.7])
    record = det.decide(1.0, "cam", candidates, scorer.both, one_way=scorer)
    assert record.accepted is False and record.pair_score == -math.inf
    assert all(c.directions > 0 for c in candidates) and det.cascade.stats.pairs == MIN_PAIRS


def test_the_learned_floor_never_skips_a_keyframe_that_may_continue_the_loop(monkeypatch):
    monkeypatch.setattr(floor_module, "MIN_LOOPS", 1)
    det = detector(ready(1.0, 5.0), score_threshold=0.0, sequence_margin=5.0)
    scorer = Logits([2.0, 2.0], [2.0, 2.0])
    det.decide(0.0, "cam", cands([0.9, 0.1]), scorer.both, one_way=scorer)  # loop to id 100
    assert det.floor.value() == pytest.approx(0.85)
    record = det.decide(1.0, "cam", cands([0.5, 0.4]), scorer.both, one_way=scorer)
    assert record.scored > 0 and not det.last_skipped  # below the floor, yet re-ranked
