"""The re-rank cascade (`DetectorConfig.rerank_cascade`): decoder passes spent where a decision
is made, the decision the same as scoring every candidate both ways where the bounds hold.

Full scoring runs 2K decoder passes a keyframe (one pass = one direction of one pair). The
cascade keeps, for every candidate, an upper bound on its re-rank score, pair score + w x global
similarity (w = `global_weight`):
- scored both ways: the score itself, logit(q,c) + logit(c,q) from the same block code as full
  scoring's (equal to float rounding; OpenVINO int8: to its quantization, docs/performance.md);
- scored one way (`FIRST`): twice that logit + the largest disagreement between the two
  directions seen so far (`CascadeStats.spread`);
- not scored: the highest pair score seen so far (`CascadeStats.top`).
It scores the global best both ways (so every record carries a full score), then, while some
candidate's bound still reaches what it must beat, gives the one with the highest bound its
next direction (with `rerank_budget_ms`: the first direction of every such candidate before
any second one, so that each gets a look before the budget runs out). A candidate must beat
`score_threshold` and the best full score so far to become the loop; with `sequence_margin`, a
candidate continuing the previous keyframe's loop must beat the margin's lower floor and the
best full score among such candidates (sequence.py); nothing else decides (temporal
consistency and verification look at the decided candidate only). When no bound reaches, the
near miss the `top` bound ruled out (the highest bound within `spread` of what it must beat)
gets one direction: `top` is learned from what was scored, and at the first revisits of a
drive it still holds only the scores of new ground (on the demo world this audit removed the
two decisions that differed). Then the best full score is full scoring's decision, as long as
the bounds hold: they are learned, not proven, so benchmarks/bench_rerank_budget.py counts the
decisions that differ.

Young: until `MIN_PAIRS` pairs were scored both ways the bounds are unknown and every
candidate is scored both ways (in global order), one direction at a time, as the statistics
need. With a budget the cascade stops where full scoring would, then scores the second
direction of the best one-way candidate if its estimate beats every full score (one step over).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from pair_vpr_ros.loops.records import Candidate, rerank_score

# Which image the decoder reads first in the first step and the second: the query first, as
# both order the same (passes 0.497 / 0.541 / 0.479 of full scoring on seeds 7 / 8 / 9, candidate
# first 0.473 / 0.541 / 0.497) and its pass costs 3-7 % less with ViT-B on OpenVINO int8 (it
# reuses the query's block-0 self-attention; docs/performance.md)
FIRST, SECOND = "query", "candidate"
MIN_PAIRS = 64  # pairs scored both ways before the bounds are trusted

OneWay = Callable[[list[Candidate], str], np.ndarray]  # (candidates, first image) -> logits [k]


@dataclass
class CascadeStats:
    """What the bounds are learned from: every pair the cascade scored both ways (and the
    one-way logits, for the highest score)."""

    pairs: int = 0
    spread: float = 0.0  # largest |logit(q,c) - logit(c,q)| seen
    top: float = -math.inf  # highest pair score seen (or twice a one-way logit)

    @property
    def ready(self) -> bool:
        return self.pairs >= MIN_PAIRS

    def add(self, cand: Candidate) -> None:
        if math.isfinite(cand.pair_score):
            self.pairs += 1
            self.spread = max(self.spread, abs(cand.logit_qc - cand.logit_cq))
            self.top = max(self.top, cand.pair_score)
        elif cand.directions == 1 and math.isfinite(first_logit(cand)):
            self.top = max(self.top, 2 * first_logit(cand))


@dataclass
class Goal:
    """What a candidate must beat to change the decision: `threshold` (`score_threshold`), and
    with a sequence to follow `floor` (score_threshold - sequence_margin) for the candidates
    `continues` says follow it."""

    threshold: float
    weight: float  # global_weight
    floor: float | None = None
    continues: Callable[[Candidate], bool] = field(default=lambda cand: False)


@dataclass
class Cascade:
    """The cascade's step rule over one keyframe's candidates (global order)."""

    stats: CascadeStats = field(default_factory=CascadeStats)

    def upper(self, cand: Candidate, weight: float) -> float:
        """The highest re-rank score `cand` can have (module docstring)."""
        if cand.directions == 2:
            return cand.rerank_score(weight)
        if cand.directions == 1:
            pair = 2 * first_logit(cand) + self.stats.spread
        else:
            pair = self.stats.top
        return rerank_score(pair, cand.global_similarity, weight)

    def contenders(
        self, cands: Sequence[Candidate], goal: Goal, slack: float = 0.0
    ) -> list[Candidate]:
        """The candidates not yet scored both ways that can still change the decision (with
        `slack`: that would, were their bound `slack` higher), highest bound first (ties:
        global order)."""
        w = goal.weight
        full = [c.rerank_score(w) for c in cands if c.directions == 2]
        best = max(full, default=-math.inf)
        found = best >= goal.threshold  # a loop above the threshold: no sequence needed
        follow = [c.rerank_score(w) for c in cands if c.directions == 2 and goal.continues(c)]
        best_follow = max(follow, default=-math.inf)
        out = []
        for cand in cands:
            if cand.directions == 2:
                continue
            bound = self.upper(cand, w) + slack
            if bound >= max(goal.threshold, best):
                out.append((bound, cand))
            elif (
                not found
                and goal.floor is not None
                and goal.continues(cand)
                and bound >= max(goal.floor, best_follow)
            ):
                out.append((bound, cand))
        out.sort(key=lambda item: (-item[0], item[1].rank_before))
        return [cand for _, cand in out]

    def run(
        self,
        cands: list[Candidate],
        one_way: OneWay,
        goal: Goal,
        step: int = 1,
        first: int = 1,
        budget_ms: float = 0.0,
        clock: Callable[[], float] = time.perf_counter,
    ) -> CascadeRun:
        """Score `cands` (global order, at least one) as the module docstring says; returns the
        passes spent and whether the budget stopped it."""
        run = CascadeRun(self, cands, one_way, budget_ms, clock)
        young = not self.stats.ready
        run.both(cands[: max(1, len(cands) if young else first)], step if young else None)
        audited = False
        while not run.cut and not young:
            need = self.contenders(cands, goal)
            if not need and not audited:  # the near miss the cap ruled out gets a look
                audited = True
                near = self.contenders(cands, goal, slack=self.stats.spread)
                need = [c for c in near if c.directions == 0][:1]
            if not need:
                break
            if budget_ms > 0:  # a look at every contender before any second direction
                need.sort(key=lambda c: c.directions)
            level = need[0].directions
            run.step([c for c in need if c.directions == level][:step], level)
        if run.cut:
            run.settle(goal.weight)
        return run


class CascadeRun:
    """One keyframe's scoring: the calls, the passes they cost, the budget."""

    def __init__(self, cascade, cands, one_way: OneWay, budget_ms: float, clock) -> None:
        self.cascade, self.cands, self.one_way = cascade, cands, one_way
        self.budget_ms, self.clock = budget_ms, clock
        self.start, self.passes, self.cut = clock(), 0, False

    def both(self, cands: list[Candidate], step: int | None) -> None:
        """Score `cands` both ways, `step` at a time with the budget (None: all at once)."""
        size = len(cands) if step is None else step
        for i in range(0, len(cands), size):
            part = cands[i : i + size]
            if not self.step(part, 0):
                return
            self.step(part, 1, check=False)

    def step(self, cands: list[Candidate], level: int, check: bool = True) -> bool:
        """Give `cands` (all scored `level` ways) their next direction; False when the budget
        stops it first (the very first step always runs)."""
        if check and self.passes and self.budget_ms > 0:
            spent_ms = (self.clock() - self.start) * 1e3
            if spent_ms + spent_ms / self.passes * len(cands) > self.budget_ms:
                self.cut = True
                return False
        logits = np.asarray(self.one_way(cands, FIRST if level == 0 else SECOND), dtype=float)
        logits[~np.isfinite(logits)] = -math.inf  # a broken pass (NaN) never wins, never loops
        for cand, logit in zip(cands, logits, strict=True):
            if level == 0:
                set_first_logit(cand, float(logit))
            else:
                set_second_logit(cand, float(logit))
                cand.pair_score = float(np.float32(cand.logit_qc) + np.float32(cand.logit_cq))
            self.cascade.stats.add(cand)
        self.passes += len(cands)
        return True

    def settle(self, weight: float) -> None:
        """After a budget cut: the best one-way candidate gets its second direction when its
        estimate (twice its logit) beats every full score."""
        best = max((c.rerank_score(weight) for c in self.cands if c.directions == 2),
                   default=-math.inf)  # fmt: skip
        half = [c for c in self.cands if c.directions == 1]
        if half:
            lead = max(half, key=lambda c: rerank_score(2 * first_logit(c),
                                                        c.global_similarity, weight))  # fmt: skip
            if rerank_score(2 * first_logit(lead), lead.global_similarity, weight) > best:
                self.step([lead], 1, check=False)

    def scored(self) -> list[Candidate]:
        """The candidates scored both ways."""
        return [c for c in self.cands if c.directions == 2]


def first_logit(cand: Candidate) -> float:
    return cand.logit_cq if FIRST == "candidate" else cand.logit_qc


def set_first_logit(cand: Candidate, logit: float) -> None:
    if FIRST == "candidate":
        cand.logit_cq = logit
    else:
        cand.logit_qc = logit


def set_second_logit(cand: Candidate, logit: float) -> None:
    if FIRST == "candidate":
        cand.logit_qc = logit
    else:
        cand.logit_cq = logit
