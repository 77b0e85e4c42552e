"""Decide a replay's keyframes again with other settings, from its `DecisionLog`, through the
detector's own code (`LoopDetector.decide`, temporal consistency and sequence margin included):
what `score_threshold` and `global_floor` would have accepted, without running the network again.

What the log cannot hold is computed as the pipeline would: a candidate the run never verified is
verified on the features the map stored for both keyframes, and a loop the run never posed is
posed from them (neither is exactly what the run would see: the query's features at run time are
the extracted ones, not their stored, compact form; `WhatIf.estimated` counts such decisions).
Candidates the run did not score (a re-rank budget) stay unscored: never accepted.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from pair_vpr_ros.geometry.relpose import relative_pose
from pair_vpr_ros.loops.detector import DetectorConfig, LoopDetector
from pair_vpr_ros.loops.records import Candidate, LoopRecord
from pair_vpr_ros.loops.sequence import track_of
from pair_vpr_ros.offline.report.decision_log import DecisionLog, LoggedKeyframe


class StoredGeometry:
    """Verification and pose of a (keyframe, candidate) pair from the features the pipeline's
    maps stored (`pipe`: the replay's `LoopClosurePipeline`, still open), cached."""

    def __init__(self, pipe, log: DecisionLog) -> None:
        self.pipe, self.log = pipe, log
        self.verify_on = pipe.config.geometric_verification
        self.pose_on = pipe.geometry.config.relative_pose
        self._verified: dict[tuple[int, int], tuple[int, float]] = {}
        self._posed: dict[tuple[int, int], bool] = {}

    def _features(self, place_map, kf_id: int):
        return self.pipe.geometry.unpack(place_map.features(kf_id)) if kf_id >= 0 else None

    def _pair(self, kf: LoggedKeyframe, cand: Candidate):
        """(the query's stored features, the match's as the pipeline verifies it: its own, or
        those a linked keyframe lends; `PipelineMaps.match_features`)."""
        query = self._features(self.pipe.place_map, kf.map_id)
        return query, self.pipe.match_features(cand)[0]

    def verify(self, kf: LoggedKeyframe, cand: Candidate) -> tuple[tuple[int, float], bool]:
        """((inliers, ratio), estimated): the run's result when it verified this pair."""
        key = (kf.row, cand.rank_before)
        if key in self.log.verified:
            return self.log.verified[key], False
        if key not in self._verified:
            self._verified[key] = self.pipe.geometry.verify(*self._pair(kf, cand))
        return self._verified[key], True

    def posed(self, kf: LoggedKeyframe, cand: Candidate) -> tuple[bool, bool]:
        """(the loop gets a relative pose, estimated)."""
        key = (kf.row, cand.rank_before)
        if key in self.log.posed:
            return bool(self.log.posed[key]), False
        if key not in self._posed:
            pose = relative_pose(*self._pair(kf, cand), self.pipe.geometry.config.pose)
            self._posed[key] = bool(pose.status)
        return self._posed[key], True


@dataclass
class WhatIf:
    """The accepted loops of one setting: records with `query_id` set, `estimated`: decisions
    that rest on a verification or pose computed from stored features."""

    threshold: float
    global_floor: float
    accepted: list[LoopRecord] = field(default_factory=list)
    estimated: int = 0


def _groups(kf: LoggedKeyframe, per_map: bool) -> list[list[Candidate]]:
    """The candidate lists the pipeline decided on, as `LoopClosurePipeline._query` forms them."""
    if not kf.searched:
        return []
    if not per_map:
        return [kf.candidates]
    by_map: dict[int, list[Candidate]] = {}
    for cand in kf.candidates:
        by_map.setdefault(cand.prior, []).append(cand)
    return [by_map[prior] for prior in sorted(by_map)]


def decide_again(
    log: DecisionLog,
    config: DetectorConfig,
    geometry: StoredGeometry,
    identity: tuple[str, str],
    threshold: float,
    global_floor: float | None = None,
) -> WhatIf:
    """Every logged keyframe decided with `score_threshold = threshold` (and `global_floor`,
    default the run's) -> the loops that would be accepted. `identity`: (robot, session) of
    the queries."""
    floor = config.global_floor if global_floor is None else global_floor
    config = config.updated(score_threshold=threshold, global_floor=floor, rerank_budget_ms=0.0)
    detector = LoopDetector(config)
    out = WhatIf(threshold, floor)
    scores: dict[int, float] = {}

    def rerank(cands: list[Candidate]) -> np.ndarray:  # the logged scores; unscored never win
        return np.array([scores[c.rank_before] for c in cands], np.float64)

    for kf in log.keyframes():
        if kf.new_session:
            detector.reset()
        scores = {
            c.rank_before: c.pair_score if math.isfinite(c.pair_score) else -math.inf
            for c in kf.candidates
        }
        estimated = [False]

        def verify(cand: Candidate, kf=kf, estimated=estimated) -> tuple[int, float]:
            result, guessed = geometry.verify(kf, cand)
            estimated[0] |= guessed
            return result

        for group in _groups(kf, config.loop_per_map):
            record = detector.decide(
                kf.stamp, kf.frame_id, group, rerank, verify if geometry.verify_on else None,
                step=len(group) or 1, query_identity=identity,
                track=track_of(group[0], config.loop_per_map) if group else None,
            )  # fmt: skip
            if record is None or not record.accepted:
                continue
            record.query_id = kf.map_id
            if geometry.pose_on:
                best = next(c for c in group if c.rank_before == record.rank_before)
                posed, guessed = geometry.posed(kf, best)
                estimated[0] |= guessed
                if not posed:  # an unposed loop ends the sequence, as in the pipeline
                    detector.end_sequence(track_of(best, config.loop_per_map))
            out.accepted.append(record)
            out.estimated += int(estimated[0])
    return out


def same_as_run(log: DecisionLog, again: WhatIf) -> int:
    """How many keyframes the decisions `again` (at the run's own settings) accept differently
    from the run: 0 when the log replays the run exactly."""
    mine = {(r.query_id, r.query_stamp, r.rank_before) for r in again.accepted}
    run = {(log.map_id[row], log.stamp[row], rank) for row, rank in log.accepted}
    return len(mine ^ run)
