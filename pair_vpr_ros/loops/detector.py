"""Loop-closure decisions: keyframe selection, top-K query, pair re-ranking, acceptance.

For each keyframe: search the map for the top-K most similar earlier keyframes (recent ones
excluded), re-rank them with the pair classifier's bidirectional score, and accept the best when
its score reaches the threshold (and, optionally, when consecutive queries agree and the images
verify geometrically). Every decision is a `LoopRecord`, accepted or with the reason it was not.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

from pair_vpr_ros.errors import ConfigError
from pair_vpr_ros.loops.cascade import Cascade, Goal, OneWay
from pair_vpr_ros.loops.floor import LearnedFloor
from pair_vpr_ros.loops.records import Candidate, LoopRecord, rank_by_pair_score
from pair_vpr_ros.loops.sequence import DecisionTracks

MODES = ("mapping", "localization")
GROWTH = ("places", "all")  # map_growth: represented keyframes not stored / every one stored


@dataclass
class DetectorConfig:
    """Detector settings. Times in seconds; similarities are cosine of global descriptors."""

    top_k: int = 10  # candidates re-ranked per keyframe
    score_threshold: float = 0.0  # accept when the re-rank score (below) >= this
    # Re-rank score = logit(q,c) + logit(c,q) + global_weight x global similarity. 0 (default):
    # the pair score alone, as the paper ranks; > 0 lets a weak pair classifier (the demo
    # model's) add to the global descriptor instead of overruling it.
    global_weight: float = 0.0
    global_floor: float = (
        -1.0
    )  # skip re-ranking when the best global similarity is lower (-1: off)
    min_frame_interval: float = 0.0  # frames closer than this to the last encoded one are skipped
    keyframe_max_similarity: float = (
        0.98  # a frame this similar to the last keyframe is no keyframe
    )
    exclude_recent_s: float = 30.0  # never match keyframes stamped this close to the query ...
    exclude_recent_keyframes: int = 10  # ... or among the newest this many
    temporal_consistency: int = 1  # accept after N consecutive agreeing queries (1: off)
    temporal_tolerance: int = 5  # "agreeing": matched ids within this many keyframes
    # > 0: when the best candidate scores below score_threshold, a candidate that continues the
    # previous query's accepted loop (same map, robot and session, id within temporal_tolerance)
    # is accepted at score_threshold - sequence_margin (verification still applies)
    sequence_margin: float = 0.0
    geometric_verification: bool = False
    min_inliers: int = 15  # with geometric verification
    mode: str = "mapping"  # "mapping": query then add; "localization": query only
    map_growth: str = "places"  # mapping: "places" stores no represented keyframe (growth.py)
    rerank_budget_ms: float = 0.0  # stop re-ranking once this is spent (0: score all top_k)
    # Score each candidate one direction first, the second only where it can still change the
    # decision (cascade.py); False: every candidate both ways, as the paper
    rerank_cascade: bool = False
    # With rerank_cascade: skip keyframes below the floor learned from accepted loops (floor.py)
    learned_floor: bool = True
    # With prior maps: each map (live, each prior) gives its own top_k and at most one loop of
    # the keyframe; False: one top_k of all maps together, one loop. One map: the same.
    loop_per_map: bool = True

    def __post_init__(self) -> None:
        checks = [
            ("top_k", self.top_k >= 1, ">= 1"),
            ("global_floor", -1.0 <= self.global_floor <= 1.0, "in [-1, 1]"),
            ("min_frame_interval", self.min_frame_interval >= 0, ">= 0"),
            ("keyframe_max_similarity", -1.0 <= self.keyframe_max_similarity <= 1.0, "in [-1, 1]"),
            ("exclude_recent_s", self.exclude_recent_s >= 0, ">= 0"),
            ("exclude_recent_keyframes", self.exclude_recent_keyframes >= 0, ">= 0"),
            ("temporal_consistency", self.temporal_consistency >= 1, ">= 1"),
            ("temporal_tolerance", self.temporal_tolerance >= 0, ">= 0"),
            (
                "sequence_margin",
                math.isfinite(self.sequence_margin) and self.sequence_margin >= 0,
                "a finite number >= 0 (0: off)",
            ),
            ("min_inliers", self.min_inliers >= 0, ">= 0"),
            ("mode", self.mode in MODES, f"one of {MODES}"),
            ("map_growth", self.map_growth in GROWTH, f"one of {GROWTH}"),
            ("loop_per_map", isinstance(self.loop_per_map, bool), "true or false"),
            ("rerank_cascade", isinstance(self.rerank_cascade, bool), "true or false"),
            ("learned_floor", isinstance(self.learned_floor, bool), "true or false"),
            ("score_threshold", math.isfinite(self.score_threshold), "a finite number"),
            (
                "global_weight",
                math.isfinite(self.global_weight) and self.global_weight >= 0,
                "a finite number >= 0 (0: the pair score alone)",
            ),
            (
                "rerank_budget_ms",
                math.isfinite(self.rerank_budget_ms) and self.rerank_budget_ms >= 0,
                "a finite number >= 0 (0: no budget)",
            ),
        ]
        for name, ok, rule in checks:
            if not ok:
                raise ConfigError(f"detector {name}={getattr(self, name)!r} must be {rule}")

    def updated(self, **changes) -> DetectorConfig:
        return replace(self, **changes)


# Named presets: the paper's "speed" setting re-ranks K=100, ours is sized for a laptop CPU.
PRESETS: dict[str, dict] = {
    "speed": dict(top_k=10, min_frame_interval=0.2),
    "performance": dict(top_k=100, min_frame_interval=0.0),
}


def preset(name: str, **overrides) -> DetectorConfig:
    if name not in PRESETS:
        raise ConfigError(f"unknown preset {name!r}: choose one of {', '.join(PRESETS)}")
    return DetectorConfig(**{**PRESETS[name], **overrides})


Verifier = Callable[[Candidate], tuple[int, float]]  # match -> (inliers, inlier ratio)


@dataclass
class LoopDetector:
    """The decision logic; `LoopClosurePipeline` feeds it descriptors and the map."""

    config: DetectorConfig = field(default_factory=DetectorConfig)
    clock: Callable[[], float] = time.perf_counter  # s, for the re-rank budget (tests fake it)
    # a rig keyframe's cameras share its budget: each query's share (ms), None: the config's
    budget_ms: float | None = None

    def __post_init__(self) -> None:
        self._tracks = DecisionTracks(self.config)
        self.cascade = Cascade()  # what its bounds learned: kept for the detector's life
        self.floor = LearnedFloor()  # reset with the map (`reset_map`)
        self.last_passes = 0  # decoder passes of the last `decide` (one direction of a pair: 1)
        self.last_cut = False  # the last `decide` stopped at rerank_budget_ms
        self.last_skipped = False  # the last `decide` skipped re-ranking (a global floor)
        self.last_covered = False  # ... scored every candidate at least one way

    def reset(self) -> None:
        self._tracks.reset()

    def reset_map(self) -> None:
        """A new, loaded or cleared map: the learned floor starts again."""
        self.floor.reset()

    def set_config(self, config: DetectorConfig) -> None:
        self.config = config
        self._tracks.set_config(config)

    def end_sequence(self, track: int | None) -> None:
        """The last accepted loop of `track` is not to be followed (the pipeline: it got no
        relative pose, the mark of many false loops)."""
        self._tracks.decided(track, None, False)

    def is_new_keyframe(self, similarity_to_last: float | None) -> bool:
        """A frame becomes a keyframe unless it nearly repeats the previous keyframe."""
        return (
            similarity_to_last is None or similarity_to_last < self.config.keyframe_max_similarity
        )

    def decide(
        self,
        query_stamp: float,
        query_frame_id: str,
        candidates: list[Candidate],
        rerank: Callable[[list[Candidate]], np.ndarray],
        verify: Verifier | None = None,
        step: int = 2,
        first: int = 1,
        query_identity: tuple[str, str] = ("", ""),
        track: int | None = None,
        one_way: OneWay | None = None,
    ) -> LoopRecord | None:
        """Re-rank `candidates` (global order) and accept or reject the best one (or, with
        `sequence_margin`, one that continues the last accepted loop: sequence.py). `rerank`
        scores a list of candidates ([k] scores); with a budget it is called for the first
        `first`, then `step` at a time. `query_identity`: (robot, session) of the query.
        `track`: whose temporal consistency this decision counts in (one per map searched on
        its own, `loop_per_map`; None: the one stream of decisions). `one_way`: one direction
        of a list of candidates ([k] logits), for `rerank_cascade` (None: full scoring)."""
        self.last_passes, self.last_cut, self.last_skipped = 0, False, False
        self.last_covered = False
        record, match = self._decide(query_stamp, query_frame_id, candidates, rerank, verify,
                                     step, first, query_identity, track, one_way)  # fmt: skip
        accepted = record is not None and record.accepted
        self._tracks.decided(track, match, accepted)
        if accepted:
            self.floor.accepted(candidates[0].global_similarity)
        return record

    def _decide(self, query_stamp, query_frame_id, candidates, rerank, verify, step, first,
                query_identity, track,
                one_way) -> tuple[LoopRecord | None, Candidate | None]:  # fmt: skip
        """`decide` without the sequence bookkeeping: (record, the candidate it is about)."""
        recent = self._tracks.recent(track)
        if not candidates:
            recent.clear()
            return None, None
        c = self.config
        query = (query_stamp, query_frame_id, *query_identity)
        best_global = candidates[0]
        floor, reason = c.global_floor, "below global floor"
        learned = self.floor.value() if c.rerank_cascade and c.learned_floor else None
        if self._tracks.follow_goal(track)[0] is not None:
            learned = None  # a keyframe that may continue the last loop is always re-ranked
        if learned is not None and learned > floor:
            floor, reason = learned, f"below learned global floor ({learned:.3f})"
        if best_global.global_similarity < floor:
            recent.clear()
            self.last_skipped = True
            record = self._record(*query, best_global, reason)
            record.candidates = len(candidates)
            return record, best_global
        if c.rerank_cascade and one_way is not None:
            scored = self._cascade(candidates, one_way, step, first, track)
        else:
            scored = self.score(candidates, rerank, step, first)
            self.last_passes = 2 * len(scored)
            self.last_cut = len(scored) < len(candidates)
        self.last_covered = all(cand.directions > 0 for cand in candidates)
        best, rank = scored[0], 1
        below = best.rerank_score(c.global_weight) < c.score_threshold
        if below and (follower := self._tracks.follower(track, scored)) is not None:
            rank, best = follower
            below = False
        reason = "score below threshold" if below else ""
        record = self._record(*query, best, reason)
        record.candidates, record.scored, record.rank_after = len(candidates), len(scored), rank
        if reason:
            recent.clear()
            return record, best
        if not self._tracks.consistent(track, best):
            seen = len(recent)
            record.reason = f"awaiting temporal consistency ({seen}/{c.temporal_consistency})"
            return record, best
        if c.geometric_verification and verify is not None:
            record.inliers, record.inlier_ratio = verify(best)
            if record.inliers < 0:
                record.reason = "geometric verification impossible (no features for the match)"
                return record, best
            if record.inliers < c.min_inliers:
                record.reason = f"geometric verification failed ({record.inliers} inliers)"
                return record, best
        record.accepted = True
        return record, best

    def _cascade(self, candidates, one_way, step, first, track) -> list[Candidate]:
        """The candidates the cascade scored both ways, best re-rank score first (cascade.py)."""
        c = self.config
        floor, continues = self._tracks.follow_goal(track)
        goal = Goal(c.score_threshold, c.global_weight, floor, continues)
        run = self.cascade.run(candidates, one_way, goal, step, first, c.rerank_budget_ms,
                               self.clock)  # fmt: skip
        self.last_passes, self.last_cut = run.passes, run.cut
        scored = run.scored()
        return sorted(scored, key=lambda x: (-x.rerank_score(c.global_weight), x.rank_before))

    def score(
        self,
        candidates: list[Candidate],
        rerank: Callable[[list[Candidate]], np.ndarray],
        step: int,
        first: int = 1,
    ) -> list[Candidate]:
        """Pair-score `candidates` (global order, at least one) best-global first; return the
        scored ones, best pair score first. The rest keep a NaN score.

        No budget (`rerank_budget_ms` 0): all in one `rerank` call. With a budget: the `first`
        best-global candidates (the global best alone by default; a back end that pads every
        call to a fixed chunk scores a whole chunk for the price of one), then `step` at a time
        while the time spent so far plus the next step's predicted cost (this query's mean per
        candidate) stays within the budget. The first call always runs, so re-ranking takes at
        most max(budget, one call)."""
        budget_ms = self.config.rerank_budget_ms if self.budget_ms is None else self.budget_ms
        if budget_ms <= 0:
            return rank_by_pair_score(candidates, rerank(candidates), self.config.global_weight)
        start, done, parts = self.clock(), 0, []
        while done < len(candidates):
            size = min(first if done == 0 else step, len(candidates) - done)
            spent_ms = (self.clock() - start) * 1e3
            if done and spent_ms + spent_ms / done * size > budget_ms:
                break
            parts.append(np.asarray(rerank(candidates[done : done + size])))
            done += size
        weight = self.config.global_weight
        return rank_by_pair_score(candidates[:done], np.concatenate(parts), weight)

    @staticmethod
    def _record(
        stamp: float, frame_id: str, robot: str, session: str, cand: Candidate, reason: str
    ) -> LoopRecord:
        """The record of `cand` as the best candidate (rank 1 after re-ranking)."""
        return LoopRecord(
            query_id=-1,
            query_stamp=stamp,
            query_frame_id=frame_id,
            match_id=cand.id,
            match_stamp=cand.stamp,
            match_frame_id=cand.frame_id,
            query_robot=robot,
            query_session=session,
            match_robot=cand.robot,
            match_session=cand.session,
            match_camera=cand.camera,
            pair_score=cand.pair_score,
            global_similarity=cand.global_similarity,
            rank_before=cand.rank_before,
            rank_after=1,
            reason=reason,
        )
